"""Step 6 of the smooth fit: the real leave-one-position-out, and the model error it reveals.

For every calibration position the smooth LUT is made again without it (:func:`leave_one_out`)
and compared with that position's samples; the residuals' excess over the noise
(:func:`model_error`, each sample's noise from its pixel's own fit, ``r_own^2 / (1 - h)``) is the
model error the sigma maps carry. Every pixel's fit without a position comes in closed form from
its fit through all of them (:func:`downdated_fits`, :class:`OwnFits`: one pass over the samples
instead of one per position); only the smoothing is redone. The per-pixel sums wait in
:mod:`ptpcore.store` row stores.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ptpcore.fit.sigma import model_variance_map
from ptpcore.fit.smooth.blocks import row_blocks, run_blocks
from ptpcore.fit.smooth.global_model import GlobalRays, global_residuals
from ptpcore.fit.smooth.pixel_fits import PixelFits, smoothed_coefficients, weighted_poly_fits
from ptpcore.io.samples import SampleStack
from ptpcore.rig.rigfile import Rig
from ptpcore.store import release_free_memory, row_store

__all__ = ["LooSetup", "LooSums", "ModelError", "OwnFits", "downdated_fits", "leave_one_out", "model_error",
           "accumulate_left_out", "left_out_variance"]


@dataclass
class LooSetup:
    """What the smooth LUT was fitted with, for its leave-one-position-out refits."""

    samples: SampleStack
    rig: Rig
    sel: np.ndarray
    z: np.ndarray
    z_norm: tuple
    rays: GlobalRays
    degree: int
    scale: float
    cv_bin: int
    level_bias: bool
    footprint: bool
    noise_scale: float
    noise_poly: object = None
    """The LUT's propagated noise variance per height, ``(2D+1, H, W)`` row store of coefficients in
    ``t`` (:func:`ptpcore.fit.smooth.uncertainty.noise_polynomial`); None: judge the left-out fits by
    the range's RMS noise times ``K / (K - 1)``."""


@dataclass
class ModelError:
    """The model-error term of the smooth LUT's sigma maps (see :func:`model_error`).

    Attributes
    ----------
    var : dict ``"x"``, ``"y"`` -> (H, W) float64, mm^2 (0 where not resolved); None once
        :func:`uncertainty` has added it to the sigma maps
    rms_mm : float
        RMS of ``sqrt(var)`` over both axes and the pixels with samples.
    limit_mm : float
        The smallest model error the image-wide mean resolves (2 standard errors, RMS over the axes).
    scale_px : dict ``"x"``, ``"y"`` -> float, optional
        The scale the map was drawn at (:func:`ptpcore.fit.sigma.model_variance_map`).
    sigma : dict ``"x"``, ``"y"`` -> (H, W) float32, mm, optional
        ``sqrt(var)``, once the variances are in the sigma maps.
    """

    var: dict
    rms_mm: float
    limit_mm: float
    scale_px: dict | None = None
    sigma: dict | None = None


