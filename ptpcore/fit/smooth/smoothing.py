"""Step 3 of the smooth fit: locally linear, inverse-variance weighted Gaussian smoothing of maps.

:func:`local_linear_smooth` fits ``a + b (col - c0) + c (row - r0)`` around every pixel with weights
``w_q G(q - p)`` (Gaussian moments by OpenCV's separable filter, closed-form 3x3 solves). On big
images the same regression runs on a grid of ``b x b`` bins (:func:`smooth_on_bins`: each bin a point
at its weighted centroid) and is interpolated back (:func:`upsample_bins`); :func:`upsample_cubic`
brings back a map sampled on a coarse grid.
"""

from __future__ import annotations

import cv2
import numpy as np

from ptpcore.fit.smooth.blocks import row_blocks

__all__ = ["CV_PIXELS", "BIN_BAND_PIXELS", "bin_factor", "final_bin_side", "local_linear_smooth",
           "local_linear_grid", "LocalLinearFit", "bin_sums", "binned_points", "binned_sigma", "smooth_on_bins",
           "SharedWeightSmoother", "upsample_bins", "upsample_cubic", "smoothed_covariance"]


CV_PIXELS = 320_000
"""Above this many pixels the cross-validation runs on a grid binned so it has about this many
points (a 5 MP image: 4 x 4 bins), and the final smoothing at scales of at least 4 bins runs on
the same binned grid (interpolated back bilinearly). Up to 640 x 480 everything is per pixel."""


def bin_factor(shape) -> int:
    """Side of the square bins of the cross-validation grid: 1 up to :data:`CV_PIXELS` pixels."""
    return max(1, int(round(np.sqrt(shape[0] * shape[1] / CV_PIXELS))))


def final_bin_side(b: int, scale: float) -> int:
    """Side (px) of the bins the final smoothing at ``scale`` px runs on: the largest power of two of
    at most the cross-validation's bin side ``b`` and at most a quarter of the scale (1: per pixel)."""
    fb = 1
    while fb * 2 <= b and fb * 2 * 4 <= scale:
        fb *= 2
    return fb


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


