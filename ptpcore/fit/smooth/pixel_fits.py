"""Step 2 and 4 of the smooth fit: every pixel's own fit in z, the pass that makes them, and the
cross-validation of the smoothing scale.

:class:`SmoothPass` reads the samples once, strip by strip: every pixel fits a polynomial in
``t = (z - zc) / zs`` to its residuals against the global model, weighted by the predicted noise
(:class:`PixelFits`, :func:`weighted_poly_fits`), and two folds of alternate positions score every
candidate scale by the held-out samples' error. :func:`smoothed_coefficients` then smooths the
coefficient maps at the chosen scale and adds the global ray back; :func:`residual_maps` gives the
LUT's residual RMS. The maps wait in :mod:`ptpcore.store` row stores (files at 5-12 MP).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from ptpcore.fit.smooth.blocks import nanmean0, row_blocks, run_blocks, sample_blocks
from ptpcore.fit.smooth.global_model import corrected_samples, footprint_bias, global_residuals
from ptpcore.fit.smooth.lsq import weighted_poly_fits
from ptpcore.fit.smooth.noise import residual_dof_variance
from ptpcore.fit.smooth.smoothing import (bin_factor, bin_sums, binned_points, binned_sigma, final_bin_side,
                                          local_linear_grid, smooth_on_bins, smoothed_covariance)
from ptpcore.io.samples import SampleStack
from ptpcore.rig.rigfile import Rig
from ptpcore.store import load, park, read_block, row_store

__all__ = ["PixelFits", "SmoothPass", "weighted_poly_fits", "range_moments", "smoothed_coefficients",
           "smoothing_weights", "residual_maps", "STRIP_ROWS"]


def range_moments(ta: np.ndarray, tb: np.ndarray, order: int) -> np.ndarray:
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


@dataclass
class PixelFits:
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
        Predicted sample variance per residual degree of freedom of the plain degree-2 fit
        (:func:`ptpcore.fit.smooth.noise.residual_dof_variance`, for :func:`sigma_scale_from`).
    own_var, own_diag : (H, W) float64
        The fit's variance averaged over the pixel's own range, with the
        covariances and with the coefficients taken as uncorrelated.
    cov_off : (P, H, W) float64
        The coefficients' covariances per unit sample variance, pairs ``(i, j)``, ``i < j``, in the
        order of ``numpy.triu_indices(D + 1, 1)``; after :func:`smoothed_coefficients`, those of the
        smoothed coefficients (:func:`ptpcore.fit.smooth.smoothing.smoothed_covariance`).
    """

    fit: np.ndarray
    var: np.ndarray
    n_pos: np.ndarray
    pz_min: np.ndarray
    pz_max: np.ndarray
    mean_var: np.ndarray
    own_var: np.ndarray
    own_diag: np.ndarray
    cov_off: np.ndarray | None = None

    @classmethod
    def empty(cls, shape, d1: int, own: bool = True) -> "PixelFits":
        """Uninitialised maps; ``fit``, ``var``, ``own_var`` and ``own_diag`` are row stores
        (:func:`ptpcore.store.row_store`: files at 5-12 MP, written by row ranges; :meth:`load` brings
        them back). Without ``own``, ``mean_var``, ``own_var`` and ``own_diag`` are None (not computed)."""
        h, w = shape
        pairs = d1 * (d1 - 1) // 2
        return cls(row_store((2, d1, h, w)), row_store((d1, h, w)), np.empty((h, w), np.int32),
                   np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w)) if own else None,
                   row_store((h, w)) if own else None, row_store((h, w)) if own else None,
                   row_store((pairs, h, w)) if own and pairs else None)

    def park(self, name: str) -> None:
        """Send map ``name`` to a row store until :meth:`load` (a file above :data:`ptpcore.store.SPILL_PIXELS`)."""
        setattr(self, name, park(getattr(self, name)))

    def load(self, *names: str) -> None:
        """Bring the maps ``names`` back into memory as arrays (no-op for maps already there)."""
        for name in names:
            setattr(self, name, load(getattr(self, name)))


STRIP_ROWS = 64
"""Rows per strip of the per-pixel cross-validation on binned (large) images (the folds' maps
hold a strip plus twice the halo: 30 float64 maps of 114 x 2448 px per fold at 5 MP, degree 3)."""


