"""Predicted noise of a per-pixel fit: each sample's phase noise propagated through it.

For a linear fit ``c = P x`` the value at ``z`` is ``v(z)^T P x`` with variance
``sum_k (v(z)^T P)_k^2 sigma_k^2`` (docs/method.md section 4 gives the phase noise).
Used by the fits' sigma maps, ``ptp demo`` and the accuracy tests.
"""

from __future__ import annotations

import numpy as np

from ptpcore.fit.perpixel import z_normalisation
from ptpcore.io.lutfile import group_by_pattern
from ptpcore.io.samples import SampleStack

__all__ = ["sample_sigma", "predicted_poly_sigma", "predicted_poly_sigma_flat", "stage_pose_sample_sigma",
           "stage_pose_sigma_maps", "add_stage_pose_sigma", "MODEL_MAP_SCALES_PX", "MODEL_MAP_SPATIAL", "MODEL_MAP_WORDS",
           "model_variance_map", "sigma_parts"]


def sample_sigma(samples: SampleStack, noise_dn, n_steps: int, period_px: int, pitch_mm: float,
                 stage_sigma_mm: float = 0.0, slope=None) -> np.ndarray:
    """Predicted 1-sigma error (mm) of every sample ``X_k``.

    Parameters
    ----------
    samples : SampleStack
        Needs ``modulation`` and ``background``.
    noise_dn : callable
        ``noise_dn(level) -> sigma`` in grey levels (e.g. :meth:`SimSettings.noise_dn`).
    n_steps, period_px : int
        N and T of the finest period.
    pitch_mm : float
    stage_sigma_mm : float
        1-sigma stage position error; it moves X by ``slope * dz``.
    slope : (H, W) array, optional
        dX/dz of each pixel's ray (for the stage term).

    Returns
    -------
    (K, H, W) float64, NaN where the sample is invalid.
    """
    b = samples.modulation.astype(float)
    sig = noise_dn(samples.background)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_phi = np.sqrt(2.0 / n_steps) * sig / b
    s = s_phi * period_px / (2 * np.pi) * pitch_mm
    if stage_sigma_mm and slope is not None:
        s = np.sqrt(s * s + (np.asarray(slope) * stage_sigma_mm) ** 2)
    return np.where(samples.valid, s, np.nan)


def predicted_poly_sigma(samples: SampleStack, sigma: np.ndarray, degree: int, positions, z_eval) -> np.ndarray:
    """Predicted 1-sigma error of an unweighted ``poly`` LUT at heights ``z_eval``.

    Parameters
    ----------
    samples : SampleStack
    sigma : (K, H, W) per-sample sigma (mm), NaN where invalid
    degree : int
    positions : sequence of int
        The positions the LUT was fitted on.
    z_eval : (E,) heights (mm)

    Returns
    -------
    (E, H, W) float64
    """
    positions = np.asarray(positions)
    t, te = normalised_heights(samples.z[positions], z_eval)
    k = len(positions)
    h, w = samples.shape
    mask = samples.valid[positions].reshape(k, -1)
    sig = sigma[positions].reshape(k, -1)
    return predicted_poly_sigma_flat(t, te, mask, sig, degree).reshape(len(te), h, w)


def normalised_heights(z: np.ndarray, z_eval) -> tuple[np.ndarray, np.ndarray]:
    """The fit's normalised heights ``t`` (K,) of the positions ``z`` and ``te`` (E,) of ``z_eval`` (mm)."""
    zc, zs = z_normalisation(z)
    return (z - zc) / zs, (np.asarray(z_eval, float) - zc) / zs


