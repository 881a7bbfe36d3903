"""ptpcore.evaluate.views: arrays for views (reason colours, levels, histograms, one pixel's curves). No Qt."""

from __future__ import annotations

import numpy as np
import pytest

from ptpcore.fit import fit_lut
from ptpcore.io import SampleStack
from ptpcore.decode import REASON_NAMES, Reason
from ptpcore.evaluate import (REASON_COLOURS, REASON_ORDER, VALID_COLOUR, histogram, pixel_series,
    reason_counts, reason_rgba, reason_text, robust_levels)


def test_reason_colours_cover_every_flag_and_follow_the_order():
    assert set(REASON_ORDER) == set(REASON_NAMES)
    reasons = np.array([[0, Reason.BORDER, Reason.BORDER | Reason.OUTSIDE_LCD,
                         Reason.LOW_MODULATION | Reason.UNWRAP]], np.uint8)
    rgba = reason_rgba(reasons)
    assert rgba.shape == (1, 4, 4) and rgba.dtype == np.uint8
    assert tuple(rgba[0, 0]) == VALID_COLOUR
    assert tuple(rgba[0, 1]) == REASON_COLOURS[Reason.BORDER]
    assert tuple(rgba[0, 2]) == REASON_COLOURS[Reason.OUTSIDE_LCD]
    assert tuple(rgba[0, 3]) == REASON_COLOURS[Reason.LOW_MODULATION]
    assert len({REASON_COLOURS[f] for f in REASON_ORDER} | {VALID_COLOUR}) == len(REASON_ORDER) + 1
    with pytest.raises(ValueError):
        reason_rgba(reasons.astype(np.int32))


def test_reason_counts_and_text():
    reasons = np.array([0, 0, Reason.SATURATED, Reason.SATURATED | Reason.UNWRAP], np.uint8)
    counts = reason_counts(reasons)
    assert counts[0] == 2 and counts[Reason.SATURATED] == 2 and counts[Reason.UNWRAP] == 1
    assert counts[Reason.BORDER] == 0
    assert reason_text(0) == "valid"
    assert reason_text(Reason.SATURATED | Reason.UNWRAP) == "saturated, unwrapping disagreement"


def test_levels_and_histogram_ignore_nan_and_subsample():
    rng = np.random.default_rng(1)
    a = rng.normal(10.0, 2.0, size=(3000, 2000))
    a[:10] = np.nan
    lo, hi = robust_levels(a)
    assert 10 - 2.33 * 2 - 0.2 < lo < 10 - 2.33 * 2 + 0.2 and 10 + 2.33 * 2 - 0.2 < hi < 10 + 2.33 * 2 + 0.2
    assert robust_levels(np.full((4, 4), np.nan)) == (0.0, 1.0)
    assert robust_levels(np.ones((4, 4)))[0] < 1.0 < robust_levels(np.ones((4, 4)))[1]
    edges, counts = histogram(a, (0.0, 20.0), bins=20)
    assert edges.size == 21 and 1_000_000 < counts.sum() <= 2_000_000


@pytest.mark.parametrize("model", ["poly", "pchip", "linear"])
def test_pixel_series_matches_the_lut(model):
    z = np.linspace(0.0, 40.0, 9)
    h, w = 3, 4
    rng = np.random.default_rng(2)
    samples = SampleStack.empty(z, (h, w), with_photometry=False)
    for k, zk in enumerate(z):
        x = 10.0 + 0.1 * zk + 1e-4 * zk ** 2 + rng.normal(0, 1e-3, (h, w))
        y = 5.0 - 0.05 * zk + rng.normal(0, 1e-3, (h, w))
        reasons = np.zeros((h, w), np.uint8)
        if k == 3:
            reasons[1, 2] = Reason.SATURATED
        samples.set_position(k, x, y, reasons)
    lut = fit_lut(samples, model, 2)
    ps = pixel_series(lut, samples, 1, 2)
    assert ps.lut_valid and not ps.used[3] and np.isnan(ps.x[3])
    i = len(ps.z_curve) // 3
    ev = lut.evaluate(ps.z_curve[i])
    assert ps.x_curve[i] == pytest.approx(ev.x[1, 2], abs=1e-12, nan_ok=True)
    assert ps.y_curve[i] == pytest.approx(ev.y[1, 2], abs=1e-12, nan_ok=True)
    if model == "poly":
        rms = np.sqrt(np.nanmean(ps.resid_x ** 2))
        assert rms == pytest.approx(lut.rms_x[1, 2], rel=1e-5)
    else:
        np.testing.assert_allclose(ps.resid_x[ps.used], 0.0, atol=1e-9)
    with pytest.raises(ValueError):
        pixel_series(lut, samples, h, 0)
