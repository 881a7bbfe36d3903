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
is about 1 for two sweeps of one rig whose models follow it. When nothing changed and the sigma
maps are right, a pixel's difference is Gaussian with at least one degree of freedom, so a pixel
is beyond ``k`` sigmas with probability at most ``2 (1 - Phi(k))`` (0.27 % at 3 sigma): the
per-pixel false-alarm rate, which the output states.

A small rigid move (a camera knocked by 0.5 µm) is far below one pixel's noise but not below the
image's: beside the per-pixel test, the **common-mode** statistic is, per axis, the mean over the
common pixels of the signed difference (``signed_x``, ``signed_y``: mean over the heights) against
its standard error. Neighbouring pixels' differences are correlated (camera blur, and a smooth
LUT's smoothing at its scale ``s``), so the standard error is not that of independent pixels: the
image is cut into square blocks of side :func:`block_side` (at least 8 correlation lengths), the
mean is the pixel-weighted mean of the block means and its variance the cluster-robust (CR1)
variance of the block means plus the covariance of side-adjacent blocks (the part of the
correlation that crosses a block border), never less than the independent-blocks value. Under
no change ``t = mean / SE`` follows Student's t with ``J - 1`` degrees of freedom (``J`` blocks);
an axis is flagged beyond the two-sided ``common_false_alarm / 2`` quantile (the two axes share
the false-alarm rate, Bonferroni). A shift common to every pixel of both LUTs that no block mean
sees (a stage error repeated in neither sweep, the global model's noise) is outside this standard
error: the statistic answers "did the image move against its own pixel-to-pixel noise?".

Compare like with like: two LUTs fitted with different models or smoothing scales differ by that
alone (the smoothing removes different parts of the noise and of the shape), even when the rig
did not change. The result says so
(``like_with_like`` False, a note in the verdict); the numbers are still computed.

Two sweeps of one rig at interleaved heights answer "is my model right?" (a model
error that depends on where the calibrated heights are does not cancel); today's
LUT against last month's answers "has the rig drifted?". No drawing here:
:func:`diff_png` draws the map with its colour bar, title and scale with OpenCV for the command
line, the GUI draws its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import special  # not scipy.stats: the desktop bundle leaves it out (9.6 MB)

from ptpcore.fit.models import describe_model
from ptpcore.io.lutfile import Lut

from .pngtext import put_text, text_width, write_png

__all__ = ["N_HEIGHTS", "COMMON_FALSE_ALARM", "CommonMode", "LutDiff", "block_side", "needed_block_side", "common_mode_shift",
           "pixel_false_alarm_rate", "diff_luts", "diff_png"]

N_HEIGHTS = 9
"""Heights the two LUTs are compared at, evenly over the common z range."""

COMMON_FALSE_ALARM = 0.01
"""Default false-alarm rate of the common-mode test (both axes together, two-sided): 1 %, a
conventional level (not fitted), so that of 100 checks of an unchanged rig about one is flagged."""

MIN_BLOCK_PX = 16
"""Smallest block side (px): a few camera-blur and footprint widths (about 1-2 px each)."""

BLOCK_CORRELATION_LENGTHS = 8
"""Block side in correlation lengths of the difference: the correlation of side-adjacent block
means through their shared border is about ``c / (sqrt(2 pi) L)`` for a Gaussian correlation of
length ``c`` (0.05 at ``L = 8 c``); what is left of it is estimated from the adjacent blocks."""


def _json_number(v) -> float | None:
    """``v`` for JSON: rounded to 6 digits, None for NaN or infinity."""
    return None if not np.isfinite(v) else round(float(v), 6)


@dataclass
class CommonMode:
    """The mean shift of one axis over the image against its standard error (module docstring).

    Attributes
    ----------
    shift_um : float
        Pixel-weighted mean of the signed difference A - B (µm).
    se_um : float
        Its standard error (µm), from block means (NaN with fewer than 2 blocks).
    t : float
        ``shift_um / se_um``.
    critical : float
        The two-sided Student-t critical value of the axis's false-alarm rate.
    n_blocks : int
    block_px : int
        Side of the square blocks.
    flagged : bool
        ``|t| > critical``.
    """

    shift_um: float
    se_um: float
    t: float
    critical: float
    n_blocks: int
    block_px: int
    flagged: bool

    @classmethod
    def not_assessed(cls, signed: np.ndarray, common: np.ndarray, needed_px: int) -> "CommonMode":
        """The mean shift alone (no standard error, never flagged): the image is too small for blocks
        of ``needed_px`` (:func:`needed_block_side`)."""
        shift = float(np.mean(signed[common])) * 1e3 if common.any() else float("nan")
        return cls(shift, float("nan"), float("nan"), float("nan"), 0, int(needed_px), False)

    @property
    def assessed(self) -> bool:
        return bool(np.isfinite(self.se_um))

    def summary(self) -> dict:
        return {"shift_um": _json_number(self.shift_um), "se_um": _json_number(self.se_um), "t": _json_number(self.t),
                "critical": _json_number(self.critical), "n_blocks": self.n_blocks, "block_px": self.block_px,
                "flagged": bool(self.flagged)}


def pixel_false_alarm_rate(tolerance_sigma: float) -> float:
    """Chance that one pixel of an unchanged rig is beyond ``tolerance_sigma`` predicted sigmas.

    The pixel's difference is Gaussian with at least one degree of freedom when the sigma maps are
    right; with one (the worst case) the chance is ``2 (1 - Phi(k))``, with more it is smaller.
    """
    return float(special.erfc(tolerance_sigma / np.sqrt(2.0)))  # 2 (1 - Phi(k))


def block_side(scale_px: float, shape) -> int:
    """Side (px) of the blocks of the common-mode standard error.

    Parameters
    ----------
    scale_px : float
        The larger smoothing scale (Gaussian sigma, px) of the two LUTs; 0 for per-pixel models.
        The difference of two independently smoothed noise fields is correlated with length
        ``c = sqrt(2) * scale`` (the autocorrelation of Gaussian-smoothed white noise), plus the
        camera's blur (about 1 px).
    shape : (int, int)
        The image's (H, W): at most a quarter of its smaller side, so there are at least 4 x 4 blocks.
    """
    return int(max(1, min(needed_block_side(scale_px), min(shape) // 4)))


def needed_block_side(scale_px: float) -> int:
    """The block side (px) the standard error needs: :data:`BLOCK_CORRELATION_LENGTHS` correlation
    lengths of the difference (``sqrt(2) * scale + 1`` px), at least :data:`MIN_BLOCK_PX`. Where the
    image cannot hold 4 x 4 such blocks, blocks cut smaller are correlated with their neighbours beyond
    what the adjacent-block term corrects and under-estimate the error (std(t) 1.3 at 2.5 correlation
    lengths on simulated noise): the common mode is then not assessed (:meth:`CommonMode.not_assessed`)."""
    c = np.sqrt(2.0) * max(float(scale_px), 0.0) + 1.0
    return max(MIN_BLOCK_PX, int(np.ceil(BLOCK_CORRELATION_LENGTHS * c)))


def common_mode_shift(signed: np.ndarray, common: np.ndarray, block_px: int, false_alarm: float) -> CommonMode:
    """The mean of ``signed`` over ``common`` against its block-mean standard error.

    Parameters
    ----------
    signed : (H, W) float64, mm
        Per-pixel signed difference (mean over the heights).
    common : (H, W) bool
    block_px : int
        Side of the square blocks (:func:`block_side`).
    false_alarm : float
        Two-sided false-alarm rate of this axis.

    Returns
    -------
    CommonMode
    """
    h, w = signed.shape
    rows, cols = -(-h // block_px), -(-w // block_px)
    pad = np.zeros((rows * block_px, cols * block_px))
    cnt = np.zeros_like(pad)
    pad[:h, :w] = np.where(common, signed, 0.0)
    cnt[:h, :w] = common
    sums = pad.reshape(rows, block_px, cols, block_px).sum(axis=(1, 3))
    n = cnt.reshape(rows, block_px, cols, block_px).sum(axis=(1, 3))
    total = n.sum()
    mean = sums.sum() / total
    # Block j's share of the mean's deviation: (n_j / N) (b_j - M) = (sum_j - n_j M) / N.
    e = (sums - n * mean) / total
    used = n > 0
    j = int(used.sum())
    if j < 2:
        return CommonMode(mean * 1e3, np.nan, np.nan, np.nan, j, block_px, False)
    independent = float(np.sum(e * e))
    adjacent = float(np.sum(e[:, 1:] * e[:, :-1]) + np.sum(e[1:, :] * e[:-1, :]))
    var = j / (j - 1) * max(independent, independent + 2.0 * adjacent)
    se = np.sqrt(var)
    t = mean / se if se > 0 else (0.0 if mean == 0 else float(np.copysign(np.inf, mean)))  # identical LUTs: 0
    critical = float(special.stdtrit(j - 1, 1.0 - false_alarm / 2.0))  # Student t's upper quantile
    return CommonMode(mean * 1e3, se * 1e3, float(t), critical, j, block_px, bool(abs(t) > critical))


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
        Neither the per-pixel test (fraction beyond at most ``max_fraction``) nor the common-mode
        test of either axis flags a difference.
    common_x, common_y : CommonMode or None
        The common-mode statistic per axis (None when not computed).
    common_false_alarm : float
        False-alarm rate of the common-mode test, both axes together.
    models : tuple of str
        The two LUTs' models (:func:`ptpcore.fit.models.describe_model`).
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
    common_x: CommonMode | None = None
    common_y: CommonMode | None = None
    common_false_alarm: float = COMMON_FALSE_ALARM
    models: tuple = ("", "")
    height: object | None = None
    """:class:`ptpcore.evaluate.scanner.HeightDiff` when both LUTs have a height map (``/height``)."""

    @property
    def pixels_consistent(self) -> bool:
        """The per-pixel test alone: at most ``max_fraction`` of the pixels beyond the tolerance."""
        return self.fraction_beyond <= self.max_fraction

    @property
    def common_flagged(self) -> bool:
        """The common-mode test flags a mean shift on either axis."""
        return any(c is not None and c.flagged for c in (self.common_x, self.common_y))

    @property
    def like_with_like(self) -> bool:
        """Both LUTs have the same model, degree and smoothing scale."""
        return self.models[0] == self.models[1]

    @property
    def pixel_false_alarm(self) -> float:
        """Per-pixel false-alarm rate of the tolerance (:func:`pixel_false_alarm_rate`)."""
        return pixel_false_alarm_rate(self.tolerance_sigma)

    def verdict_words(self) -> str:
        """``consistent`` or ``DIFFER``, with what flagged it and whether the models match."""
        why = [w for w, on in (("per pixel", not self.pixels_consistent), ("common mode", self.common_flagged),
                               ("height map", self.height is not None and not self.height.consistent)) if on]
        text = "consistent" if self.consistent else f"DIFFER ({', '.join(why)})"
        if not self.like_with_like:
            text += (f"; unlike models ({self.models[0]} vs {self.models[1]}): part of any difference is the"
                     " models', compare LUTs fitted alike")
        return text

    def summary(self) -> dict:
        """The numbers (no maps), for JSON."""
        return {"n_pixels": self.n_pixels, "heights_mm": [round(float(z), 6) for z in self.z],
                "rms_um": _json_number(self.rms_um), "p95_um": _json_number(self.p95_um), "max_um": _json_number(self.max_um),
                "predicted_rms_um": _json_number(self.predicted_rms_um), "ratio": _json_number(self.ratio),
                "fraction_beyond": _json_number(self.fraction_beyond), "tolerance_sigma": self.tolerance_sigma,
                "tolerance_um": self.tolerance_um, "max_fraction": self.max_fraction,
                "pixel_false_alarm_rate": _json_number(self.pixel_false_alarm),
                "pixels_verdict": "consistent" if self.pixels_consistent else "differ",
                "common_mode": {k: c.summary() for k, c in (("x", self.common_x), ("y", self.common_y))
                                if c is not None},
                "common_false_alarm_rate": self.common_false_alarm,
                "common_mode_verdict": "differ" if self.common_flagged else "consistent",
                "models": list(self.models), "like_with_like": self.like_with_like,
                **({"height": self.height.summary()} if self.height is not None else {}),
                "verdict": "consistent" if self.consistent else "differ"}

    def histogram(self, bins: int = 50) -> tuple[np.ndarray, np.ndarray]:
        """Counts (bins,) and edges (bins + 1,) of ``d`` (µm) over the common pixels."""
        d = self.diff[self.common] * 1e3
        return np.histogram(d, bins=bins, range=(0.0, float(np.max(d)) if d.size else 1.0))


def _check(a: Lut, b: Lut, tolerance_sigma: float, tolerance_um: float, max_fraction: float,
           common_false_alarm: float = COMMON_FALSE_ALARM) -> None:
    if a.shape != b.shape:
        raise ValueError(f"the LUTs are of different cameras: {a.shape[1]}x{a.shape[0]} and"
                         f" {b.shape[1]}x{b.shape[0]} px")
    if not (tolerance_sigma > 0 and tolerance_um >= 0 and 0 <= max_fraction <= 1):
        raise ValueError("tolerance-sigma must be > 0, tolerance-um >= 0 and max-fraction within 0..1")
    if not 0 < common_false_alarm < 1:
        raise ValueError(f"common-false-alarm must be within 0..1 (exclusive), not {common_false_alarm:g}")
    if (a.sigma_x is None or b.sigma_x is None) and tolerance_um <= 0:
        raise ValueError("a LUT has no sigma maps (/quality/sigma_x, sigma_y): give --tolerance-um")


def diff_luts(a: Lut, b: Lut, *, tolerance_sigma: float = 3.0, tolerance_um: float = 0.0,
              max_fraction: float = 0.01, n_heights: int = N_HEIGHTS,
              common_false_alarm: float = COMMON_FALSE_ALARM) -> LutDiff:
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
    common_false_alarm : float
        False-alarm rate of the common-mode test (both axes, two-sided); the LUTs also differ when it flags.

    Returns
    -------
    LutDiff

    Raises
    ------
    ValueError
        Different cameras, no common pixels or z range, bad tolerances.
    """
    _check(a, b, tolerance_sigma, tolerance_um, max_fraction, common_false_alarm)
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
    r = _verdict(a, b, z, dx, dy, sx, sy, d, common, tolerance_sigma, tolerance_um, max_fraction)
    scale = max(_smoothing_scale(a), _smoothing_scale(b))
    side, needed = block_side(scale, (h, w)), needed_block_side(scale)
    if side < needed:  # no honest standard error on this image at this smoothing scale
        r.common_x, r.common_y = (CommonMode.not_assessed(m, common, needed) for m in (sx, sy))
    else:
        r.common_x, r.common_y = (common_mode_shift(m, common, side, common_false_alarm / 2.0) for m in (sx, sy))
    r.common_false_alarm = float(common_false_alarm)
    r.models = (describe_model(a), describe_model(b))
    r.consistent = r.pixels_consistent and not r.common_flagged
    if a.height is not None and b.height is not None:
        from ptpcore.evaluate.scanner import diff_height_maps

        r.height = diff_height_maps(a.height, b.height, tolerance_sigma=tolerance_sigma, tolerance_um=tolerance_um,
                                    max_fraction=max_fraction)
        r.consistent = r.consistent and r.height.consistent
    return r


def _smoothing_scale(lut: Lut) -> float:
    """A smooth LUT's smoothing scale (px, Gaussian sigma); 0 for a per-pixel model."""
    try:
        return float(lut.extra_attrs.get("smoothing_scale_px", 0.0)) if lut.extra_attrs else 0.0
    except (TypeError, ValueError):
        return 0.0


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
