"""Drift within a sweep: positions captured again after the sweep (``[stage] repeat_z_mm``).

A repeat at the reading ``z_r`` of sweep position ``j`` sees, at every pixel, the
sample of position ``j`` again plus what moved in between (the camera warming, the
stage's zero, the LCD). Per pixel the drift is ``d = s_repeat - s_j`` (X and Y);
without drift it is the two samples' noise, ``sigma_d^2 = sigma_j^2 + sigma_r^2 +
2 (slope * stage_sigma)^2`` (phase noise, :func:`ptpcore.fit.smooth.sample_sigma_from_noise`,
and the stage readings' independent errors along the pixel's ray).

Two figures are judged: the RMS of ``|d|`` over the pixels against the predicted
RMS (:data:`RMS_LIMIT` times it at most: the noise model is good to about 20 %), and
the mean drift vector against its standard error over the pixels
(:data:`MEAN_LIMIT` standard errors at most): a shift common to all pixels is
found far below the single-pixel noise. Beyond either, the drift is a named
warning in the summary and ``/provenance`` ``drift`` (FORMATS.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from ptpcore.fit.smooth import position_sigma_from_noise
from ptpcore.io.samples import SampleStack
from ptpcore.rig.naming import position_label
from ptpcore.rig.rigfile import Rig

__all__ = ["RMS_LIMIT", "MEAN_LIMIT", "Drift", "RepeatSource", "sweep_drift"]

RMS_LIMIT = 1.5
"""Drift RMS above this multiple of the predicted noise RMS is a warning."""

MEAN_LIMIT = 5.0
"""A mean drift vector above this many of its standard errors is a warning."""


class RepeatSource:
    """The repeat positions of a frame source as a source of their own (positions 0, 1, ... = K, K+1, ...).

    ``source.frames(K + r)`` must give the repeat ``r`` (a dataset folder names its images by
    position index, FORMATS.md); the rig's stage readings are ``repeat_z_mm``.
    """

    def __init__(self, source):
        from dataclasses import replace

        rig = source.rig
        if not rig.stage.repeat_z_mm:
            raise ValueError("the rig has no [stage] repeat_z_mm")
        self.source = source
        self.k0 = rig.stage.n_positions
        self.rig = replace(rig, stage=replace(rig.stage, z_mm=tuple(rig.stage.repeat_z_mm), repeat_z_mm=()))

    def frames(self, k: int):
        return self.source.frames(self.k0 + int(k))

    def __getattr__(self, name: str):
        # The Gray-code and reference frames of a repeat, when the source has them.
        if name in ("gray_frames", "reference_frames"):
            fn = getattr(self.source, name)
            return lambda k: fn(self.k0 + int(k))
        raise AttributeError(name)


@dataclass
class Drift:
    """Drift of every repeat against its sweep position.

    Attributes
    ----------
    z : (R,) float64, mm
        Repeat readings.
    matched : (R,) int64
        Sweep position of each repeat (-1: none at that reading, not judged).
    dx, dy : (R, H, W) float64, mm
        Per-pixel drift (repeat - sweep); NaN where either sample is invalid.
    rms_um, predicted_rms_um : (R,) float64, µm
        RMS of ``|d|`` over the pixels and of its prediction.
    mean_um : (R, 2) float64, µm
        Mean drift vector (X, Y) over the pixels.
    mean_se_um : (R, 2) float64, µm
        Its standard error.
    warnings : list of str
    """

    z: np.ndarray
    matched: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    rms_um: np.ndarray
    predicted_rms_um: np.ndarray
    mean_um: np.ndarray
    mean_se_um: np.ndarray
    warnings: list

    def to_json(self) -> str:
        """The ``/provenance`` attribute ``drift`` (FORMATS.md)."""
        def num(v):
            return None if not np.isfinite(v) else round(float(v), 5)
        return json.dumps({"rms_limit": RMS_LIMIT, "mean_limit_se": MEAN_LIMIT, "warnings": list(self.warnings),
                           "repeats": [{"z_mm": float(z), "position": int(j), "rms_um": num(r),
                                        "predicted_rms_um": num(p), "mean_um": [num(v) for v in m],
                                        "mean_se_um": [num(v) for v in s]}
                                       for z, j, r, p, m, s in zip(self.z, self.matched, self.rms_um,
                                                                   self.predicted_rms_um, self.mean_um,
                                                                   self.mean_se_um)]})

    def lines(self) -> list[str]:
        """The drift in words, warnings first."""
        out = [f"DRIFT WARNING: {w}" for w in self.warnings]
        for z, j, r, p, m in zip(self.z, self.matched, self.rms_um, self.predicted_rms_um, self.mean_um):
            if j < 0:
                out.append(f"drift at z = {z:g} mm: no sweep position at that reading, not judged")
            else:
                out.append(f"drift at z = {z:g} mm ({position_label(j)} again): RMS {r:.3f} µm (noise predicts"
                           f" {p:.3f} µm), mean ({m[0]:+.3f}, {m[1]:+.3f}) µm")
        return out


def _slopes(samples: SampleStack, j: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) dX/dz and dY/dz at sweep position ``j``, from its neighbours (mm/mm; 0 where unknown)."""
    k = samples.z.size
    a, b = max(j - 1, 0), min(j + 1, k - 1)
    if a == b:
        return np.zeros(samples.shape), np.zeros(samples.shape)
    xa, ya = samples.absolute(a)
    xb, yb = samples.absolute(b)
    dz = float(samples.z[b] - samples.z[a])
    return np.nan_to_num((xb - xa) / dz), np.nan_to_num((yb - ya) / dz)


