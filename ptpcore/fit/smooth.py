"""The ``smooth`` LUT: a global camera model plus a per-pixel correction smoothed over the image.

Why: a plain per-pixel LUT is noise-limited (each pixel fits only its own
noisy samples); a pinhole model is bias-limited (it cannot follow a real
lens). Here

1. a pinhole + Brown model (:mod:`ptpcore.pinhole`) is fitted to a large
   random subset of all calibration samples: it carries the bulk of the
   geometry with almost no noise;
2. every pixel fits a polynomial in z to its residuals against that model,
   weighted by each sample's predicted phase noise (from the modulation and
   the camera noise measured in the data, :mod:`ptpcore.decode.noise`);
3. each coefficient map of that correction is smoothed over the image by a
   locally linear, inverse-variance weighted Gaussian regression (built from
   ``scipy.ndimage.gaussian_filter`` moments), so the correction keeps
   non-parametric lens features larger than the smoothing scale;
4. the smoothing scale is chosen by cross-validation on held-out calibration
   positions (the prediction error against measured samples is the true
   error plus the measurement noise, so both have the same minimum).

The result is written as ordinary ``poly`` coefficients per pixel, so
scanners read it unchanged; ``/model`` carries ``method = "smooth"`` and the
chosen scale as extra attributes.

This module also propagates the per-sample phase noise to per-pixel
uncertainty maps ``sigma_x``, ``sigma_y`` for plain and smooth LUTs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import warnings
import weakref

import cv2
import numpy as np

from ptpcore.decode.display import level_bias_at
from ptpcore.io.lutfile import Lut
from ptpcore.fit.perpixel import _z_normalisation, fit_lut
from ptpcore.io.samples import SampleStack
from ptpcore.parallel import map_in_order, release_free_memory
from ptpcore.pinhole.camera import PinholeModel, fit_pinhole
from ptpcore.rig.rigfile import Rig

def _nanmean(a, axis=None):
    """``np.nanmean`` without the all-NaN warning (all-NaN pixels are invalid anyway)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(a, axis=axis)


def _nanmean0(a: np.ndarray) -> np.ndarray:
    """``np.nanmean(a, axis=0)`` (same arithmetic), NaN where all NaN, without warnings (thread-safe)."""
    nan = np.isnan(a)
    cnt = a.shape[0] - nan.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(nan, 0.0, a).sum(axis=0) / cnt


def _remove_level_bias(values: np.ndarray, rig: Rig, axis: str, z, shift=0.0) -> np.ndarray:
    """Absolute world X or Y samples minus the display's level bias (:mod:`ptpcore.decode.display`), in place.

    Parameters
    ----------
    values : (K, n) float64, mm
        Absolute ``X`` (``axis = "x"``) or ``Y`` of ``n`` pixels at the heights ``z`` (K,).
    shift : (n,) float64 or float, mm
        What corrections added to these pixels since decoding (``SampleStack.lcd_shift``).
    """
    d = "xy".index(axis)
    slope, pitch = rig.stage.direction[d], rig.lcd.pitch_mm[d]
    for i, zk in enumerate(np.asarray(z, dtype=float)):
        coord = (values[i] - shift - slope * zk) / pitch  # the decoded LCD coordinate
        values[i] -= level_bias_at(rig.fringes, rig.lcd, axis, zk, coord) * pitch
    return values


def _lcd_shift(samples: SampleStack, axis: int, flat):
    """``samples.lcd_shift[axis]`` at flat pixel indices ``flat`` (0.0 as decoded)."""
    shift = getattr(samples, "lcd_shift", None)
    return 0.0 if shift is None else np.asarray(shift[axis]).reshape(-1)[flat]


def stage_leverage(t: np.ndarray, degree: int) -> float:
    """How a per-position stage error reaches a pixel's fitted value: ``mean_t g(t)' g(t)``.

    A stage reading that is off by ``dz`` at position ``k`` moves every
    pixel's sample by ``(dX/dz - a) dz`` at once, so smoothing over
    neighbouring pixels does not average it away: it passes through each
    pixel's fit in z like an independent error per position. ``g(t)`` are
    the unweighted least-squares weights of the fitted value at ``t``; the
    mean is over ``t`` uniform on the calibrated range.

    Parameters
    ----------
    t : (K,) normalised heights of the calibration positions
    degree : int

    Returns
    -------
    float
        Multiply by ``((dX/dz - a) * sigma_stage)**2`` for the variance (mm^2).
    """
    lo, hi = float(np.min(t)), float(np.max(t))
    pinv = np.linalg.pinv(np.vander(np.asarray(t, float), degree + 1, increasing=True))
    g = np.vander(np.linspace(lo, hi, 257), degree + 1, increasing=True) @ pinv
    return float(np.mean(np.sum(g * g, axis=1)))


__all__ = ["sample_sigma_from_noise", "position_sigma_from_noise", "fit_smooth_lut", "SmoothInfo", "poly_sigma_maps",
           "local_linear_smooth", "global_pinhole"]


def _phase_sigma_mm(samples: SampleStack, rig: Rig, background, modulation) -> np.ndarray:
    """``sqrt(2/N) * sigma(A) / B * T / (2 pi) * pitch`` (mm) for the finest period (METHOD.md section 4)."""
    f = rig.fringes
    with np.errstate(divide="ignore", invalid="ignore"):
        return (np.sqrt(2.0 / f.steps[-1]) * samples.noise.sigma_dn(background)
                / modulation * f.periods_px[-1] / (2 * np.pi) * max(rig.lcd.pitch_mm))


def sample_sigma_from_noise(samples: SampleStack, rig: Rig) -> np.ndarray:
    """Predicted 1-sigma error (mm) of every sample, from the measured camera noise.

    ``sigma_X = sqrt(2/N) * sigma(A) / B * T / (2 pi) * pitch`` for the finest
    period (METHOD.md section 4), with ``sigma(A)`` from ``samples.noise``.
    The stage readings' error is not in it: it is common to every pixel of a
    position (:func:`stage_leverage`, :func:`poly_sigma_maps`).

    Returns
    -------
    (K, H, W) float64, NaN where invalid.
    """
    _check_noise(samples)
    return np.where(samples.valid, _phase_sigma_mm(samples, rig, samples.background, samples.modulation), np.nan)


def position_sigma_from_noise(samples: SampleStack, rig: Rig, k: int) -> np.ndarray:
    """:func:`sample_sigma_from_noise` of position ``k`` alone: (H, W) float64 mm, NaN where invalid.

    Built row block by row block from the position's planes (file reads of a spilled stack), so that
    only the result is a whole map: the whole-position expression held five float64 maps at once
    (500 MB at 12 MP, the wizard's peak in the model choice). The same numbers, pixel by pixel.
    """
    from ptpcore.io.fastio import read_block

    _check_noise(samples)
    h, w = samples.shape
    out = np.empty((h, w))
    for r0 in range(0, h, _SIGMA_ROWS):
        r1 = min(h, r0 + _SIGMA_ROWS)
        s, e, pos = r0 * w, r1 * w, [int(k)]
        valid = read_block(samples.reasons, s, e, pos) == 0
        sig = _phase_sigma_mm(samples, rig, read_block(samples.background, s, e, pos),
                              read_block(samples.modulation, s, e, pos))
        out[r0:r1] = np.where(valid, sig, np.nan).reshape(r1 - r0, w)
    return out


_SIGMA_ROWS = 128
"""Rows per block of :func:`position_sigma_from_noise` (a few MB of temporaries at 4000 px wide)."""


_BLOCK_PIXELS = 1 << 15
"""Pixels per block of the per-pixel passes (fits, residuals, final evaluation)."""

CV_PIXELS = 320_000
"""Above this many pixels the cross-validation runs on a grid binned so it has about this many
points (a 5 MP image: 4 x 4 bins), and the final smoothing at scales of at least 4 bins runs on
the same binned grid (interpolated back bilinearly). Up to 640 x 480 everything is per pixel."""


_STRIP_ROWS = 64
"""Rows per strip of the per-pixel cross-validation on binned (large) images (the folds' maps
hold a strip plus twice the halo: 30 float64 maps of 114 x 2448 px per fold at 5 MP, degree 3)."""


def _bin_factor(shape) -> int:
    """Side of the square bins of the cross-validation grid: 1 up to :data:`CV_PIXELS` pixels."""
    return max(1, int(round(np.sqrt(shape[0] * shape[1] / CV_PIXELS))))


