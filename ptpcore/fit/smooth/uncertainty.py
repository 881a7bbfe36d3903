"""Step 7 of the smooth fit, and the plain LUT's: per-pixel 1-sigma maps.

``sigma^2 = noise^2 + stage + leak + model`` (:func:`uncertainty_maps`): the phase noise propagated
through the smoothed fit (:func:`smooth_sigma_maps`), the stage readings' error
(:func:`stage_variance`), the global model's own fit error that the smoothing passes on
(:func:`global_leak_variance`) and the leave-one-out's model error. :func:`poly_sigma_maps` gives
a plain ``poly`` LUT its sigma maps.
"""

from __future__ import annotations

import numpy as np

from ptpcore.fit.sigma import normalised_heights, model_variance_map, predicted_poly_sigma_flat
from ptpcore.io.lutfile import group_by_pattern
from ptpcore.store import read_block, row_store
from ptpcore.fit.smooth.blocks import nanmean0, row_blocks, run_blocks
from ptpcore.fit.smooth.leave_one_out import LooSetup, LooSums, ModelError, leave_one_out
from ptpcore.fit.smooth.noise import noise_rows, sigma_scale, stage_leverage
from ptpcore.fit.smooth.pixel_fits import PixelFits, range_moments
from ptpcore.fit.smooth.smoothing import SharedWeightSmoother, final_bin_side, upsample_cubic
from ptpcore.io.lutfile import Lut
from ptpcore.io.samples import SampleStack
from ptpcore.pinhole.camera import PinholeModel
from ptpcore.rig.rigfile import Rig

__all__ = ["uncertainty_maps", "stage_variance", "global_leak_variance", "smooth_sigma_maps", "noise_polynomial",
           "poly_sigma_maps",
           "poly_model_variance",
           "LEAK_GRID_PX"]


def stage_variance(rays, rig: Rig, t: np.ndarray, degree: int, stage_sigma_mm: float) -> dict:
    """Per-pixel variance (mm^2, float32 (H, W) per axis) from the stage readings' error; empty if none.

    Per-position stage errors move all pixels together (see :func:`stage_leverage`).
    """
    if not stage_sigma_mm:
        return {}
    lev = stage_leverage(t, degree)
    out = {a: np.empty(rays.shape, np.float32) for a in "xy"}
    for r0, r1 in row_blocks(*rays.shape):
        _, _, gsx, gsy = rays.rows(r0, r1)
        for a, gs, d in (("x", gsx, 0), ("y", gsy, 1)):
            out[a][r0:r1] = (np.square((gs - rig.stage.direction[d]) * stage_sigma_mm) * lev).astype(np.float32)
    return out


def uncertainty_maps(setup: LooSetup, gfit, inputs: dict, fits: "PixelFits", valid: np.ndarray,
                     stage_var: dict, full: bool, report):
    """The smooth LUT's sigma maps, leave-one-out maps and model-error term.

    ``sigma^2 = noise^2 + stage + leak + model``: the propagated phase noise (``inputs["noise"]``,
    (H, W) mm), the stage readings' term (``stage_var``, :func:`stage_variance`), the global
    model's error passed on by the smoothing (:func:`global_leak_variance`, with the smoothing
    weights ``inputs["leak_w"]``) and the model error the leave-one-out resolves
    (:func:`leave_one_out`). Without ``full`` only the first two, and NaN leave-one-out maps.
    ``inputs`` is emptied once its maps are used (not held through the leave-one-out).

    Returns
    -------
    sig, loo : dict ``"x"``, ``"y"`` -> (H, W) float32, mm ; model : ModelError
        (its ``sigma``: the model part of ``sig``, (H, W) float32 mm per axis)
    """
    s = setup
    leak = {}
    if full:
        report(0.91, "propagating the global model's uncertainty")
        leak = global_leak_variance(gfit, inputs["leak_w"], s.scale, s.cv_bin, fits.pz_min, fits.pz_max,
                                    s.z_norm)
    noise = inputs.pop("noise")
    inputs.clear()
    sums = LooSums(valid.shape)
    noise_var = np.square(noise.astype(np.float64))  # the same for both axes
    for a in "xy":
        sums.put("fit_var", a, noise_var + np.nan_to_num(stage_var.get(a, 0.0), nan=0.0)
                 + np.nan_to_num(leak.pop(a, 0.0), nan=0.0))
        sums.put("noise_var", a, noise_var)
    del noise, noise_var, leak
    if full:
        loo, merr = leave_one_out(s, valid, sums, lambda f, m: report(0.92 + 0.07 * f, m))
    else:
        loo = {a: np.full(valid.shape, np.nan, np.float32) for a in "xy"}
        merr = ModelError({a: np.zeros(valid.shape) for a in "xy"}, 0.0, float("nan"), None)
    sig = {a: np.empty(valid.shape, np.float32) for a in "xy"}
    for a in "xy":
        for r0, r1 in row_blocks(*valid.shape):
            sig[a][r0:r1] = np.sqrt(sums.rows("fit_var", a, r0, r1) + merr.var[a][r0:r1]).astype(np.float32)
    # In the sigma maps now; its part kept as float32 sigma maps (/quality/sigma_model_x, _y), the
    # float64 variances not held while the LUT's coefficients come back (190 MB at 12 MP).
    merr.sigma = {a: np.sqrt(merr.var[a]).astype(np.float32) for a in "xy"}
    merr.var = None
    return sig, loo, merr


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


