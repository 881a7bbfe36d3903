"""Text and PNG output for the engine's pictures (OpenCV; the engine draws no Qt).

OpenCV's Hershey fonts hold ASCII only: :func:`put_text` draws "µ" itself (a "u" with a
descender), so the pictures spell the unit as every summary does, "µm".
"""

from __future__ import annotations

import numpy as np

__all__ = ["put_text", "text_width", "write_png"]

FONT_SCALE = 0.5


def _parts(text: str):
    """``text`` split at every "µ": (segment, followed by µ?) pairs."""
    pieces = text.split("µ")
    return [(p, i < len(pieces) - 1) for i, p in enumerate(pieces)]


def text_width(text: str, scale: float = FONT_SCALE, thickness: int = 1) -> int:
    """Width in pixels of ``text`` as :func:`put_text` draws it."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    return sum(cv2.getTextSize(p, font, scale, thickness)[0][0] + (cv2.getTextSize("u", font, scale, thickness)[0][0]
                                                                  if mu else 0) for p, mu in _parts(text))


def put_text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = FONT_SCALE,
             colour=(0, 0, 0), thickness: int = 1) -> None:
    """Draw ``text`` on ``img`` (H, W, 3) uint8 BGR, in place, baseline-left at ``org`` (x, y) px."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    x, y = org
    for piece, mu in _parts(text):
        if piece:
            cv2.putText(img, piece, (x, y), font, scale, colour, thickness, cv2.LINE_AA)
            x += cv2.getTextSize(piece, font, scale, thickness)[0][0]
        if mu:  # "u" and, down its left stem, the descender of a Greek mu
            (w, h), _ = cv2.getTextSize("u", font, scale, thickness)
            cv2.putText(img, "u", (x, y), font, scale, colour, thickness, cv2.LINE_AA)
            # getTextSize's height is the capital letters': the x-height is about 0.7 of it
            stem = x + max(1, int(round(0.22 * w)))
            cv2.line(img, (stem, y - int(round(0.3 * h))), (stem, y + int(round(0.4 * h))), colour, thickness,
                     cv2.LINE_AA)
            x += w


def write_png(img: np.ndarray, path) -> None:
    """Write ``img`` (H, W, 3) uint8 BGR as a PNG, atomically (a temporary file, then renamed)."""
    import cv2

    from ptpcore.atomic import atomic_path

    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(".png", img)
        if not ok:
            raise ValueError(f"{path}: could not encode the PNG")
        with open(tmp, "wb") as fh:
            fh.write(buf.tobytes())