def local_linear_grid(values: np.ndarray, weights: np.ndarray, sigma: float, xc: np.ndarray, yc: np.ndarray,
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
    fit = LocalLinearFit(weights, sigma, xc, yc, xb, yb)
    out = fit.apply(values)
    return out, (fit.variance(np.isfinite(out[0])) if with_variance else None)


class LocalLinearFit:
    """:func:`local_linear_grid` for one set of weights, applied to any number of value maps.

    The weights' Gaussian moments and every grid point's 3 x 3 system are made once
    (:meth:`apply` then costs three filters a map): maps that share their weights (the
    global model's leak variance smooths 4 maps per parameter direction with two weight maps)
    need not pay for them again. The same arithmetic as one :func:`local_linear_grid` call.
    """

    def __init__(self, weights: np.ndarray, sigma: float, xc: np.ndarray, yc: np.ndarray, xb=None, yb=None):
        h, w = weights.shape
        self.weights, self.sigma = weights, sigma
        self.xg, self.yg = xc[None, :], yc[:, None]
        self.x = self.xg if xb is None else xb
        self.y = self.yg if yb is None else yb
        self.blocks = row_blocks(h, w)
        mom = self._raw(self._g, weights)
        s0 = self.s0 = mom[0]
        s0_max = max(float(s0.max()), 1e-300)
        row = self.row = np.empty((3, h, w))
        good = self.good = np.empty((h, w), bool)
        for r0, r1 in self.blocks:
            a = _local_moments(*[m[r0:r1] for m in mom], self.xg, self.yg[r0:r1])
            (c0, c1, c2), det = _first_row_of_inverse(*a)
            row[0, r0:r1], row[1, r0:r1], row[2, r0:r1] = c0, c1, c2
            s0b = s0[r0:r1]
            good[r0:r1] = (s0b > 1e-12 * s0_max) & (np.abs(det) > 1e-12 * np.maximum(s0b, 1e-300) ** 3)
        del mom[1:]
        self.weak = ~good & (s0 > 0)
        self.any_good = bool(good.any())

    def _g(self, arr: np.ndarray) -> np.ndarray:
        return _gauss(arr, self.sigma)

    def _raw(self, filt, wv):
        x, y = self.x, self.y
        return [filt(wv), filt(wv * x), filt(wv * y), filt(wv * x * x), filt(wv * x * y), filt(wv * y * y)]

    def apply(self, values: np.ndarray) -> np.ndarray:
        """The fitted value of each ``(n, h, w)`` map at every grid point, NaN without support."""
        xg, yg, row, good, weak, s0 = self.xg, self.yg, self.row, self.good, self.weak, self.s0
        out = np.full(values.shape, np.nan)
        for i, v in enumerate(values):
            wv = self.weights * v
            t0 = self._g(wv)
            if self.any_good:
                t1 = self._g(wv * self.x)
                t2 = self._g(wv * self.y)
                for r0, r1 in self.blocks:
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
        return out

    def variance(self, supported: np.ndarray) -> np.ndarray:
        """The fitted value's variance if the weights are inverse variances, (h, w), NaN where not
        ``supported`` (the fitted values' finite points)."""
        h, w = self.s0.shape
        xg, yg, row, good, weak, s0, sigma = self.xg, self.yg, self.row, self.good, self.weak, self.s0, self.sigma
        var = np.full((h, w), np.nan)
        # var(value_q) = 1 / w_q gives var = (A^-1 B A^-1)[0, 0], B the same
        # moments under G^2, and G_s^2 = G_{s/sqrt2} / (4 pi s^2).
        g2 = lambda arr: _gauss(arr, sigma / np.sqrt(2.0)) / (4 * np.pi * sigma ** 2)  # noqa: E731
        if self.any_good or weak.any():
            b = self._raw(g2, self.weights) if self.any_good else [g2(self.weights)]
            for r0, r1 in self.blocks:
                gb = good[r0:r1]
                if self.any_good and gb.any():
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
        return np.where(supported, var, np.nan)


    def _rows(self) -> np.ndarray:
        """(3, h, w): the first row of each point's inverse system; ``(1/s0, 0, 0)`` where the estimate
        is locally constant (:attr:`weak`), NaN without support."""
        rows = np.where(self.good, self.row, np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            rows[0] = np.where(self.weak, 1.0 / self.s0, rows[0])
        rows[1:][:, self.weak] = 0.0
        return rows

    def cross_variance(self, other: "LocalLinearFit", cross: np.ndarray) -> np.ndarray:
        """Covariance of this fit's and ``other``'s values (same grid and coordinates) when their data
        covary by ``cross / (w_self w_other)`` at each point (:func:`smoothed_covariance`), (h, w)."""
        xg, yg, sigma = self.xg, self.yg, self.sigma
        g2 = lambda arr: _gauss(arr, sigma / np.sqrt(2.0)) / (4 * np.pi * sigma ** 2)  # noqa: E731
        b = self._raw(g2, cross)
        ra, rb = self._rows(), other._rows()
        out = np.empty(self.s0.shape)
        for r0, r1 in self.blocks:
            m = _local_moments(*[v[r0:r1] for v in b], xg, yg[r0:r1])
            big = ((m[0], m[1], m[2]), (m[1], m[3], m[4]), (m[2], m[4], m[5]))
            a, c = ra[:, r0:r1], rb[:, r0:r1]
            with np.errstate(invalid="ignore", over="ignore"):
                out[r0:r1] = sum(a[i] * big[i][j] * c[j] for i in range(3) for j in range(3))
        return out


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
    out, var = local_linear_grid(vals, weights, scale_px, np.arange(w) / scale_px, np.arange(h) / scale_px,
                                 with_variance=with_variance)
    return (out if stacked else out[0]), var


def bin_sums(a: np.ndarray, b: int) -> np.ndarray:
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


def binned_points(weights: np.ndarray, values: np.ndarray, b: int, r0: int = 0, unweighted_zero: bool = False):
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
    stacked = values.ndim == 3
    vals = values if stacked else values[None]
    wsum, inv, xbar, ybar = _binned_weights(weights, b, r0)
    with np.errstate(invalid="ignore"):
        mean = _binned_sums(weights, vals, b, unweighted_zero) * inv
    return wsum, (mean if stacked else mean[0]), xbar, ybar


def _bands(h: int, w: int, b: int):
    """Bands ``(s0, s1, c0, c1)`` of whole bins' rows (:data:`BIN_BAND_PIXELS`): pixel rows and bin rows."""
    band = b * max(1, BIN_BAND_PIXELS // (b * w))
    for s0 in range(0, h, band):
        s1 = min(h, s0 + band)
        yield s0, s1, s0 // b, -(-s1 // b)


def _binned_weights(weights, b: int, r0: int = 0):
    """The bins' summed weights ``(hc, wc)``, their inverse (0 where empty) and weighted centroids
    (column, row in pixels; the bin centre where empty) (:func:`binned_points`)."""
    h, w = weights.shape
    hc, wc = -(-h // b), -(-w // b)
    wsum, wx, wy = np.empty((hc, wc)), np.empty((hc, wc)), np.empty((hc, wc))
    cols = np.arange(w, dtype=float)[None, :]
    for s0, s1, c0, c1 in _bands(h, w, b):
        wt = weights[s0:s1]
        wsum[c0:c1] = bin_sums(wt, b)
        wx[c0:c1] = bin_sums(wt * cols, b)
        wy[c0:c1] = bin_sums(wt * np.arange(r0 + s0, r0 + s1, dtype=float)[:, None], b)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(wsum > 0, 1.0 / wsum, 0.0)
        cx = np.arange(wc) * b + (b - 1) / 2.0
        cy = r0 + np.arange(hc) * b + (b - 1) / 2.0
        xbar = np.where(wsum > 0, wx * inv, cx[None, :])
        ybar = np.where(wsum > 0, wy * inv, cy[:, None])
    return wsum, inv, xbar, ybar


def _binned_sums(weights, vals: np.ndarray, b: int, unweighted_zero: bool) -> np.ndarray:
    """``sum w v`` over each bin of each ``(n, h, w)`` map, ``(n, hc, wc)``, band by band (:func:`binned_points`)."""
    h, w = weights.shape
    binned = np.empty((len(vals), -(-h // b), -(-w // b)))
    for s0, s1, c0, c1 in _bands(h, w, b):
        wt = weights[s0:s1]
        for i, v in enumerate(vals):  # one map at a time
            v = v[s0:s1]
            binned[i, c0:c1] = bin_sums(wt * (np.where(wt > 0, v, 0.0) if unweighted_zero else v), b)
    return binned


def binned_sigma(scale_px: float, b: int, interpolated: bool) -> float:
    """Gaussian sigma (in bins) on a grid of ``b x b`` bins that smooths like ``scale_px`` per pixel.

    A pixel weighted by the Gaussian at its bin's centre widens the kernel by
    the bin's variance ``(b^2 - 1) / 12``; bilinear interpolation back to the
    pixels adds ``b^2 / 6`` on average (its curvature bias): both are taken off.
    """
    extra = (b * b - 1) / 12.0 + (b * b / 6.0 if interpolated else 0.0)
    return float(np.sqrt(max(scale_px ** 2 - extra, 0.25 * scale_px ** 2))) / b


def smooth_on_bins(values: np.ndarray, weights: np.ndarray, scale_px: float, b: int, with_variance: bool = True,
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
    wsum, mean, xbar, ybar = binned_points(weights, values if stacked else values[None], b, unweighted_zero=True)
    hc, wc = wsum.shape
    cx = (np.arange(wc) * b + (b - 1) / 2.0) / scale_px
    cy = (np.arange(hc) * b + (b - 1) / 2.0) / scale_px
    out_c, var_c = local_linear_grid(mean, wsum, binned_sigma(scale_px, b, True), cx, cy, xbar / scale_px,
                                     ybar / scale_px, with_variance)
    if out is None:
        out = np.empty((len(out_c), h, w)) if stacked else np.empty((h, w))
    maps = out if stacked else out[None]
    for i, o in enumerate(out_c):  # into one array: no list of maps beside their stack
        maps[i] = upsample_bins(o, b, h, w)
    var = None
    if var_c is not None:
        var = upsample_bins(var_c, b, h, w)
        var[~np.isfinite(maps[0])] = np.nan
    return out, var


def smoothed_covariance(weights_a, weights_b, cross, scale_px: float, b: int) -> np.ndarray:
    """Covariance of two maps smoothed by :func:`smooth_on_bins`, each with its own weights.

    Map ``a`` has ``var(a_q) = 1 / weights_a(q)``, map ``b`` likewise, and at the same pixel the two
    covary by ``C(q)`` (independent between pixels). Each smoothed value is linear in its map,
    ``r^T (sum_q G(p - q) w(q) phi_q v_q)`` with ``r`` the first row of the local system's inverse,
    so their covariance is ``r_a^T B r_b``, ``B`` the moments of ``w_a w_b C`` under the squared
    kernel (:meth:`LocalLinearFit.variance` is the case ``a = b``). Smoothing two coefficient maps
    with different weights keeps less of a pixel's own anti-correlation than the diagonal shrinks:
    a ratio taken from the unsmoothed pixel under-predicted the smooth LUT's noise 1.5-2.7x (issue 30).

    Parameters
    ----------
    weights_a, weights_b : (H, W) float64 >= 0
        The inverse variances the two maps are smoothed with (0: not used).
    cross : (H, W) float64
        ``weights_a * weights_b * C`` (0 where either weight is 0).
    scale_px : float ; b : int
        As for :func:`smooth_on_bins`. On bins, both maps' points are taken at map ``a``'s weighted
        centroids (the two differ by far less than a bin).

    Returns
    -------
    (H, W) float64, in the maps' units squared; NaN where either smoothed value has no support
    """
    h, w = weights_a.shape
    if scale_px <= 0:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where((weights_a > 0) & (weights_b > 0), cross / (weights_a * weights_b), np.nan)
    if b == 1:
        grid = (np.arange(w) / scale_px, np.arange(h) / scale_px)
        fit_a, fit_b = (LocalLinearFit(np.asarray(wt, dtype=np.float64), scale_px, *grid) for wt in (weights_a, weights_b))
        u = cross
    else:
        hc, wc = -(-h // b), -(-w // b)
        grid = ((np.arange(wc) * b + (b - 1) / 2.0) / scale_px, (np.arange(hc) * b + (b - 1) / 2.0) / scale_px)
        sigma = binned_sigma(scale_px, b, True)
        wa, _inv, xbar, ybar = _binned_weights(weights_a, b)
        fit_a = LocalLinearFit(wa, sigma, *grid, xbar / scale_px, ybar / scale_px)
        fit_b = LocalLinearFit(_binned_weights(weights_b, b)[0], sigma, *grid, xbar / scale_px, ybar / scale_px)
        u = bin_sums(cross, b)
    cov = fit_a.cross_variance(fit_b, u)
    return cov if b == 1 else upsample_bins(cov, b, h, w)


class SharedWeightSmoother:
    """:func:`smooth_on_bins` without the variance, for many ``(h, w)`` maps that share one weight map.

    On bins (``b`` > 1) the weights' bins and the local fits' systems (:class:`LocalLinearFit`) are
    made once, so each map costs its own binning, three filters and the interpolation back: the
    global model's leak variance smooths two maps per parameter direction and axis with the same two
    weight maps. Map by map the same arithmetic as :func:`smooth_on_bins`. Per pixel (``b`` = 1)
    nothing is kept (the systems would be four whole-image maps: 380 MB at 12 MP). ``scale_px`` > 0.
    """

    def __init__(self, weights, scale_px: float, b: int):
        self.weights, self.scale, self.b = weights, scale_px, b
        self.shape = weights.shape
        if b == 1:
            return
        wsum, self.inv, xbar, ybar = _binned_weights(weights, b)
        hc, wc = wsum.shape
        cx = (np.arange(wc) * b + (b - 1) / 2.0) / scale_px
        cy = (np.arange(hc) * b + (b - 1) / 2.0) / scale_px
        self.fit = LocalLinearFit(wsum, binned_sigma(scale_px, b, True), cx, cy, xbar / scale_px, ybar / scale_px)

    def smooth(self, values: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``values`` (h, w) smoothed into ``out`` (h, w) float64 (may be ``values`` itself)."""
        if self.b == 1:
            return smooth_on_bins(values, self.weights, self.scale, 1, False, out=out)[0]
        h, w = self.shape
        with np.errstate(invalid="ignore"):
            mean = _binned_sums(self.weights, values[None], self.b, True) * self.inv
        out[...] = upsample_bins(self.fit.apply(mean)[0], self.b, h, w)
        return out


def upsample_bins(coarse: np.ndarray, b: int, h: int, w: int) -> np.ndarray:
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
    for r0 in range(0, h, UPSAMPLE_ROWS):
        band = lin[r0:r0 + UPSAMPLE_ROWS]
        bad = np.isnan(band)
        if bad.any():
            c0, c1 = r0 // b, -(-(r0 + len(band)) // b)
            near = np.broadcast_to(coarse[c0:c1, None, :, None], (c1 - c0, b, wc, b)).reshape((c1 - c0) * b, wc * b)
            np.copyto(band, near[r0 - c0 * b:r0 - c0 * b + len(band), :w], where=bad)
    return lin


UPSAMPLE_ROWS = 256
"""Rows per band of :func:`upsample_bins`'s nearest-bin fill (a few MB of repeated bins at a time)."""


BIN_BAND_PIXELS = 1 << 20
"""Pixels per band of whole bins' rows in which :func:`binned_points` sums (8 MB a float64 map)."""


def upsample_cubic(coarse: np.ndarray, step: int, h: int, w: int, out: np.ndarray | None = None) -> np.ndarray:
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