def leave_one_out(setup: LooSetup, valid: np.ndarray, sums: "LooSums", report) -> tuple[dict, ModelError]:
    """Leave-one-position-out of the smooth LUT, and the model error its residuals reveal.

    For every calibration position ``k`` the smooth LUT is made again without it (the global
    model, the normalisation in z and the smoothing scale kept; every pixel's fit, its weights and
    the smoothing redone) and its prediction at ``z_k`` compared with position ``k``'s corrected
    samples. No sample of position ``k`` reaches that prediction, at any pixel, so a per-position
    error common to all pixels (stage reading, a smooth pattern) is not smoothed into it.

    Every pixel's fit without ``k`` is a linear least-squares fit with one sample less: it comes in
    closed form from the pixel's fit through all positions (:func:`downdated_fits`, docs/method.md
    section 5), from one pass over the samples (:class:`OwnFits`) and position ``k``'s samples;
    only the smoothing (the same weights the refit would use, ``1 / var`` of the fit without ``k``)
    is done again for each ``k``.

    Parameters
    ----------
    setup : LooSetup
    valid : (H, W) bool
        The smooth LUT's valid pixels.
    sums : LooSums
        Holds ``fit_var``, the LUT's predicted variance from the sample noise (and stage readings),
        RMS over the calibrated range (mm^2); gets the left-out fits' residual sums.
    report : callable ``(fraction, message)``

    Returns
    -------
    loo : dict ``"x"``, ``"y"`` -> (H, W) float32, mm
        Per-pixel RMS over the positions of the leave-one-out residual.
    model : ModelError
    """
    s = setup
    k_all = s.z.size
    # The left-out fit has K-1 positions: its noise variance grows by about K / (K - 1).
    grow = k_all / max(k_all - 1, 1)
    report(0.0, "fitting every pixel through all calibration positions")
    own = OwnFits.from_samples(s)
    rank = 0  # among the interior positions: its parity splits them in halves (model_variance_map)
    for k in range(k_all):
        report(k / k_all, f"leaving calibration position {k + 1} of {k_all} out")
        # Only interior positions measure the model error: the LUT is used inside its calibrated
        # range, and the fit without an end position extrapolates to it.
        interior = s.z.min() < s.z[k] < s.z.max()
        coef, own_noise, kept = _fit_without(s, k, own, interior)
        accumulate_left_out(s, k, coef, valid, sums, grow, own_noise, kept, odd=interior and rank % 2 == 1)
        rank += interior
        del coef, own_noise, kept
        release_free_memory()  # each left-out fit's maps (~50 MB resident at 5 MP otherwise)
    own = None
    loo = {}
    for a in "xy":
        with np.errstate(all="ignore"):
            loo[a] = np.where(sums.count > 0, np.sqrt(sums.get("loo_sq", a) / sums.count), np.nan).astype(np.float32)
    return loo, model_error(sums)


def downdated_fits(coefs, cov: np.ndarray, n: np.ndarray, weight: np.ndarray, values, powers: np.ndarray):
    """Every pixel's weighted least-squares fit without one of its samples, from the fit with it.

    With ``A`` a pixel's normal matrix, ``p`` the left-out sample's powers of ``t``, ``w`` its weight,
    ``u = A^-1 p`` and ``h = w p'u`` its leverage, the fit without the sample is (Sherman-Morrison)
    ``c - u w r / (1 - h)``, ``r`` the sample's residual to ``c``, and its inverse normal matrix is
    ``A^-1 + w u u' / (1 - h)``: no refit (docs/method.md section 5's ``r / (1 - h)``).

    Parameters
    ----------
    coefs : list of (D+1, P) float64
        The fits through every sample (X and Y; :func:`weighted_poly_fits`).
    cov : (D+1, D+1, P) float64
        Their inverse normal matrix (``weighted_poly_fits(..., full=True)``).
    n : (P,) int
        Samples the fits used.
    weight : (P,) float64
        The left-out sample's weight (0 where the pixel did not use it: its fit stays).
    values : list of (P,) float64
        The left-out sample's values, X and Y (anything where ``weight == 0``).
    powers : (D+1,) float64
        ``t**j`` of the left-out sample.

    Returns
    -------
    coefs : list of (D+1, P) float64
    var : (D+1, P) float64
        The diagonal of the new inverse normal matrix. Both NaN where fewer than D+1 samples
        remain, as :func:`weighted_poly_fits` leaves them.
    resid : list of (P,) float64
        The left-out sample's residuals ``r`` to the fits through every sample.
    lev : (P,) float64
        Its leverage ``h`` (0 where unused).
    """
    d1 = powers.size
    u = np.einsum("ijp,j->ip", cov, powers)
    lev = weight * np.einsum("i,ijp,j->p", powers, cov, powers)
    drop = weight > 0
    gone = drop & (n - 1 < d1)
    with np.errstate(all="ignore"):
        gain = np.where(drop, weight / (1.0 - lev), 0.0)
        out, resid = [], []
        for c, y in zip(coefs, values):
            r = y - np.einsum("j,jp->p", powers, c)
            out.append(np.where(gone, np.nan, c - u * np.where(drop, gain * r, 0.0)))
            resid.append(r)
        var = np.where(gone, np.nan, cov[np.arange(d1), np.arange(d1)] + gain * u * u)
    return out, var, resid, lev


