"""Predicted noise of a per-pixel fit: each sample's phase noise propagated through it.

For a linear fit ``c = P x`` the value at ``z`` is ``v(z)^T P x`` with variance
``sum_k (v(z)^T P)_k^2 sigma_k^2`` (METHOD.md section 4 gives the phase noise).
Used by the fits' sigma maps, ``ptp demo`` and the accuracy tests.
"""

from __future__ import annotations

import numpy as np

from ptpcore.fit.perpixel import _z_normalisation
from ptpcore.io.lutfile import _group_by_pattern
from ptpcore.io.samples import SampleStack

__all__ = ["sample_sigma", "predicted_poly_sigma", "predicted_poly_sigma_flat", "stage_pose_sample_sigma",
           "stage_pose_sigma_maps", "add_stage_pose_sigma", "MODEL_MAP_SCALES_PX", "MODEL_MAP_SPATIAL", "MODEL_MAP_WORDS",
           "correlation_length_px",
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
    t, te = _normalised_heights(samples.z[positions], z_eval)
    k = len(positions)
    h, w = samples.shape
    mask = samples.valid[positions].reshape(k, -1)
    sig = sigma[positions].reshape(k, -1)
    return predicted_poly_sigma_flat(t, te, mask, sig, degree).reshape(len(te), h, w)


def _normalised_heights(z: np.ndarray, z_eval) -> tuple[np.ndarray, np.ndarray]:
    """The fit's normalised heights ``t`` (K,) of the positions ``z`` and ``te`` (E,) of ``z_eval`` (mm)."""
    zc, zs = _z_normalisation(z)
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
    for pattern, cols in _group_by_pattern(mask):
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
    t, _ = _normalised_heights(np.asarray(samples.z, float)[positions], [])
    zs = np.linspace(lut.z_min, lut.z_max, 4 * len(positions) + 1)
    _, te = _normalised_heights(np.asarray(samples.z, float)[positions], zs)
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
"""Candidate Gaussian scales (px) of the model-error map; cross-validation picks one per axis."""

MODEL_MAP_SPATIAL = False
"""Whether :func:`model_variance_map` shares the model variance out over the image (True) or keeps it
uniform at the image-wide level (False, the default). Measured on issue 30's harness (half A, reduced,
one draw each): the spatial map, with or without the shrinkage, made the lowest decile of predicted
sigma worse than the uniform level (realistic x: RMS(z) 4.4 against 0.75; ripple x: 1.62 against
1.34): where the leave-one-out excess maps near 0 the smooth LUT still errs (0.28 um on realistic),
so the excess does not see all of the LUT's error there. Until it does, the level is the honest map."""

MODEL_MAP_WORDS = ("mapped by Gaussian kernel regression at a cross-validated scale, shrunk toward and scaled to"
                   " the image-wide mean excess" if MODEL_MAP_SPATIAL
                   else "the image-wide mean excess, uniform over the image") + " (0 unless beyond 2 standard errors)"
"""How :func:`model_variance_map` maps the excess, in words (the LUTs' ``/provenance`` ``model_error``)."""

DECORRELATION_LENGTHS = 3
"""Pixels nearer than this many correlation lengths are left out of a pixel's cross-validated
prediction: a Gaussian correlation is below 1.1 % beyond 3 lengths."""


def correlation_length_px(smoothing_scale_px: float) -> float:
    """Correlation length (px) of a LUT's noise: ``sqrt(2) * s`` for a Gaussian smoothing of scale ``s``
    (the autocorrelation of Gaussian-smoothed white noise) plus about 1 px of camera blur."""
    return float(np.sqrt(2.0) * max(float(smoothing_scale_px), 0.0) + 1.0)


def _gauss(a: np.ndarray, scale: float) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(a, (0, 0), scale, borderType=cv2.BORDER_CONSTANT)


def _hole_kernel_sum(a: np.ndarray, scale: float, radius: int) -> np.ndarray:
    """``a`` convolved with the Gaussian of ``scale`` restricted to ``|d| <= radius`` (unnormalised
    like :func:`_gauss`: the same weights), for taking a pixel's neighbourhood out of its prediction."""
    import cv2

    r = int(radius)
    d = np.arange(-r, r + 1, dtype=float)
    g1 = np.exp(-0.5 * (d / scale) ** 2)
    k = max(int(2 * np.ceil(4 * scale) + 1), 2 * r + 1)  # cv2's kernel for float64: 8 sigma + 1 wide
    full = np.exp(-0.5 * (np.arange(-(k // 2), k // 2 + 1) / scale) ** 2)
    g1 = g1 / full.sum()
    disc = (d[:, None] ** 2 + d[None, :] ** 2) <= r * r
    kernel = np.outer(g1, g1) * disc
    return cv2.filter2D(a, -1, kernel, borderType=cv2.BORDER_CONSTANT)


def _uniform_level(e: np.ndarray, n: np.ndarray, excess_sq_sum) -> tuple[np.ndarray, float, dict]:
    """The image-wide mean of ``x`` everywhere when it is beyond 2 standard errors, else 0."""
    total = float(n.sum())
    level = float(e.sum()) / total
    limit = float("nan")
    if excess_sq_sum is not None and total > 1:
        spread = max(float(np.nansum(excess_sq_sum)) / total - level * level, 0.0)
        limit = 2.0 * np.sqrt(spread / (total - 1))
    resolved = level > 0 and not limit >= level
    info = {"cv": {}, "radius_px": 0, "mean": level, "limit": limit, "resolved": bool(resolved)}
    return np.full(e.shape, level if resolved else 0.0), float("nan"), info


def _shrink_to_level(local: np.ndarray, den: np.ndarray, n: np.ndarray, scale: float, level: float,
                     spread: float, have: np.ndarray) -> np.ndarray:
    """Empirical-Bayes shrinkage of the kernel map toward the image-wide level.

    The kernel estimate at ``p`` has sampling variance ``se2 = v sum_q G(p-q)^2 n_q / (sum_q G n)^2``
    (``v`` the per-sample variance of ``x``, ``G^2`` a Gaussian of scale ``s / sqrt(2)`` over
    ``4 pi s^2``); the true map's spread over the image is ``tau2 = var(local) - mean(se2)``. Each
    pixel keeps ``tau2 / (tau2 + se2)`` of its departure from the level (James-Stein): where the
    data resolve the map it stays, where they do not it falls back to the level, not to a noisy 0.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        se2 = spread * _gauss(n, scale / np.sqrt(2.0)) / (4.0 * np.pi * scale * scale) / (den * den)
    w = n[have]
    tau2 = max(float(np.sum(w * (local[have] - level) ** 2) / w.sum()) - float(np.sum(w * se2[have]) / w.sum()), 0.0)
    keep = np.where(np.isfinite(se2), tau2 / (tau2 + se2), 0.0) if tau2 > 0 else 0.0
    return level + keep * (local - level)


def model_variance_map(excess_sum: np.ndarray, count: np.ndarray, smoothing_scale_px: float = 0.0,
                       scales_px=MODEL_MAP_SCALES_PX, excess_sq_sum: np.ndarray | None = None,
                       shrink: bool = True, spatial: bool | None = None) -> tuple[np.ndarray, float, dict]:
    """The model's own error variance per pixel, from held-out residuals' excess over their noise.

    Per pixel ``p`` the held-out samples give ``x = r^2 - E[noise part of r^2]`` (summed:
    ``excess_sum``, their number ``count``), whose mean is the model error ``b^2`` there plus zero-mean
    noise. ``b^2`` is mapped by Gaussian kernel regression ``G * excess_sum / G * count`` at a scale
    chosen by cross-validation: each pixel's ``x`` is predicted from the pixels farther than
    :data:`DECORRELATION_LENGTHS` correlation lengths (:func:`correlation_length_px`), so that the
    pixel's own noise and its correlated neighbours' do not predict it, and the scale with the
    smallest count-weighted squared prediction error wins. The map is floored at 0 (a variance), and
    then scaled so that its count-weighted mean is the image-wide mean of ``x`` (unbiased, where the
    floor alone would bias a noisy map up): the data set the level, the map only shares it out. With
    ``excess_sq_sum`` the image-wide mean must exceed 2 of its standard errors (the data resolve a
    model error at all), else the map is 0.

    Parameters
    ----------
    excess_sum : (H, W) float64, mm^2
    count : (H, W) int
    smoothing_scale_px : float
        The LUT's smoothing scale (its noise's correlation), 0 for a per-pixel model.
    scales_px : sequence of float
    excess_sq_sum : (H, W) float64, mm^4, optional
        Per pixel the sum of ``x^2``, for the standard error of the image-wide mean.
    shrink : bool
        Shrink the kernel map toward the level by its standard error (:func:`_shrink_to_level`).
    spatial : bool, optional
        Map over the image (default :data:`MODEL_MAP_SPATIAL`); False: the level everywhere (no
        cross-validation, ``scale_px`` NaN).

    Returns
    -------
    var : (H, W) float64, mm^2 (>= 0; 0 without any held-out sample or when not resolved)
    scale_px : float
        The chosen scale (NaN without samples).
    info : dict
        ``cv`` : {scale: prediction error}, ``radius_px`` : the left-out radius, ``mean`` : the
        image-wide mean of ``x`` (mm^2), ``limit`` : 2 standard errors of it (NaN without
        ``excess_sq_sum``), ``resolved`` : bool.
    """
    e = np.nan_to_num(np.asarray(excess_sum, dtype=np.float64))
    n = np.asarray(count, dtype=np.float64)
    have = n > 0
    if not have.any():
        return np.zeros(e.shape), float("nan"), {"cv": {}, "radius_px": 0}
    if not (MODEL_MAP_SPATIAL if spatial is None else spatial):
        return _uniform_level(e, n, excess_sq_sum)
    radius = int(np.ceil(DECORRELATION_LENGTHS * correlation_length_px(smoothing_scale_px)))
    mean_x = np.where(have, e / np.maximum(n, 1), 0.0)
    cv = {}
    for s in scales_px:
        num = _gauss(e, s) - _hole_kernel_sum(e, s, radius)
        den = _gauss(n, s) - _hole_kernel_sum(n, s, radius)
        ok = have & (den > 1e-6 * n.sum() / n.size)  # a prediction that rests on some held-out data
        if ok.sum() < 0.5 * have.sum():
            continue
        pred = num[ok] / den[ok]
        cv[float(s)] = float(np.sum(n[ok] * (mean_x[ok] - pred) ** 2) / n[ok].sum())
    scale = min(cv, key=cv.get) if cv else float(max(scales_px))
    total = float(n.sum())
    level = float(e.sum()) / total
    limit, spread = float("nan"), 0.0
    if excess_sq_sum is not None and total > 1:
        spread = max(float(np.nansum(excess_sq_sum)) / total - level * level, 0.0)
        limit = 2.0 * np.sqrt(spread / (total - 1))
    resolved = level > 0 and not limit >= level
    info = {"cv": cv, "radius_px": radius, "mean": level, "limit": limit, "resolved": bool(resolved)}
    if not resolved:
        return np.zeros(e.shape), float(scale), info
    with np.errstate(invalid="ignore", divide="ignore"):
        den = _gauss(n, scale)
        var = np.nan_to_num(np.where(den > 0, _gauss(e, scale) / den, 0.0))
        if shrink and excess_sq_sum is not None:
            var = _shrink_to_level(var, den, n, scale, level, spread, have)
    var = np.maximum(var, 0.0)
    mean_map = float(np.sum(var * n)) / total
    return (var * (level / mean_map) if mean_map > 0 else np.full(e.shape, level)), float(scale), info


def sigma_parts(lut, axis: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A LUT's predicted 1-sigma along ``axis`` and its two parts (METHOD.md section 5).

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
