"""``fit_lut`` finishes each pixel tile on its own (validity, NaN fill, z range): the
result must not depend on the tiling, and no uninitialised value may leak out."""

from __future__ import annotations

import numpy as np
import pytest

import ptpcore.fit.perpixel as lut_mod
from ptpcore.fit import fit_lut
from ptpcore.io import SampleStack

FIELDS = ("x", "y", "valid", "n_positions", "pixel_z_min", "pixel_z_max", "rms_x", "rms_y", "loo_x", "loo_y")


def _stack(seed: int = 0) -> SampleStack:
    """9 positions of 20 x 300 pixels: lines plus noise, with every kind of pixel
    (all valid, some positions invalid, too few positions, never valid, a sample
    that makes the fit fail)."""
    rng = np.random.default_rng(seed)
    k, h, w = 9, 20, 300
    z = np.linspace(0, 8, k)
    x = (rng.normal(size=(k, h, w)) * 0.01 + z[:, None, None] * 0.3).astype(np.float32)
    y = (rng.normal(size=(k, h, w)) * 0.01 - z[:, None, None] * 0.2).astype(np.float32)
    reasons = np.zeros((k, h, w), np.uint8)
    reasons[rng.random((k, h, w)) < 0.05] = 1
    reasons[:6, 3, :] = 8  # 3 positions left: too few for degree 2
    reasons[:, 5, :40] = 1  # never valid
    reasons[:, 7, 10:20] = 0
    x[2, 7, 10:20] = np.inf  # a "valid" sample the fit cannot use
    x[reasons != 0] = np.nan
    y[reasons != 0] = np.nan
    return SampleStack(z, x, y, np.full((h, w), 10.0), np.full((h, w), -3.0), reasons)


@pytest.mark.parametrize("model, degree, positions", [("poly", 2, None), ("poly", 3, [0, 2, 3, 5, 6, 8]),
                                                      ("linear", 1, None), ("pchip", 1, [8, 1, 4, 2, 6, 0])])
@pytest.mark.parametrize("numba", [True, False])
def test_fit_does_not_depend_on_the_tiles(monkeypatch, model, degree, positions, numba):
    if numba:
        pytest.importorskip("numba")
        monkeypatch.delenv("PTP_NO_NUMBA", raising=False)
    else:
        monkeypatch.setenv("PTP_NO_NUMBA", "1")
    s = _stack()
    monkeypatch.setattr(lut_mod, "_TILE", 1 << 20)
    whole = fit_lut(s, model, degree, positions=positions)
    monkeypatch.setattr(lut_mod, "_TILE", 777)  # 8 tiles, the last one short
    tiled = fit_lut(s, model, degree, positions=positions)
    for name in FIELDS:
        a, b = getattr(tiled, name), getattr(whole, name)
        if name in ("valid", "n_positions", "pixel_z_min", "pixel_z_max"):
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:  # numpy's einsum may round a last bit differently for another set of columns
            np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=name)
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12, err_msg=name)  # mm, data ~10 mm
    valid = tiled.valid
    assert valid.mean() > 0.5
    assert not valid[5, :40].any() and (tiled.n_positions[5, :40] == 0).all()
    if model == "poly":
        assert not valid[3].any()  # too few positions
        assert not valid[7, 10:20].any()  # the fit failed (an infinite sample)
    # Invalid pixels hold NaN in every float field, valid ones finite numbers.
    for name in ("x", "y"):
        a = getattr(tiled, name)
        assert np.isnan(a[:, ~valid]).all()
        if model == "poly":
            assert np.isfinite(a[:, valid]).all()
    for name in ("pixel_z_min", "pixel_z_max", "rms_x", "rms_y", "loo_x", "loo_y"):
        a = getattr(tiled, name)
        assert np.isnan(a[~valid]).all(), name
    assert np.isfinite(tiled.pixel_z_min[valid]).all() and np.isfinite(tiled.rms_x[valid]).all()
    assert (tiled.pixel_z_min[valid] <= tiled.pixel_z_max[valid]).all()
