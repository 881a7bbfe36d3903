"""The ``smooth`` LUT: a global camera model plus a per-pixel correction smoothed over the image.

Why: a plain per-pixel LUT is noise-limited (each pixel fits only its own
noisy samples); a pinhole model is bias-limited (it cannot follow a real
lens). Here

1. a pinhole + Brown model (:mod:`ptpcore.pinhole`) is fitted to a large
   random subset of all calibration samples: it carries the bulk of the
   geometry with almost no noise;
2. every pixel fits a polynomial in z to its residuals against that model,
   weighted by each sample's predicted phase noise (from the modulation and
   the camera noise measured in the data, :mod:`ptpcore.noise`);
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

import cv2
import numpy as np

from .lut import Lut, SampleStack, _z_normalisation, fit_lut
from .pinhole import PinholeModel, fit_pinhole
from .rig import Rig

def _nanmean(a, axis=None):
    """``np.nanmean`` without the all-NaN warning (all-NaN pixels are invalid anyway)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(a, axis=axis)


__all__ = ["sample_sigma_from_noise", "fit_smooth_lut", "SmoothInfo", "poly_sigma_maps",
           "local_linear_smooth", "global_pinhole"]


def sample_sigma_from_noise(samples: SampleStack, rig: Rig, stage_sigma_mm: float = 0.0) -> np.ndarray:
    """Predicted 1-sigma error (mm) of every sample, from the measured camera noise.

    ``sigma_X = sqrt(2/N) * sigma(A) / B * T / (2 pi) * pitch`` for the finest
    period (METHOD.md section 4), with ``sigma(A)`` from ``samples.noise``.

    Returns
    -------
    (K, H, W) float64, NaN where invalid.
    """
    if samples.noise is None or samples.modulation is None:
        raise ValueError("samples carry no noise model or modulation: decode them with collect_samples()")
    f = rig.fringes
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (np.sqrt(2.0 / f.steps[-1]) * samples.noise.sigma_dn(samples.background)
             / samples.modulation * f.periods_px[-1] / (2 * np.pi) * max(rig.lcd.pitch_mm))
    if stage_sigma_mm:
        s = np.hypot(s, stage_sigma_mm * 0.5)  # typical |dX/dz| of a ray ~ 0.5
    return np.where(samples.valid, s, np.nan)


def _weighted_poly(t: np.ndarray, values: np.ndarray, weights: np.ndarray, degree: int):
    """Per-pixel weighted least squares, batched through the normal equations.

    Parameters
    ----------
    t : (K,) ; values, weights : (K, P) (weight 0 where invalid)

    Returns
    -------
    coef : (D+1, P) ; cov : (P, D+1, D+1) inverse normal matrix ; n : (P,) samples used
    """
    v = np.vander(t, degree + 1, increasing=True)  # (K, D+1)
    vals = np.where(weights > 0, values, 0.0)
    a = np.einsum("kp,ki,kj->pij", weights, v, v)
    b = np.einsum("kp,ki->pi", weights * vals, v)
    n = (weights > 0).sum(axis=0)
    ok = n >= degree + 1
    coef = np.full((degree + 1, values.shape[1]), np.nan)
    cov = np.full((values.shape[1], degree + 1, degree + 1), np.nan)
    if ok.any():
        inv = np.linalg.inv(a[ok])
        cov[ok] = inv
        coef[:, ok] = np.einsum("pij,pj->ip", inv, b[ok])
    return coef, cov, n


