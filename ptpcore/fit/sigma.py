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

__all__ = ["sample_sigma", "predicted_poly_sigma", "predicted_poly_sigma_flat"]


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
