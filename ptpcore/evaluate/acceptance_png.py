"""The acceptance report's page of plots (OpenCV, as :mod:`.diff` and :mod:`.residuals` draw theirs).

One panel per figure (PF, PS, SD, F): for every pose, each method's value as a bar, side by side
(PTP first), the MPE as a dashed line (both signs for the signed PS and SD); with simulator truth, a
last panel of the 3D distance error (RMS per bin of the true distance) of every method.
"""

from __future__ import annotations

import numpy as np

from .pngtext import put_text, text_width, write_png
from .vdi2634 import FIGURES, SIGNED, AcceptanceReport

__all__ = ["acceptance_page", "acceptance_png", "METHOD_COLOURS"]

METHOD_COLOURS = {"ptp": (178, 114, 0), "conventional": (0, 120, 230)}
"""BGR: PTP blue, conventional orange; any other method grey."""
PANEL_W, PANEL_H, LEFT, TOP = 760, 220, 70, 40


def _colour(m: str):
    return METHOD_COLOURS.get(m, (110, 110, 110))


def _nice_limit(v: float) -> float:
    """The smallest of 1, 2, 5 x 10^k at least ``v`` (> 0)."""
    if not np.isfinite(v) or v <= 0:
        return 1.0
    e = 10.0 ** np.floor(np.log10(v))
    return float(next(m * e for m in (1, 2, 5, 10) if m * e >= v))


def _axes(panel: np.ndarray, lo: float, hi: float, title: str, unit: str) -> callable:
    """Frame, title, y ticks; returns ``y_of(value)`` (panel px)."""
    import cv2

    h, w = panel.shape[:2]
    y0, y1 = TOP, h - 30

    def y_of(v):
        return int(round(y1 - (v - lo) / (hi - lo) * (y1 - y0)))

    cv2.rectangle(panel, (LEFT, y0), (w - 10, y1), (0, 0, 0), 1)
    put_text(panel, title, (LEFT, 24), 0.55)
    for t in np.linspace(lo, hi, 5):
        y = y_of(t)
        cv2.line(panel, (LEFT - 4, y), (LEFT, y), (0, 0, 0), 1)
        label = f"{t:.4g}"
        put_text(panel, label, (LEFT - 8 - text_width(label, 0.4), y + 4), 0.4)
    put_text(panel, unit, (6, y0 - 8), 0.4, (60, 60, 60))
    if lo < 0 < hi:
        cv2.line(panel, (LEFT, y_of(0)), (w - 10, y_of(0)), (150, 150, 150), 1)
    return y_of


def _dashed(panel, y: int, x0: int, x1: int, colour=(0, 0, 200)) -> None:
    import cv2

    for x in range(x0, x1, 12):
        cv2.line(panel, (x, y), (min(x + 6, x1), y), colour, 1)


def _figure_panel(report: AcceptanceReport, key: str) -> np.ndarray | None:
    """Bars of ``key`` per pose and method (µm), or None when no pose has it."""
    import cv2

    poses = [p for p in dict.fromkeys(f.pose for f in report.poses if key in f.figures)]
    if not poses:
        return None
    val = {(f.pose, f.method): 1e3 * f.figures[key] for f in report.poses if key in f.figures}
    mpe = 1e3 * report.mpe_mm[key] if key in report.mpe_mm else None
    top = max([abs(v) for v in val.values()] + ([mpe] if mpe else []))
    hi = _nice_limit(1.1 * top)
    lo = -hi if key in SIGNED else 0.0
    panel = np.full((PANEL_H, PANEL_W, 3), 255, np.uint8)
    words = {"PF": "PF, probing error form (sphere)", "PS": "PS, probing error size (sphere)",
             "SD": "SD, sphere-spacing error (ball bar)", "F": "F, flatness error (plane)"}
    y_of = _axes(panel, lo, hi, words[key] + (f"; MPE {mpe:g} µm" if mpe else ""), "µm")
    x0, x1 = LEFT + 6, PANEL_W - 16
    slot = (x1 - x0) / len(poses)
    bar = max(2, int(slot * 0.8 / max(len(report.methods), 1)))
    for i, pose in enumerate(poses):
        for j, m in enumerate(report.methods):
            v = val.get((pose, m))
            if v is None:
                continue
            xa = int(x0 + i * slot + 0.1 * slot + j * bar)
            cv2.rectangle(panel, (xa, y_of(0.0)), (xa + bar - 1, y_of(float(np.clip(v, lo, hi)))), _colour(m), -1)
        label = pose.split("-")[-1]
        put_text(panel, label, (int(x0 + (i + 0.5) * slot - text_width(label, 0.35) / 2), PANEL_H - 12), 0.35)
    if mpe:
        for s in ((1, -1) if key in SIGNED else (1,)):
            _dashed(panel, y_of(s * mpe), LEFT, PANEL_W - 10)
    return panel


