"""Each calibration sample's predicted noise, and its calibration against the fit residuals.

``sigma_X = sqrt(2/N) * sigma(A) / B * T / (2 pi) * pitch`` for the finest period (docs/method.md
section 4): :func:`phase_sigma_mm` from the camera noise measured in the data
(:mod:`ptpcore.decode.noise`). :func:`sigma_scale` calibrates it against the residuals of every
pixel's own fit; :func:`stage_leverage` carries the stage readings' error, common to every pixel
of a position, through a pixel's fit in z. Used by the smooth fit's weights and sigma maps, and
by the robust screening, the model choice and the drift check.
"""

from __future__ import annotations

import numpy as np

from ptpcore.fit.perpixel import fit_lut
from ptpcore.fit.smooth.blocks import nanmean0, row_blocks, run_blocks
from ptpcore.fit.smooth.lsq import weighted_poly_fits
from ptpcore.io.samples import SampleStack
from ptpcore.rig.rigfile import Rig
from ptpcore.store import read_block

__all__ = ["phase_sigma_mm", "check_noise", "noise_rows", "sample_sigma_from_noise", "position_sigma_from_noise",
           "stage_leverage", "sigma_scale", "sigma_scale_from", "residual_dof_variance"]


def phase_sigma_mm(samples: SampleStack, rig: Rig, background, modulation) -> np.ndarray:
    """``sqrt(2/N) * sigma(A) / B * T / (2 pi) * pitch`` (mm) for the finest period (docs/method.md section 4)."""
    f = rig.fringes
    with np.errstate(divide="ignore", invalid="ignore"):
        return (np.sqrt(2.0 / f.steps[-1]) * samples.noise.sigma_dn(background)
                / modulation * f.periods_px[-1] / (2 * np.pi) * max(rig.lcd.pitch_mm))


def check_noise(samples: SampleStack) -> None:
    """Raise ``ValueError`` unless the samples carry the noise model and modulation the prediction needs."""
    if samples.noise is None or samples.modulation is None:
        raise ValueError("samples carry no noise model or modulation: decode them with collect_samples()")


def noise_rows(samples: SampleStack, rig: Rig, positions, start: int, stop: int):
    """Flat pixels ``[start, stop)`` of ``positions``: validity, the finest period's ``B`` and ``A``, predicted sigma.

    Returns
    -------
    valid : (K, n) bool ; modulation, background : (K, n) as stored ;
    sigma : (K, n) float64, mm (:func:`phase_sigma_mm`), NaN where invalid
    """
    valid = read_block(samples.reasons, start, stop, positions) == 0
    mod = read_block(samples.modulation, start, stop, positions)
    bg = read_block(samples.background, start, stop, positions)
    return valid, mod, bg, np.where(valid, phase_sigma_mm(samples, rig, bg, mod), np.nan)


def sample_sigma_from_noise(samples: SampleStack, rig: Rig) -> np.ndarray:
    """Predicted 1-sigma error (mm) of every sample, from the measured camera noise.

    ``sigma_X = sqrt(2/N) * sigma(A) / B * T / (2 pi) * pitch`` for the finest
    period (docs/method.md section 4), with ``sigma(A)`` from ``samples.noise``.
    The stage readings' error is not in it: it is common to every pixel of a
    position (:func:`stage_leverage`, :func:`poly_sigma_maps`).

    Returns
    -------
    (K, H, W) float64, NaN where invalid.
    """
    check_noise(samples)
    return np.where(samples.valid, phase_sigma_mm(samples, rig, samples.background, samples.modulation), np.nan)


def position_sigma_from_noise(samples: SampleStack, rig: Rig, k: int) -> np.ndarray:
    """:func:`sample_sigma_from_noise` of position ``k`` alone: (H, W) float64 mm, NaN where invalid.

    Built row block by row block from the position's planes (file reads of a spilled stack), so that
    only the result is a whole map: the whole-position expression held five float64 maps at once
    (500 MB at 12 MP, the wizard's peak in the model choice). The same numbers, pixel by pixel.
    """
    check_noise(samples)
    h, w = samples.shape
    out = np.empty((h, w))
    for r0 in range(0, h, SIGMA_ROWS):
        r1 = min(h, r0 + SIGMA_ROWS)
        sig = noise_rows(samples, rig, [int(k)], r0 * w, r1 * w)[3]
        out[r0:r1] = sig.reshape(r1 - r0, w)
    return out