class OwnFits:
    """Every pixel's own weighted fit of its residuals to the global model through all calibration
    positions (:func:`weighted_poly_fits`): X and Y coefficients ``(2, D+1, H, W)``, the inverse
    normal matrix ``(D+1, D+1, H, W)`` (row stores: files at 5-12 MP) and the samples used ``(H, W)``.

    Made once, in one pass over the samples (:meth:`from_samples`); every left-out fit comes from it
    (:func:`downdated_fits`).
    """

    def __init__(self, shape, d1: int):
        h, w = shape
        self.coefs = row_store((2, d1, h, w))
        self.cov = row_store((d1, d1, h, w))
        self.n = np.zeros((h, w), np.int32)

    @classmethod
    def from_samples(cls, s: LooSetup) -> "OwnFits":
        h, w = s.samples.shape
        own = cls((h, w), s.degree + 1)
        t_all = (s.z - s.z_norm[0]) / s.z_norm[1]

        def block(r0, r1):
            _valid, _sig, wts, resid = global_residuals(s.samples, s.rig, s.sel, s.z, r0, r1, s.rays,
                                                        s.level_bias, s.footprint)
            coefs, _v, n, cov = weighted_poly_fits(t_all, resid, wts, s.degree, full=True)
            own.put(r0, r1, coefs, cov, n)

        run_blocks(block, row_blocks(h, w))
        return own

    def put(self, r0: int, r1: int, coefs, cov: np.ndarray, n: np.ndarray) -> None:
        """Rows ``[r0, r1)``: ``coefs`` X and Y (D+1, P), ``cov`` (D+1, D+1, P), ``n`` (P,)."""
        rows, w = r1 - r0, self.n.shape[1]
        d1 = cov.shape[0]
        self.coefs[:, :, r0:r1] = np.stack(coefs).reshape(2, d1, rows, w)
        self.cov[:, :, r0:r1] = cov.reshape(d1, d1, rows, w)
        self.n[r0:r1] = n.reshape(rows, w)

    def rows(self, r0: int, r1: int):
        """Rows ``[r0, r1)`` as :func:`downdated_fits` takes them: ``[cx, cy]`` (D+1, P), cov
        (D+1, D+1, P), n (P,)."""
        c = self.coefs.row_block(r0, r1)
        d1 = c.shape[1]
        c = c.reshape(2, d1, -1)
        return [c[0], c[1]], self.cov.row_block(r0, r1).reshape(d1, d1, -1), self.n[r0:r1].reshape(-1)


def _fit_without(s: LooSetup, k: int, own: OwnFits, interior: bool):
    """The smooth LUT's coefficients ``{"x", "y"}`` (D+1, H, W) without calibration position ``k``; for an
    ``interior`` position its samples' noise estimates ``r_own^2 / (1 - h)`` and the left-out fit's
    variance factor (:func:`_left_out_inflation`) ((4, H, W) row store: X, Y, the factor and a scratch
    plane; NaN where the pixel has no freedom left or did not use the sample), else None; and position ``k``'s
    corrected samples X, Y and validity (1.0 / 0.0) as a (3, H, W) row store, for
    :func:`accumulate_left_out` (correcting them again cost a pass over the position: 0.55 CPU-s at 2 MP).

    Every pixel's fit without ``k`` comes in closed form (:func:`downdated_fits`) from its fit
    through all positions (``own``) and position ``k``'s samples; then it is smoothed as the LUT is.
    """
    h, w = s.samples.shape
    d1 = s.degree + 1
    pos, zk = s.sel[k:k + 1], s.z[k:k + 1]
    powers = ((s.z[k] - s.z_norm[0]) / s.z_norm[1]) ** np.arange(d1)
    fits = PixelFits.empty((h, w), d1, own=False)
    noise = row_store((4, h, w)) if interior else None
    kept = row_store((3, h, w))

    def block(r0, r1):
        valid_k, _sig, wts, resid, values = global_residuals(s.samples, s.rig, pos, zk, r0, r1, s.rays,
                                                             s.level_bias, s.footprint, corrected=True)
        kept[:, r0:r1] = np.stack([values[0][0], values[1][0], valid_k[0]]).reshape(3, r1 - r0, w)
        coefs, cov, n = own.rows(r0, r1)
        c, var, r_own, lev = downdated_fits(coefs, cov, n, wts[0], [resid[0][0], resid[1][0]], powers)
        rows = r1 - r0
        fits.fit[:, :, r0:r1] = np.stack(c).reshape(2, d1, rows, w)
        fits.var[:, r0:r1] = var.reshape(d1, rows, w)
        if noise is not None:
            # As the model error has always estimated a sample's noise: from the fit with it.
            use = (wts[0] > 0) & (n > d1) & (lev < 1.0 - 1e-9)
            with np.errstate(all="ignore"):
                own_var = [np.where(use, r * r / (1.0 - lev), np.nan) for r in r_own]
                # The sample's weight and the own fit's precision at z_k (w / h): _left_out_inflation.
                precision = np.where(use, wts[0] / lev, 0.0)
                noise[:, r0:r1] = np.stack(own_var + [np.where(use, wts[0], 0.0), precision]).reshape(4, rows, w)

    run_blocks(block, row_blocks(h, w))
    if noise is not None:
        # float32 whole planes (the Gaussian needs them): 100 MB at 12 MP, before the smoothing's peak.
        inflation = _left_out_inflation(noise.plane(2).astype(np.float32), noise.plane(3).astype(np.float32),
                                        s.scale)
        for r0, r1 in row_blocks(h, w):
            noise[2, r0:r1] = inflation[r0:r1]
        del inflation
    coef = smoothed_coefficients(fits, s.scale, s.cv_bin, s.rays, *s.z_norm, variance=False)[0]
    return coef, noise, kept


