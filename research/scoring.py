"""What the research tools score a LUT with: its stage terms, its leverage, RMS(z) per decile of sigma.

Shared by :mod:`research.trust_mc`, :mod:`research.trust_split`, :mod:`research.loo_terms` and the
tools built on them; it imports only the engine, so the tools above it never import each other in a
circle.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

FRACTIONS = np.linspace(0.05, 0.95, 7)
"""Heights at which each pixel's LUT is evaluated, as fractions of its calibrated range."""


def normalised_heights(z, readings: np.ndarray) -> np.ndarray:
    """Heights ``z`` (mm) on the readings' range mapped to [-1, 1]."""
    lo, hi = readings.min(), readings.max()
    return (np.asarray(z, float) - lo) / (hi - lo) * 2 - 1


def fit_leverage(readings: np.ndarray, degree: int, heights: np.ndarray) -> np.ndarray:
    """The leverage of a degree-``degree`` fit through ``readings`` (K,) at ``heights`` (mm, any shape):
    the stage term's variance per unit stage variance."""
    v = np.vander(normalised_heights(readings, readings), degree + 1)
    vh = np.vander(normalised_heights(heights, readings).ravel(), degree + 1)
    return np.einsum("ij,jk,ik->i", vh, np.linalg.inv(v.T @ v), vh).reshape(np.shape(heights))


def stage_terms(readings: np.ndarray, z_true: np.ndarray, degree: int, heights: np.ndarray) -> tuple:
    """The realised height error a degree-``degree`` fit passes on at ``heights`` (mm, same shape),
    and the leverage of those heights (:func:`fit_leverage`).

    ``readings``, ``z_true`` : (K,) mm.
    """
    v = np.vander(normalised_heights(readings, readings), degree + 1)
    coef = np.linalg.lstsq(v, z_true - readings, rcond=None)[0]
    return np.polyval(coef, normalised_heights(heights, readings)), fit_leverage(readings, degree, heights)


def weighted_stage_terms(readings: np.ndarray, z_true: np.ndarray, degree: int, heights: np.ndarray,
                         weights: np.ndarray) -> np.ndarray:
    """:func:`stage_terms`' realised height error (mm, the shape of ``heights``) through each pixel's own
    weighted fit, as the smooth LUT fits in z: ``weights`` (K, *P), the fit's ``1 / sigma^2`` per position
    for pixels of shape ``P`` (0 where a pixel has no sample); ``heights`` (*F, *P), any number of heights
    per pixel (each pixel's system is solved once). The unweighted projection is not what the LUT passes
    on: on mild#3 (sample sigma 2.3 to 3.6 um over the sweep) the realised errors went through the weighted
    fit at 1.1x to 1.4x it (issue 30), while the expected leverage differs by 2 % only. NaN where a pixel's
    weighted system is singular."""
    k = readings.size
    v = np.vander(normalised_heights(readings, readings), degree + 1)  # (K, D+1)
    w = weights.reshape(k, -1)
    a = np.einsum("ki,kn,kj->nij", v, w, v)  # (N, D+1, D+1): each pixel's normal matrix
    b = np.einsum("ki,kn,k->ni", v, w, z_true - readings)
    ok = np.linalg.cond(a) < 1e12
    coef = np.full(b.shape, np.nan)
    coef[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
    t = normalised_heights(heights, readings).reshape(-1, w.shape[1])  # (F, N)
    vh = t[..., None] ** np.arange(degree, -1, -1)  # np.vander's column order
    return np.einsum("fni,ni->fn", vh, coef).reshape(np.shape(heights))


def fit_weights(samples, rig) -> np.ndarray:
    """(K, H, W) float64: the weights ``1 / sigma^2`` each pixel's fit in z gives its samples (the smooth
    fit's :func:`ptpcore.fit.smooth.global_model.global_residuals`), 0 where a sample is missing."""
    from ptpcore.fit.smooth.noise import noise_rows

    h, w = samples.shape
    sig = noise_rows(samples, rig, list(range(samples.z.size)), 0, h * w)[3]
    return np.where(np.isfinite(sig) & (sig > 0), 1.0 / np.square(sig), 0.0).reshape(-1, h, w)


def lut_degree(path: Path) -> int:
    """The polynomial degree in z of a written LUT (its provenance's chosen model, else its model group)."""
    with h5py.File(path, "r") as f:
        attrs = f["provenance"].attrs
        if "model_choice" in attrs:
            return int(json.loads(attrs["model_choice"])["chosen"]["degree"])
        return int(f["model"].attrs["degree"])


def deciles(err: np.ndarray, total: np.ndarray, ok: np.ndarray) -> tuple[float, list[float], float]:
    """RMS(z), RMS(z) per decile of ``total`` and the fraction of |z| > 3 (``err`` (F, H, W), ``total`` (H, W))."""
    edges = np.quantile(total[ok], np.linspace(0, 1, 11))
    dec = np.clip(np.searchsorted(edges, total, side="right") - 1, 0, 9)
    z = err[:, ok] / total[ok]
    per = [float(np.sqrt(np.mean((err[:, ok & (dec == q)] / total[ok & (dec == q)]) ** 2))) for q in range(10)]
    return float(np.sqrt(np.mean(z * z))), per, float(np.mean(np.abs(z) > 3))


def gauss_blur(a: np.ndarray, scale: float) -> np.ndarray:
    """A Gaussian blur of ``a`` (H, W) at ``scale`` px, zero outside the image: the kernel the engine's
    model-variance map (:func:`ptpcore.fit.sigma.model_variance_map`) smooths with."""
    import cv2

    return cv2.GaussianBlur(a, (0, 0), scale, borderType=cv2.BORDER_CONSTANT)
