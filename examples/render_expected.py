"""Render what an example should show: its decoded u and v maps side by side (``expected.png``).

Usage, from the checkout::

    python examples/render_expected.py sofast              # decodes examples/sofast, writes examples/sofast/expected.png
    python examples/render_expected.py kamino410 --decoded kamino410.decoded.h5   # reuse a decode

Each panel is one direction's LCD coordinate at the first position, coloured with OpenCV's viridis
map between its 1st and 99th percentile (the colour bar under it gives the range in LCD px);
pixels the decoder rejected are grey. OpenCV only (no Qt, no matplotlib).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import h5py
import numpy as np

EXAMPLES = Path(__file__).resolve().parent
PANEL_HEIGHT = 320  # px of each map in the picture
BAR_HEIGHT = 14
GREY = (128, 128, 128)
WHITE = (255, 255, 255)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def decoded_maps(decoded: Path) -> tuple[np.ndarray, np.ndarray]:
    """The first position's u and v, (H, W) float64 LCD px, NaN where the decoder rejected the pixel."""
    with h5py.File(decoded, "r") as f:
        u = np.asarray(f["u"][0], np.float64)
        v = np.asarray(f["v"][0], np.float64)
        reasons = np.asarray(f["reasons"][0])
    u[reasons[0] != 0] = np.nan
    v[reasons[1] != 0] = np.nan
    return u, v


def _panel(values: np.ndarray, label: str) -> np.ndarray:
    """One map as a BGR image with its label above and its colour bar, with the range, below."""
    valid = np.isfinite(values)
    lo, hi = np.percentile(values[valid], [1, 99]) if valid.any() else (0.0, 1.0)
    scaled = np.clip((values - lo) / max(hi - lo, 1e-9), 0, 1)
    grey8 = np.where(valid, scaled * 255, 0).astype(np.uint8)
    img = cv2.applyColorMap(grey8, cv2.COLORMAP_VIRIDIS)
    img[~valid] = GREY
    h, w = values.shape
    width = max(1, round(w * PANEL_HEIGHT / h))
    img = cv2.resize(img, (width, PANEL_HEIGHT), interpolation=cv2.INTER_NEAREST)
    ramp = np.tile(np.linspace(0, 255, width).astype(np.uint8), (BAR_HEIGHT, 1))
    bar = cv2.applyColorMap(ramp, cv2.COLORMAP_VIRIDIS)
    head = np.full((28, width, 3), 255, np.uint8)
    cv2.putText(head, label, (4, 20), FONT, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    foot = np.full((24, width, 3), 255, np.uint8)
    cv2.putText(foot, f"{lo:.0f}", (2, 17), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    text = f"{hi:.0f} LCD px"
    (tw, _th), _ = cv2.getTextSize(text, FONT, 0.45, 1)
    cv2.putText(foot, text, (width - tw - 2, 17), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([head, img, bar, foot])


def render(u: np.ndarray, v: np.ndarray, title: str) -> np.ndarray:
    """The picture: a title line, then the u and v panels side by side (BGR uint8)."""
    left, right = _panel(u, "u (direction x)"), _panel(v, "v (direction y)")
    gap = np.full((left.shape[0], 12, 3), 255, np.uint8)
    body = np.hstack([left, gap, right])
    title_row = np.full((30, body.shape[1], 3), 255, np.uint8)
    cv2.putText(title_row, title, (4, 21), FONT, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([title_row, body])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("name", help="the example's folder under examples/, e.g. sofast")
    parser.add_argument("--decoded", type=Path, help="an existing decode of it (default: decode it now)")
    parser.add_argument("--out", type=Path, help="the PNG (default: examples/NAME/expected.png)")
    args = parser.parse_args(argv)
    folder = EXAMPLES / args.name
    if not (folder / "rig.toml").is_file():
        print(f"render_expected: {folder}/rig.toml not found", file=sys.stderr)
        return 2
    out = args.out or folder / "expected.png"
    with tempfile.TemporaryDirectory(prefix="ptp-render-") as tmp:
        decoded = args.decoded
        if decoded is None:
            from ptpcore.cli.main import main as ptp

            decoded = Path(tmp) / f"{args.name}.decoded.h5"
            if ptp(["decode", str(folder), "--out", str(decoded), "-q"]) != 0:
                return 1
        u, v = decoded_maps(decoded)
    picture = render(u, v, f"ptp decode examples/{args.name}: LCD coordinates, grey = rejected")
    ok, data = cv2.imencode(".png", picture, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        print(f"render_expected: could not encode {out}", file=sys.stderr)
        return 1
    partial = out.with_name(out.name + ".partial")
    partial.write_bytes(data.tobytes())
    partial.replace(out)  # atomic
    print(f"{out}: {picture.shape[1]} x {picture.shape[0]} px, {len(data) // 1024} KB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