def _left_out_inflation(weight: np.ndarray, precision: np.ndarray, scale: float) -> np.ndarray:
    """How much the smoothed fit's variance at ``z_k`` grows without position ``k``: ``1 / (1 - h_bar)``.

    A pixel's own fit without its sample ``k`` predicts ``z_k`` with variance ``var / (1 - h)`` (``h``
    the sample's leverage, ``h = w / P`` with ``w`` its weight and ``P`` the fit's precision there). The
    smoothing averages neighbours by their precision, so the smoothed fit's precision loses the
    precision-weighted mean leverage, ``h_bar = G * w / G * P`` (``G`` a Gaussian at the smoothing
    scale): a pixel whose own fit leans hard on the sample (few positions) is outweighed by its
    neighbours, and its own ``1 / (1 - h)`` (up to 30x the true growth on the x/y-symmetric rig at
    2 px) would overstate it. At scale 0 the pixel's own.

    Parameters
    ----------
    weight, precision : (H, W) float32
        ``w`` and ``P`` (0 where the pixel did not use the sample).
    scale : float
        The LUT's smoothing scale (Gaussian sigma, px).

    Returns
    -------
    (H, W) float32; NaN where the pixel did not use the sample.
    """
    from ptpcore.fit.sigma import gaussian_blur

    use = weight > 0
    if scale > 0:
        weight, precision = gaussian_blur(weight, scale), gaussian_blur(precision, scale)
    with np.errstate(all="ignore"):
        h_bar = np.divide(weight, precision, out=weight)  # in place: no third plane
        return np.where(use & (h_bar < 1.0), np.float32(1.0) / (np.float32(1.0) - h_bar), np.float32(np.nan))