def _gauss(arr: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian filter with zeros outside the image (truncated at 3 sigma).

    OpenCV's separable SIMD filter is used rather than ``scipy.ndimage``: it is
    several times faster at the large scales the cross-validation tries.
    """
    k = 2 * int(np.ceil(3.0 * sigma)) + 1
    return cv2.GaussianBlur(np.ascontiguousarray(arr, dtype=np.float64), (k, k), sigma, sigmaY=sigma,
                            borderType=cv2.BORDER_CONSTANT)


def _first_row_of_inverse(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row 0 of the inverse of symmetric 3x3 matrices ``(..., 3, 3)``, and their determinants.

    Closed-form cofactors: batched LAPACK calls cost far more than the
    arithmetic for millions of 3x3 systems.
    """
    a00, a01, a02 = a[..., 0, 0], a[..., 0, 1], a[..., 0, 2]
    a11, a12, a22 = a[..., 1, 1], a[..., 1, 2], a[..., 2, 2]
    c0 = a11 * a22 - a12 * a12
    c1 = a02 * a12 - a01 * a22
    c2 = a01 * a12 - a02 * a11
    det = a00 * c0 + a01 * c1 + a02 * c2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([c0, c1, c2], -1) / det[..., None], det


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
    vals = np.where(weights > 0, values, 0.0)
    stacked = vals.ndim == 3
    vals = vals if stacked else vals[None]
    # Coordinates in units of the scale keep the 3x3 systems well conditioned.
    rr, cc = np.mgrid[0:h, 0:w]
    x = cc / scale_px
    y = rr / scale_px

    def moments(filt, wv):
        return _local_moments(filt(wv), filt(wv * x), filt(wv * y), filt(wv * x * x), filt(wv * x * y),
                              filt(wv * y * y), x, y)

    g = lambda arr: _gauss(arr, scale_px)  # noqa: E731
    a = moments(g, weights)
    s0 = a[..., 0, 0]
    row_all, det = _first_row_of_inverse(a)
    good = (s0 > 1e-12 * max(s0.max(), 1e-300)) & (np.abs(det) > 1e-12 * np.maximum(s0, 1e-300) ** 3)
    row = row_all[good]
    out = np.full(vals.shape, np.nan)
    t0s = []
    for i, v in enumerate(vals):
        t0 = g(weights * v)
        t0s.append(t0)
        if good.any():
            rhs = np.stack([t0[good], (g(weights * v * x) - x * t0)[good], (g(weights * v * y) - y * t0)[good]], -1)
            out[i][good] = np.einsum("pj,pj->p", row, rhs)
    var = np.full((h, w), np.nan) if with_variance else None
    if good.any() and with_variance:
        # var(value_q) = 1 / w_q gives var = (A^-1 B A^-1)[0, 0], B the same
        # moments under G^2, and G_s^2 = G_{s/sqrt2} / (4 pi s^2).
        g2 = lambda arr: _gauss(arr, scale_px / np.sqrt(2.0)) / (4 * np.pi * scale_px ** 2)  # noqa: E731
        b = moments(g2, weights)[good]
        var[good] = np.einsum("pi,pij,pj->p", row, b, row)
    # Locally constant estimate where the linear system is singular.
    weak = ~good & (s0 > 0)
    if weak.any():
        for i, t0 in enumerate(t0s):
            out[i][weak] = t0[weak] / s0[weak]
        if with_variance:
            g2w = _gauss(weights, scale_px / np.sqrt(2.0)) / (4 * np.pi * scale_px ** 2)
            var[weak] = g2w[weak] / s0[weak] ** 2
    if with_variance:
        var = np.where(np.isfinite(out[0]), var, np.nan)
    return (out if stacked else out[0]), var


def _local_moments(s0, sx, sy, sxx, sxy, syy, x, y) -> np.ndarray:
    """3x3 moment matrices about each pixel from raw weighted moments, (H, W, 3, 3)."""
    mx = sx - x * s0
    my = sy - y * s0
    mxx = sxx - 2 * x * sx + x * x * s0
    myy = syy - 2 * y * sy + y * y * s0
    mxy = sxy - x * sy - y * sx + x * y * s0
    return np.stack([np.stack([s0, mx, my], -1), np.stack([mx, mxx, mxy], -1),
                     np.stack([my, mxy, myy], -1)], -2)


def global_pinhole(samples: SampleStack, positions, n_points: int = 20000, seed: int = 0) -> PinholeModel:
    """Fit the pinhole + Brown model to a random subset of valid calibration samples."""
    rng = np.random.default_rng(seed)
    h, w = samples.shape
    pts, pix = [], []
    positions = list(positions)
    per = max(n_points // len(positions), 10)
    for k in positions:
        idx = np.flatnonzero(samples.valid[k].ravel())
        if idx.size == 0:
            continue
        pick = rng.choice(idx, size=min(per, idx.size), replace=False)
        x, y = samples.absolute(k)
        r, c = np.divmod(pick, w)
        pts.append(np.stack([x.ravel()[pick], y.ravel()[pick], np.full(pick.size, samples.z[k])], 1))
        pix.append(np.stack([c, r], 1).astype(float))
    return fit_pinhole(np.concatenate(pts), np.concatenate(pix)).model


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
    """

    pinhole: PinholeModel
    scale_px: float
    scales_px: np.ndarray
    cv_rms_mm: np.ndarray
    noise_scale: float = 1.0
    excess_sigma_mm: float = 0.0


def _uniform_moments(degree: int) -> np.ndarray:
    """``M[i, j] = mean of t^(i+j)`` for t uniform on [-1, 1]."""
    p = np.add.outer(np.arange(degree + 1), np.arange(degree + 1))
    return np.where(p % 2 == 0, 1.0 / (p + 1.0), 0.0)


def sigma_scale(samples: SampleStack, rig: Rig, positions=None, stage_sigma_mm: float = 0.0,
                degree: int = 2) -> float:
    """Factor that makes the predicted sample noise match the fit residuals.

    The per-sample prediction (:func:`sample_sigma_from_noise`) relies on the
    N-step residual variance, which also contains harmonics of a non-linear
    display or camera response (they barely move the phase of an N-step fit).
    Every pixel's own degree-2 fit over z leaves ``n - 3`` degrees of freedom
    whose residuals measure the noise that really reaches X and Y; pooled over
    all pixels they calibrate the prediction:
    ``s^2 = sum_p n_p rms_p^2 / sum_p (n_p - D - 1) mean_k sigma_pk^2``.
    """
    positions = list(range(samples.z.size)) if positions is None else list(positions)
    lut = fit_lut(samples, "poly", degree, positions=positions)
    sub = samples.subset(positions)
    sig = sample_sigma_from_noise(sub, rig, stage_sigma_mm)
    n = sub.valid.sum(axis=0)
    use = lut.valid & (n > degree + 1)
    if not use.any():
        return 1.0
    with np.errstate(all="ignore"):
        mean_var = _nanmean(sig * sig, axis=0)
    num = 0.0
    den = 0.0
    for a in ("rms_x", "rms_y"):
        r = getattr(lut, a).astype(np.float64)
        ok = use & np.isfinite(r) & np.isfinite(mean_var)
        num += float(np.sum(n[ok] * r[ok] ** 2))
        den += float(np.sum((n[ok] - degree - 1) * mean_var[ok]))
    return float(np.sqrt(num / den)) if den > 0 else 1.0


def _global_rays(model: PinholeModel, shape) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    h, w = shape
    rr, cc = np.mgrid[0:h, 0:w].astype(float)
    x0, y0 = model.pixel_to_world_at_z(cc, rr, 0.0)
    x1, y1 = model.pixel_to_world_at_z(cc, rr, 1.0)
    return x0, y0, x1 - x0, y1 - y0


def _smooth_correction(t, resid_x, resid_y, wts, degree, scale, shape, with_variance=True):
    """Per-pixel weighted fit of the X and Y residuals, then smooth each coefficient map.

    X and Y share the sample weights, hence the coefficient variances and the
    smoothing weights: both are smoothed in one pass.

    Returns
    -------
    coef : (2, D+1, H, W) smoothed coefficients of X and Y
    var : (D+1, H, W) their variance (same for X and Y; NaN without ``with_variance``)
    """
    cx, cov, _ = _weighted_poly(t, resid_x, wts, degree)
    cy, _, _ = _weighted_poly(t, resid_y, wts, degree)
    out = np.empty((2, degree + 1, *shape))
    var = np.full((degree + 1, *shape), np.nan)
    for j in range(degree + 1):
        vj = cov[:, j, j].reshape(shape)
        both = np.stack([cx[j].reshape(shape), cy[j].reshape(shape)])
        with np.errstate(divide="ignore", invalid="ignore"):
            wj = np.where(np.isfinite(both).all(axis=0) & (vj > 0), 1.0 / vj, 0.0)
        out[:, j], vj_s = local_linear_smooth(np.nan_to_num(both), wj, scale, with_variance)
        if vj_s is not None:
            var[j] = vj_s
    return out, var


def fit_smooth_lut(samples: SampleStack, rig: Rig, degree: int = 2, positions=None, *,
                   scales_px=(0.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0), stage_sigma_mm: float = 0.0,
                   seed: int = 0, rig_toml: str = "",
                   progress: Callable[[float, str], None] | None = None) -> tuple[Lut, SmoothInfo]:
    """Fit the ``smooth`` LUT (see the module docstring).

    Parameters
    ----------
    samples : SampleStack
        From :func:`ptpcore.pipeline.collect_samples` (needs its noise model).
    rig : Rig
    degree : int
        Degree in z of the correction and of the stored polynomials (1 to 5).
    positions : sequence of int, optional
        Calibration positions (default all).
    scales_px : sequence of float
        Candidate smoothing scales (camera px) for cross-validation.
    stage_sigma_mm : float
        Stage position uncertainty added to each sample's sigma.
    seed : int
        For the global model's random sample.
    progress : callable, optional

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
    report = progress or (lambda f, m: None)
    report(0.0, "fitting the global camera model")
    model = global_pinhole(samples, positions, seed=seed)
    gx0, gy0, gsx, gsy = _global_rays(model, samples.shape)
    sub = samples.subset(positions)
    z = sub.z
    zc, zs = _z_normalisation(z)
    t = (z - zc) / zs
    k = z.size
    shape = samples.shape
    sigma = sample_sigma_from_noise(sub, rig, stage_sigma_mm).reshape(k, -1)
    noise_scale = sigma_scale(samples, rig, positions, stage_sigma_mm)
    wts = np.where(np.isfinite(sigma) & (sigma > 0), 1.0 / np.square(sigma), 0.0)
    resid = {}
    for a, g0, gs in (("x", gx0, gsx), ("y", gy0, gsy)):
        absval = getattr(sub, f"{a}_ref")[None] + getattr(sub, a).astype(np.float64)
        r = absval - (g0[None] + gs[None] * z[:, None, None])
        resid[a] = r.reshape(k, -1)
    usable_global = np.isfinite(gx0) & np.isfinite(gy0)
    wts[:, ~usable_global.ravel()] = 0.0

    # Cross-validation over the smoothing scale: two folds of alternate positions
    # (each fold keeps the z range covered by the other).
    # Each fold keeps half the positions: with few positions the folds fit a
    # lower degree in z (the scale that suits the image-wide field barely
    # depends on it); with fewer than 4 positions no scale can be validated.
    scales = np.asarray(scales_px, dtype=float)
    cv_degree = min(degree, k // 2 - 1)
    folds = [np.arange(k) % 2 == f for f in (0, 1)] if cv_degree >= 1 else []
    if not folds:
        warnings.warn(f"smooth LUT: {k} calibration positions are too few to cross-validate the smoothing"
                      " scale (need 4); the correction is not smoothed", RuntimeWarning, stacklevel=2)
    cv = np.zeros(scales.size)
    excess = np.zeros(scales.size)
    sum_w = np.zeros(scales.size)
    n_used = np.zeros(scales.size)
    for fi, test in enumerate(folds):
        train = ~test
        for si, sc in enumerate(scales):
            report(0.05 + 0.8 * (fi * scales.size + si) / (len(folds) * scales.size),
                   f"cross-validating smoothing scale {sc:g} px")
            cxy, _ = _smooth_correction(t[train], resid["x"][train], resid["y"][train], wts[train], cv_degree,
                                        sc, shape, False)
            for a, c in zip("xy", cxy):
                vt = np.vander(t[test], cv_degree + 1, increasing=True)
                pred = np.tensordot(vt, c.reshape(cv_degree + 1, -1), axes=1)
                w_test = wts[test]
                err = np.where(w_test > 0, pred - resid[a][test], np.nan)
                use = np.isfinite(err)
                # Normalised by each sample's own noise: a chi-square-like score.
                cv[si] += np.sum(err[use] ** 2 * w_test[use])
                # Inverse-variance weighted excess of the error over the sample
                # noise: the fold fit's own noise plus its bias (an upper bound
                # on the final fit's model error, which uses twice the data).
                excess[si] += np.sum(w_test[use] * (err[use] ** 2 - noise_scale ** 2 / w_test[use]))
                sum_w[si] += np.sum(w_test[use])
                n_used[si] += use.sum()
    if folds:
        score = np.where(n_used > 0, cv / np.maximum(n_used, 1), np.nan)
        best = int(np.nanargmin(score))
        excess_var = max(excess[best] / sum_w[best], 0.0) if sum_w[best] > 0 else 0.0
    else:
        best = 0
        excess_var = 0.0
    scale = float(scales[best])

    report(0.9, f"fitting the smooth LUT at scale {scale:g} px")
    # Global ray as a polynomial in t: X = x0 + sx * (zc + zs t).
    h, w = shape
    coef = {}
    var = {}
    cxy, v = _smooth_correction(t, resid["x"], resid["y"], wts, degree, scale, shape)
    for a, c, g0, gs in (("x", cxy[0], gx0, gsx), ("y", cxy[1], gy0, gsy)):
        c[0] += g0 + gs * zc
        c[1] += gs * zs
        coef[a], var[a] = c, v
    n_pos = sub.valid.sum(axis=0)
    valid = np.isfinite(coef["x"]).all(axis=0) & np.isfinite(coef["y"]).all(axis=0) & (n_pos >= 1)
    zk = np.where(sub.valid, z[:, None, None], np.nan)
    with np.errstate(all="ignore"):
        pz_min = np.where(valid, np.nanmin(np.where(sub.valid, zk, np.inf), axis=0), np.nan)
        pz_max = np.where(valid, np.nanmax(np.where(sub.valid, zk, -np.inf), axis=0), np.nan)
    # Residuals and leave-one-out-like quality against the pixel's own samples.
    vander = np.vander(t, degree + 1, increasing=True)
    q = {}
    for a in "xy":
        pred = np.tensordot(vander, coef[a], axes=1)
        absval = getattr(sub, f"{a}_ref")[None] + getattr(sub, a).astype(np.float64)
        r = np.where(sub.valid, absval - pred, np.nan)
        with np.errstate(all="ignore"):
            q[a] = np.sqrt(_nanmean(r * r, axis=0)).astype(np.float32)
    # Predicted sigma: RMS over the calibrated range (uniform in t) of the
    # smoothed correction's noise propagated from the phase noise. The model
    # error beyond it (smoothing bias) is estimated by cross-validation and
    # reported in SmoothInfo.excess_sigma_mm, not folded into the map: the
    # fold fits use half the positions, so it is an upper bound.
    moments = _uniform_moments(degree)
    sig = {}
    for a in "xy":
        s2 = np.einsum("j,jhw->hw", np.diag(moments), var[a])
        sig[a] = (np.sqrt(s2) * noise_scale).astype(np.float32)
    for a in "xy":
        coef[a][:, ~valid] = np.nan
        sig[a][~valid] = np.nan
        q[a][~valid] = np.nan
    lut = Lut(
        kind="poly", degree=degree, z_center=zc, z_scale=zs, z_min=float(z.min()), z_max=float(z.max()),
        x=coef["x"], y=coef["y"], z_nodes=None, valid=valid,
        n_positions=np.where(valid, n_pos, 0).astype(np.uint16),
        pixel_z_min=pz_min.astype(np.float32), pixel_z_max=pz_max.astype(np.float32),
        rms_x=q["x"], rms_y=q["y"],
        # The smooth fit barely moves when one position is left out: its
        # leave-one-out error is its residual against the held-out sample.
        loo_x=q["x"].copy(), loo_y=q["y"].copy(),
        sigma_x=sig["x"], sigma_y=sig["y"], rig_toml=rig_toml,
        extra_attrs={"method": "smooth", "smoothing_scale_px": scale},
    )
    report(1.0, "smooth LUT fitted")
    # Reported as the chi-square per test sample (1 = prediction as good as the noise allows).
    cv_rms = score if folds else np.full(scales.size, np.nan)
    return lut, SmoothInfo(model, scale, scales, cv_rms, noise_scale, float(np.sqrt(excess_var)))


def poly_sigma_maps(samples: SampleStack, rig: Rig, lut: Lut, positions=None,
                    stage_sigma_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Predicted 1-sigma maps (mm) of a plain, unweighted ``poly`` LUT.

    The variance of the fitted value at each calibrated node, propagated from
    every sample's phase noise through the pixel's own least-squares fit, and
    averaged (RMS) over the pixel's nodes.

    Returns
    -------
    sigma_x, sigma_y : (H, W) float32
    """
    from .accuracy import predicted_poly_sigma

    positions = list(range(samples.z.size)) if positions is None else list(positions)
    scale = sigma_scale(samples, rig, positions, stage_sigma_mm)
    sig = sample_sigma_from_noise(samples, rig, stage_sigma_mm) * scale
    # RMS over the calibrated range: evaluate on a fine uniform grid of z.
    zs = np.linspace(lut.z_min, lut.z_max, 4 * len(positions) + 1)
    pred = predicted_poly_sigma(samples, sig, lut.degree, positions, zs)  # (E, H, W)
    inside = (zs[:, None, None] >= lut.pixel_z_min) & (zs[:, None, None] <= lut.pixel_z_max)
    with np.errstate(all="ignore"):
        s = np.sqrt(_nanmean(np.where(inside, pred * pred, np.nan), axis=0))
    s = np.where(lut.valid, s, np.nan).astype(np.float32)
    return s, s.copy()
