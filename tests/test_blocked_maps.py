"""The maps built after decoding come from row blocks of the samples: same numbers as whole-image arrays.

Issue 15: at 5 MP the whole-image ``(E, H, W)`` float64 arrays of the sigma maps took 4-13 GB;
the row-block versions must give the same bits (each pixel's value only involves its own samples).
"""

from __future__ import annotations

import numpy as np
import pytest

from ptpcore.fit import fit_lut, poly_sigma_maps, predicted_poly_sigma, sample_sigma_from_noise
from ptpcore.fit import smooth as smooth_mod
from ptpcore.fit.smooth import _nanmean, sigma_scale


def _whole_image_poly_sigma(samples, rig, lut, positions, stage_sigma_mm):
    """The former whole-image formula of :func:`poly_sigma_maps` (``(K, H, W)`` and ``(E, H, W)`` arrays)."""
    sig = sample_sigma_from_noise(samples, rig) * sigma_scale(samples, rig, positions)
    zs = np.linspace(lut.z_min, lut.z_max, 4 * len(positions) + 1)
    inside = (zs[:, None, None] >= lut.pixel_z_min) & (zs[:, None, None] <= lut.pixel_z_max)

    def rms_map(sample_sigma):
        pred = predicted_poly_sigma(samples, sample_sigma, lut.degree, positions, zs)
        with np.errstate(all="ignore"):
            s = np.sqrt(_nanmean(np.where(inside, pred * pred, np.nan), axis=0))
        return np.where(lut.valid, s, np.nan).astype(np.float32)

    if not stage_sigma_mm:
        return rms_map(sig), rms_map(sig)
    return tuple(rms_map(np.hypot(sig, np.abs(coef[1] / lut.z_scale - rig.stage.direction[d]) * stage_sigma_mm))
                 for d, coef in enumerate((lut.x, lut.y)))


@pytest.mark.parametrize("stage_sigma_mm", [0.0, 0.002])
def test_poly_sigma_maps_in_row_blocks_are_bit_identical(rough_rig, stage_sigma_mm, monkeypatch):
    vr, samples = rough_rig
    cal = list(range(0, samples.z.size, 2))
    lut = fit_lut(samples, "poly", 3, positions=cal)
    monkeypatch.setattr(smooth_mod, "_BLOCK_PIXELS", 4096)  # many blocks on a 320 x 240 image
    got = poly_sigma_maps(samples, vr.rig, lut, cal, stage_sigma_mm)
    want = _whole_image_poly_sigma(samples, vr.rig, lut, cal, stage_sigma_mm)
    for g, w in zip(got, want):
        assert g.dtype == np.float32 and np.isfinite(g).sum() > 0.5 * g.size
        np.testing.assert_array_equal(g, w)


def _whole_image_smooth_sigma(fits, zc, zs, degree, noise_scale):
    """The former whole-image formula of :func:`ptpcore.fit.smooth._smooth_sigma_maps` (no stage term)."""
    d1 = degree + 1
    with np.errstate(all="ignore"):
        mom = smooth_mod._range_moments(((fits.pz_min - zc) / zs).astype(np.float64),
                                        ((fits.pz_max - zc) / zs).astype(np.float64), 2 * degree)
        smooth_diag = np.einsum("jhw,jhw->hw", fits.var, mom[2 * np.arange(d1)])
        s2 = fits.own_var * np.where(fits.own_diag > 0, smooth_diag / fits.own_diag, np.nan)
        s2 = np.where(np.isfinite(s2), s2, smooth_diag)
    return (np.sqrt(s2) * noise_scale).astype(np.float32)


def test_smooth_sigma_maps_in_row_blocks_are_bit_identical(monkeypatch):
    rng = np.random.default_rng(3)
    h, w, degree = 67, 50, 3
    fits = smooth_mod._PixelFits.empty((h, w), degree + 1)
    fits.var[:] = rng.uniform(0.0, 2.0, fits.var.shape)
    lo = rng.uniform(0.0, 30.0, (h, w))
    fits.pz_min[:] = lo
    fits.pz_max[:] = lo + rng.choice([0.0, 5.0, 30.0], (h, w))
    fits.own_var[:] = rng.uniform(0.0, 1.0, (h, w))
    fits.own_diag[:] = rng.uniform(-0.1, 1.0, (h, w))  # some <= 0: the uncorrelated form
    fits.var[:, :3] = np.nan
    monkeypatch.setattr(smooth_mod, "_BLOCK_PIXELS", 512)
    got = smooth_mod._smooth_sigma_maps(fits, 30.0, 30.0, degree, 1.3, {})
    want = _whole_image_smooth_sigma(fits, 30.0, 30.0, degree, 1.3)
    np.testing.assert_array_equal(got["x"], want)
    np.testing.assert_array_equal(got["y"], want)