def accumulate_left_out(s: LooSetup, k: int, coef: dict, valid: np.ndarray, sums: "LooSums", grow: float,
                        own_noise, kept, odd: bool = False) -> None:
    """Add position ``k``'s residuals against the fit ``coef`` made without it to the per-pixel ``sums``.

    ``loo_sq`` and ``count`` (the leave-one-out map) always. For an interior position (``own_noise``
    given) also, per sample, ``x = r^2 - r_own^2 / (1 - h) - v_k`` (:func:`model_error`)
    into ``excess`` and ``x^2`` into ``excess_sq`` (``n_model`` counts them): ``r_own`` is the
    sample's residual against its pixel's own weighted fit through all calibration positions and
    ``h`` its leverage there, so ``r_own^2 / (1 - h)`` estimates the sample's noise variance whatever
    the noise model's scale (``own_noise``, (4, H, W) from :func:`_fit_without`, with the left-out
    variance factor);
    ``v_k`` is the left-out fit's predicted variance at ``z_k`` (:func:`left_out_variance`).
    ``kept``: position ``k``'s corrected samples and
    validity (:func:`_fit_without`). ``odd``: the position's rank among the interior ones is odd; its
    ``x`` go to ``excess_odd`` and ``n_odd`` as well (the halves of :func:`model_error`'s map).
    """
    h, w = s.samples.shape
    t_all = (s.z - s.z_norm[0]) / s.z_norm[1]
    powers = t_all[k] ** np.arange(s.degree + 1)

    def block(r0, r1):
        corrected = kept.row_block(r0, r1).reshape(3, -1)
        ok_s = corrected[2] > 0
        own = own_noise.row_block(r0, r1).reshape(4, -1) if own_noise is not None else None
        for i_axis, a in enumerate("xy"):
            pred = np.einsum("j,jp->p", powers, coef[a][:, r0:r1].reshape(s.degree + 1, -1))
            r = corrected[i_axis] - pred
            ok = ok_s & valid[r0:r1].reshape(-1) & np.isfinite(r)
            sums.add("loo_sq", a, r0, r1, np.where(ok, r * r, 0.0).reshape(r1 - r0, w))
            if i_axis == 0:
                sums.count[r0:r1] += ok.reshape(r1 - r0, w)
            if own is None:
                continue
            x = r * r - own[i_axis] - left_out_variance(s, sums, a, r0, r1, t_all[k], own[2], grow)
            ok &= np.isfinite(x)
            sums.add("excess", a, r0, r1, np.where(ok, x, 0.0).reshape(r1 - r0, w))
            sums.add("excess_sq", a, r0, r1, np.where(ok, x * x, 0.0).reshape(r1 - r0, w))
            if odd:
                sums.add("excess_odd", a, r0, r1, np.where(ok, x, 0.0).reshape(r1 - r0, w))
            if i_axis == 0:
                sums.n_model[r0:r1] += ok.reshape(r1 - r0, w)
                if odd:
                    sums.n_odd[r0:r1] += ok.reshape(r1 - r0, w)

    run_blocks(block, row_blocks(h, w))


def left_out_variance(s: LooSetup, sums: "LooSums", axis: str, r0: int, r1: int, t_k: float,
                      inflate: np.ndarray, grow: float) -> np.ndarray:
    """The predicted variance of the fit without position ``k`` at its height, rows ``[r0, r1)`` flat, mm^2.

    Its noise part is the LUT's noise variance at ``t_k`` (``s.noise_poly``) times ``1 / (1 - h_bar)``
    (``inflate``, :func:`_left_out_inflation`): a least-squares fit without a sample predicts it with
    variance ``var_full / (1 - h)``. Not the range's RMS times ``K / (K - 1)``: that is
    up to 1.5x low next to the ends and 0.8x high in the middle, and the difference passed for a model
    error of 0.1-0.15 um on white noise at the 2 px scale (issue 30, the x/y-symmetric rig). The stage
    and global-model parts of ``fit_var`` keep the ``grow = K / (K - 1)`` scaling (they are shared by
    all pixels of a position, and small). Where the polynomial gives no finite positive value, the
    range's RMS form.
    """
    fit_var = sums.rows("fit_var", axis, r0, r1).reshape(-1)
    if s.noise_poly is None:
        return fit_var * grow
    coeffs = s.noise_poly.row_block(r0, r1).reshape(s.noise_poly.shape[0], -1)
    at_k = np.einsum("m,mp->p", t_k ** np.arange(coeffs.shape[0]), coeffs)
    noise_range = sums.rows("noise_var", axis, r0, r1).reshape(-1)
    with np.errstate(invalid="ignore"):
        left_out = grow * (fit_var - noise_range) + at_k * inflate
    return np.where(np.isfinite(left_out) & (at_k > 0), left_out, fit_var * grow)


