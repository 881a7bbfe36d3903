"""Per-pixel LUTs: fitting, leave-one-out, evaluation, ranges and the ptp-lut/1 file."""

import h5py
from dataclasses import replace

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator

from ptpcore.errors import FileFormatError
from ptpcore.io import load_lut, save_lut
from ptpcore.fit import fit_lut
from ptpcore.io import SampleStack


def _stack(k=9, h=6, w=7, seed=0, missing=0.2, noise=0.0, degree=2):
    rng = np.random.default_rng(seed)
    z = np.linspace(-5.0, 35.0, k)
    zc, zs = 15.0, 20.0
    t = (z - zc) / zs
    coef_x = rng.normal(size=(degree + 1, h, w)) * np.array([50, 3, 0.01, 0.001][: degree + 1])[:, None, None]
    coef_y = rng.normal(size=(degree + 1, h, w)) * np.array([40, 2, 0.01, 0.001][: degree + 1])[:, None, None]
    x = sum(c[None] * t[:, None, None] ** p for p, c in enumerate(coef_x))
    y = sum(c[None] * t[:, None, None] ** p for p, c in enumerate(coef_y))
    x = x + noise * rng.normal(size=x.shape)
    y = y + noise * rng.normal(size=y.shape)
    s = SampleStack.empty(z, (h, w), with_photometry=False)
    for i in range(k):
        reasons = (rng.random((h, w)) < missing).astype(np.uint8)
        s.set_position(i, x[i], y[i], reasons)
    return s, coef_x, coef_y, x, y


def test_poly_fit_recovers_exact_polynomials_with_missing_positions():
    s, cx, cy, _, _ = _stack()
    lut = fit_lut(s, "poly", 2)
    assert lut.valid.mean() > 0.8
    n = s.valid.sum(axis=0)
    assert np.array_equal(lut.valid, n >= 4)
    v = lut.valid
    # Samples are stored as float32 offsets from each pixel's first sample
    # (|offset| < 10 mm here): rounding of 2**-24 relative, i.e. below 1 nm, times
    # the conditioning of a degree-2 fit -> a few nm on the coefficients.
    assert np.allclose(lut.x[:, v], cx[:, v], rtol=0, atol=5e-6)
    assert np.allclose(lut.y[:, v], cy[:, v], rtol=0, atol=5e-6)
    assert np.all(lut.rms_x[v] < 1e-6)
    assert np.all(np.isnan(lut.x[:, ~v]))


def test_leave_one_out_equals_brute_force_refit():
    s, *_ = _stack(noise=0.01, missing=0.15, seed=4)
    lut = fit_lut(s, "poly", 2)
    t = (s.z - lut.z_center) / lut.z_scale
    for r, c in zip(*np.nonzero(lut.valid)):
        m = s.valid[:, r, c]
        xs = (s.x_ref[r, c] + s.x[:, r, c])[m]
        ts = t[m]
        errs = []
        for i in range(m.sum()):
            keep = np.arange(m.sum()) != i
            p = np.polynomial.polynomial.polyfit(ts[keep], xs[keep], 2)
            errs.append(np.polynomial.polynomial.polyval(ts[i], p) - xs[i])
        assert lut.loo_x[r, c] == pytest.approx(np.sqrt(np.mean(np.square(errs))), rel=1e-4)
        fit = np.polynomial.polynomial.polyfit(ts, xs, 2)
        rms = np.sqrt(np.mean((np.polynomial.polynomial.polyval(ts, fit) - xs) ** 2))
        assert lut.rms_x[r, c] == pytest.approx(rms, rel=1e-4)


@pytest.mark.parametrize("kind", ["linear", "pchip"])
def test_tables_interpolate_each_pixel_over_its_valid_run(kind):
    s, *_ = _stack(noise=0.05, missing=0.0, seed=2)
    s.reasons[4, 0, 0] = 1  # a hole in the middle of pixel (0, 0)
    s.x[4, 0, 0] = np.nan
    lut = fit_lut(s, kind)
    z = 12.3
    ev = lut.evaluate(z)
    xs = s.x_ref + s.x
    for r, c in [(1, 1), (3, 5)]:
        want = (np.interp(z, s.z, xs[:, r, c]) if kind == "linear"
                else PchipInterpolator(s.z, xs[:, r, c])(z))
        assert ev.x[r, c] == pytest.approx(want, abs=1e-9)
    # (0, 0) lacks node 4 (z = 15): invalid between nodes 3 and 5, fine elsewhere.
    assert np.isnan(lut.evaluate(12.3).x[0, 0]) and np.isnan(lut.evaluate(17.0).x[0, 0])
    assert np.isfinite(lut.evaluate(2.0).x[0, 0])