class SmoothPass:
    """One pass over the samples, in strips of rows, and the smoothing scale's cross-validation.

    Every pixel gets its own weighted fit of its residuals to the global model
    (:class:`PixelFits`, all positions); for each of two folds of alternate
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
        b = self.b = int(cv_bin) if cv_bin else bin_factor(self.shape)
        self.hc, self.wc = -(-h // b), -(-w // b)
        # Scales of fewer than 4 bins are cross-validated per pixel (in strips of rows
        # with a halo the Gaussian cannot see past), larger ones on the binned grid.
        scales = self.scales
        self.fine = np.flatnonzero(scales < 4 * b) if b > 1 else np.arange(scales.size)
        self.coarse = np.flatnonzero(scales >= 4 * b) if b > 1 else np.arange(0)
        self.halo = 0 if b == 1 else int(np.ceil(3.0 * max(scales[self.fine].max(initial=0.0), 0.0))) + 1
        self.strip = h if b == 1 else max(b, (STRIP_ROWS // b) * b)
        # Sums over test samples, per scale: sum w (v.c - r)^2, samples, sum w.
        self.q_sum = np.zeros(scales.size)
        self.n_sum = np.zeros(scales.size)
        self.w_sum = np.zeros(scales.size)
        # The leave-one-out refits need the pixel fits only, not their own-range variances (own=False:
        # a fifth of each refit's time at 5 MP went to moments that were thrown away).
        self.own = own
        self.fits = PixelFits.empty(self.shape, self.d1, own=own)
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
        valid, sig, wts, (rx, ry) = global_residuals(self.samples, self.rig, self.sel, self.z, r0, r1, self.rays,
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
        (cx, cy), v, _, cov = weighted_poly_fits(self.t, [rx, ry], wts, degree, full=True)
        f.fit[0, :, r0:r1] = cx.reshape(d1, rows, w)
        f.fit[1, :, r0:r1] = cy.reshape(d1, rows, w)
        f.var[:, r0:r1] = v.reshape(d1, rows, w)
        if not self.own:
            return
        # For the noise scale (sigma_scale_from), which the plain degree-2 fit's residuals calibrate.
        f.mean_var[r0:r1] = residual_dof_variance(self.t, valid, sig, 2).reshape(rows, w)
        # The pixel's own fit's variance, averaged over its own calibrated
        # range, with the covariances (a pixel seen at a few positions at
        # one end of the range has strongly correlated coefficients).
        zc, zs = self.zc, self.zs
        mom = range_moments(((f.pz_min[r0:r1] - zc) / zs).ravel().astype(np.float64),
                            ((f.pz_max[r0:r1] - zc) / zs).ravel().astype(np.float64), 2 * degree)
        idx = np.add.outer(np.arange(d1), np.arange(d1))
        f.own_var[r0:r1] = np.einsum("ijp,ijp->p", cov, mom[idx]).reshape(rows, w)
        f.own_diag[r0:r1] = np.einsum("jp,jp->p", v, mom[2 * np.arange(d1)]).reshape(rows, w)
        if f.cov_off is not None:
            iu, ju = np.triu_indices(d1, 1)
            f.cov_off[:, r0:r1] = cov[iu, ju].reshape(len(iu), rows, w)

    def _fold_statistics(self, st: dict, test, s0: int, s1: int, wts, rx, ry) -> None:
        """One fold's training fit and test statistics at rows ``s0:s1`` of its maps ``st``."""
        rows, w = s1 - s0, self.shape[1]
        dc, cv_degree, t = self.dc, self.cv_degree, self.t
        train = ~test
        (fx, fy), fv, _ = weighted_poly_fits(t[train], [rx[train], ry[train]], wts[train], cv_degree)
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
            jobs = [(p0 + done, p1 + done) for p0, p1 in sample_blocks(a1 - done, w, k)]
            run_blocks(lambda p0, p1: self.block(p0, p1, a0, window, True), jobs)
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
                    c[:, j] = local_linear_grid(st["mean"][:, j], st["w"][j], sc, xs / sc, ys / sc,
                                                with_variance=False)[0][:, inner]
            self.score(st, c, inner, si)

    def _bin_strip(self, bn: dict, st: dict, inner: slice, r0: int, r1: int) -> None:
        """A strip's fold statistics, added to the fold's binned grid."""
        b = self.b
        c0, c1 = r0 // b, -(-r1 // b)
        for j in range(self.dc):
            ws, mean, xb, yb = binned_points(st["w"][j, inner], st["mean"][:, j, inner], b, r0)
            bn["w"][j, c0:c1], bn["mean"][:, j, c0:c1], bn["xbar"][j, c0:c1], bn["ybar"][j, c0:c1] = \
                ws, mean, xb, yb
        for name in ("m", "b", "r", "n"):
            bn[name][..., c0:c1, :] = bin_sums(st[name][..., inner, :], b)

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
                    c[:, j] = local_linear_grid(bn["mean"][:, j], bn["w"][j], binned_sigma(sc, b, False), xg / sc,
                                                yg / sc, bn["xbar"][j] / sc, bn["ybar"][j] / sc, False)[0]
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


