"""The per-pixel height map ``u_p -> Z`` of a scanner's projector (docs/method.md section 9).

Along one camera pixel's ray, a pinhole projector's coordinate ``u_p`` and the height are related by
a linear fractional function; distortion and defocus bend it slightly:

    Z = (p_0 + p_1 s + ... + p_D s^D) / (1 + q_1 s),    s = (u_p - u_center) / u_scale

with ``u_center``, ``u_scale`` the middle and half-width of the pixel's own ``u_p`` range. Multiplied
out, ``Z = p_0 + ... + p_D s^D - q_1 s Z`` is linear in the unknowns. The noise is in ``u_p`` (the
heights are stage readings): the linearised equation of sample k has the variance
``((1 + q_1 s_k) dZ/du_p sigma_u,k)^2`` from the current fit, so the fit is weighted by its inverse
and repeated (each pass a weighted linear least squares, all pixels at once). Samples beyond
:data:`K_SIGMA` of their predicted noise are left out (robust), the degree is chosen by held-out
positions as for the XY LUT, and a pixel whose denominator would vanish within its range
(``|q_1| >= Q_MAX``) has no map.

The sigma of the map (:attr:`HeightMap.sigma_z`): the propagated noise of its samples (the
weighted fit's covariance, RMS over the pixel's range) and the model's own error, estimated from
held-out positions' residuals beyond their predicted noise, mapped over the image
(:func:`ptpcore.fit.sigma.model_variance_map`), in quadrature.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ptpcore.fit.choice import choice_folds
from ptpcore.fit.sigma import model_variance_map
from ptpcore.io.heightmap import HeightMap

__all__ = ["fit_height_map", "HeightFit", "K_SIGMA", "Q_MAX", "DEGREES"]

K_SIGMA = 5.0
"""A sample whose residual exceeds this many of its predicted sigmas is left out of its pixel."""

Q_MAX = 0.9
"""Largest ``|q_1|`` kept: the pole ``s = -1/q_1`` at least 1/0.9 half-widths from the middle, so the
denominator stays at least 0.1 over the pixel's range."""

MIN_HALF_RANGE_PX = 0.5
"""A pixel whose ``u_p`` spans less than twice this (projector px) over the sweep has no map: its
heights cannot be told apart by ``u_p``."""

DEGREES = (1, 2, 3)
"""Candidate numerator degrees (1: the pinhole projector's exact form)."""

PASSES = 4
"""Weighted passes before any rejection."""

REJECT_ROUNDS = 3
"""Rejection rounds (each leaves out at most one sample per pixel, then refits)."""


TILE_PIXELS = 1 << 15
"""Pixels fitted together: the (K, T, D+2) design arrays stay a few tens of MB."""

_EVAL_S, _EVAL_W = np.polynomial.legendre.leggauss(8)
_EVAL_W = _EVAL_W / _EVAL_W.sum()
"""Where (and with which weights) the fit's noise is averaged for its RMS over the pixel's range
(Gauss-Legendre: the mean over ``s`` in [-1, 1], exact for the polynomial part)."""


@dataclass
class HeightFit:
    """One degree's per-pixel fit, flat over pixels (P = H*W).

    Attributes
    ----------
    coef : (D+2, P) float64
        ``p_0 .. p_D, q_1``; NaN where invalid.
    cov : (P, D+2, D+2) float64
        Their covariance (mm^2 units for p) from the weighted fit.
    valid : (P,) bool
    used : (K, P) bool
        Samples the fit kept (valid, not rejected).
    residual : (K, P) float64, mm
        ``Z_k - Z(u_k)`` (NaN where the sample is not valid).
    var : (K, P) float64, mm^2
        Predicted noise variance of each sample in Z: ``(dZ/du_p sigma_u)^2``.
    leverage : (K, P) float64
        Hat-matrix diagonal of the weighted linearised fit.
    """

    degree: int
    coef: np.ndarray
    cov: np.ndarray
    valid: np.ndarray
    used: np.ndarray
    residual: np.ndarray
    var: np.ndarray
    leverage: np.ndarray


def _design(s: np.ndarray, z: np.ndarray, degree: int) -> np.ndarray:
    """Rows ``[1, s, .., s^D, -s Z]`` of the linearised equation: (K, P, D+2)."""
    cols = [s ** i for i in range(degree + 1)] + [-s * z[:, None]]
    return np.stack(cols, axis=-1)


