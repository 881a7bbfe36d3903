"""Accuracy of a LUT at held-out heights against the simulator's exact truth.

Used by ``ptp demo`` and by the accuracy tests; the predicted noise it is judged
against comes from :mod:`ptpcore.fit.sigma`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ptpcore.io.lutfile import Lut

__all__ = ["HeldOutAccuracy", "held_out_accuracy"]


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