def smoothed_coefficients(fits: PixelFits, scale: float, b: int, rays, zc: float, zs: float,
                          variance: bool = True) -> tuple[dict, tuple]:
    """The pixel fits smoothed at ``scale`` plus the global ray: ``{"x", "y"}`` (D+1, H, W) coefficients in t,
    and the global rays used.

    Smooths ``fits.fit`` and ``fits.var`` in place (the final smoothing runs on bins of at
    most the cross-validation's side and at most a quarter of the scale); a spilled ``fit`` is
    brought back first, a spilled ``var`` is read and written back a plane at a time. Without
    ``variance`` (the leave-one-out refits: coefficients only) ``fits.var`` only weights the
    smoothing and is not smoothed.
    ``rays`` is a callable returning the global rays
    (:class:`GlobalRays`) or the rays themselves: a callable is called after the
    smoothing, so that the rays are not held during it (160 MB at 5 MP).
    """
    fits.load("fit")
    fit, var = fits.fit, fits.var
    d1, h, w = fit.shape[1:]
    fb = final_bin_side(b, scale)
    if variance and fits.cov_off is not None:
        _smooth_covariances(fits, scale, fb)
    for j in range(d1):
        vj = var.plane(j)
        with np.errstate(divide="ignore", invalid="ignore"):
            wj = np.where(np.isfinite(fit[:, j]).all(axis=0) & (vj > 0), 1.0 / vj, 0.0)
        del vj
        # Smoothed in place: the (2, H, W) maps are read into bins before they are written (no copy).
        smoothed_var = smooth_on_bins(np.nan_to_num(fit[:, j], copy=False), wj, scale, fb, variance, out=fit[:, j])[1]
        if variance:
            var[j, 0:h] = smoothed_var
        del wj, smoothed_var
    coef = {"x": fit[0], "y": fit[1]}
    rays = rays() if callable(rays) else rays
    # Global ray as a polynomial in t: X = x0 + sx * (zc + zs t).
    for r0, r1 in row_blocks(h, w):
        gx0, gy0, gsx, gsy = rays.rows(r0, r1)
        for a, g0, gs in (("x", gx0, gsx), ("y", gy0, gsy)):
            coef[a][0, r0:r1] += g0 + gs * zc
            coef[a][1, r0:r1] += gs * zs
    return coef, rays


def _coefficient_weights(fits: PixelFits, j: int) -> np.ndarray:
    """Coefficient ``j``'s smoothing weights ``1 / var_j``, (H, W) float64, 0 where a pixel has no fit."""
    vj = fits.var.plane(j)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(fits.fit[:, j]).all(axis=0) & (vj > 0), 1.0 / vj, 0.0)


def _smooth_covariances(fits: PixelFits, scale: float, fb: int) -> None:
    """``fits.cov_off`` replaced by the smoothed coefficients' covariances (each coefficient map smoothed
    with its own weights, :func:`smoothed_covariance`), pair by pair; before the variances are."""
    d1, h = fits.var.shape[0], fits.var.shape[1]
    for p, (i, j) in enumerate(zip(*np.triu_indices(d1, 1))):
        wi, wj = _coefficient_weights(fits, i), _coefficient_weights(fits, j)
        cross = np.nan_to_num(wi * wj * fits.cov_off.plane(p))
        fits.cov_off[p, 0:h] = smoothed_covariance(wi, wj, cross, scale, fb)
        del wi, wj, cross


def smoothing_weights(fits: "PixelFits", n: int):
    """The final smoothing's weights ``1 / var_j`` of the first ``n`` coefficient maps, (n, H, W) float64
    (0 where a pixel has no fit), as :func:`smoothed_coefficients` uses them (call it before: it
    smooths ``fits.var`` in place). A row store: a file above :data:`ptpcore.store.SPILL_PIXELS` pixels
    (read a plane at a time by :func:`global_leak_variance`; 190 MB not held through the smoothing at 12 MP)."""
    h, w = fits.var.shape[1:]
    out = row_store((n, h, w), zeros=True)
    for j in range(n):
        if j >= fits.var.shape[0]:
            out[j, 0:h] = 0.0
            continue
        vj = fits.var.plane(j)
        with np.errstate(divide="ignore", invalid="ignore"):
            out[j, 0:h] = np.where(np.isfinite(fits.fit[:, j]).all(axis=0) & (vj > 0), 1.0 / vj, 0.0)
    return out


def residual_maps(samples: SampleStack, rig: Rig, sel, z: np.ndarray, t: np.ndarray, coef: dict, rays,
                  level_bias: bool, footprint: bool) -> dict:
    """RMS residual (mm, float32 (H, W) per axis) of the smooth LUT against each pixel's own corrected samples."""
    h, w = samples.shape
    d1 = coef["x"].shape[0]
    vander = np.vander(t, d1, increasing=True)
    q = {a: np.empty((h, w), np.float32) for a in "xy"}

    def quality(r0, r1):
        s, e = r0 * w, r1 * w
        ok = read_block(samples.reasons, s, e, sel) == 0
        fb = None
        if footprint:  # the rays' rows are read only for it
            near, lo = rays.window(r0, r1)
            fb = footprint_bias(near, rig, z, read_block(samples.modulation, s, e, sel),
                                read_block(samples.background, s, e, sel), r0 - lo, r1 - lo)
        for i_axis, a in enumerate("xy"):
            pred = np.einsum("kj,jp->kp", vander, coef[a][:, r0:r1].reshape(d1, -1))
            absval = corrected_samples(samples, rig, i_axis, s, e, sel, z, level_bias, fb)
            r = np.where(ok, absval - pred, np.nan)
            with np.errstate(all="ignore"):
                q[a][r0:r1] = np.sqrt(nanmean0(r * r)).astype(np.float32).reshape(r1 - r0, w)

    run_blocks(quality, sample_blocks(h, w, len(sel)))
    return q