def _rational(coef: np.ndarray, s: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Z and dZ/ds of the map ``coef`` (D+2, P) at ``s`` (E, P)."""
    num = np.zeros(s.shape)
    dnum = np.zeros(s.shape)
    for i in range(degree, -1, -1):
        dnum = dnum * s + num
        num = num * s + coef[i]
    q = coef[degree + 1]
    den = 1.0 + q * s
    with np.errstate(divide="ignore", invalid="ignore"):  # a vanishing denominator: that pixel is dropped (Q_MAX)
        return num / den, (dnum * den - num * q) / (den * den)


def _weighted_solve(a: np.ndarray, z: np.ndarray, w: np.ndarray):
    """Per-pixel weighted least squares: ``a`` (K, P, m), ``z`` (K,), ``w`` (K, P) (0 leaves a sample out).

    Returns coefficients (m, P), the inverse normal matrix (P, m, m) and the leverages (K, P); NaN
    where the normal matrix is singular.
    """
    aw = a * w[..., None]
    normal = np.einsum("kpi,kpj->pij", aw, a)
    rhs = np.einsum("kpi,k->pi", aw, z)
    m = a.shape[-1]
    # Fewer samples than unknowns: singular; such a pixel gets the identity and NaN results.
    ok = np.count_nonzero(w > 0, axis=0) >= m
    normal[~ok] = np.eye(m)
    try:
        inv = np.linalg.inv(normal)
    except np.linalg.LinAlgError:  # a degenerate pixel among them (e.g. repeated u_p): slower, per pixel
        inv = np.linalg.pinv(normal)
    ok &= np.all(np.isfinite(inv), axis=(1, 2))
    coef = np.einsum("pij,pj->ip", inv, rhs)
    lev = np.einsum("kpi,pij,kpj->kp", aw, inv, a)
    coef[:, ~ok] = np.nan
    inv[~ok] = np.nan
    return coef, inv, lev


def fit_degree(s: np.ndarray, z: np.ndarray, mask: np.ndarray, sigma_u: np.ndarray, u_scale: np.ndarray,
               degree: int, k_sigma: float | None = K_SIGMA) -> HeightFit:
    """The weighted, robust rational fit of one degree to every pixel's samples.

    Parameters
    ----------
    s : (K, P) float64
        Normalised projector coordinates (any value where ``mask`` is False).
    z : (K,) float64, mm
        The heights.
    mask : (K, P) bool
        Valid samples.
    sigma_u : (K, P) float64, projector px
        Predicted 1-sigma of each ``u_p``.
    u_scale : (P,) float64
    degree : int
    k_sigma : float or None
        Leave out samples beyond this many predicted sigmas (None: keep all).

    Returns
    -------
    HeightFit
    """
    s = np.where(mask, s, 0.0)
    a = _design(s, z, degree)
    used = mask.copy()
    sig_s = np.where(mask, sigma_u / u_scale, 1.0)  # sigma of s
    factor = np.ones(s.shape)  # (1 + q s) dZ/ds, from the previous pass
    total = PASSES + (REJECT_ROUNDS if k_sigma else 0)
    for it in range(total):
        var_lin = (factor * sig_s) ** 2
        w = np.where(used, 1.0 / np.maximum(var_lin, 1e-300), 0.0)
        coef, inv, lev = _weighted_solve(a, z, w)
        zf, dz_ds = _rational(coef, s, degree)
        q = coef[degree + 1]
        with np.errstate(invalid="ignore", over="ignore"):  # degenerate pixels are dropped below
            factor = np.where(np.isfinite(dz_ds), (1.0 + q * s) * dz_ds, 1.0)
        if k_sigma and PASSES - 1 <= it < total - 1:
            with np.errstate(invalid="ignore", divide="ignore"):
                # studentised: a kept sample's residual has (1 - h) of its noise's variance
                stud2 = (z[:, None] - zf) ** 2 / ((dz_ds * sig_s) ** 2 * np.maximum(1.0 - lev, 1e-3))
            used = used & ~_outliers(stud2, used, k_sigma, a.shape[-1])
    n = used.sum(axis=0)
    q = coef[degree + 1]
    valid = np.all(np.isfinite(coef), axis=0) & (n >= degree + 3) & (np.abs(q) < Q_MAX)
    coef[:, ~valid] = np.nan
    # cov of the linearised fit: the weights were 1 / var of each equation, so (A^T W A)^-1.
    return HeightFit(degree, coef, inv, valid, used & valid, np.where(mask, z[:, None] - zf, np.nan),
                     (dz_ds * sig_s) ** 2, np.where(used, lev, np.nan))


def _robust_scale2(stud2: np.ndarray, sel: np.ndarray) -> float:
    """Squared spread of studentised residuals over the image, from their median (|N(0,1)| has median
    0.6745), at least 1: where a model cannot follow its data everywhere, every residual grows, and
    the threshold with them (the model's error is not an outlier; a few wild samples are)."""
    vals = np.sqrt(stud2[sel & np.isfinite(stud2)])
    if vals.size == 0:
        return 1.0
    return max(1.0, (float(np.median(vals)) / 0.6745) ** 2)


def _outliers(stud2: np.ndarray, used: np.ndarray, k_sigma: float, n_unknowns: int) -> np.ndarray:
    """Per pixel, its worst kept sample when beyond ``k_sigma`` robust sigmas (one a round: a wild
    sample drags the fit, and its neighbours' residuals with it), unless that would leave fewer than
    ``n_unknowns + 1`` samples."""
    scale2 = _robust_scale2(stud2, used)
    s2 = np.where(used & np.isfinite(stud2), stud2, -1.0)
    worst = np.argmax(s2, axis=0)
    cols = np.arange(s2.shape[1])
    beyond = (s2[worst, cols] > k_sigma ** 2 * scale2) & (used.sum(axis=0) > n_unknowns + 1)
    bad = np.zeros(used.shape, bool)
    bad[worst[beyond], cols[beyond]] = True
    return bad


def _fit_noise_var(fit: HeightFit, s_eval: np.ndarray) -> np.ndarray:
    """Variance (mm^2) of the fitted Z at ``s_eval`` (E, P) from the fit's covariance (noise only)."""
    d = fit.degree
    z, _ = _rational(fit.coef, s_eval, d)
    q = fit.coef[d + 1]
    den = 1.0 + q * s_eval
    grad = np.stack([s_eval ** i / den for i in range(d + 1)] + [-s_eval * z / den], axis=-1)  # (E, P, m)
    return np.einsum("epi,pij,epj->ep", grad, fit.cov, grad)


def _normalise(u: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel: the middle and half-width of its valid ``u_p`` (P,), and its range (P,)."""
    lo = np.min(np.where(mask, u, np.inf), axis=0)
    hi = np.max(np.where(mask, u, -np.inf), axis=0)
    centre = 0.5 * (lo + hi)
    scale = 0.5 * (hi - lo)
    bad = ~np.isfinite(centre) | ~(scale >= MIN_HALF_RANGE_PX)
    centre[bad], scale[bad] = np.nan, np.nan
    return centre, scale, lo, hi


def _held_out(u, sigma_u, z, mask, degree, folds, k_sigma):
    """Held-out residuals of one degree: per fold, fit on its calibration positions, predict the others.

    Returns squared residuals (K, P) and their predicted variances (noise of the sample plus the
    fit's own noise there), NaN where not predicted.
    """
    k_all, p_all = mask.shape
    r2 = np.full((k_all, p_all), np.nan)
    v = np.full((k_all, p_all), np.nan)
    for cal, held in folds:
        c_mask = mask[cal]
        centre, scale, lo, hi = _normalise(u[cal], c_mask)
        s_cal = (u[cal] - centre) / scale
        fit = fit_degree(s_cal, z[cal], c_mask, sigma_u[cal], scale, degree, k_sigma)
        s_h = (u[held] - centre) / scale
        inside = mask[held] & fit.valid & (u[held] >= lo) & (u[held] <= hi)
        s_h = np.where(inside, s_h, 0.0)
        zh, dz_ds = _rational(fit.coef, s_h, degree)
        fit_var = _fit_noise_var(fit, s_h)
        r2[held] = np.where(inside, (z[held][:, None] - zh) ** 2, np.nan)
        v[held] = np.where(inside, (dz_ds * sigma_u[held] / scale) ** 2 + fit_var, np.nan)
    if k_sigma:  # a wild held-out sample is not the model's error either
        with np.errstate(invalid="ignore"):
            stud2 = r2 / v
        wild = np.isfinite(r2) & ~(stud2 <= k_sigma ** 2 * _robust_scale2(stud2, np.isfinite(r2)))
        r2[wild], v[wild] = np.nan, np.nan
    return r2, v


def _choose_degree(sums: dict, n: int) -> tuple[int, dict]:
    """The lowest degree whose held-out mean squared error is within two standard errors of the best.

    ``sums``: per degree the sum of squared held-out residuals over the ``n`` samples every degree
    predicted. The standard error of a mean of n squared residuals is ``sqrt(2 / n)`` of it
    (chi-square): a higher degree must beat a lower one by more than that to be worth its extra unknown.
    """
    mse = {d: total / n if n else float("inf") for d, total in sums.items()}
    best = min(mse.values())
    limit = best * (1.0 + 2.0 * np.sqrt(2.0 / max(n, 1)))
    pick = min(d for d, m in mse.items() if m <= limit)
    return pick, {"held_out_rms_mm": {str(d): float(np.sqrt(m)) for d, m in mse.items()}, "n_samples": int(n),
                  "pick": pick, "rule": "lowest degree within 2 standard errors of the best held-out mean square"}


def _tiles(p_total: int):
    for start in range(0, p_total, TILE_PIXELS):
        yield slice(start, min(start + TILE_PIXELS, p_total))


def fit_height_map(u: np.ndarray, sigma_u: np.ndarray, z, *, degree: int | None = None, positions=None,
                   k_sigma: float | None = K_SIGMA, design: dict | None = None, direction: str = "x") -> HeightMap:
    """Fit the per-pixel height map to a height sweep's decoded projector coordinates.

    Pixels are fitted in tiles of :data:`TILE_PIXELS` (a bounded working set on a big sensor; the
    robust scale is each tile's). The degree is chosen over the whole image, then every tile is
    fitted with it on all positions, and the model's error is mapped over the image.

    Parameters
    ----------
    u : (K, H, W) float, projector px
        Decoded ``u_p`` at every height; NaN where invalid.
    sigma_u : (K, H, W) float, projector px
        Predicted 1-sigma of each ``u_p``.
    z : (K,) float, mm
        The plate's height readings.
    degree : int, optional
        Numerator degree; default: chosen among :data:`DEGREES` by held-out positions.
    positions : sequence of int, optional
        Fit only these heights (e.g. the calibration half of a split).
    k_sigma : float or None
        Robust rejection threshold (None: keep every valid sample).
    design : dict
        The projector's pattern design (``/height`` attributes).
    direction : {"x", "y"}

    Returns
    -------
    HeightMap
    """
    k_all, h, w = np.shape(u)
    idx = np.arange(k_all) if positions is None else np.asarray(positions)
    z = np.asarray(z, float)[idx]
    # views (a spilled decode's memory maps stay on disk); each tile reads its pixels of the positions
    uf = _positions(u, idx)
    sf = _positions(sigma_u, idx)
    folds = choice_folds(len(idx))
    cands = DEGREES if degree is None else (int(degree),)
    excess = {d: np.zeros((3, h * w)) for d in cands}  # per pixel: sum of x, of x^2, count (held out)
    sums, n_common = {d: 0.0 for d in cands}, 0
    for sl in _tiles(h * w):
        ut, st, mask = _tile(uf, sf, sl)
        held = {d: _held_out(ut, st, z, mask, d, folds, k_sigma) for d in cands}
        common = np.logical_and.reduce([np.isfinite(r2) for r2, _v in held.values()])
        n_common += int(common.sum())
        for d, (r2, v) in held.items():
            sums[d] += float(r2[common].sum())
            ok = np.isfinite(r2)
            x = np.where(ok, r2 - v, 0.0)
            excess[d][:, sl] = x.sum(axis=0), (x * x).sum(axis=0), ok.sum(axis=0)
    if degree is None:
        degree, choice = _choose_degree(sums, n_common)
        chosen_by = "held-out positions"
    else:
        choice, chosen_by = {"pick": int(degree)}, "user"
    model_var, model_info = _model_variance(excess[degree], (h, w))
    out = _FlatMap.empty(h * w, degree)
    for sl in _tiles(h * w):
        ut, st, mask = _tile(uf, sf, sl)
        out.fill(sl, ut, st, z, mask, degree, k_sigma)
    return out.height_map(model_var, (h, w), design or {}, direction, chosen_by,
                          {"degree_choice": choice, "model_error": model_info})


class _positions:
    """Some positions of a ``(K, H, W)`` array, read by pixel tiles: ``[:, sl]`` gives ``(K', T)``."""

    def __init__(self, a, idx: np.ndarray):
        self.flat = np.asarray(a).reshape(np.shape(a)[0], -1)  # a view, also of a memory map
        self.idx = idx

    def __getitem__(self, key) -> np.ndarray:
        _all, sl = key
        return self.flat[self.idx, sl]


def _tile(uf, sf, sl: slice):
    """One tile's ``u_p``, sigma (float64 copies, (K, T)) and valid samples."""
    ut = np.asarray(uf[:, sl], float)
    st = np.asarray(sf[:, sl], float)
    with np.errstate(invalid="ignore"):
        mask = np.isfinite(ut) & np.isfinite(st) & (st > 0)
    return ut, st, mask


def _model_variance(excess: np.ndarray, shape) -> tuple[np.ndarray, dict]:
    """The model's own error variance map (mm^2) from held-out residuals beyond their predicted noise
    (``excess``: (3, P) per pixel the sum of x = r^2 - predicted, of x^2, and their count)."""
    var, scale, info = model_variance_map(excess[0].reshape(shape), excess[2].reshape(shape),
                                          excess_sq_sum=excess[1].reshape(shape))
    return var.reshape(-1), {"scale_px": scale, "mean_mm2": info.get("mean"), "resolved": info.get("resolved")}


@dataclass
class _FlatMap:
    """A height map's per-pixel results over the flat image (P = H*W), filled tile by tile."""

    degree: int
    centre: np.ndarray
    scale: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    coef: np.ndarray
    valid: np.ndarray
    n: np.ndarray
    n_rejected: np.ndarray
    rms: np.ndarray
    loo: np.ndarray
    noise_var: np.ndarray

    @classmethod
    def empty(cls, p_total: int, degree: int) -> "_FlatMap":
        f = lambda: np.full(p_total, np.nan)  # noqa: E731
        return cls(degree, f(), f(), f(), f(), np.full((degree + 2, p_total), np.nan), np.zeros(p_total, bool),
                   np.zeros(p_total, int), np.zeros(p_total, int), f(), f(), f())

    def fill(self, sl: slice, ut, st, z, mask, degree: int, k_sigma) -> None:
        """Fit one tile on every position and keep its per-pixel results."""
        centre, scale, lo, hi = _normalise(ut, mask)
        fit = fit_degree((ut - centre) / scale, z, mask, st, scale, degree, k_sigma)
        used = fit.used
        n = used.sum(axis=0)
        res = np.where(used, fit.residual, 0.0)
        loo = np.where(used, fit.residual / np.maximum(1.0 - np.nan_to_num(fit.leverage), 1e-6), 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.rms[sl] = np.sqrt((res ** 2).sum(axis=0) / n)
            self.loo[sl] = np.sqrt((loo ** 2).sum(axis=0) / n)
        self.centre[sl], self.scale[sl], self.lo[sl], self.hi[sl] = centre, scale, lo, hi
        self.coef[:, sl], self.valid[sl], self.n[sl] = fit.coef, fit.valid, n
        self.n_rejected[sl] = (np.isfinite(fit.residual) & ~used).sum(axis=0)
        grid = np.broadcast_to(_EVAL_S[:, None], (len(_EVAL_S), n.size))
        self.noise_var[sl] = _EVAL_W @ _fit_noise_var(fit, grid)

    def height_map(self, model_var, shape, design, direction, chosen_by, provenance) -> HeightMap:
        """The :class:`HeightMap` (flat arrays reshaped to the image; NaN / 0 where invalid)."""
        h, w = shape
        v = self.valid
        d = self.degree

        def img(a, dtype=np.float32, fill=np.nan):
            return np.where(v, a, fill).astype(dtype).reshape(h, w)

        coef = np.where(v, self.coef, np.nan)
        return HeightMap(
            degree=d, direction=direction, u_center=img(self.centre, np.float64), u_scale=img(self.scale, np.float64),
            p=coef[:d + 1].reshape(d + 1, h, w), q=coef[d + 1:].reshape(1, h, w), valid=v.reshape(h, w),
            u_min=img(self.lo), u_max=img(self.hi), rms_z=img(self.rms), loo_z=img(self.loo),
            sigma_z=img(np.sqrt(self.noise_var + model_var)), n_positions=img(self.n, np.uint16, 0),
            design=dict(design), chosen_by=chosen_by, sigma_model_z=img(np.sqrt(model_var)),
            n_rejected=img(self.n_rejected, np.uint16, 0), provenance=provenance,
        )
