"""Accuracy of a LUT against the simulator's exact truth, and its predicted noise.

Used by ``ptp demo`` and by the accuracy tests. The prediction propagates each
sample's phase noise (METHOD.md section 4) through the per-pixel fit: for a
linear fit ``c = P x`` the value at ``z`` is ``v(z)^T P x`` with variance
``sum_k (v(z)^T P)_k^2 sigma_k^2``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .lut import Lut, SampleStack, _group_by_pattern, _z_normalisation

__all__ = ["sample_sigma", "predicted_poly_sigma", "HeldOutAccuracy", "held_out_accuracy"]


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
    z = samples.z[positions]
    zc, zs = _z_normalisation(z)
    t = (z - zc) / zs
    te = (np.asarray(z_eval, float) - zc) / zs
    k = len(positions)
    h, w = samples.shape
    mask = samples.valid[positions].reshape(k, -1)
    sig = sigma[positions].reshape(k, -1)
    out = np.full((len(te), h * w), np.nan)
    vander = np.vander(t, degree + 1, increasing=True)
    ve = np.vander(te, degree + 1, increasing=True)
    for pattern, cols in _group_by_pattern(mask):
        if pattern.sum() < degree + 2:
            continue
        g = ve @ np.linalg.pinv(vander[pattern])  # (E, n): value weights per sample
        out[:, cols] = np.sqrt((g * g) @ (sig[pattern][:, cols] ** 2))
    return out.reshape(len(te), h, w)


@dataclass
class HeldOutAccuracy:
    """Errors of a LUT at held-out heights against exact truth (µm).

    Attributes
    ----------
    positions : (E,) int
    rms_um, p95_um, max_um : float
        Over all X and Y errors of in-range pixels at all held-out positions.
    per_position_rms_um : (E,) float
    predicted_rms_um : float or None
        RMS of the predicted sigma over the same pixels (if a prediction was given).
    error_x, error_y : (E, H, W) float64, mm
    """

    positions: np.ndarray
    rms_um: float
    p95_um: float
    max_um: float
    per_position_rms_um: np.ndarray
    predicted_rms_um: float | None
    error_x: np.ndarray
    error_y: np.ndarray


def held_out_accuracy(lut: Lut, truth, z_readings, positions, predicted_sigma=None) -> HeldOutAccuracy:
    """Compare the LUT with the true rays at the stage readings of ``positions``.

    ``truth`` is a :class:`ptpcore.simulate.GroundTruth`. The LUT is evaluated
    at the stage reading; the true ray at the same height.
    """
    ex, ey, per = [], [], []
    pred_sq = []
    for i, k in enumerate(positions):
        z = float(z_readings[k])
        ev = lut.evaluate(z)
        tx, ty = truth.xy(z)
        m = ev.in_range
        dx = np.where(m, ev.x - tx, np.nan)
        dy = np.where(m, ev.y - ty, np.nan)
        ex.append(dx)
        ey.append(dy)
        both = np.concatenate([dx[m], dy[m]])
        per.append(np.sqrt(np.mean(both ** 2)) * 1e3 if both.size else np.nan)
        if predicted_sigma is not None:
            ps = predicted_sigma[i][m]
            pred_sq.append(np.concatenate([ps, ps]) ** 2)
    ex = np.stack(ex)
    ey = np.stack(ey)
    allv = np.abs(np.concatenate([ex[np.isfinite(ex)], ey[np.isfinite(ey)]]))
    pred = None
    if pred_sq:
        pq = np.concatenate(pred_sq)
        pred = float(np.sqrt(np.nanmean(pq)) * 1e3)
    return HeldOutAccuracy(np.asarray(positions), float(np.sqrt(np.mean(allv ** 2)) * 1e3),
                           float(np.percentile(allv, 95) * 1e3), float(allv.max() * 1e3),
                           np.asarray(per), pred, ex, ey)