SIGMA_ROWS = 128
"""Rows per block of :func:`position_sigma_from_noise` (a few MB of temporaries at 4000 px wide)."""


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


def sigma_scale(samples: SampleStack, rig: Rig, positions=None, degree: int = 2) -> float:
    """Factor that makes the predicted sample noise match the fit residuals.

    The per-sample prediction (:func:`sample_sigma_from_noise`) relies on the
    N-step residual variance, which also contains harmonics of a non-linear
    display or camera response (they barely move the phase of an N-step fit).
    Every pixel's own degree-2 fit over z leaves ``n - 3`` degrees of freedom
    whose residuals measure the noise that really reaches X and Y; pooled over
    all pixels they calibrate the prediction:
    ``s^2 = sum_p n_p rms_p^2 / sum_p sum_k (1 - h_pkk) sigma_pk^2`` (:func:`residual_dof_variance`).
    """
    check_noise(samples)
    positions = list(range(samples.z.size)) if positions is None else list(positions)
    lut = fit_lut(samples, "poly", degree, positions=positions)
    rms_x, rms_y = np.where(lut.valid, lut.rms_x, np.nan), np.where(lut.valid, lut.rms_y, np.nan)
    del lut
    h, w = samples.shape
    n = np.empty((h, w), np.int64)
    mean_var = np.empty((h, w))
    sel = np.asarray(positions)
    z = np.asarray(samples.z, dtype=float)[sel]
    t = (z - z.mean()) / max(float(np.ptp(z)) / 2, 1e-12)  # leverages do not depend on the normalisation

    def block(r0, r1):
        valid, _, _, sig = noise_rows(samples, rig, sel, r0 * w, r1 * w)
        n[r0:r1] = valid.sum(axis=0).reshape(r1 - r0, w)
        mean_var[r0:r1] = residual_dof_variance(t, valid, sig, degree).reshape(r1 - r0, w)

    run_blocks(block, row_blocks(h, w))
    return sigma_scale_from(rms_x, rms_y, n, mean_var, degree)


def residual_dof_variance(t: np.ndarray, valid: np.ndarray, sig: np.ndarray, degree: int = 2) -> np.ndarray:
    """Each pixel's expected residual variance per degree of freedom of its plain degree-D fit over z.

    An unweighted least-squares fit leaves ``E[sum_k r_k^2] = sum_k (1 - h_kk) sigma_k^2`` (``h`` its
    leverages): where the noise differs between positions (defocus at the ends of the sweep) the
    ends, which have the highest leverage, keep less of their noise in the residuals than the mean
    ``sigma^2`` says. With ``(n - D - 1) * mean(sigma^2)`` in its place the noise scale came out
    0.92 for samples of exactly their predicted noise, varying 3x over the positions (issue 30).

    Parameters
    ----------
    t : (K,) the positions' normalised heights ; valid : (K, P) bool ; sig : (K, P) predicted sigma (mm)
    degree : int

    Returns
    -------
    (P,) float64, mm^2: ``sum_k (1 - h_kk) sigma_k^2 / (n - D - 1)``; NaN with ``n <= D + 1`` samples
    """
    d1 = degree + 1
    _coefs, _var, n, inv = weighted_poly_fits(t, [], valid.astype(np.float64), degree, full=True)
    v = np.vander(np.asarray(t, float), d1, increasing=True)  # (K, D+1)
    lev = np.einsum("ki,ijp,kj->kp", v, inv, v)  # h_kk of every pixel's fit (for its valid samples)
    with np.errstate(all="ignore"):
        rss = np.sum(np.where(valid, (1.0 - lev) * np.square(sig), 0.0), axis=0)
        return np.where(n > d1, rss / (n - d1), np.nan)


def sigma_scale_from(rms_x, rms_y, n: np.ndarray, mean_var: np.ndarray, degree: int) -> float:
    """:func:`sigma_scale` from the plain fit's residual RMS maps, the valid counts and each pixel's predicted
    variance per residual degree of freedom (:func:`residual_dof_variance`)."""
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