def sweep_drift(samples: SampleStack, repeats: SampleStack, rig: Rig, *, stage_sigma_mm: float = 0.0,
                tolerance_mm: float = 1e-6) -> Drift:
    """Judge the repeats against the sweep (module docstring).

    Parameters
    ----------
    samples : SampleStack
        The sweep.
    repeats : SampleStack
        The repeat positions (same camera; e.g. ``collect_samples(RepeatSource(source))``).
    rig : Rig
    stage_sigma_mm : float
        1-sigma error of a stage reading (mm).
    tolerance_mm : float
        A repeat matches the sweep position whose reading is within this.

    Returns
    -------
    Drift

    Raises
    ------
    ValueError
        Different camera sizes.
    """
    if repeats.shape != samples.shape:
        raise ValueError(f"the repeats are {repeats.shape} px, the sweep {samples.shape}")
    r_all, (h, w) = repeats.z.size, samples.shape
    noise = samples.noise is not None and samples.modulation is not None and repeats.modulation is not None
    matched = np.full(r_all, -1, np.int64)
    dx, dy = np.full((r_all, h, w), np.nan), np.full((r_all, h, w), np.nan)
    rms, pred = np.full(r_all, np.nan), np.full(r_all, np.nan)
    mean, se = np.full((r_all, 2), np.nan), np.full((r_all, 2), np.nan)
    warnings = []
    for r in range(r_all):
        near = np.flatnonzero(np.abs(samples.z - repeats.z[r]) <= tolerance_mm)
        if near.size == 0:
            continue
        j = matched[r] = int(near[0])
        xs, ys = samples.absolute(j)
        xr, yr = repeats.absolute(r)
        ok = (samples.reasons[j] == 0) & (repeats.reasons[r] == 0) & np.isfinite(xs) & np.isfinite(xr)
        if not ok.any():
            continue
        dx[r], dy[r] = np.where(ok, xr - xs, np.nan), np.where(ok, yr - ys, np.nan)
        d2 = (dx[r] ** 2 + dy[r] ** 2)[ok]
        rms[r] = float(np.sqrt(d2.mean()) * 1e3)
        v = np.stack([dx[r][ok], dy[r][ok]])
        mean[r] = v.mean(axis=1) * 1e3
        gx, gy = _slopes(samples, j)
        # The two stage readings' errors move every pixel along its ray at once: common to the mean.
        common = np.array([gx[ok].mean(), gy[ok].mean()]) * np.sqrt(2.0) * stage_sigma_mm
        se[r] = np.sqrt(v.var(axis=1, ddof=1) / v.shape[1] + common ** 2) * 1e3 if v.shape[1] > 1 else np.nan
        if noise:
            s2 = position_sigma_from_noise(samples, rig, j) ** 2 + position_sigma_from_noise(repeats, rig, r) ** 2
            var = 2 * s2[ok] + 2 * (gx[ok] ** 2 + gy[ok] ** 2) * stage_sigma_mm ** 2  # |d|^2: X and Y
            pred[r] = float(np.sqrt(np.nanmean(var)) * 1e3)
        where = f"z = {repeats.z[r]:g} mm ({position_label(j)} again)"
        if np.isfinite(pred[r]) and rms[r] > RMS_LIMIT * pred[r]:
            warnings.append(f"{where}: RMS {rms[r]:.3f} µm, {rms[r] / pred[r]:.1f}x the predicted noise"
                            f" {pred[r]:.3f} µm")
        big = np.abs(mean[r]) > MEAN_LIMIT * se[r]
        if big.any():
            warnings.append(f"{where}: the whole image moved by ({mean[r][0]:+.3f}, {mean[r][1]:+.3f}) µm"
                            f" (+- {se[r][0]:.3f}, {se[r][1]:.3f} µm)")
    return Drift(repeats.z.astype(float).copy(), matched, dx, dy, rms, pred, mean, se, warnings)
