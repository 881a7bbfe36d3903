"""The maps built after decoding come from row blocks of the samples: same numbers as whole-image arrays.

Issue 15: at 5 MP the whole-image ``(E, H, W)`` float64 arrays of the sigma maps took 4-13 GB;
the row-block versions must give the same bits (each pixel's value only involves its own samples).
"""

from __future__ import annotations

import numpy as np
import pytest

from ptpcore.fit import fit_lut, poly_sigma_maps, predicted_poly_sigma, sample_sigma_from_noise
from ptpcore.fit import smooth as smooth_mod
from ptpcore.fit.smooth import (blocks as smooth_blocks, global_model, noise as smooth_noise,
                                pixel_fits, smoothing, uncertainty as smooth_uncertainty)
from ptpcore.fit.smooth import sigma_scale
from ptpcore.store import FileRows
from ptpcore.store import rows as store_rows


def _nanmean(a, axis=None):
    """``np.nanmean`` without the all-NaN warning (all-NaN pixels are invalid anyway)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(a, axis=axis)


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
    monkeypatch.setattr(smooth_blocks, "BLOCK_PIXELS", 4096)  # many blocks on a 320 x 240 image
    got = poly_sigma_maps(samples, vr.rig, lut, cal, stage_sigma_mm)
    want = _whole_image_poly_sigma(samples, vr.rig, lut, cal, stage_sigma_mm)
    for g, w in zip(got, want):
        assert g.dtype == np.float32 and np.isfinite(g).sum() > 0.5 * g.size
        np.testing.assert_array_equal(g, w)


def _whole_image_smooth_sigma(fits, zc, zs, degree, noise_scale):
    """The former whole-image formula of :func:`ptpcore.fit.smooth.uncertainty.smooth_sigma_maps` (no stage term)."""
    d1 = degree + 1
    with np.errstate(all="ignore"):
        mom = pixel_fits.range_moments(((fits.pz_min - zc) / zs).astype(np.float64),
                                        ((fits.pz_max - zc) / zs).astype(np.float64), 2 * degree)
        smooth_diag = np.einsum("jhw,jhw->hw", fits.var, mom[2 * np.arange(d1)])
        if fits.cov_off is not None:  # the smoothed coefficients' covariances (issue 30)
            i, j = np.triu_indices(d1, 1)
            s2 = smooth_diag + 2 * np.einsum("phw,phw->hw", np.asarray(fits.cov_off), mom[i + j])
        else:
            s2 = fits.own_var * np.where(fits.own_diag > 0, smooth_diag / fits.own_diag, np.nan)
        s2 = np.where(np.isfinite(s2) & (s2 >= 0), s2, smooth_diag)
    return (np.sqrt(s2) * noise_scale).astype(np.float32)


def test_smooth_sigma_maps_in_row_blocks_are_bit_identical(monkeypatch):
    rng = np.random.default_rng(3)
    h, w, degree = 67, 50, 3
    fits = pixel_fits.PixelFits.empty((h, w), degree + 1)
    fits.var[:] = rng.uniform(0.0, 2.0, fits.var.shape)
    lo = rng.uniform(0.0, 30.0, (h, w))
    fits.pz_min[:] = lo
    fits.pz_max[:] = lo + rng.choice([0.0, 5.0, 30.0], (h, w))
    fits.own_var[:] = rng.uniform(0.0, 1.0, (h, w))
    fits.own_diag[:] = rng.uniform(-0.1, 1.0, (h, w))  # some <= 0: the uncorrelated form
    fits.var[:, :3] = np.nan
    fits.cov_off[:] = rng.uniform(-0.8, 0.3, fits.cov_off.shape)  # some pixels' sums negative: the diagonal form
    fits.cov_off[:, 5:7] = np.nan
    monkeypatch.setattr(smooth_blocks, "BLOCK_PIXELS", 512)
    for cov_off in (fits.cov_off, None):  # with the smoothed covariances, and the ratio form without them
        fits.cov_off = cov_off
        got = smooth_uncertainty.smooth_sigma_maps(fits, 30.0, 30.0, degree, 1.3, {})
        want = _whole_image_smooth_sigma(fits, 30.0, 30.0, degree, 1.3)
        np.testing.assert_array_equal(got["x"], want)
        np.testing.assert_array_equal(got["y"], want)


_LUT_MAPS = ("x", "y", "valid", "n_positions", "pixel_z_min", "pixel_z_max", "rms_x", "rms_y", "loo_x", "loo_y",
             "sigma_x", "sigma_y")


def test_smooth_lut_memory_layout_keeps_its_bits(rough_rig, monkeypatch):
    """The smooth pass's memory layout (issue 15) does not change the LUT: the folds' maps as a window
    of 8-row strips sliding down the image against one strip over the whole image, sample blocks of
    one row against the default, and the pixel fits and the leave-one-out's sums spilled to a file
    against held in memory. The
    cross-validation scores are sums over strips: the same to rounding (1e-12 relative)."""
    vr, samples = rough_rig
    monkeypatch.setattr(pixel_fits, "STRIP_ROWS", 10 ** 6)
    ref, ref_info = smooth_mod.fit_smooth_lut(samples, vr.rig, 2, cv_bin=2)
    monkeypatch.setattr(pixel_fits, "STRIP_ROWS", 8)
    monkeypatch.setattr(smooth_blocks, "BLOCK_SAMPLES", 1)
    monkeypatch.setattr(store_rows, "SPILL_PIXELS", 0)
    got, info = smooth_mod.fit_smooth_lut(samples, vr.rig, 2, cv_bin=2)
    for name in _LUT_MAPS:
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    assert info.scale_px == ref_info.scale_px
    np.testing.assert_allclose(info.cv_rms_mm, ref_info.cv_rms_mm, rtol=1e-12)
    assert info.excess_sigma_mm == pytest.approx(ref_info.excess_sigma_mm, rel=1e-9, abs=1e-15)


def test_row_spill_round_trip():
    """:class:`ptpcore.store.FileRows`: row ranges written with leading indices read back whole."""
    rng = np.random.default_rng(0)
    want = rng.standard_normal((2, 3, 7, 5))
    spill = FileRows(want.shape)
    for r0, r1 in ((0, 3), (3, 4), (4, 7)):
        spill[0, :, r0:r1] = want[0, :, r0:r1]
        spill[1, :, r0:r1] = want[1, :, r0:r1]
    np.testing.assert_array_equal(spill.rows(4, 2, 6), want[1, 1, 2:6])  # plane 4 = [1, 1]
    np.testing.assert_array_equal(spill.row_block(3, 5), want[:, :, 3:5])
    np.testing.assert_array_equal(spill.load(), want)
    flat = FileRows((7, 5))
    flat[0:7] = want[1, 2]
    np.testing.assert_array_equal(flat.load(), want[1, 2])


def test_row_spill_dropped_unread_closes_its_file():
    """A spill never read back closes its file itself: ``ptp calibrate`` printed an "unclosed file"
    warning for each of the leave-one-out refits' ``own_var``, ``own_diag`` at 5 MP (now not made)."""
    import gc
    import warnings

    spill = FileRows((4, 3))
    spill[0:4] = 1.0
    fh = spill._file
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        del spill
        gc.collect()
    assert fh.closed
    assert not [w for w in caught if issubclass(w.category, ResourceWarning)]