def _distance_panel(report: AcceptanceReport) -> np.ndarray | None:
    """RMS 3D distance error per bin of true distance, per method (pairs across scans, else within)."""
    import cv2

    if not report.distance:
        return None
    kind = "across_scans" if all("across_scans" in d.kinds for d in report.distance.values()) else "same_scan"
    curves = {m: d.kinds[kind][1] for m, d in report.distance.items()}
    top = max(float(np.nanmax(c.rms_um)) if np.isfinite(c.rms_um).any() else 0.0 for c in curves.values())
    hi = _nice_limit(1.1 * top)
    panel = np.full((PANEL_H, PANEL_W, 3), 255, np.uint8)
    dmax = max(float(c.edges_mm[-1]) for c in curves.values())
    y_of = _axes(panel, 0.0, hi, f"3D distance error against truth, RMS per bin of the true distance in mm"
                                 f" ({kind.replace('_', ' ')} pairs)", "µm")

    def x_of(d):
        return int(round(LEFT + d / max(dmax, 1e-9) * (PANEL_W - 10 - LEFT)))

    for m, c in curves.items():
        mid = 0.5 * (c.edges_mm[1:] + c.edges_mm[:-1])
        pts = [(x_of(d), y_of(v)) for d, v in zip(mid, c.rms_um) if np.isfinite(v)]
        for a, b in zip(pts, pts[1:]):
            cv2.line(panel, a, b, _colour(m), 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(panel, p, 3, _colour(m), -1, cv2.LINE_AA)
    for d in np.linspace(0, dmax, 5):
        label = f"{d:.0f}"
        put_text(panel, label, (x_of(d) - text_width(label, 0.35) // 2, PANEL_H - 12), 0.35)
    return panel


def acceptance_page(report: AcceptanceReport, title: str = "VDI/VDE 2634-2 acceptance") -> np.ndarray:
    """The page as an image: (H, 760, 3) uint8 BGR (panels stacked, a legend under the title).

    Parameters
    ----------
    report : AcceptanceReport
    title : str
    """
    panels = [p for p in [_figure_panel(report, k) for k in FIGURES] + [_distance_panel(report)] if p is not None]
    head = np.full((56, PANEL_W, 3), 255, np.uint8)
    put_text(head, title, (10, 22), 0.6)
    x = 10
    for m in report.methods:
        head[34:46, x:x + 18] = _colour(m)
        put_text(head, m, (x + 24, 45), 0.45)
        x += 40 + text_width(m, 0.45)
    put_text(head, "bars: each pose (number under it), the methods side by side; dashed: MPE", (x + 10, 45), 0.4,
             (60, 60, 60))
    return np.concatenate([head, *panels])


def acceptance_png(report: AcceptanceReport, path, title: str = "VDI/VDE 2634-2 acceptance") -> None:
    """Write :func:`acceptance_page` as PNG, atomically."""
    write_png(acceptance_page(report, title), path)
