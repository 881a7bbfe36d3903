"""Arrays for views: what a GUI or a report draws, computed without any GUI.

Compute and display are separate: these functions return plain numpy arrays
and dataclasses (reason colours, robust colour levels, histograms, one
pixel's curves); ``ptp_studio`` only renders them. Nothing here loops over
pixels in Python, so every function stays fast on 5-12 megapixel maps.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ptpcore.decode.phase import REASON_NAMES, Reason

__all__ = [
    "REASON_ORDER",
    "REASON_COLOURS",
    "VALID_COLOUR",
    "reason_rgba",
    "reason_counts",
    "reason_text",
    "mask_rgba",
    "subsample",
    "DISPLAY_PIXELS",
    "display_step",
    "reduce_for_display",
    "robust_levels",
    "histogram",
    "DisplayMap",
    "prepare_display",
    "ScaledMap",
    "PixelSeries",
    "pixel_series",
    "predicted_signal",
]

# Which reason colours a pixel that has several: the most fundamental first
# (a pixel outside the LCD also has low modulation; that is a consequence).
REASON_ORDER: tuple[int, ...] = (
    Reason.OUTSIDE_LCD,
    Reason.SATURATED,
    Reason.BLACK_CLIPPED,
    Reason.LOW_MODULATION,
    Reason.GRAY_CODE,
    Reason.UNWRAP,
    Reason.BORDER,
    Reason.SPATIAL,
)

# RGBA, 0-255. Distinguishable for the common colour-vision deficiencies
# (Okabe-Ito palette).
REASON_COLOURS: dict[int, tuple[int, int, int, int]] = {
    Reason.OUTSIDE_LCD: (90, 90, 90, 255),
    Reason.SATURATED: (213, 94, 0, 255),
    Reason.LOW_MODULATION: (0, 114, 178, 255),
    Reason.UNWRAP: (204, 121, 167, 255),
    Reason.BORDER: (230, 159, 0, 255),
    Reason.BLACK_CLIPPED: (40, 40, 40, 255),
    Reason.GRAY_CODE: (86, 180, 233, 255),
    Reason.SPATIAL: (240, 228, 66, 255),
}
VALID_COLOUR: tuple[int, int, int, int] = (0, 158, 115, 255)

if set(REASON_ORDER) != set(REASON_NAMES) or set(REASON_COLOURS) != set(REASON_NAMES):
    raise AssertionError("views.REASON_ORDER / REASON_COLOURS must cover every Reason flag")


def _reason_table() -> np.ndarray:
    """(256, 4) uint8: the colour of every possible ``reasons`` byte."""
    table = np.zeros((256, 4), np.uint8)
    table[0] = VALID_COLOUR
    for value in range(1, 256):
        for flag in REASON_ORDER:
            if value & flag:
                table[value] = REASON_COLOURS[flag]
                break
        else:  # bits no Reason defines: magenta, so they are noticed
            table[value] = (255, 0, 255, 255)
    return table


_REASON_TABLE = _reason_table()


def reason_rgba(reasons: np.ndarray) -> np.ndarray:
    """Colour a validity map by rejection reason.

    Parameters
    ----------
    reasons : (H, W) uint8
        :class:`ptpcore.decode.phase.Reason` bit flags; 0 where valid.

    Returns
    -------
    (H, W, 4) uint8
        ``VALID_COLOUR`` where valid, else the colour of the first reason of
        ``REASON_ORDER`` the pixel has.
    """
    reasons = np.asarray(reasons)
    if reasons.dtype != np.uint8:
        raise ValueError(f"reasons must be uint8 bit flags, got {reasons.dtype}")
    return _REASON_TABLE[reasons]


def reason_counts(reasons: np.ndarray) -> dict[int, int]:
    """How many pixels have each reason (a pixel may count under several), and 0 for valid.

    Returns
    -------
    dict
        ``{0: n_valid, Reason.X: n_with_X, ...}`` for every flag of ``REASON_ORDER``.
    """
    counts = np.bincount(np.asarray(reasons, np.uint8).ravel(), minlength=256)
    values = np.arange(256)
    out = {0: int(counts[0])}
    for flag in REASON_ORDER:
        out[flag] = int(counts[(values & flag) != 0].sum())
    return out


def reason_text(value: int) -> str:
    """Every reason of one pixel in words (``"valid"`` for 0)."""
    value = int(value)
    if value == 0:
        return "valid"
    return ", ".join(REASON_NAMES[f] for f in REASON_ORDER if value & f) or f"unknown flags {value}"


def mask_rgba(mask: np.ndarray, colour=(255, 0, 0, 200)) -> np.ndarray:
    """(H, W, 4) uint8 overlay: ``colour`` where ``mask``, transparent elsewhere."""
    mask = np.asarray(mask, bool)
    out = np.zeros((*mask.shape, 4), np.uint8)
    out[mask] = colour
    return out


DISPLAY_PIXELS = 1 << 20
"""A live preview larger than this (about a megapixel: more than a screen shows) is reduced first."""


def display_step(shape, max_pixels: int = DISPLAY_PIXELS) -> int:
    """The smallest whole reduction factor that brings an image of ``shape`` (H, W, ...) to ``max_pixels``.

    1 for images that are small enough.
    """
    h, w = shape[:2]
    step = 1
    while -(-h // step) * -(-w // step) > max_pixels:
        step += 1
    return step


def reduce_for_display(image: np.ndarray, step: int, how: str = "mean") -> np.ndarray:
    """``image`` (H, W) reduced ``step`` times along each side: (ceil(H/step), ceil(W/step)).

    Block ``(i, j)`` is camera rows ``[i step, (i+1) step)`` and columns ``[j step, (j+1) step)``
    (the last ones padded by repeating the edge). ``how="mean"``: the block's mean (OpenCV's
    area interpolation at a whole factor), in the image's dtype; ``how="any"``: whether any
    pixel of the block is set (a bool mask: one saturated pixel stays visible).
    A preview of a 5-12 MP frame drawn at full size costs the GUI thread an image
    pyramid on every frame; reduced here (on the worker thread) it costs nothing.
    """
    a = np.asarray(image)
    if step <= 1:
        return a
    if how not in ("mean", "any"):
        raise ValueError(f"how must be 'mean' or 'any', not {how!r}")
    h, w = a.shape[:2]
    hs, ws = -(-h // step), -(-w // step)
    if (hs * step, ws * step) != (h, w):
        a = np.pad(a, ((0, hs * step - h), (0, ws * step - w)), mode="edge")
    if how == "any":
        return a.reshape(hs, step, ws, step).any(axis=(1, 3))
    import cv2

    return cv2.resize(a, (ws, hs), interpolation=cv2.INTER_AREA)


def subsample(values: np.ndarray, max_samples: int = 250_000) -> np.ndarray:
    """A strided view of ``values`` with at most about ``max_samples`` elements.

    Strides rows and columns alike, so a 2-D map keeps its spatial spread.
    """
    a = np.asarray(values)
    if a.size <= max_samples:
        return a
    step = int(np.ceil(np.sqrt(a.size / max_samples)))
    if a.ndim >= 2:
        return a[::step, ::step]
    return a[:: step * step]


def robust_levels(values: np.ndarray, lower_pct: float = 1.0, upper_pct: float = 99.0,
                  max_samples: int = 250_000) -> tuple[float, float]:
    """Colour levels from percentiles of a subsample, ignoring NaN.

    Parameters
    ----------
    values : array_like
        Any shape (e.g. an (H, W) map).
    lower_pct, upper_pct : float
        Percentiles (0-100) that map to the ends of the colour scale.
    max_samples : int
        Percentiles are taken on a strided subsample of about this size.

    Returns
    -------
    (lo, hi) : floats with ``lo < hi``; ``(0, 1)`` if no finite value exists.
    """
    sub = np.asarray(subsample(values, max_samples), dtype=np.float64)
    sub = sub[np.isfinite(sub)]
    if sub.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(sub, [lower_pct, upper_pct])
    if not hi > lo:
        lo, hi = float(sub.min()), float(sub.max())
        if not hi > lo:
            lo, hi = lo - 0.5, hi + 0.5
    return float(lo), float(hi)


def histogram(values: np.ndarray, levels: tuple[float, float] | None = None, bins: int = 100,
              max_samples: int = 2_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Histogram of the finite values (of a subsample if large).

    Parameters
    ----------
    values : array_like
    levels : (lo, hi), optional
        Range of the bins; default :func:`robust_levels` widened to 0.1-99.9 %.
        Values outside the range are counted in the end bins, so nothing vanishes.
    bins : int
    max_samples : int

    Returns
    -------
    edges : (bins + 1,) float64
    counts : (bins,) int64
    """
    sub = np.asarray(subsample(values, max_samples), dtype=np.float64).ravel()
    sub = sub[np.isfinite(sub)]
    if levels is None:
        levels = robust_levels(sub, 0.1, 99.9, max_samples)
    lo, hi = float(levels[0]), float(levels[1])
    if not hi > lo:
        hi = lo + 1.0
    counts, edges = np.histogram(np.clip(sub, lo, hi), bins=bins, range=(lo, hi))
    return edges, counts