def test_second_differences_of_one_edge_row_are_the_whole_images():
    """:func:`ptpcore.fit.smooth.global_model._second_differences` of one-row blocks (sample blocks at 12 MP and 31
    positions are one row) equal the whole image's, edge rows included, for all three."""
    rng = np.random.default_rng(1)
    a = rng.standard_normal((6, 5))
    whole = global_model._second_differences(a, 0, 6)
    rows = [global_model._second_differences(a, r, r + 1) for r in range(6)]
    for i in range(3):
        np.testing.assert_array_equal(np.concatenate([r[i] for r in rows]), whole[i])


def _whole_map_upsample(coarse, b, h, w):
    """The former :func:`ptpcore.fit.smooth.smoothing.upsample_bins`: OpenCV's bilinear resize of the padded grid, then every
    NaN pixel from a whole map of repeated bins."""
    import cv2

    hc, wc = coarse.shape
    # Linear extrapolation by one bin (2 c[0] - c[1]), rows then columns; a single row or column repeats.
    def extend(a, axis):
        widths = [(1, 1) if i == axis else (0, 0) for i in range(2)]
        odd = {"mode": "reflect", "reflect_type": "odd"} if a.shape[axis] > 1 else {"mode": "edge"}
        return np.pad(a, widths, **odd)

    p = extend(extend(coarse, 0), 1)
    lin = cv2.resize(p, ((wc + 2) * b, (hc + 2) * b), interpolation=cv2.INTER_LINEAR)[b:b + h, b:b + w]
    bad = np.isnan(lin)
    lin[bad] = np.repeat(np.repeat(coarse, b, axis=0), b, axis=1)[:h, :w][bad]
    return lin


