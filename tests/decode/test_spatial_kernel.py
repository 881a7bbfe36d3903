"""The spatial-consistency check's numba kernels equal its numpy path bit for bit (issue 13)."""

import numpy as np
import pytest

from ptpcore.decode import spatial
from ptpcore.decode.phase import fused_kernels

pytestmark = pytest.mark.skipif(fused_kernels() is None, reason="numba kernels off")


def test_the_generated_row_kernels_are_the_generators_output():
    """``_median_rows.py`` is written by ``python -m ptpcore.decode.median_networks``: never edited by hand."""
    from pathlib import Path

    from ptpcore.decode import median_networks

    written = Path(median_networks.__file__).with_name("_median_rows.py").read_text()
    assert written == median_networks.render_module()


def test_median_networks_select_the_middle_values():
    from ptpcore.decode.median_networks import NET24, NET25, SLOTS24, SLOTS25

    rng = np.random.default_rng(0)
    for net, slots, m in ((NET25, SLOTS25, 25), (NET24, SLOTS24, 24)):
        v = np.concatenate([rng.random((m, 500)), rng.integers(0, 4, (m, 500)).astype(float)], axis=1)
        s = np.sort(v, axis=0)
        w = v.copy()
        for a, b in net:
            w[a], w[b] = np.minimum(w[a], w[b]), np.maximum(w[a], w[b])
        assert np.array_equal(w[slots[0]], s[(m - 1) // 2]) and np.array_equal(w[slots[1]], s[m // 2])


@pytest.mark.parametrize("band_rows", [None, 9, 16])
@pytest.mark.parametrize("holes", ["clustered", "scattered"])
def test_kernels_equal_the_numpy_path(monkeypatch, holes, band_rows):
    """Also with the fused residual in bands of a few rows (the numpy path takes the whole map)."""
    rng = np.random.default_rng(3)
    h, w = 150, 211
    if band_rows:
        monkeypatch.setattr(spatial, "SPATIAL_BAND_PIXELS", band_rows * w)
    r, c = np.mgrid[0:h, 0:w].astype(float)
    coord = 0.9 * c + 2e-4 * (c - 100) ** 2 + 0.3 * r + 0.02 * rng.standard_normal((h, w))
    coord[40:45, 60:66] += 2.0  # a defect
    valid = np.ones((h, w), bool)
    if holes == "clustered":
        valid[:7] = False
        valid[:, 190:] = False
        valid[80:95, 100:130] = False
    else:
        valid = rng.random((h, w)) > 0.1
    fused = spatial.neighbourhood_residual(coord, valid)
    flagged, used = spatial.spatial_outliers(coord, valid, 0.02)
    monkeypatch.setattr(spatial, "_kernels", lambda: None)
    plain = spatial.neighbourhood_residual(coord, valid)
    assert np.array_equal(fused[0], plain[0], equal_nan=True)
    assert np.array_equal(fused[1], plain[1])
    flagged2, used2 = spatial.spatial_outliers(coord, valid, 0.02)
    assert np.array_equal(flagged, flagged2) and used == used2
    assert flagged[40:45, 60:66].mean() > 0.5


def test_the_sigma_used_is_the_median_of_the_predicted_sigma_floored_by_the_spread():
    rng = np.random.default_rng(5)
    h, w = 120, 90
    r, c = np.mgrid[0:h, 0:w].astype(float)
    coord = 0.9 * c + 0.3 * r + 0.02 * rng.standard_normal((h, w))
    valid = rng.random((h, w)) > 0.1
    sigma = np.abs(0.02 + 0.01 * rng.standard_normal((h, w)))
    sigma[rng.random((h, w)) < 0.05] = np.nan
    resid, _ = spatial.neighbourhood_residual(coord, valid)
    spread = spatial.ROBUST_SIGMA * np.median(np.abs(resid[np.isfinite(resid)]))
    assert np.nanmin(sigma) < spread < np.nanmax(sigma)  # both sides of the floor are exercised
    _, used = spatial.spatial_outliers(coord, valid, sigma)
    assert used == float(np.nanmedian(np.maximum(sigma, spread)))
    _, used_scalar = spatial.spatial_outliers(coord, valid, 0.5 * spread)
    assert used_scalar == spread


def test_sigma_given_by_rows_flags_as_the_whole_map(monkeypatch):
    """The decoder hands the predicted sigma over as rows (no whole map at 12 MP): bands of 7 rows
    (the last one short) give the flags and the sigma used of the map itself, bit for bit."""
    rng = np.random.default_rng(6)
    h, w = 120, 90
    r, c = np.mgrid[0:h, 0:w].astype(float)
    coord = 0.9 * c + 0.3 * r + 0.02 * rng.standard_normal((h, w))
    coord[50:53, 20:24] += 1.0  # a few outliers to flag
    valid = rng.random((h, w)) > 0.1
    sigma = np.abs(0.02 + 0.01 * rng.standard_normal((h, w)))
    sigma[rng.random((h, w)) < 0.05] = np.nan
    whole = spatial.spatial_outliers(coord, valid, sigma)
    monkeypatch.setattr(spatial, "FLAG_ROWS", 7)
    asked = []

    def rows(r0, r1):
        asked.append((r0, r1))
        return sigma[r0:r1].copy()

    by_rows = spatial.spatial_outliers(coord, valid, rows)
    assert np.array_equal(whole[0], by_rows[0]) and whole[1] == by_rows[1]
    assert whole[0][50:53, 20:24].any()
    assert asked[0] == (0, 7) and asked[-1] == (119, 120) and len(asked) == -(-h // 7)


@pytest.mark.parametrize("kind", ["normal", "abs", "ties", "sorted", "reversed", "constant"])
@pytest.mark.parametrize("n", [11, 262_144, 262_145, 600_001, 600_002])
def test_median_exact_is_numpys_median(kind, n):
    """The spread's and the sigma's medians by a bracketing sub-sample: numpy's number, bit for bit."""
    rng = np.random.default_rng(n)
    x = rng.standard_normal(n)
    x = {"normal": x, "abs": np.abs(x), "ties": np.round(3 * x) / 3, "sorted": np.sort(x),
         "reversed": np.sort(x)[::-1].copy(), "constant": np.ones(n)}[kind]
    assert spatial.median_exact(x) == float(np.median(x))


@pytest.mark.parametrize("lo, hi", [(0, None), (0, 9), (5, 17), (20, 30), (27, 30)])
@pytest.mark.parametrize("w", [1, 2, 13])
def test_padded_maps_are_nan_wherever_not_written(lo, hi, w):
    """The padded maps are made with np.empty and only their border set to NaN: every value is
    the one a NaN-filled map would hold (the residual's room NaN but where the residual goes)."""
    rng = np.random.default_rng(w)
    h, pad = 30, 4
    coord = rng.standard_normal((h, w))
    valid = rng.random((h, w)) > 0.2
    cp, gcp, grp, rp = spatial._padded_maps(coord, valid, pad, lo, hi)
    hi = h if hi is None else hi
    ref = np.full((h + 2 * pad, w + 2 * pad), np.nan)  # the whole image's maps, padded
    ref[pad:pad + h, pad:pad + w] = np.where(valid, coord, np.nan)
    rows = slice(lo, hi + 2 * pad)  # padded rows of image rows [lo - pad, hi + pad)
    assert np.array_equal(cp, ref[rows], equal_nan=True)
    gc = np.full_like(ref, np.nan)
    if w > 2:
        gc[:, pad + 1:pad + w - 1] = 0.5 * (ref[:, pad + 2:pad + w] - ref[:, pad:pad + w - 2])
    assert np.array_equal(gcp, gc[rows], equal_nan=True)
    gr = np.full_like(ref, np.nan)
    gr[pad + 1:pad + h - 1] = 0.5 * (ref[pad + 2:pad + h] - ref[pad:pad + h - 2])
    gr[:, :pad], gr[:, pad + w:] = np.nan, np.nan
    assert np.array_equal(grp, gr[rows], equal_nan=True)
    assert np.isnan(rp).all() or np.isnan(np.delete(rp[:, :], np.s_[pad:pad + hi - lo], axis=0)).all()
    assert np.isnan(rp[:, :pad]).all() and np.isnan(rp[:, pad + w:]).all()


@pytest.mark.parametrize("amplitude, n_fine, period", [(0.9, 8, 16.0), (1.0, 5, 24), (0.37, 12, 7.5)])
def test_coordinate_sigma_kernel_is_numpys_bit_for_bit(monkeypatch, amplitude, n_fine, period):
    """The predicted sigma's rows in one numba pass: the numpy expression's numbers (zeros, a NaN
    and negative backgrounds included)."""
    from types import SimpleNamespace

    from ptpcore.decode import position
    from ptpcore.decode.noise import NoiseModel
    from ptpcore.decode.phase import fused_kernels

    if fused_kernels() is None:
        pytest.skip("numba kernels off")
    rng = np.random.default_rng(n_fine)
    bg = rng.uniform(-5, 250, (37, 41)).astype(np.float32)
    mod = rng.uniform(0, 120, (37, 41)).astype(np.float32)
    bg[3, 4], mod[5, 6], mod[7, 8] = np.nan, 0.0, np.nan
    fine = SimpleNamespace(background=bg, modulation=mod)
    model = NoiseModel(0.7, 0.031)
    got = position.coordinate_sigma(model, fine, n_fine, amplitude, period)(2, 30)
    monkeypatch.setattr(position, "fused_kernels", lambda: None)
    with np.errstate(all="ignore"):
        want = position.coordinate_sigma(model, fine, n_fine, amplitude, period)(2, 30)
    assert np.array_equal(got, want, equal_nan=True)