def predicted_poly_sigma_flat(t: np.ndarray, te: np.ndarray, mask: np.ndarray, sig: np.ndarray,
                              degree: int) -> np.ndarray:
    """:func:`predicted_poly_sigma` of ``n`` pixels (any block of them: each pixel's value is its own).

    Parameters
    ----------
    t : (K,) float64
        Normalised heights of the fitted positions.
    te : (E,) float64
        Normalised heights to evaluate at.
    mask : (K, n) bool
        Valid samples.
    sig : (K, n) float
        Per-sample sigma (mm), any value where ``mask`` is False.
    degree : int

    Returns
    -------
    (E, n) float64, mm; NaN where a pixel has fewer than ``degree + 2`` valid samples.
    """
    out = np.full((len(te), mask.shape[1]), np.nan)
    vander = np.vander(t, degree + 1, increasing=True)
    ve = np.vander(te, degree + 1, increasing=True)
    for pattern, cols in group_by_pattern(mask):
        if pattern.sum() < degree + 2:
            continue
        g = ve @ np.linalg.pinv(vander[pattern])  # (E, n): value weights per sample
        out[:, cols] = np.sqrt((g * g) @ (sig[pattern][:, cols] ** 2))
    return out


def stage_pose_sample_sigma(samples: SampleStack, rig, pose_sigma: np.ndarray, slopes, k: int,
                            rows=slice(None)) -> tuple[np.ndarray, np.ndarray]:
    """1-sigma (mm) of every sample ``X_k``, ``Y_k`` from position ``k``'s pose uncertainty.

    A pose error moves a sample at LCD point ``(u, v)`` (mm from the LCD centre)
    by ``dX = dx - roll*v - sx*(dz + pitch*v - yaw*u)``,
    ``dY = dy + roll*u - sy*(dz + pitch*v - yaw*u)`` (:mod:`ptpcore.fit.stage_pose`);
    the six are taken as independent with the 1-sigma of ``pose_sigma[k]``.

    Parameters
    ----------
    samples : SampleStack
    rig : Rig
        LCD centre and the stage direction.
    pose_sigma : (K, 6) float64
        ``dx, dy, dz`` (um), ``pitch, yaw, roll`` (urad) 1-sigma; NaN counts as 0.
    slopes : (2,) tuple of (H, W) float64
        Every pixel's ``dX/dZ``, ``dY/dZ``.
    k : int
    rows : slice
        Image rows to compute.

    Returns
    -------
    sigma_x, sigma_y : (h, W) float64, mm (NaN where ``X_k`` is)
    """
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    zk = float(samples.z[k])
    xa = samples.x_ref[rows] + np.asarray(samples.x[k, rows], dtype=float)
    ya = samples.y_ref[rows] + np.asarray(samples.y[k, rows], dtype=float)
    u = xa - a * zk - (rig.lcd.width - 1) / 2 * px
    v = ya - b * zk - (rig.lcd.height - 1) / 2 * py
    sdx, sdy, sdz, spitch, syaw, sroll = np.nan_to_num(np.asarray(pose_sigma[k], dtype=float))
    sx, sy = (np.nan_to_num(np.asarray(s[rows], dtype=float)) for s in slopes)
    var_z = (1e-3 * sdz) ** 2 + (1e-6 * spitch * v) ** 2 + (1e-6 * syaw * u) ** 2
    var_x = (1e-3 * sdx) ** 2 + (1e-6 * sroll * v) ** 2 + sx * sx * var_z
    var_y = (1e-3 * sdy) ** 2 + (1e-6 * sroll * u) ** 2 + sy * sy * var_z
    return np.sqrt(var_x), np.sqrt(var_y)