def _row_blocks(h: int, w: int, mult: int = 1) -> list[tuple[int, int]]:
    """Row ranges of about :data:`_BLOCK_PIXELS` pixels, each a multiple of ``mult`` rows (but the last)."""
    rows = max(mult, (_BLOCK_PIXELS // max(w, 1)) // mult * mult)
    return [(r, min(h, r + rows)) for r in range(0, h, rows)]


_BLOCK_SAMPLES = 5 * _BLOCK_PIXELS
"""Samples (positions x pixels) per block of the passes over the samples: their ``(K, n)``
float64 temporaries keep one size whatever the number of positions K (up to 5 positions,
blocks of :data:`_BLOCK_PIXELS` pixels; fewer pixels above)."""


def _sample_blocks(h: int, w: int, k: int) -> list[tuple[int, int]]:
    """Row ranges of about ``_BLOCK_SAMPLES / max(k, 5)`` pixels for ``(K, n)`` sample blocks.

    At least one row each; every pixel's numbers come from its own samples (and, for
    :func:`footprint_bias`, the global rays of the rows next to it), whatever the block.
    """
    rows = max(1, (_BLOCK_SAMPLES // max(k, 5)) // max(w, 1))
    return [(r, min(h, r + rows)) for r in range(0, h, rows)]


def _run_blocks(fn, blocks) -> None:
    """``fn(r0, r1)`` for every block, on the engine's tile pool (results go to disjoint rows)."""
    for _ in map_in_order(lambda b: fn(*b), blocks):
        pass


def _weighted_poly(t: np.ndarray, values_list, weights: np.ndarray, degree: int, full: bool = False):
    """Per-pixel weighted least squares of several value arrays sharing the weights (X and Y).

    The normal equations of every pixel are solved together by Gauss-Jordan
    elimination vectorised over the pixels (symmetric positive definite: no
    pivoting); batched LAPACK calls cost far more than the arithmetic.

    Parameters
    ----------
    t : (K,) ; values_list : list of (K, P) (anything where ``weights == 0``) ; weights : (K, P)

    Returns
    -------
    coefs : list of (D+1, P), NaN where fewer than D+1 samples
    var : (D+1, P) diagonal of the inverse normal matrix (coefficient variances for inverse-variance weights)
    n : (P,) samples used
    cov : (D+1, D+1, P), only with ``full``: the whole inverse normal matrix
    """
    d1 = degree + 1
    p = weights.shape[1]
    used = weights > 0
    n = used.sum(axis=0)
    ok = n >= d1
    tp = t[:, None] ** np.arange(2 * degree + 1)  # (K, 2D+1)
    m = np.einsum("kp,km->mp", weights, tp)
    a = m[np.add.outer(np.arange(d1), np.arange(d1))]  # (D+1, D+1, P)
    inv = np.zeros((d1, d1, p))
    inv[np.arange(d1), np.arange(d1)] = 1.0
    with np.errstate(divide="ignore", invalid="ignore"):
        for i in range(d1):
            piv = a[i, i].copy()
            a[i] /= piv
            inv[i] /= piv
            for r in range(d1):
                if r != i:
                    f = a[r, i].copy()
                    a[r] -= f * a[i]
                    inv[r] -= f * inv[i]
    inv[:, :, ~ok] = np.nan
    coefs = []
    for values in values_list:
        wv = weights * np.where(used, values, 0.0)
        b = np.einsum("kp,kj->jp", wv, tp[:, :d1])
        coefs.append(np.einsum("ijp,jp->ip", inv, b))
    var = inv[np.arange(d1), np.arange(d1)]
    if full:
        return coefs, var, n, inv
    return coefs, var, n


def _range_moments(ta: np.ndarray, tb: np.ndarray, order: int) -> np.ndarray:
    """Mean of ``t**m`` for ``t`` uniform on ``[ta, tb]`` (per pixel), ``m = 0 .. order``.

    Returns
    -------
    (order + 1, *ta.shape) float64; where ``tb == ta`` the value ``ta**m``.
    """
    span = tb - ta
    wide = span > 1e-9
    out = np.empty((order + 1, *np.shape(ta)))
    with np.errstate(all="ignore"):
        for m in range(order + 1):
            out[m] = np.where(wide, (tb ** (m + 1) - ta ** (m + 1)) / ((m + 1) * np.where(wide, span, 1.0)),
                              ta ** m)
    return out


def _gauss(arr: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian filter with zeros outside the image (truncated at 3 sigma).

    OpenCV's separable SIMD filter is used rather than ``scipy.ndimage``: it is
    several times faster at the large scales the cross-validation tries.
    """
    k = 2 * int(np.ceil(3.0 * sigma)) + 1
    return cv2.GaussianBlur(np.ascontiguousarray(arr, dtype=np.float64), (k, k), sigma, sigmaY=sigma,
                            borderType=cv2.BORDER_CONSTANT)


def _first_row_of_inverse(a00, a01, a02, a11, a12, a22):
    """Row 0 of the inverse of symmetric 3x3 matrices given by their six entries, and the determinants.

    Closed-form cofactors: batched LAPACK calls cost far more than the
    arithmetic for millions of 3x3 systems.
    """
    c0 = a11 * a22 - a12 * a12
    c1 = a02 * a12 - a01 * a22
    c2 = a01 * a12 - a02 * a11
    det = a00 * c0 + a01 * c1 + a02 * c2
    with np.errstate(divide="ignore", invalid="ignore"):
        return (c0 / det, c1 / det, c2 / det), det


def _local_moments(s0, sx, sy, sxx, sxy, syy, x, y):
    """Entries (00, 01, 02, 11, 12, 22) of the 3x3 moment matrices about each point from raw weighted moments."""
    mx = sx - x * s0
    my = sy - y * s0
    mxx = sxx - 2 * x * sx + x * x * s0
    myy = syy - 2 * y * sy + y * y * s0
    mxy = sxy - x * sy - y * sx + x * y * s0
    return s0, mx, my, mxx, mxy, myy


def _ll_grid(values: np.ndarray, weights: np.ndarray, sigma: float, xc: np.ndarray, yc: np.ndarray,
             xb=None, yb=None, with_variance: bool = True):
    """Locally linear weighted Gaussian regression on a grid of points (the core of :func:`local_linear_smooth`).

    Parameters
    ----------
    values : (n, h, w) float64 (anything where ``weights == 0``)
    weights : (h, w) float64 >= 0
    sigma : float
        Gaussian sigma in grid steps (> 0).
    xc, yc : (w,), (h,)
        Coordinates of the grid columns and rows, in units of the smoothing scale.
    xb, yb : (h, w), optional
        Where each grid point's datum sits (e.g. the weighted centroid of a bin);
        default the grid point itself.
    with_variance : bool

    Returns
    -------
    out : (n, h, w) the fitted value at every grid point, NaN without support
    var : (h, w) or None
    """
    h, w = weights.shape
    xg = xc[None, :]
    yg = yc[:, None]
    x = xg if xb is None else xb
    y = yg if yb is None else yb
    blocks = _row_blocks(h, w)

    def raw(filt, wv):
        return [filt(wv), filt(wv * x), filt(wv * y), filt(wv * x * x), filt(wv * x * y), filt(wv * y * y)]

    g = lambda arr: _gauss(arr, sigma)  # noqa: E731
    mom = raw(g, weights)
    s0 = mom[0]
    s0_max = max(float(s0.max()), 1e-300)
    row = np.empty((3, h, w))
    good = np.empty((h, w), bool)
    for r0, r1 in blocks:
        a = _local_moments(*[m[r0:r1] for m in mom], xg, yg[r0:r1])
        (c0, c1, c2), det = _first_row_of_inverse(*a)
        row[0, r0:r1], row[1, r0:r1], row[2, r0:r1] = c0, c1, c2
        s0b = s0[r0:r1]
        good[r0:r1] = (s0b > 1e-12 * s0_max) & (np.abs(det) > 1e-12 * np.maximum(s0b, 1e-300) ** 3)
    del mom[1:], a
    weak = ~good & (s0 > 0)
    any_good = bool(good.any())
    out = np.full(values.shape, np.nan)
    for i, v in enumerate(values):
        wv = weights * v
        t0 = g(wv)
        if any_good:
            t1 = g(wv * x)
            t2 = g(wv * y)
            for r0, r1 in blocks:
                tb = t0[r0:r1]
                with np.errstate(invalid="ignore", over="ignore"):  # rows of singular systems: not used
                    est = (row[0, r0:r1] * tb + row[1, r0:r1] * (t1[r0:r1] - xg * tb)
                           + row[2, r0:r1] * (t2[r0:r1] - yg[r0:r1] * tb))
                out[i, r0:r1] = np.where(good[r0:r1], est, np.nan)
            del t1, t2
        # Locally constant estimate where the linear system is singular.
        if weak.any():
            out[i][weak] = t0[weak] / s0[weak]
        del wv, t0
    var = None
    if with_variance:
        var = np.full((h, w), np.nan)
        # var(value_q) = 1 / w_q gives var = (A^-1 B A^-1)[0, 0], B the same
        # moments under G^2, and G_s^2 = G_{s/sqrt2} / (4 pi s^2).
        g2 = lambda arr: _gauss(arr, sigma / np.sqrt(2.0)) / (4 * np.pi * sigma ** 2)  # noqa: E731
        if any_good or weak.any():
            b = raw(g2, weights) if any_good else [g2(weights)]
            for r0, r1 in blocks:
                gb = good[r0:r1]
                if any_good and gb.any():
                    b00, b01, b02, b11, b12, b22 = _local_moments(*[m[r0:r1] for m in b], xg, yg[r0:r1])
                    r_0, r_1, r_2 = row[0, r0:r1], row[1, r0:r1], row[2, r0:r1]
                    with np.errstate(invalid="ignore", over="ignore"):
                        v = (r_0 * (b00 * r_0 + b01 * r_1 + b02 * r_2) + r_1 * (b01 * r_0 + b11 * r_1 + b12 * r_2)
                             + r_2 * (b02 * r_0 + b12 * r_1 + b22 * r_2))
                    var[r0:r1][gb] = v[gb]
                wb = weak[r0:r1]
                if wb.any():
                    var[r0:r1][wb] = b[0][r0:r1][wb] / s0[r0:r1][wb] ** 2
            del b
        var = np.where(np.isfinite(out[0]), var, np.nan)
    return out, var


def local_linear_smooth(values: np.ndarray, weights: np.ndarray, scale_px: float,
                        with_variance: bool = True):
    """Inverse-variance weighted, locally linear Gaussian smoothing of a map.

    At every pixel fits ``a + b*(col - c0) + c*(row - r0)`` to the neighbours
    with weights ``w_q * G(q - p)``; unbiased for linear trends, also at the
    edge of the valid region (where a plain normalised convolution is not).

    Parameters
    ----------
    values : (H, W) or (n, H, W) float64 (anything where ``weights == 0``)
        One map or a stack of maps that share the weights (smoothed together:
        the moment matrices are built once).
    weights : (H, W) float64 >= 0, e.g. inverse variances
    scale_px : float
        Gaussian sigma in camera pixels; 0 returns the input.
    with_variance : bool
        Also compute the variance (costs six more filters).

    Returns
    -------
    smoothed : same shape as ``values``, float64, NaN where there is no support
    variance : (H, W) float64 or None
        Variance of the estimate if ``weights`` are inverse variances.
    """
    if scale_px <= 0:
        with np.errstate(divide="ignore"):
            return np.where(weights > 0, values, np.nan), np.where(weights > 0, 1.0 / weights, np.nan)
    h, w = weights.shape
    weights = np.asarray(weights, dtype=np.float64)
    vals = np.where(weights > 0, values, 0.0)
    stacked = vals.ndim == 3
    vals = vals if stacked else vals[None]
    # Coordinates in units of the scale keep the 3x3 systems well conditioned.
    out, var = _ll_grid(vals, weights, scale_px, np.arange(w) / scale_px, np.arange(h) / scale_px,
                        with_variance=with_variance)
    return (out if stacked else out[0]), var


def _bin(a: np.ndarray, b: int) -> np.ndarray:
    """Sums over ``b x b`` bins of the last two axes (zero-padded up to multiples of ``b``)."""
    if b == 1:
        return a
    h, w = a.shape[-2:]
    hc, wc = -(-h // b), -(-w // b)
    if (hc * b, wc * b) != (h, w):
        pad = np.zeros((*a.shape[:-2], hc * b, wc * b), a.dtype)
        pad[..., :h, :w] = a
        a = pad
    return a.reshape(*a.shape[:-2], hc, b, wc, b).sum(axis=(-3, -1))


def _binned_points(weights: np.ndarray, values: np.ndarray, b: int, r0: int = 0, unweighted_zero: bool = False):
    """Bin ``(n, h, w)`` values with ``(h, w)`` weights into inverse-variance weighted means.

    Returns the bins' summed weights, their weighted-mean values ``(n, hc, wc)``
    (0 where empty) and the weighted centroids (column, row in pixels; the bin
    centre where empty). ``r0``: the image row of the first row (a multiple of ``b``).
    ``unweighted_zero``: values where the weight is not positive count as 0.

    The sums are made in bands of whole bins' rows (:data:`BIN_BAND_PIXELS`): each bin's sum
    is the same reduction of the same numbers, without the weighted maps, the padded copies
    and the centroid products of the whole image (five float64 maps: 480 MB at 12 MP, the
    smooth LUT's peak in the global model's leak variance).
    """
    h, w = weights.shape
    stacked = values.ndim == 3
    vals = values if stacked else values[None]
    hc, wc = -(-h // b), -(-w // b)
    wsum, wx, wy = np.empty((hc, wc)), np.empty((hc, wc)), np.empty((hc, wc))
    binned = np.empty((len(vals), hc, wc))
    cols = np.arange(w, dtype=float)[None, :]
    band = b * max(1, BIN_BAND_PIXELS // (b * w))
    for s0 in range(0, h, band):
        s1 = min(h, s0 + band)
        c0, c1 = s0 // b, -(-s1 // b)
        wt = weights[s0:s1]
        wsum[c0:c1] = _bin(wt, b)
        for i, v in enumerate(vals):  # one map at a time
            v = v[s0:s1]
            binned[i, c0:c1] = _bin(wt * (np.where(wt > 0, v, 0.0) if unweighted_zero else v), b)
        wx[c0:c1] = _bin(wt * cols, b)
        wy[c0:c1] = _bin(wt * np.arange(r0 + s0, r0 + s1, dtype=float)[:, None], b)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(wsum > 0, 1.0 / wsum, 0.0)
        mean = binned * inv
        cx = np.arange(wc) * b + (b - 1) / 2.0
        cy = r0 + np.arange(hc) * b + (b - 1) / 2.0
        xbar = np.where(wsum > 0, wx * inv, cx[None, :])
        ybar = np.where(wsum > 0, wy * inv, cy[:, None])
    return wsum, (mean if stacked else mean[0]), xbar, ybar


def _binned_sigma(scale_px: float, b: int, interpolated: bool) -> float:
    """Gaussian sigma (in bins) on a grid of ``b x b`` bins that smooths like ``scale_px`` per pixel.

    A pixel weighted by the Gaussian at its bin's centre widens the kernel by
    the bin's variance ``(b^2 - 1) / 12``; bilinear interpolation back to the
    pixels adds ``b^2 / 6`` on average (its curvature bias): both are taken off.
    """
    extra = (b * b - 1) / 12.0 + (b * b / 6.0 if interpolated else 0.0)
    return float(np.sqrt(max(scale_px ** 2 - extra, 0.25 * scale_px ** 2))) / b


def _smooth_binned(values: np.ndarray, weights: np.ndarray, scale_px: float, b: int, with_variance: bool = True,
                   out: np.ndarray | None = None):
    """:func:`local_linear_smooth` on a grid of ``b x b`` bins (each bin a point at its weighted centroid,
    with the bin's weighted-mean value and summed weight), interpolated back to every pixel (bilinear).

    Exact for linear trends like the per-pixel version; the Gaussian weight of a
    pixel is taken at its bin's centre. For scales of several bins.
    ``out``: where the smoothed maps go (the shape of ``values``; may be ``values`` itself, which is
    read before it is written). Returns ``(smoothed, variance or None)``.
    """
    if b == 1 or scale_px <= 0:
        smoothed, var = local_linear_smooth(values, np.asarray(weights), scale_px, with_variance)
        if out is None:
            return smoothed, var
        out[...] = smoothed
        return out, var
    h, w = weights.shape
    stacked = values.ndim == 3
    wsum, mean, xbar, ybar = _binned_points(weights, values if stacked else values[None], b, unweighted_zero=True)
    hc, wc = wsum.shape
    cx = (np.arange(wc) * b + (b - 1) / 2.0) / scale_px
    cy = (np.arange(hc) * b + (b - 1) / 2.0) / scale_px
    out_c, var_c = _ll_grid(mean, wsum, _binned_sigma(scale_px, b, True), cx, cy, xbar / scale_px,
                            ybar / scale_px, with_variance)
    if out is None:
        out = np.empty((len(out_c), h, w)) if stacked else np.empty((h, w))
    maps = out if stacked else out[None]
    for i, o in enumerate(out_c):  # into one array: no list of maps beside their stack
        maps[i] = _upsample(o, b, h, w)
    var = None
    if var_c is not None:
        var = _upsample(var_c, b, h, w)
        var[~np.isfinite(maps[0])] = np.nan
    return out, var


def _upsample(coarse: np.ndarray, b: int, h: int, w: int) -> np.ndarray:
    """Bilinear interpolation of a map of ``b x b`` bin centres back to ``(h, w)`` pixels.

    Linearly extrapolated half a bin past the outer centres (exact for planes up
    to the image edge); pixels next to a bin without a value take their own bin's value.
    """
    hc, wc = coarse.shape
    if hc == wc == 1:
        # One bin (the model error's single region): its value everywhere, as the interpolation of a
        # constant gives it, without OpenCV's (3 b)^2 grid (1.15 GB of float64 at 12 MP).
        return np.full((h, w), coarse[0, 0], dtype=np.float64)
    p = np.empty((hc + 2, wc + 2))
    p[1:-1, 1:-1] = coarse
    p[0, 1:-1] = 2 * coarse[0] - coarse[1] if hc > 1 else coarse[0]
    p[-1, 1:-1] = 2 * coarse[-1] - coarse[-2] if hc > 1 else coarse[-1]
    p[:, 0] = 2 * p[:, 1] - p[:, 2] if wc > 1 else p[:, 1]
    p[:, -1] = 2 * p[:, -2] - p[:, -3] if wc > 1 else p[:, -2]
    lin = cv2.resize(p, ((wc + 2) * b, (hc + 2) * b), interpolation=cv2.INTER_LINEAR)[b:b + h, b:b + w]
    # NaN next to an empty bin: the pixel's own bin's value, band by band of rows. A whole map of
    # repeated bins (np.repeat: 100 MB at 12 MP, freshly paged in while holding the GIL) stalled the
    # wizard's event loop for 200 ms.
    for r0 in range(0, h, _UPSAMPLE_ROWS):
        band = lin[r0:r0 + _UPSAMPLE_ROWS]
        bad = np.isnan(band)
        if bad.any():
            c0, c1 = r0 // b, -(-(r0 + len(band)) // b)
            near = np.broadcast_to(coarse[c0:c1, None, :, None], (c1 - c0, b, wc, b)).reshape((c1 - c0) * b, wc * b)
            np.copyto(band, near[r0 - c0 * b:r0 - c0 * b + len(band), :w], where=bad)
    return lin


_UPSAMPLE_ROWS = 256
"""Rows per band of :func:`_upsample`'s nearest-bin fill (a few MB of repeated bins at a time)."""

BIN_BAND_PIXELS = 1 << 20
"""Pixels per band of whole bins' rows in which :func:`_binned_points` sums (8 MB a float64 map)."""


class _GlobalRays:
    """The global model's rays ``X = x0 + sx z``, ``Y = y0 + sy z``: four (H, W) float64 maps read by rows.

    Above :data:`_SPILL_FITS_PIXELS` pixels they wait in a temporary file (:class:`_RowSpill`) and each
    row block reads its rows: at 12 MP the four maps (380 MB) are not held beside the pixel fits
    through the smoothing and every leave-one-out refit. The values are the same either way.
    """

    def __init__(self, model: PinholeModel, shape):
        h, w = self.shape = tuple(shape)
        spill = h * w > _SPILL_FITS_PIXELS
        self._maps = _RowSpill((4, h, w)) if spill else np.empty((4, h, w))

        def block(r0, r1):
            rr, cc = np.mgrid[r0:r1, 0:w].astype(float)
            a0, b0 = model.pixel_to_world_at_z(cc, rr, 0.0)
            a1, b1 = model.pixel_to_world_at_z(cc, rr, 1.0)
            self._maps[:, r0:r1] = np.stack((a0, b0, a1 - a0, b1 - b0))

        _run_blocks(block, _row_blocks(h, w))

    def rows(self, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``x0, y0, sx, sy`` of rows ``[r0, r1)``: four ``(r1 - r0, W)`` maps."""
        m = self._maps
        block = m.row_block(r0, r1) if isinstance(m, _RowSpill) else m[:, r0:r1]
        return tuple(block)

    def window(self, r0: int, r1: int) -> tuple[tuple, int]:
        """The rows :func:`footprint_bias` reads for rows ``[r0, r1)`` (their neighbours, three rows
        at least) and the first one's index: pass ``(rays, r0 - first, r1 - first)`` to it."""
        lo, hi = _laplacian_rows(r0, r1, self.shape[0])
        return self.rows(lo, hi), lo


#: Largest footprint second moment (camera px^2) the correction believes: a blur sigma of 2 px.
#: Ambient light or a camera black level lower the contrast like blur does; this bounds the damage.
FOOTPRINT_M2_MAX_PX2 = 4.0


def _laplacian_rows(r0: int, r1: int, h: int) -> tuple[int, int]:
    """The rows :func:`_laplacian` reads for rows ``[r0, r1)`` of an ``h``-row map: their neighbours,
    three rows at least (they also cover :func:`_gradients`' rows)."""
    return max(min(r0 - 1, h - 3), 0), min(max(r1 + 1, 3), h)


def _laplacian(a: np.ndarray, r0: int, r1: int) -> np.ndarray:
    """Laplacian (per camera px^2) of rows ``[r0, r1)`` of a smooth (H, W) map.

    Second differences at the image's edges repeat the nearest interior one (the block is widened
    to three rows there, so a block of one edge row gives the whole image's value).
    """
    lo, hi = _laplacian_rows(r0, r1, a.shape[0])
    blk = a[lo:hi]
    d2 = np.zeros_like(blk)
    if blk.shape[1] >= 3:
        d2[:, 1:-1] = blk[:, 2:] - 2.0 * blk[:, 1:-1] + blk[:, :-2]
        d2[:, 0], d2[:, -1] = d2[:, 1], d2[:, -2]
    if blk.shape[0] >= 3:
        d2r = np.empty_like(blk)
        d2r[1:-1] = blk[2:] - 2.0 * blk[1:-1] + blk[:-2]
        d2r[0], d2r[-1] = d2r[1], d2r[-2]
        d2 += d2r
    sl = slice(r0 - lo, r0 - lo + (r1 - r0))
    return d2[sl]


def footprint_bias(rays, rig: Rig, z: np.ndarray, modulation: np.ndarray, background: np.ndarray,
                   r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
    """How far each decoded sample sits from its pixel's centre ray: the footprint's curvature term.

    A camera pixel reports the phase averaged over its footprint on the LCD
    (the pixel's square plus the lens blur), i.e. the footprint's centroid,
    not the point its centre ray hits. Where the mapping pixel -> LCD bends
    (lens distortion), the two differ by ``m2 / 2 * laplacian(X)`` with
    ``m2`` the footprint's second moment (camera px^2; 1/12 for the bare
    square). The same footprint lowers the fringe contrast: the finest
    period's contrast ``B / A`` against the displayed ``amplitude / offset``
    is ``exp(-2 pi^2 m2_X / (T pitch)^2)``, which gives ``m2_X`` on the LCD
    (mm^2) and ``m2 = m2_X / |grad X|^2``. The derivatives come from the
    global model (smooth, noise-free). On the presets this removes a
    0.001 LCD px (0.05 um) bias that grows towards the image's edges.

    Parameters
    ----------
    rays : (x0, y0, sx, sy) float64 maps of the global model: the whole image, or rows of it
        (:meth:`_GlobalRays.window`) with ``r0``, ``r1`` counted from their first
    rig : Rig
    z : (K,) heights (mm)
    modulation, background : (K, n) finest-period ``B`` and ``A`` of rows ``[r0, r1)`` (n = rows * W)
    r0, r1 : int

    Returns
    -------
    bias_x, bias_y : (K, n) float64, mm
        To subtract from the samples; 0 where the contrast says nothing.
    """
    f = rig.fringes
    period_mm = f.periods_px[-1] * np.asarray(rig.lcd.pitch_mm, float)
    c0 = f.amplitude / f.offset  # the emitted contrast when the display follows the pre-compensated gamma
    with np.errstate(all="ignore"):
        neg_log = -np.log(np.clip(modulation / background / c0, 0.05, 1.0))  # (K, n)
    out = []
    for a, (x0, slope) in enumerate(((rays[0], rays[2]), (rays[1], rays[3]))):
        # X(z) = x0 + slope z: its Laplacian and gradient are those of the two maps, combined per z.
        lap0 = _laplacian(x0, r0, r1)
        lap1 = _laplacian(slope, r0, r1)
        g0r, g0c = _gradients(x0, r0, r1)
        g1r, g1c = _gradients(slope, r0, r1)
        bias = np.empty_like(neg_log)
        for i, zk in enumerate(np.asarray(z, float)):
            g2 = ((g0r + g1r * zk) ** 2 + (g0c + g1c * zk) ** 2).ravel()
            with np.errstate(all="ignore"):
                m2 = np.minimum(neg_log[i] * period_mm[a] ** 2 / (2.0 * np.pi ** 2) / g2, FOOTPRINT_M2_MAX_PX2)
                bias[i] = 0.5 * m2 * (lap0 + lap1 * zk).ravel()
        out.append(np.nan_to_num(bias, nan=0.0, posinf=0.0, neginf=0.0))
    return out[0], out[1]


def _gradients(a: np.ndarray, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
    """d/drow and d/dcol (per camera px) of rows ``[r0, r1)`` of an (H, W) map (central differences)."""
    lo, hi = max(r0 - 1, 0), min(r1 + 1, a.shape[0])
    blk = a[lo:hi]
    gr = np.gradient(blk, axis=0) if blk.shape[0] >= 2 else np.zeros_like(blk)
    gc = np.gradient(blk, axis=1) if blk.shape[1] >= 2 else np.zeros_like(blk)
    sl = slice(r0 - lo, r0 - lo + (r1 - r0))
    return gr[sl], gc[sl]


def _corrected_absolute(samples: SampleStack, rig: Rig, axis: int, s: int, e: int, sel, z,
                        level_bias: bool, footprint) -> np.ndarray:
    """Absolute X (``axis`` 0) or Y (1) of flat pixels ``[s, e)`` at positions ``sel``, corrected.

    Returns
    -------
    (K, e - s) float64, mm: minus the level bias if ``level_bias``, minus
    ``footprint[axis]`` (from :func:`footprint_bias`) unless it is None.
    """
    from ptpcore.io.fastio import read_block

    name = "xy"[axis]
    values = getattr(samples, f"{name}_ref").reshape(-1)[s:e][None] + read_block(
        getattr(samples, name), s, e, sel).astype(np.float64)
    if level_bias:
        _remove_level_bias(values, rig, name, z, _lcd_shift(samples, axis, slice(s, e)))
    if footprint is not None:
        values -= footprint[axis]
    return values


def _block_samples(samples: SampleStack, rig: Rig, sel, z, r0: int, r1: int, rays,
                   level_bias: bool = False, footprint: bool = False):
    """Rows ``[r0, r1)`` of the chosen positions: validity, sample sigma, weights and residuals to the global model.

    ``rays``: the global model's :class:`_GlobalRays`, or None for validity and sigma only.

    Returns
    -------
    valid : (K, n) bool ; sigma : (K, n) float64 (NaN where invalid) ; wts : (K, n) float64
    (0 where invalid or off the global model) ; resid : (rx, ry) (K, n) float64 or None without ``rays``
    """
    from ptpcore.io.fastio import read_block

    w = samples.shape[1]
    s, e = r0 * w, r1 * w
    valid = read_block(samples.reasons, s, e, sel) == 0
    mod = read_block(samples.modulation, s, e, sel)
    bg = read_block(samples.background, s, e, sel)
    sig = np.where(valid, _phase_sigma_mm(samples, rig, bg, mod), np.nan)
    if rays is None:
        return valid, sig, None, None
    wts = np.where(np.isfinite(sig) & (sig > 0), 1.0 / np.square(sig), 0.0)
    near, lo = rays.window(r0, r1)
    g = [r[r0 - lo:r1 - lo].reshape(-1) for r in near]
    wts[:, ~(np.isfinite(g[0]) & np.isfinite(g[1]))] = 0.0
    fb = footprint_bias(near, rig, z, mod, bg, r0 - lo, r1 - lo) if footprint else None
    resid = [_corrected_absolute(samples, rig, a, s, e, sel, z, level_bias, fb) - (g0[None] + gs[None] * z[:, None])
             for a, (g0, gs) in enumerate(((g[0], g[2]), (g[1], g[3])))]
    return valid, sig, wts, resid


def global_pinhole(samples: SampleStack, positions, n_points: int = 20000, seed: int = 0,
                   rig: Rig | None = None, full: bool = False):
    """Fit the pinhole + Brown model to a random subset of valid calibration samples.

    With ``rig``, the samples lose the display's level bias first (:mod:`ptpcore.decode.display`).
    Returns the :class:`PinholeModel`, or with ``full`` the whole
    :class:`ptpcore.pinhole.camera.PinholeFit` (with its parameter covariance).
    """
    rng = np.random.default_rng(seed)
    h, w = samples.shape
    pts, pix = [], []
    positions = list(positions)
    per = max(n_points // len(positions), 10)
    from ptpcore.io.fastio import read_block

    for k in positions:
        idx = np.flatnonzero(read_block(samples.reasons, 0, h * w, [k])[0] == 0)
        if idx.size == 0:
            continue
        pick = rng.choice(idx, size=min(per, idx.size), replace=False)
        r, c = np.divmod(pick, w)
        x = samples.x_ref.ravel()[pick] + read_block(samples.x, 0, h * w, [k])[0][pick]
        y = samples.y_ref.ravel()[pick] + read_block(samples.y, 0, h * w, [k])[0][pick]
        if rig is not None:
            x = _remove_level_bias(x[None], rig, "x", [samples.z[k]], _lcd_shift(samples, 0, pick))[0]
            y = _remove_level_bias(y[None], rig, "y", [samples.z[k]], _lcd_shift(samples, 1, pick))[0]
        pts.append(np.stack([x, y, np.full(pick.size, samples.z[k])], 1))
        pix.append(np.stack([c, r], 1).astype(float))
    fit = fit_pinhole(np.concatenate(pts), np.concatenate(pix))
    return fit if full else fit.model


@dataclass
class SmoothInfo:
    """How the smooth LUT was made.

    Attributes
    ----------
    pinhole : PinholeModel
        The global model.
    scale_px : float
        Chosen smoothing scale (camera px); 0 means no smoothing.
    scales_px : (S,) candidate scales
    cv_rms_mm : (S,) cross-validated prediction error against held-out samples,
        as mean squared error over each sample's noise variance (chi-square per sample)
    noise_scale : float
        Factor applied to the predicted sample noise (see :func:`sigma_scale`).
    excess_sigma_mm : float
        Model error beyond the noise, measured by cross-validation.
    model_sigma_mm : float
        RMS over the valid pixels of the model-error term in the sigma maps
        (what the smoothing and the global model cannot follow), from the
        leave-one-position-out residuals (:func:`_leave_one_out`); 0 where the data do not resolve it.
    model_limit_mm : float
        The smallest model error the leave-one-out resolves (2 standard errors,
        RMS over the regions): below it the term is left out.
    """

    pinhole: PinholeModel
    scale_px: float
    scales_px: np.ndarray
    cv_rms_mm: np.ndarray
    noise_scale: float = 1.0
    excess_sigma_mm: float = 0.0
    model_sigma_mm: float = 0.0
    model_limit_mm: float = 0.0


def _sigma_scale_from(rms_x, rms_y, n: np.ndarray, mean_var: np.ndarray, degree: int) -> float:
    """:func:`sigma_scale` from the plain fit's residual RMS maps, the valid counts and the mean predicted variance."""
    use = np.isfinite(rms_x) & (n > degree + 1)  # rms is NaN where the plain LUT is invalid
    if not use.any():
        return 1.0
    num = 0.0
    den = 0.0
    for rms in (rms_x, rms_y):
        r = rms.astype(np.float64)
        ok = use & np.isfinite(r) & np.isfinite(mean_var)
        num += float(np.sum(n[ok] * r[ok] ** 2))
        den += float(np.sum((n[ok] - degree - 1) * mean_var[ok]))
    return float(np.sqrt(num / den)) if den > 0 else 1.0


def _check_noise(samples: SampleStack) -> None:
    if samples.noise is None or samples.modulation is None:
        raise ValueError("samples carry no noise model or modulation: decode them with collect_samples()")


def sigma_scale(samples: SampleStack, rig: Rig, positions=None, degree: int = 2) -> float:
    """Factor that makes the predicted sample noise match the fit residuals.

    The per-sample prediction (:func:`sample_sigma_from_noise`) relies on the
    N-step residual variance, which also contains harmonics of a non-linear
    display or camera response (they barely move the phase of an N-step fit).
    Every pixel's own degree-2 fit over z leaves ``n - 3`` degrees of freedom
    whose residuals measure the noise that really reaches X and Y; pooled over
    all pixels they calibrate the prediction:
    ``s^2 = sum_p n_p rms_p^2 / sum_p (n_p - D - 1) mean_k sigma_pk^2``.
    """
    _check_noise(samples)
    positions = list(range(samples.z.size)) if positions is None else list(positions)
    lut = fit_lut(samples, "poly", degree, positions=positions)
    rms_x, rms_y = np.where(lut.valid, lut.rms_x, np.nan), np.where(lut.valid, lut.rms_y, np.nan)
    del lut
    h, w = samples.shape
    n = np.empty((h, w), np.int64)
    mean_var = np.empty((h, w))
    sel = np.asarray(positions)
    z = np.asarray(samples.z, dtype=float)[sel]

    def block(r0, r1):
        valid, sig, _, _ = _block_samples(samples, rig, sel, z, r0, r1, None)
        n[r0:r1] = valid.sum(axis=0).reshape(r1 - r0, w)
        with np.errstate(all="ignore"):
            mean_var[r0:r1] = _nanmean0(sig * sig).reshape(r1 - r0, w)

    _run_blocks(block, _row_blocks(h, w))
    return _sigma_scale_from(rms_x, rms_y, n, mean_var, degree)


def fit_smooth_lut(samples: SampleStack, rig: Rig, degree: int = 2, positions=None, *,
                   scales_px=(0.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0), stage_sigma_mm: float = 0.0,
                   level_bias: bool = True, footprint: bool = True, global_points: int = 100_000,
                   seed: int = 0, rig_toml: str = "", cv_bin: int | None = None,
                   progress: Callable[[float, str], None] | None = None,
                   uncertainty: bool = True) -> tuple[Lut, SmoothInfo]:
    """Fit the ``smooth`` LUT (see the module docstring).

    Parameters
    ----------
    samples : SampleStack
        From :func:`ptpcore.run.pipeline.collect_samples` (needs its noise model).
        File-backed (spilled) stacks are read block by block, never whole.
    rig : Rig
    degree : int
        Degree in z of the correction and of the stored polynomials (1 to 5).
    positions : sequence of int, optional
        Calibration positions (default all).
    scales_px : sequence of float
        Candidate smoothing scales (camera px) for cross-validation.
    stage_sigma_mm : float
        1-sigma error of the stage readings (mm), from the stage's specification.
        It is common to every pixel of a position, so smoothing does not
        reduce it: it is added to the sigma maps through each pixel's fit in z
        (:func:`stage_leverage`) and slope, and left out of the weights.
    level_bias : bool
        Remove the bias that the LCD's integer levels put into the decoded
        coordinates (:mod:`ptpcore.decode.display`) before fitting. Off for a display
        that dithers.
    footprint : bool
        Move every sample from its pixel's footprint centroid to the pixel's
        centre ray (:func:`footprint_bias`, the footprint measured from the
        fringe contrast). Off where ambient light or a camera black level
        lower the contrast (it would be taken for blur).
    global_points : int
        Samples the global model is fitted to (random, all calibration
        positions). Its error varies slowly over the image, where smoothing
        cannot tell it from the lens: on the mild preset 20 000 points leave
        0.047 um at held-out heights, 100 000 (1 s) 0.026 um, 200 000 the same.
    seed : int
        For the global model's random sample.
    cv_bin : int, optional
        Side (px) of the bins the cross-validation runs on; default 1 up to
        :data:`CV_PIXELS` pixels, about ``sqrt(pixels / CV_PIXELS)`` above
        (4 at 5 MP). The final smoothing at a chosen scale of at least 4
        bins also runs on bins (of at most ``scale / 4`` px).
    progress : callable, optional
    uncertainty : bool
        The full sigma maps and the real leave-one-out (:func:`_uncertainty`, ~1.8x the fit's time);
        off for fits judged only by their predictions (auto's candidates): noise-only sigma, NaN LOO.

    Returns
    -------
    lut : Lut
        ``kind = "poly"``, with ``sigma_x``/``sigma_y`` maps.
    info : SmoothInfo
    """
    if not 1 <= degree <= 5:
        raise ValueError(f"smooth degree must be 1 to 5, got {degree}")
    positions = list(range(samples.z.size)) if positions is None else list(positions)
    if len(positions) < degree + 2:
        raise ValueError(f"smooth LUT of degree {degree} needs at least {degree + 2} positions, got {len(positions)}")
    _check_noise(samples)
    report = progress or (lambda f, m: None)
    report(0.0, "fitting the global camera model")
    gfit = global_pinhole(samples, positions, n_points=global_points, seed=seed,
                          rig=rig if level_bias else None, full=True)
    sel = np.asarray(positions)
    z = np.asarray(samples.z, dtype=float)[sel]
    zc, zs = _z_normalisation(z)
    # The plain degree-2 fit that calibrates the predicted noise (sigma_scale): its residual RMS only.
    report(0.02, "calibrating the noise prediction")
    plain = fit_lut(samples, "poly", 2, positions=positions)
    rms_x = np.where(plain.valid, plain.rms_x, np.float32(np.nan))
    rms_y = np.where(plain.valid, plain.rms_y, np.float32(np.nan))
    del plain
    rays = _GlobalRays(gfit.model, samples.shape)

    run = _SmoothPass(samples, rig, sel, z, (zc, zs), rays, degree, scales_px, cv_bin, level_bias, footprint)
    report(0.05, "fitting every pixel and cross-validating")
    run.fit_and_cross_validate_fine(report)
    fits = run.fits
    noise_scale = _sigma_scale_from(rms_x, rms_y, fits.n_pos, fits.mean_var, 2)
    rms_x = rms_y = fits.mean_var = None
    run.cross_validate_coarse(report)
    scale, cv_score, excess_var = run.choose_scale(noise_scale)

    report(0.9, f"fitting the smooth LUT at scale {scale:g} px")
    t, b = run.t, run.b
    run = rays = None  # the pass's maps and the global rays (160 MB at 5 MP; in a file above 0.3 MP) not held
    fits.load("fit")  # fits.var stays in its file, a plane at a time (150 MB at 5 MP and degree 3)
    leak_w = _smoothing_weights(fits, 2)  # before the smoothing changes fits.var in place
    coef, rays = _smoothed_coefficients(fits, scale, b, lambda: _GlobalRays(gfit.model, samples.shape), zc, zs)
    stage_var = _stage_variance(rays, rig, t, degree, stage_sigma_mm)
    d1 = degree + 1
    # A pixel needs its own data to pin its curve in z (at least D+1 positions): with fewer, its
    # polynomial would come from neighbours seen over other heights (4 um off on the rough preset).
    valid = np.isfinite(coef["x"]).all(axis=0) & np.isfinite(coef["y"]).all(axis=0) & (fits.n_pos >= d1)
    fits.pz_min[~valid] = np.nan
    fits.pz_max[~valid] = np.nan
    q = _residual_maps(samples, rig, sel, z, t, coef, rays, level_bias, footprint)
    setup = _LooSetup(samples, rig, sel, z, (zc, zs), rays, degree, scale, b, level_bias, footprint, noise_scale)
    rays = None
    fits.load("own_var", "own_diag")
    noise = _smooth_sigma_maps(fits, zc, zs, degree, noise_scale, {})["x"]
    fits.var = fits.own_var = fits.own_diag = None
    # What only the uncertainty needs goes in with it (released there once used); the LUT's
    # coefficients wait in a file while its leave-one-out runs: 440 MB at 5 MP and degree 3.
    inputs = {"leak_w": leak_w, "noise": noise}
    leak_w = noise = coef = None
    fits.park("fit")
    release_free_memory()  # the pass's freed heap, before the uncertainty's peak (the leak variance)
    sig, loo, merr = _uncertainty(setup, gfit, inputs, fits, valid, stage_var, uncertainty, report)
    fits.load("fit")
    coef = {"x": fits.fit[0], "y": fits.fit[1]}
    lut = _assemble_lut(degree, (zc, zs), z, coef, valid, fits, q, loo, sig, rig_toml, scale)
    report(1.0, "smooth LUT fitted")
    return lut, SmoothInfo(gfit.model, scale, np.asarray(scales_px, dtype=float), cv_score, noise_scale,
                           float(np.sqrt(excess_var)), merr.rms_mm, merr.limit_mm)


def _assemble_lut(degree: int, z_norm, z, coef: dict, valid, fits: "_PixelFits", q: dict, loo: dict, sig: dict,
                  rig_toml: str, scale: float) -> Lut:
    """The smooth LUT from its maps, NaN at the pixels that are not ``valid`` ((H, W) bool)."""
    for a in "xy":
        coef[a][:, ~valid] = np.nan
        for maps in (sig, q, loo):
            maps[a][~valid] = np.nan
    return Lut(
        kind="poly", degree=degree, z_center=z_norm[0], z_scale=z_norm[1], z_min=float(z.min()), z_max=float(z.max()),
        x=coef["x"], y=coef["y"], z_nodes=None, valid=valid,
        n_positions=np.where(valid, fits.n_pos, 0).astype(np.uint16),
        pixel_z_min=fits.pz_min, pixel_z_max=fits.pz_max,
        rms_x=q["x"], rms_y=q["y"], loo_x=loo["x"], loo_y=loo["y"],
        sigma_x=sig["x"], sigma_y=sig["y"], rig_toml=rig_toml,
        extra_attrs={"method": "smooth", "smoothing_scale_px": scale},
    )


@dataclass
class _PixelFits:
    """Every pixel's own weighted fit of its residuals to the global model (all calibration positions).

    Attributes
    ----------
    fit : (2, D+1, H, W) float64, mm
        X and Y coefficients in ``t`` (lowest power first).
    var : (D+1, H, W) float64
        Their variances per unit sample variance (uncorrelated form).
    n_pos : (H, W) int32
        Valid calibration positions per pixel.
    pz_min, pz_max : (H, W) float32, mm
        The pixel's calibrated range.
    mean_var : (H, W) float64, mm^2
        Mean predicted sample variance (for :func:`_sigma_scale_from`).
    own_var, own_diag : (H, W) float64
        The fit's variance averaged over the pixel's own range, with the
        covariances and with the coefficients taken as uncorrelated.
    """

    fit: np.ndarray
    var: np.ndarray
    n_pos: np.ndarray
    pz_min: np.ndarray
    pz_max: np.ndarray
    mean_var: np.ndarray
    own_var: np.ndarray
    own_diag: np.ndarray

    @classmethod
    def empty(cls, shape, d1: int, spill: bool = False, own: bool = True) -> "_PixelFits":
        """Uninitialised maps; with ``spill``, ``fit``, ``var``, ``own_var`` and ``own_diag`` are
        :class:`_RowSpill` files (written by row ranges, :meth:`load` brings them back). Without
        ``own``, ``mean_var``, ``own_var`` and ``own_diag`` are None (not computed)."""
        h, w = shape
        big = _RowSpill if spill else (lambda s: np.empty(s))
        return cls(big((2, d1, h, w)), big((d1, h, w)), np.empty((h, w), np.int32),
                   np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w)) if own else None,
                   big((h, w)) if own else None, big((h, w)) if own else None)

    def park(self, name: str) -> None:
        """Map ``name`` to a temporary file until :meth:`load`, above :data:`_SPILL_FITS_PIXELS` pixels."""
        a = getattr(self, name)
        if isinstance(a, np.ndarray) and a.shape[-2] * a.shape[-1] > _SPILL_FITS_PIXELS:
            setattr(self, name, _RowSpill.park(a))

    def load(self, *names: str) -> None:
        """Bring the spilled maps ``names`` back into memory (no-op for maps already there)."""
        for name in names:
            a = getattr(self, name)
            if isinstance(a, _RowSpill):
                setattr(self, name, a.load())


_SPILL_FITS_PIXELS = CV_PIXELS
"""Above this many pixels the smooth pass writes the pixel fits to a temporary file while it
runs (at 5 MP and degree 3: 560 MB of float64 maps not held beside the folds' statistics)."""


class _RowSpill:
    """A float64 ``(*lead, H, W)`` array in a temporary file, written by row ranges.

    Plain file reads and writes (no memory map; one at a time, under a lock), so its pages stay out of the
    process's resident memory; writes of disjoint rows may come from several threads.
    The file is in ``PTP_SPILL_DIR`` (default the system's temporary folder) and
    disappears when closed.
    """

    def __init__(self, shape):
        import os
        import tempfile
        import threading

        self.shape = tuple(int(n) for n in shape)
        self._row_bytes = self.shape[-1] * 8
        self._plane = self.shape[-2] * self._row_bytes
        self._file = tempfile.TemporaryFile(prefix="ptp-fits-", dir=os.environ.get("PTP_SPILL_DIR") or None)
        self._file.truncate(int(np.prod(self.shape)) * 8)
        self._lock = threading.Lock()
        # A spill dropped unread closes its file when collected, without a ResourceWarning
        # ("unclosed file" at the end of `ptp calibrate`, when the refits' own_var, own_diag were spilled).
        self.close = weakref.finalize(self, self._file.close)

    def __setitem__(self, key, values) -> None:
        """``spill[i, ..., r0:r1] = values``: leading indices (int or ``:``), then a row slice."""
        import itertools

        key = key if isinstance(key, tuple) else (key,)
        lead, rows = key[:-1], key[-1]
        nlead = len(self.shape) - 2
        lead = lead + (slice(None),) * (nlead - len(lead))
        r0, r1, _ = rows.indices(self.shape[-2])
        ranges = [[k] if isinstance(k, (int, np.integer)) else range(*k.indices(n)) for k, n in zip(lead, self.shape)]
        sel_shape = tuple(len(r) for k, r in zip(lead, ranges) if not isinstance(k, (int, np.integer)))
        vals = np.broadcast_to(np.asarray(values, dtype=np.float64), sel_shape + (r1 - r0, self.shape[-1]))
        vals = vals.reshape(-1, r1 - r0, self.shape[-1])
        for i, idx in enumerate(itertools.product(*ranges)):
            plane = int(np.ravel_multi_index(idx, self.shape[:-2])) if idx else 0
            data = np.ascontiguousarray(vals[i])
            with self._lock:
                self._file.seek(plane * self._plane + r0 * self._row_bytes)
                self._file.write(data.data.cast("B"))

    def plane(self, index: int) -> np.ndarray:
        """One ``(H, W)`` plane (flat index over the leading axes), read into memory."""
        return self._read(int(index) * self._plane, np.empty(self.shape[-2:]))

    def rows(self, index: int, r0: int, r1: int) -> np.ndarray:
        """Rows ``[r0, r1)`` of one plane (flat index over the leading axes): ``(r1 - r0, W)``, read into memory."""
        return self._read(int(index) * self._plane + int(r0) * self._row_bytes, np.empty((r1 - r0, self.shape[-1])))

    def row_block(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``[r0, r1)`` of every plane: ``(*lead, r1 - r0, W)``, read into memory."""
        n = int(np.prod(self.shape[:-2]))
        out = np.stack([self.rows(i, r0, r1) for i in range(n)]) if n else np.empty((0, r1 - r0, self.shape[-1]))
        return out.reshape(*self.shape[:-2], r1 - r0, self.shape[-1])

    def plane_rows(self, index: int) -> "_PlaneRows":
        """One plane as a read-only ``(H, W)`` map whose row slices are read from the file."""
        return _PlaneRows(self, int(index))

    def _read(self, offset: int, out: np.ndarray) -> np.ndarray:
        buf, done = out.data.cast("B"), 0
        with self._lock:
            self._file.seek(offset)
            while done < len(buf):
                n = self._file.readinto(buf[done:])
                if not n:
                    raise OSError("the pixel fits' temporary file ended early")
                done += n
        return out

    @classmethod
    def park(cls, array: np.ndarray) -> "_RowSpill":
        """A copy of a float64 ``(*lead, H, W)`` array in a new spill (:meth:`load` brings it back)."""
        spill = cls(array.shape)
        spill[(slice(None),) * (array.ndim - 2) + (slice(0, array.shape[-2]),)] = array
        return spill

    def load(self) -> np.ndarray:
        """The whole array, read into memory; the file is closed."""
        out = self._read(0, np.empty(self.shape))
        self.close()
        return out


class _SmoothPass:
    """One pass over the samples, in strips of rows, and the smoothing scale's cross-validation.

    Every pixel gets its own weighted fit of its residuals to the global model
    (:class:`_PixelFits`, all positions); for each of two folds of alternate
    positions (each keeps the z range covered by the other) the training fit
    and the test samples' sufficient statistics, so that the squared error of
    any prediction ``c`` is ``c'Mc - 2c'B + R``: per pixel over the strip for
    fine scales, on bins for coarse ones. With few positions the folds fit a
    lower degree in z (the scale that suits the image-wide field barely
    depends on it); with fewer than 4 positions no scale can be validated.
    """

    def __init__(self, samples: SampleStack, rig: Rig, sel, z: np.ndarray, z_norm, rays, degree: int,
                 scales_px, cv_bin, level_bias: bool, footprint: bool, cross_validate: bool = True,
                 own: bool = True):
        self.samples, self.rig, self.sel, self.z, self.rays = samples, rig, sel, z, rays
        self.level_bias, self.footprint = level_bias, footprint
        self.zc, self.zs = z_norm
        self.t = (z - self.zc) / self.zs
        self.degree, self.d1 = degree, degree + 1
        h, w = self.shape = samples.shape
        k = z.size
        self.scales = np.asarray(scales_px, dtype=float)
        self.cv_degree = min(degree, k // 2 - 1)
        self.dc = self.cv_degree + 1
        self.folds = [np.arange(k) % 2 == f for f in (0, 1)] if self.cv_degree >= 1 and cross_validate else []
        if not self.folds and cross_validate:
            warnings.warn(f"smooth LUT: {k} calibration positions are too few to cross-validate the smoothing"
                          " scale (need 4); the correction is not smoothed", RuntimeWarning, stacklevel=3)
        b = self.b = int(cv_bin) if cv_bin else _bin_factor(self.shape)
        self.hc, self.wc = -(-h // b), -(-w // b)
        # Scales of fewer than 4 bins are cross-validated per pixel (in strips of rows
        # with a halo the Gaussian cannot see past), larger ones on the binned grid.
        scales = self.scales
        self.fine = np.flatnonzero(scales < 4 * b) if b > 1 else np.arange(scales.size)
        self.coarse = np.flatnonzero(scales >= 4 * b) if b > 1 else np.arange(0)
        self.halo = 0 if b == 1 else int(np.ceil(3.0 * max(scales[self.fine].max(initial=0.0), 0.0))) + 1
        self.strip = h if b == 1 else max(b, (_STRIP_ROWS // b) * b)
        # Sums over test samples, per scale: sum w (v.c - r)^2, samples, sum w.
        self.q_sum = np.zeros(scales.size)
        self.n_sum = np.zeros(scales.size)
        self.w_sum = np.zeros(scales.size)
        # The leave-one-out refits need the pixel fits only, not their own-range variances (own=False:
        # a fifth of each refit's time at 5 MP went to moments that were thrown away).
        self.own = own
        self.fits = _PixelFits.empty(self.shape, self.d1, spill=h * w > _SPILL_FITS_PIXELS, own=own)
        dc, hc, wc = self.dc, self.hc, self.wc
        self.binned = [{"w": np.zeros((dc, hc, wc)), "mean": np.zeros((2, dc, hc, wc)),
                        "xbar": np.zeros((dc, hc, wc)), "ybar": np.zeros((dc, hc, wc)),
                        "m": np.zeros((2 * self.cv_degree + 1, hc, wc)), "b": np.zeros((2, dc, hc, wc)),
                        "r": np.zeros((2, hc, wc)), "n": np.zeros((hc, wc))}
                       for _ in self.folds] if self.coarse.size else []

    def fold_maps(self, rows: int) -> dict:
        """A fold's per-pixel training fit and test statistics for ``rows`` rows."""
        dc, w = self.dc, self.shape[1]
        return {"w": np.zeros((dc, rows, w)), "mean": np.zeros((2, dc, rows, w)),
                "m": np.zeros((2 * self.cv_degree + 1, rows, w)), "b": np.zeros((2, dc, rows, w)),
                "r": np.zeros((2, rows, w)), "n": np.zeros((rows, w))}

    def block(self, r0: int, r1: int, a0: int, fmaps, final: bool) -> None:
        """Rows [r0, r1): the pixel fits if ``final``, the folds' maps at rows ``r - a0`` of ``fmaps``."""
        valid, sig, wts, (rx, ry) = _block_samples(self.samples, self.rig, self.sel, self.z, r0, r1, self.rays,
                                                   self.level_bias, self.footprint)
        if final:
            self._pixel_fits(r0, r1, valid, sig, wts, rx, ry)
        del sig, valid
        for test, st in zip(self.folds, fmaps):
            self._fold_statistics(st, test, r0 - a0, r1 - a0, wts, rx, ry)

    def _pixel_fits(self, r0, r1, valid, sig, wts, rx, ry) -> None:
        f, degree, d1 = self.fits, self.degree, self.d1
        rows, w = r1 - r0, self.shape[1]
        z = self.z
        f.n_pos[r0:r1] = valid.sum(axis=0).reshape(rows, w)
        zk = np.broadcast_to(z[:, None], valid.shape)
        f.pz_min[r0:r1] = np.min(np.where(valid, zk, np.inf), axis=0).reshape(rows, w)
        f.pz_max[r0:r1] = np.max(np.where(valid, zk, -np.inf), axis=0).reshape(rows, w)
        del zk
        (cx, cy), v, _, cov = _weighted_poly(self.t, [rx, ry], wts, degree, full=True)
        f.fit[0, :, r0:r1] = cx.reshape(d1, rows, w)
        f.fit[1, :, r0:r1] = cy.reshape(d1, rows, w)
        f.var[:, r0:r1] = v.reshape(d1, rows, w)
        if not self.own:
            return
        with np.errstate(all="ignore"):
            f.mean_var[r0:r1] = _nanmean0(sig * sig).reshape(rows, w)
        # The pixel's own fit's variance, averaged over its own calibrated
        # range, with the covariances (a pixel seen at a few positions at
        # one end of the range has strongly correlated coefficients).
        zc, zs = self.zc, self.zs
        mom = _range_moments(((f.pz_min[r0:r1] - zc) / zs).ravel().astype(np.float64),
                             ((f.pz_max[r0:r1] - zc) / zs).ravel().astype(np.float64), 2 * degree)
        idx = np.add.outer(np.arange(d1), np.arange(d1))
        f.own_var[r0:r1] = np.einsum("ijp,ijp->p", cov, mom[idx]).reshape(rows, w)
        f.own_diag[r0:r1] = np.einsum("jp,jp->p", v, mom[2 * np.arange(d1)]).reshape(rows, w)

    def _fold_statistics(self, st: dict, test, s0: int, s1: int, wts, rx, ry) -> None:
        """One fold's training fit and test statistics at rows ``s0:s1`` of its maps ``st``."""
        rows, w = s1 - s0, self.shape[1]
        dc, cv_degree, t = self.dc, self.cv_degree, self.t
        train = ~test
        (fx, fy), fv, _ = _weighted_poly(t[train], [rx[train], ry[train]], wts[train], cv_degree)
        for j in range(dc):
            both = np.stack([fx[j], fy[j]]).reshape(2, rows, w)
            with np.errstate(divide="ignore", invalid="ignore"):
                wj = np.where(np.isfinite(both).all(axis=0) & (fv[j] > 0).reshape(rows, w),
                              1.0 / fv[j].reshape(rows, w), 0.0)
            st["w"][j, s0:s1] = wj
            st["mean"][:, j, s0:s1] = np.where(wj > 0, both, 0.0)
        wt = wts[test]
        tp = t[test][:, None] ** np.arange(2 * cv_degree + 1)
        st["m"][:, s0:s1] = np.einsum("kp,km->mp", wt, tp).reshape(-1, rows, w)
        st["n"][s0:s1] = (wt > 0).sum(axis=0).reshape(rows, w)
        for a, r in enumerate((rx[test], ry[test])):
            wr = wt * np.where(wt > 0, r, 0.0)
            st["b"][a, :, s0:s1] = np.einsum("kp,kj->jp", wr, tp[:, :dc]).reshape(dc, rows, w)
            st["r"][a, s0:s1] = (wr * np.where(wt > 0, r, 0.0)).sum(axis=0).reshape(rows, w)

    def score(self, st: dict, c: np.ndarray, sl, acc_index: int) -> None:
        """Add the test error of predictions ``c`` (2, dc, rows, cols) at rows ``sl`` of the stats ``st``."""
        dc = self.dc
        for a in range(2):
            ca = c[a]
            use = np.isfinite(ca).all(axis=0)
            cu = ca[:, use]
            m = st["m"][:, sl][:, use]
            # Sum over the test samples of w (v.c - r)^2: a chi-square-like score.
            quad = st["r"][a][sl][use] - 2 * np.einsum("jp,jp->p", cu, st["b"][a][:, sl][:, use])
            for i in range(dc):
                for j in range(dc):
                    quad += m[i + j] * cu[i] * cu[j]
            self.q_sum[acc_index] += np.sum(quad)
            self.n_sum[acc_index] += np.sum(st["n"][sl][use])
            self.w_sum[acc_index] += np.sum(m[0])

    def fit_and_cross_validate_fine(self, report) -> None:
        """The pass over the samples, strip by strip: pixel fits, fine scales scored, coarse stats binned.

        The folds' maps are a window sliding down the image: a strip's rows plus a halo above and
        below (which only feeds the folds' smoothing); every row is read and fitted once, and the
        rows the next strip shares with this one are moved to the window's top.
        """
        h, w = self.shape
        halo, k = self.halo, self.sel.size
        strips = [(r, min(h, r + self.strip)) for r in range(0, h, self.strip)]
        window = [self.fold_maps(min(h, self.strip + 2 * halo)) for _ in self.folds]
        a0 = done = 0  # the window holds image rows [a0, done)
        for i_strip, (r0, r1) in enumerate(strips):
            n0, a1 = max(0, r0 - halo), min(h, r1 + halo)
            if n0 > a0:
                for st in window:
                    for arr in st.values():
                        arr[..., :done - n0, :] = arr[..., n0 - a0:done - a0, :]
                a0 = n0
            jobs = [(p0 + done, p1 + done) for p0, p1 in _sample_blocks(a1 - done, w, k)]
            _run_blocks(lambda p0, p1: self.block(p0, p1, a0, window, True), jobs)
            done = a1
            inner = slice(r0 - a0, r1 - a0)
            for fi, full in enumerate(window):
                st = {name: arr[..., :a1 - a0, :] for name, arr in full.items()}
                self._score_fine(st, inner, a0, a1, r0, r1,
                                 lambda sc: report(0.05 + 0.7 * i_strip / len(strips),
                                                   f"cross-validating smoothing scale {sc:g} px"))
                if self.coarse.size:
                    self._bin_strip(self.binned[fi], st, inner, r0, r1)
        window = None

    def _score_fine(self, st: dict, inner: slice, a0: int, a1: int, r0: int, r1: int, announce) -> None:
        w, dc = self.shape[1], self.dc
        xs = np.arange(w, dtype=float)
        ys = np.arange(a0, a1, dtype=float)
        for si in self.fine:
            sc = self.scales[si]
            announce(sc)
            c = np.empty((2, dc, r1 - r0, w))
            for j in range(dc):
                if sc <= 0:
                    c[:, j] = np.where(st["w"][j, inner] > 0, st["mean"][:, j, inner], np.nan)
                else:
                    c[:, j] = _ll_grid(st["mean"][:, j], st["w"][j], sc, xs / sc, ys / sc,
                                       with_variance=False)[0][:, inner]
            self.score(st, c, inner, si)

    def _bin_strip(self, bn: dict, st: dict, inner: slice, r0: int, r1: int) -> None:
        """A strip's fold statistics, added to the fold's binned grid."""
        b = self.b
        c0, c1 = r0 // b, -(-r1 // b)
        for j in range(self.dc):
            ws, mean, xb, yb = _binned_points(st["w"][j, inner], st["mean"][:, j, inner], b, r0)
            bn["w"][j, c0:c1], bn["mean"][:, j, c0:c1], bn["xbar"][j, c0:c1], bn["ybar"][j, c0:c1] = \
                ws, mean, xb, yb
        for name in ("m", "b", "r", "n"):
            bn[name][..., c0:c1, :] = _bin(st[name][..., inner, :], b)

    def cross_validate_coarse(self, report) -> None:
        """Score the coarse scales on the folds' binned grids."""
        b, dc = self.b, self.dc
        xg = np.arange(self.wc) * b + (b - 1) / 2.0
        yg = np.arange(self.hc) * b + (b - 1) / 2.0
        coarse = self.coarse
        for fi, bn in enumerate(self.binned):
            for ci, si in enumerate(coarse):
                sc = self.scales[si]
                report(0.75 + 0.15 * (fi * coarse.size + ci) / (len(self.folds) * coarse.size),
                       f"cross-validating smoothing scale {sc:g} px (on {b} x {b} px bins)")
                c = np.empty((2, dc, self.hc, self.wc))
                for j in range(dc):
                    c[:, j] = _ll_grid(bn["mean"][:, j], bn["w"][j], _binned_sigma(sc, b, False), xg / sc, yg / sc,
                                       bn["xbar"][j] / sc,
                                       bn["ybar"][j] / sc, False)[0]
                self.score(bn, c, slice(None), si)
        self.binned = None

    def choose_scale(self, noise_scale: float) -> tuple[float, np.ndarray, float]:
        """The scale of least test error, its score per scale and the excess variance beyond the noise.

        Returns
        -------
        scale : float, px
        cv_score : (S,) float64
            Chi-square per test sample (1 = prediction as good as the noise allows); NaN without folds.
        excess_var : float, mm^2
            Inverse-variance weighted excess of the error over the sample noise: the
            fold fit's own noise plus its bias (an upper bound on the final fit's
            model error, which uses twice the data).
        """
        q_sum, n_sum, w_sum = self.q_sum, self.n_sum, self.w_sum
        excess = q_sum - noise_scale ** 2 * n_sum
        if not self.folds:
            return float(self.scales[0]), np.full(self.scales.size, np.nan), 0.0
        score_ = np.where(n_sum > 0, q_sum / np.maximum(n_sum, 1), np.nan)
        best = int(np.nanargmin(score_))
        excess_var = max(excess[best] / w_sum[best], 0.0) if w_sum[best] > 0 else 0.0
        return float(self.scales[best]), score_, excess_var


def _smoothed_coefficients(fits: _PixelFits, scale: float, b: int, rays, zc: float, zs: float,
                           variance: bool = True) -> tuple[dict, tuple]:
    """The pixel fits smoothed at ``scale`` plus the global ray: ``{"x", "y"}`` (D+1, H, W) coefficients in t,
    and the global rays used.

    Smooths ``fits.fit`` and ``fits.var`` in place (the final smoothing runs on bins of at
    most the cross-validation's side and at most a quarter of the scale); a spilled ``fit`` is
    brought back first, a spilled ``var`` is read and written back a plane at a time. Without
    ``variance`` (the leave-one-out refits: coefficients only) ``fits.var`` only weights the
    smoothing and is not smoothed.
    ``rays`` is a callable returning the global rays
    (:class:`_GlobalRays`) or the rays themselves: a callable is called after the
    smoothing, so that the rays are not held during it (160 MB at 5 MP).
    """
    fits.load("fit")
    fit, var = fits.fit, fits.var
    d1, h, w = fit.shape[1:]
    fb = 1
    while fb * 2 <= b and fb * 2 * 4 <= scale:
        fb *= 2
    for j in range(d1):
        vj = var.plane(j) if isinstance(var, _RowSpill) else var[j]
        with np.errstate(divide="ignore", invalid="ignore"):
            wj = np.where(np.isfinite(fit[:, j]).all(axis=0) & (vj > 0), 1.0 / vj, 0.0)
        del vj
        # Smoothed in place: the (2, H, W) maps are read into bins before they are written (no copy).
        smoothed_var = _smooth_binned(np.nan_to_num(fit[:, j], copy=False), wj, scale, fb, variance, out=fit[:, j])[1]
        if variance and isinstance(var, _RowSpill):
            var[j, 0:h] = smoothed_var
        elif variance:
            var[j] = smoothed_var
        del wj, smoothed_var
    coef = {"x": fit[0], "y": fit[1]}
    rays = rays() if callable(rays) else rays
    # Global ray as a polynomial in t: X = x0 + sx * (zc + zs t).
    for r0, r1 in _row_blocks(h, w):
        gx0, gy0, gsx, gsy = rays.rows(r0, r1)
        for a, g0, gs in (("x", gx0, gsx), ("y", gy0, gsy)):
            coef[a][0, r0:r1] += g0 + gs * zc
            coef[a][1, r0:r1] += gs * zs
    return coef, rays


def _stage_variance(rays, rig: Rig, t: np.ndarray, degree: int, stage_sigma_mm: float) -> dict:
    """Per-pixel variance (mm^2, float32 (H, W) per axis) from the stage readings' error; empty if none.

    Per-position stage errors move all pixels together (see :func:`stage_leverage`).
    """
    if not stage_sigma_mm:
        return {}
    lev = stage_leverage(t, degree)
    out = {a: np.empty(rays.shape, np.float32) for a in "xy"}
    for r0, r1 in _row_blocks(*rays.shape):
        _, _, gsx, gsy = rays.rows(r0, r1)
        for a, gs, d in (("x", gsx, 0), ("y", gsy, 1)):
            out[a][r0:r1] = (np.square((gs - rig.stage.direction[d]) * stage_sigma_mm) * lev).astype(np.float32)
    return out


def _residual_maps(samples: SampleStack, rig: Rig, sel, z: np.ndarray, t: np.ndarray, coef: dict, rays,
                   level_bias: bool, footprint: bool) -> dict:
    """RMS residual (mm, float32 (H, W) per axis) of the smooth LUT against each pixel's own corrected samples."""
    h, w = samples.shape
    d1 = coef["x"].shape[0]
    vander = np.vander(t, d1, increasing=True)
    q = {a: np.empty((h, w), np.float32) for a in "xy"}

    def quality(r0, r1):
        from ptpcore.io.fastio import read_block

        s, e = r0 * w, r1 * w
        ok = read_block(samples.reasons, s, e, sel) == 0
        fb = None
        if footprint:  # the rays' rows are read only for it
            near, lo = rays.window(r0, r1)
            fb = footprint_bias(near, rig, z, read_block(samples.modulation, s, e, sel),
                                read_block(samples.background, s, e, sel), r0 - lo, r1 - lo)
        for i_axis, a in enumerate("xy"):
            pred = np.einsum("kj,jp->kp", vander, coef[a][:, r0:r1].reshape(d1, -1))
            absval = _corrected_absolute(samples, rig, i_axis, s, e, sel, z, level_bias, fb)
            r = np.where(ok, absval - pred, np.nan)
            with np.errstate(all="ignore"):
                q[a][r0:r1] = np.sqrt(_nanmean0(r * r)).astype(np.float32).reshape(r1 - r0, w)

    _run_blocks(quality, _sample_blocks(h, w, len(sel)))
    return q


MODEL_ERROR_REGIONS = 1
"""Regions along the image's longer side over which the model-error term of the smooth LUT's
sigma maps is measured (square regions; the term is interpolated bilinearly between their centres).
One: the term is a small excess over the sample noise, so its standard error per region grows as the
square root of the number of regions; on the presets at 96 x 72 px four regions per side leave a
2-standard-error limit of 3.1 um (realistic) against a model error of 2.3 um."""


@dataclass
class _LooSetup:
    """What the smooth LUT was fitted with, for its leave-one-position-out refits."""

    samples: SampleStack
    rig: Rig
    sel: np.ndarray
    z: np.ndarray
    z_norm: tuple
    rays: _GlobalRays
    degree: int
    scale: float
    cv_bin: int
    level_bias: bool
    footprint: bool
    noise_scale: float


@dataclass
class _ModelError:
    """The model-error term of the smooth LUT's sigma maps (see :func:`_model_error`).

    Attributes
    ----------
    var : dict ``"x"``, ``"y"`` -> (H, W) float64, mm^2 (0 where not resolved); None once
        :func:`_uncertainty` has added it to the sigma maps
    rms_mm : float
        RMS of ``sqrt(var)`` over both axes and the pixels with samples.
    limit_mm : float
        RMS over regions and axes of the smallest resolvable model error (2 standard errors).
    """

    var: dict
    rms_mm: float
    limit_mm: float


def _uncertainty(setup: _LooSetup, gfit, inputs: dict, fits: "_PixelFits", valid: np.ndarray,
                 stage_var: dict, full: bool, report):
    """The smooth LUT's sigma maps, leave-one-out maps and model-error term.

    ``sigma^2 = noise^2 + stage + leak + model``: the propagated phase noise (``inputs["noise"]``,
    (H, W) mm), the stage readings' term (``stage_var``, :func:`_stage_variance`), the global
    model's error passed on by the smoothing (:func:`_global_leak_variance`, with the smoothing
    weights ``inputs["leak_w"]``) and the model error the leave-one-out resolves
    (:func:`_leave_one_out`). Without ``full`` only the first two, and NaN leave-one-out maps.
    ``inputs`` is emptied once its maps are used (not held through the leave-one-out).

    Returns
    -------
    sig, loo : dict ``"x"``, ``"y"`` -> (H, W) float32, mm ; model : _ModelError
    """
    s = setup
    leak = {}
    if full:
        report(0.91, "propagating the global model's uncertainty")
        leak = _global_leak_variance(gfit, inputs["leak_w"], s.scale, s.cv_bin, fits.pz_min, fits.pz_max,
                                     s.z_norm)
    noise = inputs.pop("noise")
    inputs.clear()
    sums = _LooSums(valid.shape)
    for a in "xy":
        sums.put("fit_var", a, np.square(noise.astype(np.float64)) + np.nan_to_num(stage_var.get(a, 0.0), nan=0.0)
                 + np.nan_to_num(leak.pop(a, 0.0), nan=0.0))
    del noise, leak
    if full:
        loo, merr = _leave_one_out(s, valid, sums, lambda f, m: report(0.92 + 0.07 * f, m))
    else:
        loo = {a: np.full(valid.shape, np.nan, np.float32) for a in "xy"}
        merr = _ModelError({a: np.zeros(valid.shape) for a in "xy"}, 0.0, float("nan"))
    sig = {a: np.empty(valid.shape, np.float32) for a in "xy"}
    for a in "xy":
        for r0, r1 in _row_blocks(*valid.shape):
            sig[a][r0:r1] = np.sqrt(sums.rows("fit_var", a, r0, r1) + merr.var[a][r0:r1]).astype(np.float32)
    merr.var = None  # in the sigma maps now: not held while the LUT's coefficients come back (190 MB at 12 MP)
    return sig, loo, merr


def _leave_one_out(setup: _LooSetup, valid: np.ndarray, sums: "_LooSums", report) -> tuple[dict, _ModelError]:
    """Leave-one-position-out of the smooth LUT, and the model error its residuals reveal.

    For every calibration position ``k`` the smooth LUT is fitted again
    without it (the global model, the normalisation in z and the smoothing
    scale kept; every pixel's fit, its weights and the smoothing redone) and
    its prediction at ``z_k`` compared with position ``k``'s corrected samples.
    No sample of position ``k`` reaches that prediction, at any pixel, so a
    per-position error common to all pixels (stage reading, a smooth pattern)
    is not smoothed into it.

    Parameters
    ----------
    setup : _LooSetup
    valid : (H, W) bool
        The smooth LUT's valid pixels.
    sums : _LooSums
        Holds ``fit_var``, the LUT's predicted variance from the sample noise (and stage readings),
        RMS over the calibrated range (mm^2); gets the refits' residual sums.
    report : callable ``(fraction, message)``

    Returns
    -------
    loo : dict ``"x"``, ``"y"`` -> (H, W) float32, mm
        Per-pixel RMS over the positions of the leave-one-out residual.
    model : _ModelError
    """
    s = setup
    k_all = s.z.size
    # The left-out fit has K-1 positions: its noise variance grows by about K / (K - 1).
    grow = k_all / max(k_all - 1, 1)
    report(0.0, "estimating each sample's noise from its pixel's own fit")
    own_noise = _own_noise_all(s, [k for k in range(k_all) if s.z.min() < s.z[k] < s.z.max()])
    for k in range(k_all):
        report(k / k_all, f"leaving calibration position {k + 1} of {k_all} out")
        coef = _refit_without(s, k)
        # Only interior positions measure the model error: the LUT is used inside its calibrated
        # range, and the fit without an end position extrapolates to it.
        interior = s.z.min() < s.z[k] < s.z.max()
        _accumulate_left_out(s, k, coef, valid, sums, grow, interior, own_noise)
        del coef
        release_free_memory()  # each refit left ~50 MB resident at 5 MP (3.2 -> 3.6 GB over 21 refits)
    loo = {}
    for a in "xy":
        with np.errstate(all="ignore"):
            loo[a] = np.where(sums.count > 0, np.sqrt(sums.get("loo_sq", a) / sums.count), np.nan).astype(np.float32)
    return loo, _model_error(sums)


def _refit_without(s: _LooSetup, k: int) -> dict:
    """The smooth LUT's coefficients ``{"x", "y"}`` (D+1, H, W) fitted without calibration position ``k``."""
    keep = np.arange(s.z.size) != k
    run = _SmoothPass(s.samples, s.rig, s.sel[keep], s.z[keep], s.z_norm, s.rays, s.degree, [s.scale],
                      s.cv_bin, s.level_bias, s.footprint, cross_validate=False, own=False)
    run.fit_and_cross_validate_fine(lambda f, m: None)
    return _smoothed_coefficients(run.fits, s.scale, run.b, s.rays, *s.z_norm, variance=False)[0]


def _accumulate_left_out(s: _LooSetup, k: int, coef: dict, valid: np.ndarray, sums: "_LooSums", grow: float,
                         interior: bool, own_noise: "_OwnNoise") -> None:
    """Add position ``k``'s residuals against the fit ``coef`` made without it to the per-pixel ``sums``.

    ``loo_sq`` and ``count`` (the leave-one-out map) always. For an ``interior`` position also, per
    sample, ``x = r^2 - r_own^2 / (1 - h) - grow fit_var`` (:func:`_model_error`) into ``excess`` and
    ``x^2`` into ``excess_sq`` (``n_model`` counts them): ``r_own`` is the sample's residual
    against its pixel's own weighted fit through all calibration positions and ``h`` its leverage
    there, so ``r_own^2 / (1 - h)`` estimates the sample's noise variance whatever the noise
    model's scale (``own_noise``, :func:`_own_noise_all`); ``grow`` scales ``fit_var`` to a fit
    with one position less.
    """
    from ptpcore.io.fastio import read_block

    h, w = s.samples.shape
    pos = [int(s.sel[k])]
    zk = s.z[k:k + 1]
    t_all = (s.z - s.z_norm[0]) / s.z_norm[1]
    powers = t_all[k] ** np.arange(s.degree + 1)

    def block(r0, r1):
        a0, a1 = r0 * w, r1 * w
        ok_s, _sig, _, _ = _block_samples(s.samples, s.rig, pos, zk, r0, r1, None)
        fb = None
        if s.footprint:  # the rays' rows are read only for it
            near, lo = s.rays.window(r0, r1)
            fb = footprint_bias(near, s.rig, zk, read_block(s.samples.modulation, a0, a1, pos),
                                read_block(s.samples.background, a0, a1, pos), r0 - lo, r1 - lo)
        own = own_noise.get(k, a0, a1) if interior else None
        for i_axis, a in enumerate("xy"):
            pred = np.einsum("j,jp->p", powers, coef[a][:, r0:r1].reshape(s.degree + 1, -1))
            r = _corrected_absolute(s.samples, s.rig, i_axis, a0, a1, pos, zk, s.level_bias, fb)[0] - pred
            ok = ok_s[0] & valid[r0:r1].reshape(-1) & np.isfinite(r)
            sums.add("loo_sq", a, r0, r1, np.where(ok, r * r, 0.0).reshape(r1 - r0, w))
            if i_axis == 0:
                sums.count[r0:r1] += ok.reshape(r1 - r0, w)
            if own is None:
                continue
            x = r * r - own[i_axis] - (sums.rows("fit_var", a, r0, r1) * grow).reshape(-1)
            ok &= np.isfinite(x)
            sums.add("excess", a, r0, r1, np.where(ok, x, 0.0).reshape(r1 - r0, w))
            sums.add("excess_sq", a, r0, r1, np.where(ok, x * x, 0.0).reshape(r1 - r0, w))
            if i_axis == 0:
                sums.n_model[r0:r1] += ok.reshape(r1 - r0, w)

    _run_blocks(block, _row_blocks(h, w))


class _LooSums:
    """The leave-one-out's per-pixel float64 sums, X and Y (``loo_sq``, ``excess``, ``excess_sq``) and
    the predicted variance they are judged by (``fit_var``), with the counts ``count`` and
    ``n_model`` ((H, W) int32, in memory).

    Above :data:`_SPILL_FITS_PIXELS` the sums wait in a temporary file (:class:`_RowSpill`) while the
    refits run, and each refit's residuals are added row block by row block: at 5 MP they are 310 MB
    that each refit's own maps would otherwise sit on top of. Adding ``old + new`` read back from the
    file gives the very bits the in-memory ``+=`` gives.
    """

    NAMES = ("loo_sq", "excess", "excess_sq", "fit_var")

    def __init__(self, shape):
        h, w = shape
        self.count = np.zeros((h, w), np.int32)  # counts: exact in any type (the float64 sums saw the same values)
        self.n_model = np.zeros((h, w), np.int32)
        n = len(self.NAMES) * 2
        self._spill = _RowSpill((n, h, w)) if h * w > _SPILL_FITS_PIXELS else None
        self._mem = np.zeros((n, h, w)) if self._spill is None else None  # the file starts as zeros too

    def _index(self, name: str, axis: str) -> int:
        return 2 * self.NAMES.index(name) + "xy".index(axis)

    def rows(self, name: str, axis: str, r0: int, r1: int) -> np.ndarray:
        """Rows ``[r0, r1)`` of one sum, ``(r1 - r0, W)`` (a copy when spilled, else a view)."""
        i = self._index(name, axis)
        return self._spill.rows(i, r0, r1) if self._spill is not None else self._mem[i, r0:r1]

    def add(self, name: str, axis: str, r0: int, r1: int, values: np.ndarray) -> None:
        """Add ``values`` ``(r1 - r0, W)`` to rows ``[r0, r1)`` of one sum (blocks of disjoint rows may
        come from several threads)."""
        i = self._index(name, axis)
        if self._spill is None:
            self._mem[i, r0:r1] += values
        else:
            self._spill[i, r0:r1] = self._spill.rows(i, r0, r1) + values

    def put(self, name: str, axis: str, values: np.ndarray) -> None:
        """Set one whole ``(H, W)`` sum."""
        i = self._index(name, axis)
        if self._spill is None:
            self._mem[i] = values
        else:
            self._spill[i, 0:values.shape[0]] = values

    def get(self, name: str, axis: str) -> np.ndarray:
        """One whole ``(H, W)`` sum (read into memory when spilled)."""
        i = self._index(name, axis)
        return self._spill.plane(i) if self._spill is not None else self._mem[i]


class _OwnNoise:
    """``r_own^2 / (1 - h)`` of the calibration samples, X and Y, per position: ``(2, K, H * W)``
    float64, in memory up to :data:`_OWN_NOISE_BYTES`, else in a temporary file (positional writes
    and reads, :class:`ptpcore.io.fastio.SpillStore`: 1.7 GB at 5 MP x 21 positions)."""

    def __init__(self, k: int, shape):
        from ptpcore.io.fastio import SpillStore

        h, w = shape
        self.w = w
        if 2 * k * h * w * 8 <= _OWN_NOISE_BYTES:
            self.store, self.mem = None, np.full((2, k, h * w), np.nan)
        else:
            self.store = SpillStore(k, shape, {"x": np.float64, "y": np.float64}, {"x": np.nan, "y": np.nan})
            self.mem = None

    def put(self, axis: int, k: int, r0: int, r1: int, values: np.ndarray) -> None:
        """Rows ``[r0, r1)`` of position ``k``, axis 0 (X) or 1 (Y): ``((r1 - r0) * W,)`` values."""
        if self.mem is not None:
            self.mem[axis, k, r0 * self.w:r1 * self.w] = values
        else:
            self.store.write_rows("xy"[axis], k, r0, values.reshape(r1 - r0, self.w))

    def get(self, k: int, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``[start, stop)`` (flat) of position ``k``: the X and Y values."""
        if self.mem is not None:
            return self.mem[0, k, start:stop], self.mem[1, k, start:stop]
        return self.store.read("x", start, stop, [k])[0], self.store.read("y", start, stop, [k])[0]


_OWN_NOISE_BYTES = 1 << 28
"""Above this size (256 MiB) :class:`_OwnNoise` goes to a temporary file."""


def _own_noise_all(s: _LooSetup, positions) -> _OwnNoise:
    """``r_own^2 / (1 - h)`` of every sample of calibration ``positions`` (indices into ``s.z``),
    X and Y; NaN where the pixel has no fit of its own with freedom left, or the sample is not used.

    Every pixel's own fit through all calibration positions is the same whichever position is
    left out, so it is made once, block by block (the row blocks :func:`_accumulate_left_out`
    reads them by), for all positions: one pass over the samples instead of one per position.
    """
    h, w = s.samples.shape
    store = _OwnNoise(s.z.size, (h, w))
    t_all = (s.z - s.z_norm[0]) / s.z_norm[1]

    def block(r0, r1):
        _valid, _sig, wts, resid = _block_samples(s.samples, s.rig, s.sel, s.z, r0, r1, s.rays, s.level_bias,
                                                  s.footprint)
        coefs, _v, n, cov = _weighted_poly(t_all, resid, wts, s.degree, full=True)
        for k in positions:
            powers = t_all[k] ** np.arange(s.degree + 1)
            lev = wts[k] * np.einsum("i,ijp,j->p", powers, cov, powers)
            use = (wts[k] > 0) & (n > s.degree + 1) & (lev < 1.0 - 1e-9)
            for axis, (c, rv) in enumerate(zip(coefs, resid)):
                with np.errstate(all="ignore"):
                    r_own = rv[k] - np.einsum("j,jp->p", powers, c)
                    store.put(axis, k, r0, r1, np.where(use, r_own * r_own / (1.0 - lev), np.nan))

    if positions:
        _run_blocks(block, _row_blocks(h, w))
    return store


def _model_error(sums: "_LooSums") -> _ModelError:
    """The model-error variance per region from the leave-one-out residuals' excess over the noise.

    A left-out sample's residual ``r`` is its own noise, the left-out fit's
    noise and the model error ``b`` (what the smoothing and the global model
    cannot follow) at once: ``E[r^2] = sigma^2 + sigma_fit^2 + b^2``. The
    sample's noise variance ``sigma^2`` is estimated from its pixel's own
    weighted fit through all positions, ``E[r_own^2 / (1 - h)] = sigma^2``
    (exact for any scale of the noise model: a 1 % error of that scale would
    otherwise pass for a model error of 0.7 um on the mild preset at 320 px),
    ``sigma_fit^2`` is the predicted noise of the left-out fit. Per region
    (:data:`MODEL_ERROR_REGIONS` along the longer side) the mean of
    ``x = r^2 - r_own^2 / (1 - h) - sigma_fit^2`` estimates ``b^2``, its
    standard error from the spread of ``x``. It is kept where it exceeds 2
    standard errors (the data resolve it) and interpolated bilinearly between
    the regions' centres; elsewhere the model error is below what the data can
    tell from the noise and left out. ``sums`` holds ``x`` and ``x^2`` summed per pixel
    (``excess``, ``excess_sq``) and their count (``n_model``).
    """
    count = sums.n_model
    h, w = count.shape
    side = max(1, int(np.ceil(max(h, w) / MODEL_ERROR_REGIONS)))
    n = _bin(count, side)
    var, limits = {}, []
    for a in "xy":
        with np.errstate(all="ignore"):
            b2 = _bin(sums.get("excess", a), side) / n
            spread = np.maximum(_bin(sums.get("excess_sq", a), side) / n - b2 * b2, 0.0)
            se = np.sqrt(spread / np.maximum(n - 1, 1))
        resolved = (n > 1) & (b2 > 2.0 * se)
        limits.append(np.where(n > 1, 2.0 * se, np.nan))
        var[a] = np.maximum(_upsample(np.where(resolved, b2, 0.0), side, h, w), 0.0)
    has = count > 0
    rms = float(np.sqrt(np.mean([np.mean(var[a][has]) for a in "xy"]))) if has.any() else 0.0
    lim = np.concatenate([x.ravel() for x in limits])
    lim = lim[np.isfinite(lim)]
    return _ModelError(var, rms, float(np.sqrt(np.mean(lim))) if lim.size else 0.0)


class _PlaneRows:
    """A :class:`_RowSpill` plane where an ``(H, W)`` map is read by rows: ``shape``, ``plane[r0:r1]``
    (a file read) and ``np.asarray(plane)`` (the whole plane). :func:`_binned_points` reads its
    weights so, band by band: the leak variance's two weight maps (190 MB at 12 MP) stay in their file."""

    def __init__(self, spill: "_RowSpill", index: int):
        self.spill, self.index = spill, index
        self.shape = spill.shape[-2:]

    def __getitem__(self, rows: slice) -> np.ndarray:
        r0, r1, step = rows.indices(self.shape[0])
        if step != 1:
            raise IndexError("a spilled plane is read by row ranges only")
        return self.spill.rows(self.index, r0, max(r0, r1))

    def __array__(self, dtype=None, copy=None):
        a = self.spill.plane(self.index)
        return a if dtype is None else a.astype(dtype, copy=False)


def _smoothing_weights(fits: "_PixelFits", n: int):
    """The final smoothing's weights ``1 / var_j`` of the first ``n`` coefficient maps, (n, H, W) float64
    (0 where a pixel has no fit), as :func:`_smoothed_coefficients` uses them (call it before: it
    smooths ``fits.var`` in place). Above :data:`_SPILL_FITS_PIXELS` pixels a :class:`_RowSpill`
    (read a plane at a time by :func:`_global_leak_variance`; 190 MB not held through the smoothing at 12 MP)."""
    h, w = fits.var.shape[1:]
    out = _RowSpill((n, h, w)) if h * w > _SPILL_FITS_PIXELS else np.zeros((n, h, w))
    for j in range(n):
        if j >= fits.var.shape[0]:
            out[j, 0:h] = 0.0
            continue
        vj = fits.var.plane(j) if isinstance(fits.var, _RowSpill) else fits.var[j]
        with np.errstate(divide="ignore", invalid="ignore"):
            out[j, 0:h] = np.where(np.isfinite(fits.fit[:, j]).all(axis=0) & (vj > 0), 1.0 / vj, 0.0)
    return out


def _pinhole_from_params(names, values) -> PinholeModel:
    """A :class:`PinholeModel` from :class:`PinholeFit`-ordered parameter values."""
    v = dict(zip(names, values))
    K = np.array([[v["fx"], 0.0, v["cx"]], [0.0, v["fy"], v["cy"]], [0.0, 0.0, 1.0]])
    dist = [v[n] for n in names if n[0] in "kp"]
    return PinholeModel(K=K, dist=np.asarray(dist), rvec=np.array([v["rx"], v["ry"], v["rz"]]),
                        tvec=np.array([v["tx"], v["ty"], v["tz"]]))


def _rays_at(model: PinholeModel, cols: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, ...]:
    """``x0, y0, sx, sy`` (len(rows), len(cols)) of ``model``'s rays at the grid of ``cols`` x ``rows`` (px)."""
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    a0, b0 = model.pixel_to_world_at_z(cc, rr, 0.0)
    a1, b1 = model.pixel_to_world_at_z(cc, rr, 1.0)
    return a0, b0, a1 - a0, b1 - b0


def _upsample_grid(coarse: np.ndarray, step: int, h: int, w: int, out: np.ndarray | None = None) -> np.ndarray:
    """A map sampled at every ``step``-th pixel back to (h, w) by Catmull-Rom cubics (two matrices).

    Node ``i`` sits at pixel ``(i - 1) * step``: one node before the image and two past its end,
    so every pixel has its four nodes. ``out``: an (h, w) float64 array to write the map into.
    """
    def weights(n: int, nc: int) -> np.ndarray:
        pos = np.arange(n) / step + 1.0
        i = np.floor(pos).astype(int)
        f = pos - i
        m = np.zeros((n, nc))
        rows = np.arange(n)
        for off, wt in ((-1, (-f ** 3 + 2 * f ** 2 - f) / 2), (0, (3 * f ** 3 - 5 * f ** 2 + 2) / 2),
                        (1, (-3 * f ** 3 + 4 * f ** 2 + f) / 2), (2, (f ** 3 - f ** 2) / 2)):
            m[rows, i + off] += wt
        return m

    hc, wc = coarse.shape
    return np.matmul(weights(h, hc) @ coarse, weights(w, wc).T, out=out)


LEAK_GRID_PX = 8
"""Grid step (px) on which :func:`_global_leak_variance` recomputes the perturbed global rays."""

def _global_leak_variance(gfit, weights: np.ndarray, scale: float, b: int, pz_min, pz_max,
                          z_norm) -> dict:
    """Per-pixel variance (mm^2) of the global model's own fit error that the smoothed correction passes on.

    The correction is fitted to the samples minus the global model, so an error
    ``dg`` of the global rays reaches the LUT as ``dg - S dg``, ``S`` the final
    smoothing (locally linear: it follows ``dg`` only where ``dg`` is linear
    over the smoothing scale). ``dg`` comes from the global fit's parameter
    covariance (:func:`ptpcore.pinhole.camera.fit_pinhole`): along each of its
    eigenvectors (1 sigma) the rays are recomputed, the change written as
    coefficients in ``t`` (``x0 + sx z``), smoothed with the final smoothing's
    weights, and the remainder's square averaged over the pixel's calibrated
    range; the directions' contributions add.

    Parameters
    ----------
    gfit : PinholeFit
    weights : (2, H, W) float64 or its :class:`_RowSpill`, the smoothing weights of coefficients 0 and 1
        (:func:`_smoothing_weights`)
    scale : float, px ; b : int, the cross-validation's bin side
    pz_min, pz_max : (H, W) the pixels' calibrated range (mm)
    z_norm : (zc, zs)

    Returns
    -------
    dict ``"x"``, ``"y"`` -> (H, W) float64, mm^2 (zeros without smoothing or covariance)
    """
    h, w = pz_min.shape
    out = {a: np.zeros((h, w)) for a in "xy"}
    cov = getattr(gfit, "covariance", None)
    if scale <= 0 or cov is None or not np.all(np.isfinite(cov)):
        return out
    zc, zs = z_norm
    fb = 1
    while fb * 2 <= b and fb * 2 * 4 <= scale:
        fb *= 2
    def moments(r0, r1):  # of the pixels' calibrated ranges, rows [r0, r1) (not held whole: 120 MB at 5 MP)
        with np.errstate(all="ignore"):
            return _range_moments(((pz_min[r0:r1] - zc) / zs).astype(np.float64),
                                  ((pz_max[r0:r1] - zc) / zs).astype(np.float64), 2)

    if isinstance(weights, _RowSpill):  # read band by band where they are used
        weights = [weights.plane_rows(j) for j in range(2)]
    lam, vec = np.linalg.eigh(0.5 * (cov + cov.T))
    # The change of a pinhole's rays is smooth over the image: computed on a grid of every
    # LEAK_GRID_PX-th pixel and interpolated (cubic).
    step = max(1, min(LEAK_GRID_PX, (min(h, w) - 1) // 4))
    rows = np.arange(-step, h + 2 * step, step, dtype=float)[: (h - 1) // step + 4]
    cols = np.arange(-step, w + 2 * step, step, dtype=float)[: (w - 1) // step + 4]
    base = _rays_at(gfit.model, cols, rows)
    dirs = [np.sqrt(li) * vi for li, vi in zip(lam, vec.T) if li > 0]
    # One direction and one axis at a time (issue 15): the directions' maps smoothed together were the
    # smooth command's peak; each map is smoothed alone either way, and the remainders add per pixel
    # in the same order.
    for dv in dirs:
        moved = _rays_at(_pinhole_from_params(gfit.param_names, gfit.param_values + dv), cols, rows)
        for a, (i0, i1) in zip("xy", ((0, 2), (1, 3))):
            # The change as coefficients in t, d0 + d1 zc and d1 zs, made in place (the changes
            # d0, d1 and the products beside them were the 12 MP wizard's peak, 380 MB).
            c = np.empty((2, 1, h, w))  # [coefficient j][map]
            _upsample_grid(moved[i0] - base[i0], step, h, w, out=c[0, 0])
            _upsample_grid(moved[i1] - base[i1], step, h, w, out=c[1, 0])
            for r0, r1 in _row_blocks(h, w):
                c[0, 0, r0:r1] += c[1, 0, r0:r1] * zc
            c[1, 0] *= zs
            for j in range(2):
                smoothed = np.nan_to_num(c[j])
                c[j] -= _smooth_binned(smoothed, weights[j], scale, fb, False, out=smoothed)[0]
                del smoothed
            for r0, r1 in _row_blocks(h, w):
                mom = moments(r0, r1)
                l0, l1 = c[0, 0, r0:r1], c[1, 0, r0:r1]
                out[a][r0:r1] += np.nan_to_num(l0 ** 2 * mom[0] + 2 * l0 * l1 * mom[1] + l1 ** 2 * mom[2])
            del c
    return out


def _smooth_sigma_maps(fits: _PixelFits, zc: float, zs: float, degree: int, noise_scale: float,
                       stage_var: dict) -> dict:
    """Predicted 1-sigma maps (mm, float32 (H, W) per axis) of the smooth LUT.

    RMS over the calibrated range (uniform in t) of the smoothed correction's
    noise propagated from the phase noise. The model error beyond it
    (smoothing bias) is estimated by cross-validation and reported in
    SmoothInfo.excess_sigma_mm, not folded into the map: the fold fits use half
    the positions, so it is an upper bound. Smoothing averages neighbouring
    pixels' coefficients, each map on its own: its variance reduction is
    measured on the uncorrelated form and applied to the pixel's own exact
    variance over its calibrated range.
    """
    d1 = degree + 1
    h, w = fits.pz_min.shape
    sig1 = np.empty((h, w), np.float32)
    for r0, r1 in _row_blocks(h, w):  # row blocks: the moments are (2D+1) float64 maps
        with np.errstate(all="ignore"):
            mom = _range_moments(((fits.pz_min[r0:r1] - zc) / zs).astype(np.float64),
                                 ((fits.pz_max[r0:r1] - zc) / zs).astype(np.float64), 2 * degree)
            var = fits.var.row_block(r0, r1) if isinstance(fits.var, _RowSpill) else fits.var[:, r0:r1]
            smooth_diag = np.einsum("jhw,jhw->hw", var, mom[2 * np.arange(d1)])
            own_diag = fits.own_diag[r0:r1]
            s2 = fits.own_var[r0:r1] * np.where(own_diag > 0, smooth_diag / own_diag, np.nan)
            # Pixels without a fit of their own (filled in by the smoothing): the uncorrelated form.
            s2 = np.where(np.isfinite(s2), s2, smooth_diag)
        sig1[r0:r1] = np.sqrt(s2) * noise_scale
    sig = {"x": sig1, "y": sig1.copy()}
    for a, sv in stage_var.items():
        sig[a] = np.sqrt(np.square(sig[a]) + np.nan_to_num(sv, nan=0.0)).astype(np.float32)
    return sig


def poly_sigma_maps(samples: SampleStack, rig: Rig, lut: Lut, positions=None,
                    stage_sigma_mm: float = 0.0, scale: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Predicted 1-sigma maps (mm) of a plain, unweighted ``poly`` LUT.

    The variance of the fitted value at each calibrated node, propagated from
    every sample's phase noise through the pixel's own least-squares fit, and
    averaged (RMS) over the pixel's calibrated range. With ``stage_sigma_mm``
    (the stage readings' 1-sigma error) each sample also carries
    ``|dX/dz - a| * stage_sigma_mm``, with the pixel's own slope ``dX/dz``.
    Built in row blocks from the (possibly spilled) samples: never a whole
    ``(K, H, W)`` array.

    ``scale``: :func:`sigma_scale` of these samples and positions when already known.

    Returns
    -------
    sigma_x, sigma_y : (H, W) float32
    """
    from ptpcore.fit.sigma import _normalised_heights, predicted_poly_sigma_flat

    positions = list(range(samples.z.size)) if positions is None else list(positions)
    if scale is None:
        scale = sigma_scale(samples, rig, positions)
    sel = np.asarray(positions)
    z = np.asarray(samples.z, dtype=float)[sel]
    # RMS over the calibrated range: evaluate on a fine uniform grid of z.
    zs = np.linspace(lut.z_min, lut.z_max, 4 * len(positions) + 1)
    t, te = _normalised_heights(z, zs)
    h, w = samples.shape
    # A stage reading off by dz moves the sample by (dX/dz - a) dz: the pixel's own slope.
    axes = ((0, lut.x), (1, lut.y)) if stage_sigma_mm else ((0, None),)
    maps = [np.empty((h, w), np.float32) for _ in axes]

    def block(r0, r1):
        valid, sig, _, _ = _block_samples(samples, rig, sel, z, r0, r1, None)
        sig = sig * scale
        inside = (zs[:, None] >= lut.pixel_z_min[r0:r1].reshape(-1)) & (zs[:, None] <= lut.pixel_z_max[r0:r1].reshape(-1))
        for (d, coef), out in zip(axes, maps):
            s = sig if coef is None else np.hypot(sig, np.abs(
                coef[1, r0:r1].reshape(-1) / lut.z_scale - rig.stage.direction[d]) * stage_sigma_mm)
            pred = predicted_poly_sigma_flat(t, te, valid, s, lut.degree)  # (E, n)
            with np.errstate(all="ignore"):
                rms = np.sqrt(_nanmean0(np.where(inside, pred * pred, np.nan)))
            out[r0:r1] = np.where(lut.valid[r0:r1].reshape(-1), rms, np.nan).reshape(r1 - r0, w)

    _run_blocks(block, _row_blocks(h, w))
    return (maps[0], maps[0].copy()) if len(maps) == 1 else tuple(maps)
