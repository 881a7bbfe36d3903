"""``ptp diff``: are two LUTs of one camera consistent within their predicted noise?

Both LUTs are evaluated at :data:`N_HEIGHTS` heights spread over the z range both
cover; at every pixel valid in both and in range at a height, the differences
``dX = X_A - X_B`` and ``dY`` are taken. Their RMS over the heights and both axes
is the pixel's difference ``d``; the difference the sigma maps predict is
``s = sqrt(sigma_A^2 + sigma_B^2)`` (each sigma map is the pixel's 1-sigma error
as its RMS over its z range, FORMATS.md; the two calibrations' noise is
independent). A pixel is beyond the tolerance when
``d > max(tolerance_sigma * s, tolerance_um)``; the LUTs differ when more than
``max_fraction`` of the common pixels are. The overall ratio ``RMS(d) / RMS(s)``
is about 1 for two sweeps of one rig whose models follow it.

Two sweeps of one rig at interleaved heights answer "is my model right?" (a model
error that depends on where the calibrated heights are does not cancel); today's
LUT against last month's answers "has the rig drifted?". No drawing here:
:func:`diff_png` draws the map with its colour bar, title and scale with OpenCV for the command
line, the GUI draws its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ptpcore.io.lutfile import Lut

from .pngtext import put_text, text_width, write_png

__all__ = ["N_HEIGHTS", "LutDiff", "diff_luts", "diff_png"]

N_HEIGHTS = 9
"""Heights the two LUTs are compared at, evenly over the common z range."""


@dataclass
class LutDiff:
    """The difference of two LUTs (see the module docstring).

    Attributes
    ----------
    z : (E,) float64, mm
        Heights compared at.
    diff_x, diff_y : (H, W) float64, mm
        Per-pixel RMS over the heights of X_A - X_B and Y_A - Y_B (NaN outside the common pixels).
    signed_x, signed_y : (H, W) float64, mm
        Per-pixel mean over the heights of X_A - X_B, Y_A - Y_B (direction of a shift).
    diff : (H, W) float64, mm
        Per-pixel RMS over heights and both axes (``d``).
    predicted : (H, W) float64, mm
        ``sqrt(sigma_A^2 + sigma_B^2)`` (NaN without sigma maps).
    beyond : (H, W) bool
        Common pixels beyond the tolerance.
    common : (H, W) bool
    n_pixels : int
    rms_um, p95_um, max_um : float
        Of ``d`` over the common pixels.
    predicted_rms_um : float
        RMS of ``predicted`` over the common pixels (NaN without sigma maps).
    ratio : float
        ``rms_um / predicted_rms_um``.
    fraction_beyond : float
    tolerance_sigma, tolerance_um, max_fraction : float
    consistent : bool
    """

    z: np.ndarray
    diff_x: np.ndarray
    diff_y: np.ndarray
    signed_x: np.ndarray
    signed_y: np.ndarray
    diff: np.ndarray
    predicted: np.ndarray
    beyond: np.ndarray
    common: np.ndarray
    n_pixels: int
    rms_um: float
    p95_um: float
    max_um: float
    predicted_rms_um: float
    ratio: float
    fraction_beyond: float
    tolerance_sigma: float
    tolerance_um: float
    max_fraction: float
    consistent: bool

    def summary(self) -> dict:
        """The numbers (no maps), for JSON."""
        def num(v):
            return None if not np.isfinite(v) else round(float(v), 6)
        return {"n_pixels": self.n_pixels, "heights_mm": [round(float(z), 6) for z in self.z],
                "rms_um": num(self.rms_um), "p95_um": num(self.p95_um), "max_um": num(self.max_um),
                "predicted_rms_um": num(self.predicted_rms_um), "ratio": num(self.ratio),
                "fraction_beyond": num(self.fraction_beyond), "tolerance_sigma": self.tolerance_sigma,
                "tolerance_um": self.tolerance_um, "max_fraction": self.max_fraction,
                "verdict": "consistent" if self.consistent else "differ"}

    def histogram(self, bins: int = 50) -> tuple[np.ndarray, np.ndarray]:
        """Counts (bins,) and edges (bins + 1,) of ``d`` (µm) over the common pixels."""
        d = self.diff[self.common] * 1e3
        return np.histogram(d, bins=bins, range=(0.0, float(np.max(d)) if d.size else 1.0))


def _check(a: Lut, b: Lut, tolerance_sigma: float, tolerance_um: float, max_fraction: float) -> None:
    if a.shape != b.shape:
        raise ValueError(f"the LUTs are of different cameras: {a.shape[1]}x{a.shape[0]} and"
                         f" {b.shape[1]}x{b.shape[0]} px")
    if not (tolerance_sigma > 0 and tolerance_um >= 0 and 0 <= max_fraction <= 1):
        raise ValueError("tolerance-sigma must be > 0, tolerance-um >= 0 and max-fraction within 0..1")
    if (a.sigma_x is None or b.sigma_x is None) and tolerance_um <= 0:
        raise ValueError("a LUT has no sigma maps (/quality/sigma_x, sigma_y): give --tolerance-um")


def diff_luts(a: Lut, b: Lut, *, tolerance_sigma: float = 3.0, tolerance_um: float = 0.0,
              max_fraction: float = 0.01, n_heights: int = N_HEIGHTS) -> LutDiff:
    """Compare two LUTs of one camera (see the module docstring).

    Parameters
    ----------
    a, b : Lut
    tolerance_sigma : float
        Tolerance in predicted sigmas of the difference (default 3).
    tolerance_um : float
        Absolute floor of the tolerance (µm); required when a LUT has no sigma maps.
    max_fraction : float
        The LUTs differ when more than this fraction of the common pixels is beyond the tolerance.
    n_heights : int

    Returns
    -------
    LutDiff

    Raises
    ------
    ValueError
        Different cameras, no common pixels or z range, bad tolerances.
    """
    _check(a, b, tolerance_sigma, tolerance_um, max_fraction)
    z0, z1 = max(a.z_min, b.z_min), min(a.z_max, b.z_max)
    if not z1 > z0:
        raise ValueError(f"the LUTs cover no common heights ({a.z_min:g}..{a.z_max:g} and"
                         f" {b.z_min:g}..{b.z_max:g} mm)")
    z = np.linspace(z0, z1, int(n_heights))
    h, w = a.shape
    sq = {"x": np.zeros((h, w)), "y": np.zeros((h, w))}
    mean = {"x": np.zeros((h, w)), "y": np.zeros((h, w))}
    n = np.zeros((h, w))
    for zz in z:
        ea, eb = a.evaluate(zz), b.evaluate(zz)
        m = ea.in_range & eb.in_range & a.valid & b.valid
        n += m
        for axis, da in (("x", ea.x - eb.x), ("y", ea.y - eb.y)):
            da = np.where(m, da, 0.0)
            sq[axis] += da * da
            mean[axis] += da
    common = n > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        dx = np.where(common, np.sqrt(sq["x"] / n), np.nan)
        dy = np.where(common, np.sqrt(sq["y"] / n), np.nan)
        sx, sy = (np.where(common, mean[k] / n, np.nan) for k in "xy")
    if not common.any():
        raise ValueError("the LUTs have no valid pixel in common")
    d = np.sqrt(0.5 * (dx * dx + dy * dy))
    return _verdict(a, b, z, dx, dy, sx, sy, d, common, tolerance_sigma, tolerance_um, max_fraction)


def _verdict(a, b, z, dx, dy, sx, sy, d, common, tolerance_sigma, tolerance_um, max_fraction) -> LutDiff:
    """Statistics, tolerance and verdict of the per-pixel differences."""
    if a.sigma_x is not None and b.sigma_x is not None:
        var = 0.5 * (a.sigma_x.astype(float) ** 2 + a.sigma_y.astype(float) ** 2
                     + b.sigma_x.astype(float) ** 2 + b.sigma_y.astype(float) ** 2)
        pred = np.where(common, np.sqrt(var), np.nan)
    else:
        pred = np.full(d.shape, np.nan)
    tol = np.fmax(tolerance_sigma * pred, tolerance_um * 1e-3)  # fmax: NaN prediction -> the floor
    beyond = common & (d > tol)
    dc = d[common] * 1e3
    pc = pred[common]
    pred_rms = float(np.sqrt(np.nanmean(pc ** 2)) * 1e3) if np.isfinite(pc).any() else float("nan")
    rms = float(np.sqrt(np.mean(dc ** 2)))
    frac = float(beyond.sum() / common.sum())
    return LutDiff(z, dx, dy, sx, sy, d, pred, beyond, common, int(common.sum()), rms,
                   float(np.percentile(dc, 95)), float(dc.max()), pred_rms,
                   rms / pred_rms if pred_rms > 0 else float("nan"), frac, float(tolerance_sigma),
                   float(tolerance_um), float(max_fraction), frac <= max_fraction)


def diff_png(result: LutDiff, path, title: str | None = None) -> None:
    """Write the per-pixel difference in units of its tolerance as a colour PNG (OpenCV), atomically.

    The map (pixels of the camera, enlarged to at least 400 px) with a title, a line saying what the
    colour is, and a colour bar with its scale: 0 (dark) to 2x the tolerance and beyond (bright,
    ``COLORMAP_INFERNO``), marked in units of the tolerance and in µm at the median tolerance. Pixels
    outside the common set are grey.

    Parameters
    ----------
    result : LutDiff
    path : str or Path
    title : str, optional
        The first line (default "LUT difference per pixel"); ``ptp diff`` names the two LUTs.
    """
    import cv2

    tol = np.fmax(result.tolerance_sigma * result.predicted, result.tolerance_um * 1e-3)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.clip(result.diff / tol / 2.0, 0.0, 1.0)
    img = cv2.applyColorMap(np.nan_to_num(r * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    img[~result.common] = 128
    f = 1
    if max(img.shape[:2]) < 400:
        f = int(np.ceil(400 / max(img.shape[:2])))
        img = cv2.resize(img, None, fx=f, fy=f, interpolation=cv2.INTER_NEAREST)
    tol_med_um = float(np.nanmedian(tol[result.common])) * 1e3 if result.common.any() else float("nan")
    what = (f"colour: |difference| / tolerance ({result.tolerance_sigma:g} sigma"
            + (f", at least {result.tolerance_um:g} µm" if result.tolerance_um else "")
            + f", median {tol_med_um:.3g} µm); grey: not in both LUTs")
    h, w = result.diff.shape
    scale_line = (f"{w} x {h} camera pixels" + (f", shown {f}x" if f > 1 else "")
                  + f"; {100 * result.fraction_beyond:.2f} % beyond the tolerance:"
                  f" {'consistent' if result.consistent else 'DIFFER'}")
    page = _diff_page(img, title or "LUT difference per pixel", what, scale_line, tol_med_um)
    write_png(page, path)


COLOUR_BAR_TICKS = (0.0, 0.5, 1.0, 1.5, 2.0)
"""Marks of the colour bar, in units of the tolerance (2: the top, and everything beyond)."""


def _diff_page(img: np.ndarray, title: str, what: str, scale_line: str, tol_med_um: float) -> np.ndarray:
    """``img`` (H, W, 3) on a white page with the title and notes above and the colour bar beside it."""
    import cv2

    top, left, gap, bar_w = 64, 10, 16, 22
    labels = [f"{t:g}" + (" = tolerance" if t == 1 else "+" if t == 2 else "")
              + (f"  ({t * tol_med_um:.3g} µm)" if np.isfinite(tol_med_um) else "") for t in COLOUR_BAR_TICKS]
    label_w = max(text_width(t, 0.45) for t in labels) + 12
    h, w = img.shape[:2]
    width = max(left + w + gap + bar_w + label_w, text_width(what, 0.45) + 2 * left,
                text_width(title, 0.6) + 2 * left)
    page = np.full((top + h + 34, width, 3), 255, np.uint8)
    page[top:top + h, left:left + w] = img
    put_text(page, title, (left, 22), 0.6)
    put_text(page, what, (left, 48), 0.45, (60, 60, 60))
    put_text(page, scale_line, (left, top + h + 24), 0.45, (60, 60, 60))
    x0 = left + w + gap
    levels = np.linspace(255, 0, h).astype(np.uint8)  # top: 2x the tolerance, bottom: 0
    bar = cv2.applyColorMap(np.repeat(levels[:, None], bar_w, axis=1), cv2.COLORMAP_INFERNO)
    page[top:top + h, x0:x0 + bar_w] = bar
    cv2.rectangle(page, (x0 - 1, top - 1), (x0 + bar_w, top + h), (0, 0, 0), 1)
    for t, label in zip(COLOUR_BAR_TICKS, labels):
        y = top + int(round((1 - t / 2) * (h - 1)))
        cv2.line(page, (x0 + bar_w, y), (x0 + bar_w + 4, y), (0, 0, 0), 1)
        put_text(page, label, (x0 + bar_w + 7, min(max(y + 5, top + 10), top + h)), 0.45)
    return page