LEAK_GRID_PX = 8
"""Grid step (px) on which :func:`global_leak_variance` recomputes the perturbed global rays."""


def global_leak_variance(gfit, weights: np.ndarray, scale: float, b: int, pz_min, pz_max,
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
    weights : (2, H, W) float64 row store (:func:`ptpcore.store.row_store`), the smoothing weights of
        coefficients 0 and 1
        (:func:`smoothing_weights`)
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
    fb = final_bin_side(b, scale)
    # Every direction and axis smooths with the same two weight maps: their bins and the local fits'
    # systems are made once (SharedWeightSmoother), not once per direction and axis (issue 33); the
    # pixels' range moments once too (a row store: 120 MB at 5 MP not held).
    smoothers = [SharedWeightSmoother(weights.plane_rows(j), scale, fb) for j in range(2)]
    mom = row_store((3, h, w))
    for r0, r1 in row_blocks(h, w):
        with np.errstate(all="ignore"):
            mom[:, r0:r1] = range_moments(((pz_min[r0:r1] - zc) / zs).astype(np.float64),
                                          ((pz_max[r0:r1] - zc) / zs).astype(np.float64), 2)
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
            c = np.empty((2, h, w))  # [coefficient j]
            upsample_cubic(moved[i0] - base[i0], step, h, w, out=c[0])
            upsample_cubic(moved[i1] - base[i1], step, h, w, out=c[1])
            for r0, r1 in row_blocks(h, w):
                c[0, r0:r1] += c[1, r0:r1] * zc
            c[1] *= zs
            for j in range(2):
                smoothed = np.nan_to_num(c[j])
                c[j] -= smoothers[j].smooth(smoothed, out=smoothed)
                del smoothed
            for r0, r1 in row_blocks(h, w):
                m = mom.row_block(r0, r1)
                l0, l1 = c[0, r0:r1], c[1, r0:r1]
                out[a][r0:r1] += np.nan_to_num(l0 ** 2 * m[0] + 2 * l0 * l1 * m[1] + l1 ** 2 * m[2])
            del c
    return out


def smooth_sigma_maps(fits: PixelFits, zc: float, zs: float, degree: int, noise_scale: float,
                      stage_var: dict) -> dict:
    """Predicted 1-sigma maps (mm, float32 (H, W) per axis) of the smooth LUT.

    RMS over the calibrated range (uniform in t) of the smoothed correction's noise propagated from
    the phase noise: ``sum_ij m_(i+j) cov_ij`` with the smoothed coefficients' variances
    (``fits.var``) and covariances (``fits.cov_off``, :func:`smoothed_covariance`: each coefficient
    map is smoothed with its own weights) and ``m`` the range's moments of ``t``. Without the
    covariances (an old caller), the pixel's own ratio of full to diagonal variance scales the
    smoothed diagonal: that form under-predicted 1.5-2.7x (issue 30). The model error beyond the
    noise is the leave-one-out's (:func:`uncertainty_maps`).
    """
    d1 = degree + 1
    h, w = fits.pz_min.shape
    pairs = np.triu_indices(d1, 1)
    sig1 = np.empty((h, w), np.float32)
    for r0, r1 in row_blocks(h, w):  # row blocks: the moments are (2D+1) float64 maps
        with np.errstate(all="ignore"):
            mom = range_moments(((fits.pz_min[r0:r1] - zc) / zs).astype(np.float64),
                                ((fits.pz_max[r0:r1] - zc) / zs).astype(np.float64), 2 * degree)
            var = fits.var.row_block(r0, r1)
            smooth_diag = np.einsum("jhw,jhw->hw", var, mom[2 * np.arange(d1)])
            if fits.cov_off is not None:
                cov = fits.cov_off.row_block(r0, r1)
                s2 = smooth_diag + 2 * np.einsum("phw,phw->hw", cov, mom[pairs[0] + pairs[1]])
            else:
                own_diag = fits.own_diag[r0:r1]
                s2 = fits.own_var[r0:r1] * np.where(own_diag > 0, smooth_diag / own_diag, np.nan)
            # Where the covariances are not known (no support), the uncorrelated form.
            s2 = np.where(np.isfinite(s2) & (s2 >= 0), s2, smooth_diag)
        sig1[r0:r1] = np.sqrt(s2) * noise_scale
    sig = {"x": sig1, "y": sig1.copy()}
    for a, sv in stage_var.items():
        sig[a] = np.sqrt(np.square(sig[a]) + np.nan_to_num(sv, nan=0.0)).astype(np.float32)
    return sig


def noise_polynomial(fits: PixelFits, degree: int, noise_scale: float):
    """The smoothed LUT's propagated noise variance at any height, as a polynomial in ``t``.

    ``var(t) = sum_m c_m t**m`` with ``c_m = noise_scale**2 sum_(i+j=m) C_ij``, ``C`` the smoothed
    coefficients' covariance (``fits.var``, ``fits.cov_off``): the same variance
    :func:`smooth_sigma_maps` averages over each pixel's range, here kept per height for the
    leave-one-out, whose left-out fit must be judged at the left-out height
    (:func:`ptpcore.fit.smooth.leave_one_out.model_error`).

    Returns
    -------
    (2D+1, H, W) float64 row store, mm^2 per ``t**m`` (a file above :data:`ptpcore.store.SPILL_PIXELS`
    pixels), or None without the covariances.
    """
    if fits.cov_off is None:
        return None
    d1 = degree + 1
    h, w = fits.pz_min.shape
    out = row_store((2 * d1 - 1, h, w))
    pairs = np.triu_indices(d1, 1)
    for r0, r1 in row_blocks(h, w):
        var, cov = fits.var.row_block(r0, r1), fits.cov_off.row_block(r0, r1)
        c = np.zeros((2 * d1 - 1, r1 - r0, w))
        for j in range(d1):
            c[2 * j] += var[j]
        for p, (i, j) in enumerate(zip(*pairs)):
            c[i + j] += 2.0 * cov[p]
        out[:, r0:r1] = c * noise_scale ** 2
    return out


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
    positions = list(range(samples.z.size)) if positions is None else list(positions)
    if scale is None:
        scale = sigma_scale(samples, rig, positions)
    sel = np.asarray(positions)
    z = np.asarray(samples.z, dtype=float)[sel]
    # RMS over the calibrated range: evaluate on a fine uniform grid of z.
    zs = np.linspace(lut.z_min, lut.z_max, 4 * len(positions) + 1)
    t, te = normalised_heights(z, zs)
    h, w = samples.shape
    # A stage reading off by dz moves the sample by (dX/dz - a) dz: the pixel's own slope.
    axes = ((0, lut.x), (1, lut.y)) if stage_sigma_mm else ((0, None),)
    maps = [np.empty((h, w), np.float32) for _ in axes]

    def block(r0, r1):
        valid, _, _, sig = noise_rows(samples, rig, sel, r0 * w, r1 * w)
        sig = sig * scale
        inside = (zs[:, None] >= lut.pixel_z_min[r0:r1].reshape(-1)) & (zs[:, None] <= lut.pixel_z_max[r0:r1].reshape(-1))
        for (d, coef), out in zip(axes, maps):
            s = sig if coef is None else np.hypot(sig, np.abs(
                coef[1, r0:r1].reshape(-1) / lut.z_scale - rig.stage.direction[d]) * stage_sigma_mm)
            pred = predicted_poly_sigma_flat(t, te, valid, s, lut.degree)  # (E, n)
            with np.errstate(all="ignore"):
                rms = np.sqrt(nanmean0(np.where(inside, pred * pred, np.nan)))
            out[r0:r1] = np.where(lut.valid[r0:r1].reshape(-1), rms, np.nan).reshape(r1 - r0, w)

    run_blocks(block, row_blocks(h, w))
    return (maps[0], maps[0].copy()) if len(maps) == 1 else tuple(maps)


def poly_model_variance(samples: SampleStack, rig: Rig, lut: Lut, positions=None, stage_sigma_mm: float = 0.0,
                        scale: float = 1.0) -> tuple[dict, dict]:
    """The model's own error variance of a plain, unweighted ``poly`` LUT, per pixel and axis (mm^2).

    Every interior calibration sample's leave-one-out residual ``e_k = r_k / (1 - h_kk)`` (the closed
    form of the pixel's least-squares fit, no refit) has ``E[e_k^2] = Var(r_k) / (1 - h_kk)^2 + b_k^2``
    with ``Var(r_k) = sum_j (I - H)_kj^2 sigma_j^2`` from the samples' predicted noise (``scale`` x
    :func:`ptpcore.fit.smooth.noise.phase_sigma_mm`, with the stage readings' term as in
    :func:`poly_sigma_maps`) and ``b_k`` the error of the curve fitted without the sample: the model's
    own error between the calibrated heights. ``x_k = e_k^2 - Var(r_k) / (1 - h_kk)^2`` summed per
    pixel is mapped by :func:`ptpcore.fit.sigma.model_variance_map` (0 unless the image-wide mean is
    beyond 2 standard errors). Only interior positions count:
    the LUT is used between its calibrated heights, and leaving an end out extrapolates.

    Returns
    -------
    var : dict ``"x"``, ``"y"`` -> (H, W) float64, mm^2 (>= 0, NaN where the LUT is invalid)
    info : dict ``scale_px`` per axis, ``n_samples``, ``resolved_limit_mm`` per axis (the square root of
        2 standard errors of the image-wide mean excess)
    """
    positions = list(range(samples.z.size)) if positions is None else list(positions)
    sel = np.asarray(positions)
    z = np.asarray(samples.z, dtype=float)[sel]
    t, _ = normalised_heights(z, [])
    interior = (z > z.min()) & (z < z.max())
    h, w = samples.shape
    sums = {a: np.zeros(h * w) for a in "xy"}
    sums_sq = {a: np.zeros(h * w) for a in "xy"}
    sums_odd = {a: np.zeros(h * w) for a in "xy"}
    count = np.zeros(h * w)
    count_odd = np.zeros(h * w)
    vander = np.vander(t, lut.degree + 1, increasing=True)
    odd = np.zeros(sel.size, bool)  # interior positions of odd rank: the halves of the map's validation
    odd[np.flatnonzero(interior)[1::2]] = True

    def block(r0, r1):
        a0, a1 = r0 * w, r1 * w
        valid, _, _, sig = noise_rows(samples, rig, sel, a0, a1)
        valid = valid & lut.valid[r0:r1].reshape(-1)[None, :]
        sig = sig * scale
        for d, a in enumerate("xy"):
            coef = getattr(lut, a)[:, r0:r1].reshape(lut.degree + 1, -1)
            s = sig if not stage_sigma_mm else np.hypot(sig, np.abs(
                coef[1] / lut.z_scale - rig.stage.direction[d]) * stage_sigma_mm)
            ref = getattr(samples, f"{a}_ref").reshape(-1)[a0:a1]
            vals = read_block(getattr(samples, a), a0, a1, sel).astype(np.float64) + ref[None, :]
            r = vals - vander @ coef
            x = np.zeros(r.shape)
            use = np.zeros(r.shape, bool)
            for pattern, cols in group_by_pattern(valid):
                if pattern.sum() < lut.degree + 2:
                    continue
                vp = vander[pattern]
                m = np.eye(int(pattern.sum())) - vp @ np.linalg.pinv(vp)  # I - H
                var_r = (m * m) @ (s[pattern][:, cols] ** 2)
                one_minus_h = np.diag(m)[:, None]
                xp = (r[pattern][:, cols] ** 2 - var_r) / one_minus_h ** 2
                inner = interior[pattern]
                rows_idx = np.flatnonzero(pattern)[inner]
                x[np.ix_(rows_idx, cols)] = xp[inner]
                use[np.ix_(rows_idx, cols)] = np.isfinite(xp[inner])
            sums[a][a0:a1] = np.where(use, x, 0.0).sum(axis=0)
            sums_sq[a][a0:a1] = np.where(use, x * x, 0.0).sum(axis=0)
            sums_odd[a][a0:a1] = np.where(use & odd[:, None], x, 0.0).sum(axis=0)
            if d == 0:
                count[a0:a1] = use.sum(axis=0)
                count_odd[a0:a1] = (use & odd[:, None]).sum(axis=0)

    run_blocks(block, row_blocks(h, w))
    var, scales, limits = {}, {}, {}
    for a in "xy":
        v, scales[a], info = model_variance_map(sums[a].reshape(h, w), count.reshape(h, w),
                                                excess_sq_sum=sums_sq[a].reshape(h, w),
                                                odd=(sums_odd[a].reshape(h, w), count_odd.reshape(h, w)))
        var[a] = np.where(lut.valid, v, np.nan)
        limits[a] = float(np.sqrt(info["limit"])) if np.isfinite(info["limit"]) else float("nan")
    return var, {"scale_px": scales, "n_samples": int(count.sum()), "resolved_limit_mm": limits}