def stage_pose_sigma_maps(samples: SampleStack, rig, lut, pose_sigma: np.ndarray, slopes, positions=None,
                          rows_per_block: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The stage pose's uncertainty propagated to each pixel's LUT: (H, W) 1-sigma maps (mm).

    Every sample carries :func:`stage_pose_sample_sigma`; through the pixel's own
    least-squares polynomial (the LUT's degree, its fitted positions) that gives
    the LUT's 1-sigma at every height, averaged (RMS) over the pixel's
    calibrated range, as the phase-noise maps are. A pose error moves every
    pixel of a position at once, so smoothing across pixels does not average it
    away: the same maps hold for the smooth LUT.

    Parameters
    ----------
    samples : SampleStack
        The samples the LUT was fitted to.
    rig : Rig
    lut : ptpcore.io.lutfile.Lut
        A ``poly`` LUT (``degree``, ``z_min``/``z_max``, ``pixel_z_min``/``max``, ``valid``).
    pose_sigma : (K, 6) float64
    slopes : (2,) tuple of (H, W) float64
    positions : sequence of int, optional
        The LUT's positions (default all).
    rows_per_block : int

    Returns
    -------
    sigma_x, sigma_y : (H, W) float64, mm; NaN where the LUT is invalid.
    """
    positions = np.arange(len(samples.z)) if positions is None else np.asarray(list(positions))
    t, _ = normalised_heights(np.asarray(samples.z, float)[positions], [])
    zs = np.linspace(lut.z_min, lut.z_max, 4 * len(positions) + 1)
    _, te = normalised_heights(np.asarray(samples.z, float)[positions], zs)
    h, w = samples.shape
    out = (np.full((h, w), np.nan), np.full((h, w), np.nan))
    for r0 in range(0, h, rows_per_block):
        rows = slice(r0, min(h, r0 + rows_per_block))
        n = (rows.stop - r0) * w
        mask = (np.asarray(samples.reasons[positions, rows]) == 0).reshape(len(positions), n)
        per = [stage_pose_sample_sigma(samples, rig, pose_sigma, slopes, int(k), rows) for k in positions]
        zmin, zmax = lut.pixel_z_min[rows].reshape(-1), lut.pixel_z_max[rows].reshape(-1)
        inside = (zs[:, None] >= zmin) & (zs[:, None] <= zmax)
        for axis, dest in enumerate(out):
            sig = np.nan_to_num(np.stack([p[axis] for p in per]).reshape(len(positions), n))
            pred = predicted_poly_sigma_flat(t, te, mask, sig, int(lut.degree or 1))
            with np.errstate(all="ignore"):
                sq = np.where(inside, pred * pred, np.nan)
                rms = np.sqrt(np.nansum(sq, axis=0) / np.maximum(np.isfinite(sq).sum(axis=0), 1))
            dest[rows] = np.where(lut.valid[rows].reshape(-1), rms, np.nan).reshape(rows.stop - r0, w)
    return out


def add_stage_pose_sigma(lut, samples: SampleStack, rig, pose_sigma: np.ndarray, slopes, positions=None) -> None:
    """:func:`stage_pose_sigma_maps` into the LUT's sigma maps, in quadrature (in place; nothing without maps)."""
    if lut.sigma_x is None or lut.sigma_y is None or lut.degree is None:
        return
    mx, my = stage_pose_sigma_maps(samples, rig, lut, pose_sigma, slopes, positions)
    lut.sigma_x = np.hypot(lut.sigma_x, np.nan_to_num(mx)).astype(np.float32)
    lut.sigma_y = np.hypot(lut.sigma_y, np.nan_to_num(my)).astype(np.float32)


# ---- the model's own error, mapped over the image --------------------------------------------

MODEL_MAP_SCALES_PX = (4.0, 8.0, 16.0, 32.0, 64.0, 128.0)
"""Candidate Gaussian scales (px) of the model-error map; a split-half cross-validation picks one per axis."""

MODEL_MAP_SPATIAL = True
"""Whether :func:`model_variance_map` maps the model variance over the image (True, the default, when
the fit gives the excess split by the parity of the held-out position) or keeps the image-wide level
everywhere (False). Issue 30's diagnosis (``python -m research.trust_excess``): the held-out excess
sees the LUT's error well (without image noise its map follows the error at 0.99 correlation), but
with noise the map's own error, about 0.1 um^2 at its best scale on the realistic preset at 640 px,
is as large as the smallest model variances: a map floored at 0 then predicts almost nothing where
the LUT still errs, and a uniform level cannot follow an error that varies 3x over the image. The
map is therefore each pixel's posterior mean of the model variance given its noisy estimate."""

MODEL_MAP_WORDS = ("mapped by Gaussian kernel regression at a scale chosen by split-half cross-validation"
                   " (held-out positions of odd against even rank), each pixel's value the posterior mean under"
                   " a log-normal spread of the model variance over the image, the map's own error from the"
                   " two halves' difference" if MODEL_MAP_SPATIAL
                   else "the image-wide mean excess, uniform over the image") + " (0 unless beyond 2 standard errors)"
"""How :func:`model_variance_map` maps the excess, in words (the LUTs' ``/provenance`` ``model_error``)."""

MAP_BIN_PX = 2
"""The model-error map is drawn on bins of this many pixels a side (sums kept): its smallest scale
is 4 px, and the Gaussian blurs' maps at 12 MP would otherwise be 100 MB each."""


def gaussian_blur(a: np.ndarray, scale: float) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(a, (0, 0), scale, borderType=cv2.BORDER_CONSTANT)


def _binned(a: np.ndarray, b: int) -> np.ndarray:
    """Sums of ``a`` (H, W) over ``b x b`` bins (the last bins short), float64."""
    rows = np.add.reduceat(a, np.arange(0, a.shape[0], b), axis=0, dtype=np.float64)
    return np.nan_to_num(np.add.reduceat(rows, np.arange(0, a.shape[1], b), axis=1))


def _unbinned(a: np.ndarray, b: int, shape) -> np.ndarray:
    """A smooth binned map back on the pixels (bilinear, bin centres), ``shape`` (H, W)."""
    import cv2

    h, w = shape
    up = cv2.resize(a, (a.shape[1] * b, a.shape[0] * b), interpolation=cv2.INTER_LINEAR)
    return up[:h, :w]


def _local_mean(s_sum: np.ndarray, s_n: np.ndarray, scale: float) -> np.ndarray:
    """Gaussian kernel regression ``G * sum / G * n`` (0 where no count reaches). Scales of 16 or more are
    drawn on coarser bins (an eighth of the scale or finer) and brought back bilinearly: a blur's cost
    grows with its kernel, 64 bins wide at 128 px, and the map is smooth at its scale."""
    f = 1
    while scale / (2 * f) >= 8.0:
        f *= 2
    if f > 1:
        small = _local_mean(_binned(s_sum, f), _binned(s_n, f), scale / f)
        return _unbinned(small, f, s_sum.shape)
    den = gaussian_blur(s_n, scale)
    return np.where(den > 1e-12, gaussian_blur(s_sum, scale) / np.maximum(den, 1e-300), 0.0)


def _split_half_scale(halves, scales) -> tuple[float, dict, tuple]:
    """The kernel scale (in bins) whose map from one half of the held-out positions best predicts the
    other half's per-bin mean (both ways, count-weighted): the halves' noise is independent, so no
    neighbourhood has to be left out and the smallest scales can win where the data resolve them.
    Also the two halves' maps at that scale (for the map's own error)."""
    cv, best = {}, None
    for s in scales:
        err, wsum = 0.0, 0.0
        maps = tuple(_local_mean(e_a, n_a, s) for e_a, n_a in halves)
        for pred, (e_b, n_b) in zip(maps, halves[::-1]):
            have = n_b > 0
            err += float(np.sum(n_b[have] * (e_b[have] / n_b[have] - pred[have]) ** 2))
            wsum += float(n_b[have].sum())
        cv[float(s)] = err / wsum if wsum > 0 else float("inf")
        if best is None or cv[float(s)] < cv[best[0]]:
            best = (float(s), maps)  # only the best scale's maps are kept
    return best[0], cv, best[1]


def _lognormal_posterior_mean(m: np.ndarray, se: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Each value's posterior mean of ``b2 >= 0`` given ``m ~ N(b2, se^2)``, under a log-normal spread of
    ``b2`` with the mean and variance of the values less their noise (moments, weighted).

    Written here because no library gives an empirical-Bayes posterior with a per-value noise: the
    integral over a log grid of ``b2`` is tabulated on a grid of (``m``, ``se``) and interpolated
    (scipy), so its cost does not grow with the image.
    """
    from scipy.interpolate import RegularGridInterpolator

    mu = float(np.sum(weight * m) / weight.sum())
    if not mu > 0:
        return np.full(m.shape, max(mu, 0.0))
    tau2 = float(np.sum(weight * (m - mu) ** 2) / weight.sum()) - float(np.sum(weight * se * se) / weight.sum())
    tau2 = max(tau2, 1e-6 * mu * mu)
    sl2 = float(np.log1p(tau2 / (mu * mu)))
    ml = float(np.log(mu)) - sl2 / 2.0
    u = np.linspace(-5.0, 5.0, 401)
    t = np.exp(ml + np.sqrt(sl2) * u)  # the prior on a log grid: density exp(-u^2 / 2) per step of log t
    m_grid = np.linspace(float(m.min()), float(m.max()), 512)
    s_hi = max(float(se.max()), 1e-30)
    s_grid = np.geomspace(max(float(se.min()), 1e-6 * s_hi), s_hi * (1 + 1e-9), 48)
    table = np.empty((m_grid.size, s_grid.size))
    for j, sd in enumerate(s_grid):
        log_like = -0.5 * ((m_grid[:, None] - t[None, :]) / sd) ** 2 - 0.5 * u * u
        like = np.exp(log_like - log_like.max(axis=1, keepdims=True))  # no underflow far from the prior
        table[:, j] = (like @ t) / like.sum(axis=1)
    look = RegularGridInterpolator((m_grid, s_grid), table, bounds_error=False, fill_value=None)
    out = np.empty(m.shape)
    for i in range(0, m.size, 1 << 18):  # the interpolator's temporaries are several times its input
        out[i:i + (1 << 18)] = look(np.stack([m[i:i + (1 << 18)], np.clip(se[i:i + (1 << 18)], s_grid[0], s_grid[-1])],
                                             axis=-1))
    return out


def _posterior_map(e: np.ndarray, n: np.ndarray, odd: tuple, scales_px) -> tuple[np.ndarray, float, dict]:
    """The spatial model-variance map (see :func:`model_variance_map`), (H, W) mm^2, its scale (px) and
    the cross-validation ``{scale px: error}``."""
    b = MAP_BIN_PX
    odd_half = (_binned(odd[0], b), _binned(odd[1], b))
    halves = [(_binned(e, b) - odd_half[0], _binned(n, b) - odd_half[1]), odd_half]
    scale, cv, (m0, m1) = _split_half_scale(halves, [s / b for s in scales_px])
    (e0, n0), (e1, n1) = halves
    n_all = n0 + n1
    m = _local_mean(e0 + e1, n_all, scale)
    # The map's own variance from the halves' difference: Var(m0 - m1) = Var(m0) + Var(m1), and m
    # (the count-weighted mean of the two, half 0's kernel weight p) has p (1 - p) of it; averaged
    # over 4 scales (the noise level changes slowly: vignetting, modulation), where one scale's
    # square is noisy.
    p = _local_mean(n0, n_all, scale)
    frac = p * (1.0 - p)
    se = np.sqrt(np.maximum(_local_mean((m0 - m1) ** 2 * n_all, n_all, 4 * scale) * frac, 0.0))
    have = (n_all > 0) & (frac > 0)
    post = np.zeros_like(m)
    post[have] = _lognormal_posterior_mean(m[have], se[have], n_all[have])
    return np.maximum(_unbinned(post, b, e.shape), 0.0), float(scale * b), {float(k * b): v for k, v in cv.items()}


def model_variance_map(excess_sum: np.ndarray, count: np.ndarray, scales_px=MODEL_MAP_SCALES_PX, excess_sq_sum: np.ndarray | None = None,
                       odd: tuple | None = None, spatial: bool | None = None) -> tuple[np.ndarray, float, dict]:
    """The model's own error variance per pixel, from held-out residuals' excess over their noise.

    Per pixel ``p`` the held-out samples give ``x = r^2 - E[noise part of r^2]`` (summed:
    ``excess_sum``, their number ``count``), whose mean is the model error ``b^2`` there plus zero-mean
    noise. With ``excess_sq_sum`` the image-wide mean must exceed 2 of its standard errors (the data
    resolve a model error at all), else the map is 0. Then, with ``odd`` (the same sums over the
    held-out positions of odd rank among the interior ones) and :data:`MODEL_MAP_SPATIAL`:

    1. ``b^2`` is mapped by Gaussian kernel regression ``G * excess_sum / G * count``, at the scale of
       :data:`MODEL_MAP_SCALES_PX` whose map from one half of the positions best predicts the other
       half (the halves' noise is independent: the pixel's own noise cannot predict itself);
    2. the map's own standard error at each pixel comes from the two halves' maps' difference;
    3. each pixel's value is the posterior mean of ``b^2`` given its map value and standard error,
       under a log-normal spread of ``b^2`` over the image whose mean and variance are the map's less
       its noise. A floor at 0 would put the noisiest low values at nothing where the LUT still errs;
       the posterior mean is calibrated given the value it is computed from, which is what sigma
       maps judged per decile of themselves need.

    Without ``odd`` (or with ``spatial`` False) the image-wide level is used everywhere.

    Parameters
    ----------
    excess_sum : (H, W) float64, mm^2
    count : (H, W) int
    scales_px : sequence of float
    excess_sq_sum : (H, W) float64, mm^4, optional
        Per pixel the sum of ``x^2``, for the standard error of the image-wide mean.
    odd : ((H, W) float64, (H, W) int), optional
        ``excess_sum`` and ``count`` of the held-out positions of odd rank only.
    spatial : bool, optional
        Default :data:`MODEL_MAP_SPATIAL`.

    Returns
    -------
    var : (H, W) float64, mm^2 (>= 0; 0 without any held-out sample or when not resolved)
    scale_px : float
        The chosen scale (NaN when uniform).
    info : dict
        ``cv`` : {scale px: split-half prediction error}, ``mean`` : the image-wide mean of ``x``
        (mm^2), ``limit`` : 2 standard errors of it (NaN without ``excess_sq_sum``), ``resolved`` : bool,
        ``spatial`` : bool (whether the map was drawn over the image).
    """
    e, n = excess_sum, count  # not copied: 100 MB each at 12 MP
    if not (n > 0).any():
        return np.zeros(e.shape), float("nan"), {"cv": {}, "spatial": False}
    total = float(np.sum(n, dtype=np.float64))
    level = float(np.nansum(e, dtype=np.float64)) / total
    limit = float("nan")
    if excess_sq_sum is not None and total > 1:
        spread = max(float(np.nansum(excess_sq_sum)) / total - level * level, 0.0)
        limit = 2.0 * np.sqrt(spread / (total - 1))
    resolved = level > 0 and not limit >= level
    info = {"cv": {}, "mean": level, "limit": limit, "resolved": bool(resolved), "spatial": False}
    if not resolved:
        return np.zeros(e.shape), float("nan"), info
    halves = odd is not None and bool(np.any(odd[1] > 0)) and bool(np.any(n > odd[1]))
    if not ((MODEL_MAP_SPATIAL if spatial is None else spatial) and halves):
        return np.full(e.shape, level), float("nan"), info
    var, scale, info["cv"] = _posterior_map(e, n, odd, scales_px)
    info["spatial"] = True
    return var, scale, info


def sigma_parts(lut, axis: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A LUT's predicted 1-sigma along ``axis`` and its two parts (docs/method.md section 5).

    The total is written (``/quality/sigma_x``); the model's part too when the fit estimated it
    (``/quality/sigma_model_x``); the noise part is what the total holds beside it in quadrature.

    Parameters
    ----------
    lut : Lut
    axis : {"x", "y"}

    Returns
    -------
    total : (H, W) float32 or None
        mm; None when the LUT has no sigma maps.
    noise : (H, W) float64 or None
        mm: propagated phase noise (and the stage-pose and glass tolerances when given); None
        without a model part (then the total is the noise alone).
    model : (H, W) float32 or None
        mm: the model's own error estimated from held-out positions; None when not estimated.
    """
    total, model = getattr(lut, f"sigma_{axis}"), getattr(lut, f"sigma_model_{axis}")
    if total is None or model is None:
        return total, None, None
    with np.errstate(invalid="ignore"):
        noise = np.sqrt(np.maximum(total.astype(np.float64) ** 2 - model.astype(np.float64) ** 2, 0.0))
    return total, noise, model