def test_out_of_range_is_flagged_not_extrapolated():
    s, *_ = _stack(missing=0.0)
    s.reasons[-2:, 2, 3] = 1  # pixel (2, 3) only valid up to z = 25
    s.x[-2:, 2, 3] = np.nan
    lut = fit_lut(s, "poly", 2)
    assert lut.pixel_z_max[2, 3] == pytest.approx(25.0)
    ev = lut.evaluate(30.0)
    assert not ev.in_range[2, 3] and np.isnan(ev.x[2, 3])
    assert ev.in_range[2, 2] and np.isfinite(ev.x[2, 2])
    ex = lut.evaluate(30.0, extrapolate=True)
    assert np.isfinite(ex.x[2, 3]) and not ex.in_range[2, 3]
    zmap = np.full(lut.shape, 10.0)
    zmap[0, 0] = 99.0
    ev = lut.evaluate(zmap)
    assert not ev.in_range[0, 0] and ev.in_range[1, 1]


def test_a_reading_that_float32_cannot_hold_is_in_its_own_range():
    """/quality/z_min, z_max are float32: 0.1 mm is stored as 0.10000000149. The reading itself is in
    range (it once was not: the 1e-9 tolerance vanished in float32); a micrometre beyond is not."""
    s, *_ = _stack(missing=0.0)
    lut = fit_lut(s, "poly", 2)
    lo, hi = 0.1, 20.3  # neither is a float32 number
    lut = replace(lut, pixel_z_min=np.full(lut.shape, lo, np.float32), pixel_z_max=np.full(lut.shape, hi, np.float32))
    assert float(np.float32(lo)) > lo and float(np.float32(hi)) < hi
    for z in (lo, hi, np.full(lut.shape, lo)):
        ev = lut.evaluate(z)
        assert ev.in_range[lut.valid].all() and np.isfinite(ev.x[lut.valid]).all()
    for z in (lo - 1e-3, hi + 1e-3):
        assert not lut.evaluate(z).in_range.any()


def _plain_h5py_evaluate(path, z):
    """A reader that knows only FORMATS.md: poly and linear tables."""
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "ptp-lut/1"
        m = f["model"].attrs
        x, y, valid = f["x"][()], f["y"][()], f["valid"][()].astype(bool)
        zmin, zmax = f["quality/z_min"][()], f["quality/z_max"][()]
        if m["kind"] == "poly":
            t = (z - m["z_center"]) / m["z_scale"]
            powers = t ** np.arange(x.shape[0])
            xv = np.tensordot(powers, x, axes=1)
            yv = np.tensordot(powers, y, axes=1)
        else:
            zn = f["z_nodes"][()]
            i = np.clip(np.searchsorted(zn, z, side="right") - 1, 0, len(zn) - 2)
            w = (z - zn[i]) / (zn[i + 1] - zn[i])
            xv = (1 - w) * x[i] + w * x[i + 1]
            yv = (1 - w) * y[i] + w * y[i + 1]
    ok = valid & (z >= zmin) & (z <= zmax)
    return np.where(ok, xv, np.nan), np.where(ok, yv, np.nan)


@pytest.mark.parametrize("kind", ["poly", "linear"])
def test_file_read_with_plain_h5py_gives_the_same_xy(tmp_path, rough_rig, kind):
    _, samples = rough_rig
    lut = fit_lut(samples, kind, 3)
    path = tmp_path / "a.lut.h5"
    save_lut(lut, path)
    back = load_lut(path)
    for z in (3.3, 17.0, 38.9):
        ev = back.evaluate(z)
        px, py = _plain_h5py_evaluate(path, z)
        assert np.array_equal(np.isnan(ev.x), np.isnan(px))
        m = np.isfinite(px)
        assert m.mean() > 0.5
        assert np.max(np.abs(ev.x[m] - px[m])) < 1e-9
        assert np.max(np.abs(ev.y[m] - py[m])) < 1e-9
        assert np.array_equal(ev.x, lut.evaluate(z).x, equal_nan=True)


def test_load_refuses_other_files(tmp_path):
    p = tmp_path / "x.lut.h5"
    with h5py.File(p, "w") as f:
        f.attrs["format"] = "ptp-lut/9"
    with pytest.raises(FileFormatError, match="newer"):
        load_lut(p)
    (tmp_path / "junk.lut.h5").write_bytes(b"not hdf5")
    with pytest.raises(FileFormatError, match="junk.lut.h5"):
        load_lut(tmp_path / "junk.lut.h5")