@dataclass
class DisplayMap:
    """A map made ready to draw: reduced to about a screen's pixels, its colour levels and histogram.

    Built by :func:`prepare_display` off the GUI thread: at 5-12 MP the reduction, the levels and
    the histogram cost the GUI thread 0.1-0.3 s a map (issue 15).

    Attributes
    ----------
    image : (ceil(H / step), ceil(W / step)) array
        Block means of the map (:func:`reduce_for_display`); the map itself when ``step`` is 1.
    step : int
        Camera pixels per image pixel along each side.
    extent : (H, W)
        The camera shape the image covers.
    levels : (lo, hi)
        Colour levels, from the full map.
    hist_edges : (bins + 1,) float64
    hist_counts : (bins,) int64
        Histogram of the full map's values (of a subsample, :func:`histogram`).
    """

    image: np.ndarray
    step: int
    extent: tuple[int, int]
    levels: tuple[float, float]
    hist_edges: np.ndarray
    hist_counts: np.ndarray


class ScaledMap:
    """An (H, W) map in other units without a copy: ``base * scale``, computed where it is read.

    The Calibrate page shows the LUT's own maps (mm) in µm: a scaled copy of each was 290 MB at
    12 MP beside the LUT. Indexing gives ``base[index] * scale`` (the very values of the scaled
    copy); ``numpy.asarray`` builds the whole scaled map (for a computation over all of it).

    Parameters
    ----------
    base : (H, W) array
    scale : numpy scalar
        Of the dtype the scaled values should have with ``base`` (``np.float32(1000)`` for mm -> µm).
    """

    def __init__(self, base: np.ndarray, scale):
        self.base, self.scale = base, scale
        self.shape, self.ndim = base.shape, base.ndim
        self.dtype = np.result_type(base.dtype, scale)

    def __getitem__(self, index):
        return self.base[index] * self.scale

    def __array__(self, dtype=None, copy=None):
        out = self.base * self.scale
        return out if dtype is None else out.astype(dtype, copy=False)

    def __len__(self) -> int:
        return len(self.base)