@pytest.mark.parametrize("hc, wc, b, h, w", [(40, 30, 4, 160, 117), (13, 9, 3, 38, 27), (1, 1, 900, 600, 900),
                                             (1, 7, 5, 4, 33), (6, 1, 2, 11, 2)])
def test_upsample_in_row_bands_keeps_its_bits(monkeypatch, hc, wc, b, h, w):
    """Bands of a few rows (not multiples of the bin) and a single bin: the whole-map result."""
    rng = np.random.default_rng(hc * wc)
    coarse = rng.normal(size=(hc, wc)) * 10.0 ** rng.integers(-6, 3)
    coarse[rng.random((hc, wc)) < 0.25] = np.nan
    monkeypatch.setattr(smoothing, "UPSAMPLE_ROWS", 7)
    assert np.array_equal(smoothing.upsample_bins(coarse, b, h, w), _whole_map_upsample(coarse, b, h, w), equal_nan=True)


def test_one_positions_sigma_in_row_blocks_is_the_stacks(rough_rig, monkeypatch):
    """The model choice's and the drift check's per-position noise (row blocks of 7 rows) is the
    whole stack's :func:`sample_sigma_from_noise`, bit for bit, NaN where invalid."""
    vr, samples = rough_rig
    whole = sample_sigma_from_noise(samples, vr.rig)
    monkeypatch.setattr(smooth_noise, "SIGMA_ROWS", 7)
    for k in (0, samples.z.size - 1):
        got = smooth_mod.position_sigma_from_noise(samples, vr.rig, k)
        assert np.isnan(got).any() and np.isfinite(got).any()
        np.testing.assert_array_equal(got, whole[k])


@pytest.mark.parametrize("h, w, b, r0, unweighted_zero", [(301, 257, 7, 14, False), (96, 130, 8, 0, True),
                                                          (50, 40, 1, 0, True)])
def test_binning_in_bands_of_bin_rows_keeps_its_bits(monkeypatch, h, w, b, r0, unweighted_zero):
    """The binned weights, means and centroids summed in bands of whole bins' rows (down to one bin's
    rows, the last band cut short) are those of one band over the whole image, for a stack of maps
    and for one map, NaN values where the weight is 0 included."""
    rng = np.random.default_rng(b)
    weights = rng.random((h, w)) * (rng.random((h, w)) > 0.2)
    values = rng.normal(size=(2, h, w))
    values[:, weights == 0] = np.nan if unweighted_zero else 0.0
    monkeypatch.setattr(smoothing, "BIN_BAND_PIXELS", h * w)
    whole = [smoothing.binned_points(weights, v, b, r0, unweighted_zero) for v in (values, values[0])]
    for band_rows in (b, 3 * b):
        monkeypatch.setattr(smoothing, "BIN_BAND_PIXELS", band_rows * w)
        banded = [smoothing.binned_points(weights, v, b, r0, unweighted_zero) for v in (values, values[0])]
        for one, other in zip(whole, banded):
            for a, c in zip(one, other):
                assert a.shape == c.shape
                np.testing.assert_array_equal(a, c)
    wsum, mean, xbar, ybar = whole[0]
    assert mean.shape == (2, -(-h // b), -(-w // b)) and np.all(np.isfinite(mean)) and wsum.sum() > 0
