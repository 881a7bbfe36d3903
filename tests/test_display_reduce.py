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
