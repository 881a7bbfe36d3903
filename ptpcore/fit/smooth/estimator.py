"""The smooth LUT's pipeline: :func:`fit_smooth_lut`, the method of the package docstring step by step."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ptpcore.fit.perpixel import z_normalisation, fit_lut
from ptpcore.fit.sigma import MODEL_MAP_WORDS
from ptpcore.fit.smooth.global_model import GlobalRays, global_pinhole
from ptpcore.fit.smooth.leave_one_out import LooSetup
from ptpcore.fit.smooth.noise import check_noise, sigma_scale_from
from ptpcore.fit.smooth.pixel_fits import PixelFits, SmoothPass, residual_maps, smoothed_coefficients, smoothing_weights
from ptpcore.fit.smooth.uncertainty import noise_polynomial, smooth_sigma_maps, stage_variance, uncertainty_maps
from ptpcore.io.lutfile import Lut
from ptpcore.io.samples import SampleStack
from ptpcore.pinhole.camera import PinholeModel
from ptpcore.rig.rigfile import Rig
from ptpcore.store import release_free_memory

__all__ = ["fit_smooth_lut", "SmoothInfo", "smooth_global_fit"]


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
        leave-one-position-out residuals (:func:`leave_one_out`); 0 where the data do not resolve it.
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


def fit_smooth_lut(samples: SampleStack, rig: Rig, degree: int = 2, positions=None, *,
                   scales_px=(0.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0), stage_sigma_mm: float = 0.0,
                   level_bias: bool = True, footprint: bool = True, global_points: int = 100_000,
                   seed: int = 0, rig_toml: str = "", cv_bin: int | None = None,
                   progress: Callable[[float, str], None] | None = None,
                   uncertainty: bool = True, global_fit=None) -> tuple[Lut, SmoothInfo]:
    """Fit the ``smooth`` LUT (the method: :mod:`ptpcore.fit.smooth`'s docstring).

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
        The full sigma maps and the real leave-one-out
        (:func:`ptpcore.fit.smooth.uncertainty.uncertainty_maps`: about 3.5x the rest of the fit's CPU
        time at 2 MP x 21, most of it the leave-one-out's smoothing, once per position);
        off for fits judged only by their predictions (auto's candidates): noise-only sigma, NaN LOO.
    global_fit : PinholeFit, optional
        :func:`smooth_global_fit` of these samples, positions, ``level_bias``, ``global_points`` and
        ``seed``, to reuse: it does not depend on the degree or the scales, and the model choice
        fits several smooth candidates on the same positions (3.5 s of CPU each at any image size).

    Returns
    -------
    lut : Lut
        ``kind = "poly"``, with ``sigma_x``/``sigma_y`` maps.
    info : SmoothInfo
    """
    positions = _checked_positions(samples, degree, positions)
    report = progress or (lambda f, m: None)
    # 1. The global model, fitted to a random subset of every position's samples.
    report(0.0, "fitting the global camera model")
    gfit = global_fit if global_fit is not None else smooth_global_fit(samples, rig, positions, level_bias,
                                                                       global_points, seed)
    sel = np.asarray(positions)
    z = np.asarray(samples.z, dtype=float)[sel]
    z_norm = z_normalisation(z)
    # 2 and 4. Every pixel's own fit of its residuals, and the smoothing scale chosen on held-out positions.
    fits, t, b, noise_scale, (scale, cv_score, excess_var) = _fit_pixels_and_choose_scale(
        samples, rig, positions, z, z_norm, gfit, degree, scales_px, cv_bin, level_bias, footprint, report)
    # 3. The correction smoothed at that scale, plus the global ray: the LUT's coefficients.
    report(0.9, f"fitting the smooth LUT at scale {scale:g} px")
    coef, rays, leak_w = _smooth_at_scale(fits, gfit, samples.shape, scale, b, z_norm)
    stage_var = stage_variance(rays, rig, t, degree, stage_sigma_mm)
    # A pixel needs its own data to pin its curve in z (at least D+1 positions): with fewer, its
    # polynomial would come from neighbours seen over other heights (4 um off on the rough preset).
    valid = np.isfinite(coef["x"]).all(axis=0) & np.isfinite(coef["y"]).all(axis=0) & (fits.n_pos >= degree + 1)
    fits.pz_min[~valid] = np.nan
    fits.pz_max[~valid] = np.nan
    q = residual_maps(samples, rig, sel, z, t, coef, rays, level_bias, footprint)
    setup = LooSetup(samples, rig, sel, z, z_norm, rays, degree, scale, b, level_bias, footprint, noise_scale)
    rays = None
    # What only the uncertainty needs goes in with it (released there once used); the LUT's
    # coefficients wait in a file while its leave-one-out runs: 440 MB at 5 MP and degree 3.
    noise, setup.noise_poly = _propagated_noise(fits, z_norm, degree, noise_scale, uncertainty)
    inputs = {"leak_w": leak_w, "noise": noise}
    noise = None
    leak_w = coef = None
    fits.park("fit")
    release_free_memory()  # the pass's freed heap, before the uncertainty's peak (the leak variance)
    # 5. Sigma maps, the real leave-one-out and the model error it reveals.
    sig, loo, merr = uncertainty_maps(setup, gfit, inputs, fits, valid, stage_var, uncertainty, report)
    fits.load("fit")
    coef = {"x": fits.fit[0], "y": fits.fit[1]}
    lut = _assemble_lut(degree, z_norm, z, coef, valid, fits, q, loo, sig, rig_toml, scale)
    if uncertainty and merr.sigma is not None:
        _add_model_part(lut, merr, valid)
    report(1.0, "smooth LUT fitted")
    return lut, SmoothInfo(gfit.model, scale, np.asarray(scales_px, dtype=float), cv_score, noise_scale,
                           float(np.sqrt(excess_var)), merr.rms_mm, merr.limit_mm)


def smooth_global_fit(samples: SampleStack, rig: Rig, positions, level_bias: bool = True,
                      global_points: int = 100_000, seed: int = 0):
    """The smooth fit's global model (step 1): :func:`global_pinhole` on ``positions``' samples.

    Returns
    -------
    PinholeFit
        For :func:`fit_smooth_lut`'s ``global_fit`` (same arguments give the same fit).
    """
    return global_pinhole(samples, list(positions), n_points=global_points, seed=seed,
                          rig=rig if level_bias else None, full=True)


def _checked_positions(samples: SampleStack, degree: int, positions) -> list[int]:
    """The calibration positions (default all), after checking the degree, their number and the noise model."""
    if not 1 <= degree <= 5:
        raise ValueError(f"smooth degree must be 1 to 5, got {degree}")
    positions = list(range(samples.z.size)) if positions is None else list(positions)
    if len(positions) < degree + 2:
        raise ValueError(f"smooth LUT of degree {degree} needs at least {degree + 2} positions, got {len(positions)}")
    check_noise(samples)
    return positions


def _fit_pixels_and_choose_scale(samples: SampleStack, rig: Rig, positions: list, z, z_norm, gfit, degree: int,
                                 scales_px, cv_bin, level_bias: bool, footprint: bool, report):
    """The pass over the samples (:class:`SmoothPass`) and the scale it chooses.

    Returns
    -------
    fits : PixelFits ; t : (K,) normalised heights ; b : the cross-validation's bin side (px) ;
    noise_scale : float (:func:`sigma_scale_from`) ; (scale, cv_score, excess_var) from
    :meth:`SmoothPass.choose_scale`
    """
    # The plain degree-2 fit that calibrates the predicted noise (sigma_scale): its residual RMS only.
    report(0.02, "calibrating the noise prediction")
    plain = fit_lut(samples, "poly", 2, positions=positions)
    rms_x = np.where(plain.valid, plain.rms_x, np.float32(np.nan))
    rms_y = np.where(plain.valid, plain.rms_y, np.float32(np.nan))
    del plain
    rays = GlobalRays(gfit.model, samples.shape)
    run = SmoothPass(samples, rig, np.asarray(positions), z, z_norm, rays, degree, scales_px, cv_bin, level_bias,
                     footprint)
    report(0.05, "fitting every pixel and cross-validating")
    run.fit_and_cross_validate_fine(report)
    fits = run.fits
    noise_scale = sigma_scale_from(rms_x, rms_y, fits.n_pos, fits.mean_var, 2)
    rms_x = rms_y = fits.mean_var = None
    run.cross_validate_coarse(report)
    return fits, run.t, run.b, noise_scale, run.choose_scale(noise_scale)


def _smooth_at_scale(fits: PixelFits, gfit, shape, scale: float, b: int, z_norm):
    """The LUT's coefficients ``{"x", "y"}`` (D+1, H, W) (:func:`smoothed_coefficients`), the global rays
    (made again after the smoothing: not held during it, 160 MB at 5 MP) and the smoothing weights of
    coefficients 0 and 1 (:func:`smoothing_weights`, for the global model's leak variance)."""
    fits.load("fit")  # fits.var stays in its file, a plane at a time (150 MB at 5 MP and degree 3)
    leak_w = smoothing_weights(fits, 2)  # before the smoothing changes fits.var in place
    coef, rays = smoothed_coefficients(fits, scale, b, lambda: GlobalRays(gfit.model, shape), *z_norm)
    return coef, rays, leak_w


def _propagated_noise(fits: PixelFits, z_norm, degree: int, noise_scale: float, per_height: bool):
    """The smoothed LUT's propagated phase noise, (H, W) float32 mm (:func:`smooth_sigma_maps`), and with
    ``per_height`` its variance as a polynomial in ``t`` (:func:`noise_polynomial`, for the leave-one-out;
    else None); the variance maps they read are released."""
    fits.load("own_var", "own_diag")
    noise = smooth_sigma_maps(fits, *z_norm, degree, noise_scale, {})["x"]
    poly = noise_polynomial(fits, degree, noise_scale) if per_height else None
    fits.var = fits.own_var = fits.own_diag = fits.cov_off = None
    return noise, poly


def _add_model_part(lut: Lut, merr, valid) -> None:
    """The model's part of the sigma maps into ``lut`` (``sigma_model_x``, ``_y``) and how it was
    estimated into ``/provenance`` ``model_error``."""
    import json

    lut.sigma_model_x, lut.sigma_model_y = (np.where(valid, merr.sigma[a], np.float32(np.nan)) for a in "xy")
    lut.provenance["model_error"] = json.dumps({
        "method": "smooth leave-one-position-out: per interior held-out sample, residual^2 minus its noise"
                  " (own fit r^2 / (1 - h)) minus the left-out fit's predicted variance at that height; " + MODEL_MAP_WORDS
                  + "; added to the noise in quadrature",
        "scale_px": {a: float(v) for a, v in (merr.scale_px or {}).items()},
        "rms_um": round(1e3 * merr.rms_mm, 6), "resolved_limit_um": round(1e3 * merr.limit_mm, 6),
        "spatial": any(np.isfinite(v) for v in (merr.scale_px or {}).values())})


def _assemble_lut(degree: int, z_norm, z, coef: dict, valid, fits: "PixelFits", q: dict, loo: dict, sig: dict,
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
