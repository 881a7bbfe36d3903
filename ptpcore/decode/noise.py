"""Camera noise measured from the data itself.

Every N-step fit with N > 3 leaves N - 3 degrees of freedom: the scatter of
the samples about the fitted sinusoid estimates the noise variance at that
pixel, once the display's harmonics are taken out of it
(:mod:`ptpcore.decode.harmonics`).
Pooled over millions of pixels and binned by grey level it gives the sensor's
photon-transfer curve ``var = read_var + gain * level`` without any dark or
flat frames. The phase noise of every sample then follows from docs/method.md
section 4: ``sigma_phi = sqrt(2/N) * sigma / B``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import lsq_linear

__all__ = ["NoiseModel", "NoiseAccumulator"]


@dataclass(frozen=True)
class NoiseModel:
    """Noise variance as a linear function of the mean grey level.

    Attributes
    ----------
    read_var : float
        Variance at level 0 (read noise and quantisation), grey levels^2.
    gain : float
        Variance per grey level of signal (shot noise), grey levels.
    """

    read_var: float
    gain: float
    source: str = "residual"
    """Where it was measured: the N-step residual with the display's harmonics taken out
    (``"residual"``, ``"residual of period T"`` for another level than the finest), or the
    spread of the decoded coordinate over the neighbourhood (``"neighbourhood"``)."""

    def sigma_dn(self, level) -> np.ndarray:
        """1-sigma noise (grey levels) of a sample at mean ``level``."""
        return np.sqrt(self.read_var + self.gain * np.maximum(np.asarray(level, dtype=float), 0.0))


class NoiseAccumulator:
    """Bins residual variances by background level over many positions.

    Parameters
    ----------
    max_level : int
        The sensor's full scale (grey levels).
    bins : int
    """

    def __init__(self, max_level: int, bins: int = 64, source: str = "residual"):
        self.source = source
        self.edges = np.linspace(0.0, float(max_level), bins + 1)
        self.sum_var = np.zeros(bins)
        self.sum_level = np.zeros(bins)
        self.count = np.zeros(bins)
        self.dof = 0

    def add(self, background: np.ndarray, residual_var: np.ndarray, mask: np.ndarray, dof: int) -> None:
        """Add the pixels of one N-step fit (``dof = N - 3``) where ``mask`` is True."""
        a = background[mask].astype(np.float64)
        v = residual_var[mask].astype(np.float64)
        idx = np.clip(np.searchsorted(self.edges, a, side="right") - 1, 0, self.count.size - 1)
        w = float(dof)
        self.sum_var += w * np.bincount(idx, v, self.count.size)
        self.sum_level += w * np.bincount(idx, a, self.count.size)
        self.count += w * np.bincount(idx, minlength=self.count.size)
        self.dof += dof

    def model(self) -> NoiseModel | None:
        """Weighted least-squares photon-transfer fit, or None without data."""
        use = self.count > 0
        if use.sum() < 1:
            return None
        level = self.sum_level[use] / self.count[use]
        var = self.sum_var[use] / self.count[use]
        # Each bin mean has relative scatter ~ sqrt(2/count); weight accordingly.
        w = np.sqrt(self.count[use] / 2.0) / np.maximum(var, 1e-12)
        design = np.stack([np.ones_like(level), level], axis=1)
        if use.sum() == 1:
            return NoiseModel(float(var[0]), 0.0, self.source)
        fit = lsq_linear(design * w[:, None], var * w, bounds=(0.0, np.inf))
        return NoiseModel(float(fit.x[0]), float(fit.x[1]), self.source)
