"""Previews reduced for display (``ptpcore.evaluate.views``): exact block means and masks."""

import numpy as np
import pytest

from ptpcore.evaluate.views import DISPLAY_PIXELS, display_step, reduce_for_display


def test_display_step_is_the_smallest_that_fits():
    assert display_step((480, 640)) == 1
    for shape in [(2048, 2448), (3000, 4000), (1025, 1025)]:
        s = display_step(shape)
        h, w = shape
        assert -(-h // s) * -(-w // s) <= DISPLAY_PIXELS
        assert -(-h // (s - 1)) * -(-w // (s - 1)) > DISPLAY_PIXELS


def test_mean_is_the_block_mean_with_edges_repeated():
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (10, 14)).astype(np.float32)
    out = reduce_for_display(img, 4)
    assert out.shape == (3, 4)
    padded = np.pad(img, ((0, 2), (0, 2)), mode="edge")
    expect = padded.reshape(3, 4, 4, 4).mean(axis=(1, 3))
    np.testing.assert_allclose(out, expect, rtol=1e-6)


def test_any_keeps_a_single_pixel_visible():
    mask = np.zeros((2048, 2448), bool)
    mask[2047, 2447] = True  # the last pixel, in a padded edge block
    mask[5, 7] = True
    s = display_step(mask.shape)
    out = reduce_for_display(mask, s, "any")
    assert out.sum() == 2 and out[-1, -1] and out[5 // s, 7 // s]


def test_step_one_and_bad_mode():
    img = np.ones((4, 4), np.uint8)
    assert reduce_for_display(img, 1) is img
    with pytest.raises(ValueError, match="how must be"):
        reduce_for_display(img, 2, "median")


def test_prepare_display_reduces_and_keeps_the_full_maps_levels_and_histogram():
    from ptpcore.evaluate.views import histogram, prepare_display, robust_levels

    rng = np.random.default_rng(2)
    data = rng.gamma(2.0, 1.5, size=(2048, 2448)).astype(np.float32)
    data[:40] = np.nan
    shown = prepare_display(data)
    assert shown.step == 3 and shown.extent == (2048, 2448)
    np.testing.assert_array_equal(shown.image, reduce_for_display(data, 3))
    assert shown.levels == robust_levels(data)  # the full map's, not the reduced one's
    edges, counts = histogram(data)
    np.testing.assert_array_equal(shown.hist_edges, edges)
    np.testing.assert_array_equal(shown.hist_counts, counts)
    assert np.isnan(shown.image[:13]).all() and np.isfinite(shown.image[14:]).all()  # block 13 holds row 40


def test_prepare_display_of_counts_bins_one_value_each_and_takes_any_integer_type():
    from ptpcore.evaluate.views import prepare_display

    counts_map = np.repeat(np.arange(3, 9, dtype=np.int32), 200)[:, None] * np.ones(1799, np.int32)  # 1200 x 1799, 3..8
    shown = prepare_display(counts_map, integer=True)
    assert shown.levels == (2.5, 8.5)
    np.testing.assert_array_equal(shown.hist_edges, np.arange(2.5, 9.0, 1.0))
    assert shown.hist_counts.sum() > 0 and (shown.hist_counts > 0).all()
    assert shown.step == 2 and shown.image.dtype == np.float32
    np.testing.assert_allclose(shown.image, reduce_for_display(counts_map.astype(np.float32), 2))
    small = prepare_display(np.ones((4, 5), np.uint8), integer=True)
    assert small.step == 1 and small.image.dtype == np.uint8 and small.levels == (0.5, 1.5)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        prepare_display(np.zeros(5))


def test_a_scaled_map_reads_as_its_scaled_copy():
    """The Calibrate page's µm maps (no copy of the LUT's mm maps): indexing, the whole array and the
    display prepared from it equal those of the scaled copy, bit for bit."""
    from ptpcore.evaluate.views import ScaledMap, prepare_display

    rng = np.random.default_rng(4)
    mm = (rng.random((300, 410)) * 2e-3).astype(np.float32)
    mm[rng.random(mm.shape) < 0.1] = np.nan
    um = np.float32(1000.0)
    copy, scaled = mm * um, ScaledMap(mm, um)
    assert scaled.shape == copy.shape and scaled.dtype == copy.dtype == np.float32
    valid = np.isfinite(mm)
    np.testing.assert_array_equal(scaled[valid], copy[valid])
    np.testing.assert_array_equal(scaled[10:20, 5:300:7], copy[10:20, 5:300:7])
    assert scaled[7, 9] == copy[7, 9] or (np.isnan(scaled[7, 9]) and np.isnan(copy[7, 9]))
    np.testing.assert_array_equal(np.asarray(scaled), copy)
    a, b = prepare_display(scaled, max_pixels=10_000), prepare_display(copy, max_pixels=10_000)
    np.testing.assert_array_equal(a.image, b.image)
    assert a.levels == b.levels and a.step == b.step
    np.testing.assert_array_equal(a.hist_counts, b.hist_counts)
    flags = ScaledMap(mm > 1e-3, np.uint8(1))
    np.testing.assert_array_equal(np.asarray(flags), (mm > 1e-3).astype(np.uint8))