class LooSums:
    """The leave-one-out's per-pixel float64 sums, X and Y (``loo_sq``, ``excess``, ``excess_sq``, and
    ``excess_odd`` over the interior positions of odd rank) and the predicted variance they are judged
    by (``fit_var``, and ``noise_var``: its propagated-noise part), with the counts ``count``, ``n_model`` and ``n_odd`` ((H, W) int32, in memory).

    The sums are one row store (:func:`ptpcore.store.row_store`): above
    :data:`ptpcore.store.SPILL_PIXELS` they wait in a temporary file while the left-out fits run, and
    each one's residuals are added row block by row block: at 5 MP they are 310 MB that each left-out
    fit's own maps would otherwise sit on top of.
    """

    NAMES = ("loo_sq", "excess", "excess_sq", "excess_odd", "fit_var", "noise_var")

    def __init__(self, shape):
        h, w = shape
        self.count = np.zeros((h, w), np.int32)  # counts: exact in any type (the float64 sums saw the same values)
        self.n_model = np.zeros((h, w), np.int32)
        self.n_odd = np.zeros((h, w), np.int32)
        self._sums = row_store((len(self.NAMES) * 2, h, w), zeros=True)

    def _index(self, name: str, axis: str) -> int:
        return 2 * self.NAMES.index(name) + "xy".index(axis)

    def rows(self, name: str, axis: str, r0: int, r1: int) -> np.ndarray:
        """Rows ``[r0, r1)`` of one sum, ``(r1 - r0, W)`` (a copy when spilled, else a view)."""
        return self._sums.rows(self._index(name, axis), r0, r1)

    def add(self, name: str, axis: str, r0: int, r1: int, values: np.ndarray) -> None:
        """Add ``values`` ``(r1 - r0, W)`` to rows ``[r0, r1)`` of one sum (blocks of disjoint rows may
        come from several threads)."""
        self._sums.add_rows(self._index(name, axis), r0, values)

    def put(self, name: str, axis: str, values: np.ndarray) -> None:
        """Set one whole ``(H, W)`` sum."""
        self._sums[self._index(name, axis), 0:values.shape[0]] = values

    def get(self, name: str, axis: str) -> np.ndarray:
        """One whole ``(H, W)`` sum (read into memory when spilled)."""
        return self._sums.plane(self._index(name, axis))


def model_error(sums: "LooSums") -> ModelError:
    """The model-error variance per pixel from the leave-one-out residuals' excess over the noise.

    A left-out sample's residual ``r`` is its own noise, the left-out fit's
    noise and the model error ``b`` (what the smoothing and the global model
    cannot follow) at once: ``E[r^2] = sigma^2 + sigma_fit^2 + b^2``. The
    sample's noise variance ``sigma^2`` is estimated from its pixel's own
    weighted fit through all positions, ``E[r_own^2 / (1 - h)] = sigma^2``
    (exact for any scale of the noise model: a 1 % error of that scale would
    otherwise pass for a model error of 0.7 um on the mild preset at 320 px),
    ``sigma_fit^2`` is the left-out fit's predicted variance at the left-out height
    (:func:`left_out_variance`: the LUT's at that height over ``1 - h``). The mean of
    ``x = r^2 - r_own^2 / (1 - h) - sigma_fit^2`` estimates ``b^2``; it is mapped over the image by
    :func:`ptpcore.fit.sigma.model_variance_map` (kernel regression at a scale chosen by split-half
    cross-validation, each pixel's posterior mean given the map's own error; 0 where the image-wide
    mean is within 2 standard errors of 0: the data do not resolve a model error). ``sums`` holds
    ``x`` and ``x^2`` summed per pixel (``excess``, ``excess_sq``; ``excess_odd`` over the interior
    positions of odd rank) and their counts (``n_model``, ``n_odd``). ``limit_mm`` is the
    2-standard-error limit of the image-wide mean.
    """
    count = sums.n_model
    var, limits, scales = {}, [], {}
    for a in "xy":
        var[a], scales[a], info = model_variance_map(sums.get("excess", a), count,
                                                     excess_sq_sum=sums.get("excess_sq", a),
                                                     odd=(sums.get("excess_odd", a), sums.n_odd))
        if np.isfinite(info["limit"]):
            limits.append(info["limit"])
    has = count > 0
    rms = float(np.sqrt(np.mean([np.mean(var[a][has]) for a in "xy"]))) if has.any() else 0.0
    return ModelError(var, rms, float(np.sqrt(np.mean(limits))) if limits else 0.0, scales)