def prepare_display(data: np.ndarray, *, integer: bool = False, levels: tuple[float, float] | None = None,
                    max_pixels: int = DISPLAY_PIXELS, with_histogram: bool = True) -> DisplayMap:
    """Reduce ``data`` (H, W) for display and compute its colour levels and histogram (any thread).

    Parameters
    ----------
    data : (H, W) array
        The map in display units; NaN where it has no value (a block with a NaN shows none).
    integer : bool
        Integer-valued map (counts): levels min - 0.5 .. max + 0.5 and one histogram bin per value
        (at most 200).
    levels : (lo, hi), optional
        Default: :func:`robust_levels` of the full map (min-max for integer maps).
    max_pixels : int
        The reduced image's largest size (:func:`display_step`).
    with_histogram : bool
        Without it the histogram is empty (a view that draws none).
    """
    data = np.asarray(data)
    if data.ndim != 2:
        raise ValueError(f"a map must be (H, W), got shape {data.shape}")
    if levels is None and integer:
        sub = subsample(data)
        finite = sub[np.isfinite(sub)] if sub.dtype.kind == "f" else sub
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        levels = (lo - 0.5, hi + 0.5)
    elif levels is None:
        levels = robust_levels(data)
    if not with_histogram:
        edges, counts = np.zeros(0), np.zeros(0, np.int64)
    elif integer:
        bins = int(max(1, min(round(levels[1] - levels[0]), 200)))
        edges, counts = histogram(data, levels, bins=bins)
    else:
        edges, counts = histogram(data)
    step = display_step(data.shape, max_pixels)
    # OpenCV's area reduction takes 8/16-bit integers and floats: counts and flags as float32 (exact).
    shown = data if step == 1 or data.dtype in (np.float32, np.float64, np.uint8, np.uint16, np.int16) \
        else data.astype(np.float32)
    return DisplayMap(reduce_for_display(shown, step), step, data.shape, (float(levels[0]), float(levels[1])),
                      edges, counts)


@dataclass
class PixelSeries:
    """One camera pixel's samples and fitted LUT curve (all lengths mm).

    Attributes
    ----------
    row, col : int
    z : (K,) float64
        Stage readings of every position.
    x, y : (K,) float64
        The pixel's measured X, Y per position (NaN where invalid).
    reasons : (K,) uint8
    used : (K,) bool
        The sample is valid and its position was used to fit the LUT.
    z_curve : (M,) float64
        Heights over the pixel's calibrated range.
    x_curve, y_curve : (M,) float64
        The LUT's X(z), Y(z) there.
    resid_x, resid_y : (K,) float64
        Sample minus LUT at each valid position (NaN where the LUT has no value).
    lut_valid : bool
    """

    row: int
    col: int
    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    reasons: np.ndarray
    used: np.ndarray
    z_curve: np.ndarray
    x_curve: np.ndarray
    y_curve: np.ndarray
    resid_x: np.ndarray
    resid_y: np.ndarray
    lut_valid: bool


def _pixel_lut(lut, row: int, col: int, n: int):
    """The LUT of one pixel repeated over a (1, n) image, for vectorised evaluation."""
    def rep(a):
        if a is None:
            return None
        a = np.asarray(a)
        if a.ndim == 3:
            return np.repeat(a[:, row:row + 1, col:col + 1], n, axis=2)
        return np.repeat(a[row:row + 1, col:col + 1], n, axis=1)

    return replace(lut, x=rep(lut.x), y=rep(lut.y), valid=rep(lut.valid),
                   n_positions=rep(lut.n_positions), pixel_z_min=rep(lut.pixel_z_min),
                   pixel_z_max=rep(lut.pixel_z_max), rms_x=rep(lut.rms_x), rms_y=rep(lut.rms_y),
                   loo_x=rep(lut.loo_x), loo_y=rep(lut.loo_y), sigma_x=rep(lut.sigma_x),
                   sigma_y=rep(lut.sigma_y))


def pixel_series(lut, samples, row: int, col: int, positions=None, n_curve: int = 200) -> PixelSeries:
    """One pixel's samples, its fitted curve and residuals, for a plot.

    Parameters
    ----------
    lut : ptpcore.io.lutfile.Lut
    samples : ptpcore.io.SampleStack
        The samples the LUT was fitted on (same camera shape).
    row, col : int
        Camera pixel.
    positions : sequence of int, optional
        Positions used for the fit (default all).
    n_curve : int
        Points on the fitted curve.

    Returns
    -------
    PixelSeries
    """
    h, w = samples.shape
    if not (0 <= row < h and 0 <= col < w):
        raise ValueError(f"pixel (row {row}, col {col}) is outside the {w}x{h} camera")
    k = len(samples.z)
    z = np.asarray(samples.z, dtype=np.float64)
    x = samples.x_ref[row, col] + samples.x[:, row, col].astype(np.float64)
    y = samples.y_ref[row, col] + samples.y[:, row, col].astype(np.float64)
    reasons = samples.reasons[:, row, col].copy()
    in_fit = np.zeros(k, bool)
    in_fit[np.arange(k) if positions is None else np.asarray(positions, int)] = True
    used = (reasons == 0) & in_fit
    valid = bool(lut.valid[row, col])
    if valid:
        z_lo, z_hi = float(lut.pixel_z_min[row, col]), float(lut.pixel_z_max[row, col])
        z_curve = np.linspace(z_lo, z_hi, n_curve)
        one = _pixel_lut(lut, row, col, n_curve)
        ev = one.evaluate(z_curve[None, :])
        x_curve, y_curve = ev.x[0], ev.y[0]
        at = _pixel_lut(lut, row, col, k).evaluate(z[None, :])
        resid_x = np.where(reasons == 0, x - at.x[0], np.nan)
        resid_y = np.where(reasons == 0, y - at.y[0], np.nan)
    else:
        z_curve = np.zeros(0)
        x_curve = y_curve = np.zeros(0)
        resid_x = resid_y = np.full(k, np.nan)
    return PixelSeries(int(row), int(col), z, x, y, reasons, used, z_curve, x_curve, y_curve,
                       resid_x, resid_y, valid)


def predicted_signal(rig, settings) -> tuple[np.ndarray, float]:
    """Expected fringe modulation per position and sample noise of a simulated rig.

    A first-order prediction for :func:`ptpcore.decode.patterns.design_check`: the
    LCD's luminance swing through its gamma, the exposure, vignetting at the
    image corner and defocus ignored.

    Parameters
    ----------
    rig : ptpcore.rig.Rig
    settings : ptpcore.simulate.SimSettings

    Returns
    -------
    modulation_dn : (K,) float64, grey levels
    noise_dn : float, grey levels (at the mean level)
    """
    f = rig.fringes
    full = rig.camera.max_level

    def lum(g):
        g = np.clip(g, 0.0, 255.0)
        if f.gamma != 1.0:
            g = 255.0 * (g / 255.0) ** (1.0 / f.gamma)
        return settings.lcd_black + (1 - settings.lcd_black) * (g / 255.0) ** settings.display_gamma

    hi, lo, mid = lum(f.offset + f.amplitude), lum(f.offset - f.amplitude), lum(f.offset)
    scale = settings.exposure * (1.0 - settings.vignetting) * full
    modulation = 0.5 * (hi - lo) * scale
    level = mid * scale + settings.ambient * full
    noise = float(settings.noise_dn(rig.camera, level))
    return np.full(rig.stage.n_positions, modulation), noise
