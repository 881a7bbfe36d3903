"""Using the LUT: ``Lut.points``, ``Lut.ray`` and ``ptp apply`` against the simulator's exact rays."""

from dataclasses import replace

import cv2
import h5py
import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.evaluate import held_out_accuracy
from ptpcore.fit import fit_lut
from ptpcore.io import load_lut, read_height_map, save_lut
from ptpcore.simulate.virtual_rig import load_truth, save_truth

EPS = 1e-9  # the range tolerance of Lut.evaluate (mm)


@pytest.fixture(scope="module")
def applied(mild_rig, tmp_path_factory):
    """A poly-3 LUT fitted on every second position of the mild rig, its file, truth.h5 and held-out error."""
    vr, samples = mild_rig
    d = tmp_path_factory.mktemp("apply")
    k = samples.z.size
    cal, held = list(range(0, k, 2)), list(range(1, k, 2))
    lut = fit_lut(samples, "poly", 3, positions=cal)
    save_lut(lut, d / "rig.lut.h5")
    save_truth(d / "truth.h5", vr)
    truth, _, _ = load_truth(d / "truth.h5")
    acc = held_out_accuracy(lut, truth, vr.rig.stage.z_mm, held)
    return load_lut(d / "rig.lut.h5"), d, truth, acc, np.asarray(vr.rig.stage.z_mm)[cal]


def _read_npy(path):
    rec = np.load(path, allow_pickle=False)
    assert rec.dtype.names[:5] == ("x", "y", "z", "row", "col")
    return rec


def _rms_um(rec, truth, z):
    tx, ty = truth.xy(z)
    r, c = rec["row"], rec["col"]
    zz = z if np.ndim(z) == 0 else z[r, c]
    e = np.concatenate([rec["x"] - (tx if np.ndim(tx) == 0 else tx[r, c]),
                        rec["y"] - (ty if np.ndim(ty) == 0 else ty[r, c])])
    assert np.array_equal(rec["z"], np.broadcast_to(zz, rec["z"].shape))
    return float(np.sqrt(np.mean(e ** 2)) * 1e3)


def test_apply_between_calibrated_heights_matches_the_held_out_error(applied, capsys):
    """Heights halfway between a calibrated and a held-out position: the points are as far from the
    exact rays as the LUT is at the held-out positions (1.1x either way), and every valid pixel whose
    own range holds the height is there, once."""
    lut, d, truth, acc, cal_z = applied
    errs = []
    for z in np.arange(2.0, 40.0, 4.0):  # between cal (0, 8, ..) and held-out (4, 12, ..) positions
        out = d / f"z{z:g}.npy"
        assert main(["apply", str(d / "rig.lut.h5"), "--z", f"{z:g}", "--out", str(out)]) == 0
        line = capsys.readouterr().out.strip()
        rec = _read_npy(out)
        assert line.startswith(f"{out}: {rec.size} points of {lut.valid.size} pixels")
        want = lut.valid & (z >= lut.pixel_z_min - EPS) & (z <= lut.pixel_z_max + EPS)
        got = np.zeros_like(want)
        got[rec["row"], rec["col"]] = True
        assert rec.size == want.sum() > 0.5 * lut.valid.size
        assert np.array_equal(got, want)
        assert not rec["extrapolated"].any()
        n_out = int((lut.valid & ~want).sum())
        n_invalid = int((~lut.valid).sum())
        assert f"{n_invalid} invalid in the LUT" in line
        assert (f"{n_out} outside their calibrated z range" in line) == (n_out > 0)
        errs.append(_rms_um(rec, truth, z))
    rms = float(np.sqrt(np.mean(np.square(errs))))
    assert acc.rms_um / 1.1 <= rms <= 1.1 * acc.rms_um, (rms, acc.rms_um)


def test_tilted_plane_comes_back(applied):
    """A tilted plane's height map (heights where each pixel's exact ray meets it, NaN holes) gives
    points on that plane: X, Y as close to the rays as the held-out error, the plane's slopes back."""
    lut, d, truth, acc, _ = applied
    a0, bx, by = 20.0, 0.08, -0.05  # Z = a0 + bx (X - 90) + by (Y - 45), mm
    a = a0 - 90 * bx - 45 * by
    zmap = (a + bx * truth.x0 + by * truth.y0) / (1 - bx * truth.sx - by * truth.sy)
    zmap[::7, ::5] = np.nan
    tif = d / "plane.tif"
    assert cv2.imwrite(str(tif), zmap.astype(np.float32))
    z32 = read_height_map(tif, lut.shape)
    assert np.array_equal(np.isnan(z32), np.isnan(zmap))
    out = d / "plane.npy"
    assert main(["apply", str(d / "rig.lut.h5"), "--z", str(tif), "--out", str(out)]) == 0
    rec = _read_npy(out)
    cloud = lut.points(z32)
    assert cloud.n_no_height == int(np.isnan(zmap).sum())
    assert cloud.n_points + cloud.n_no_height + cloud.n_invalid + cloud.n_out_of_range + cloud.n_no_value \
        == lut.valid.size
    assert rec.size == cloud.n_points > 0.5 * lut.valid.size
    assert _rms_um(rec, truth, z32) <= 1.1 * acc.rms_um
    # The plane's slopes from the points: Z errors are the slopes times the X, Y errors.
    design = np.column_stack([np.ones(rec.size), rec["x"] - 90, rec["y"] - 45])
    coef, *_ = np.linalg.lstsq(design, rec["z"], rcond=None)
    resid = rec["z"] - design @ coef
    xy_err_mm = acc.rms_um * 1e-3
    assert np.sqrt(np.mean(resid ** 2)) <= 2 * np.hypot(bx, by) * xy_err_mm + 1e-5
    assert np.allclose(coef, [a0, bx, by], atol=1e-4)


def test_extrapolate_keeps_and_flags_pixels_outside_their_range(applied):
    lut, d, _, _, _ = applied
    z = float(lut.z_max) + 1.0  # above every pixel's calibrated range
    plain = lut.points(z)
    more = lut.points(z, extrapolate=True)
    assert plain.n_points == 0 and plain.n_out_of_range == lut.valid.sum() and more.n_out_of_range == 0
    assert more.n_points == plain.n_points + plain.n_out_of_range
    assert more.n_extrapolated == plain.n_out_of_range
    out = d / "extra.ply"
    assert main(["apply", str(d / "rig.lut.h5"), "--z", f"{z!r}", "--out", str(out), "--extrapolate"]) == 0
    header, rec = _read_ply(out)
    assert rec.size == more.n_points and int(rec["extrapolated"].sum()) == more.n_extrapolated


def _read_ply(path):
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    types = {"double": "<f8", "float": "<f4", "int": "<i4", "uchar": "u1"}
    fields = [(p.split()[2], types[p.split()[1]]) for p in header if p.startswith("property ")]
    n = int(next(p for p in header if p.startswith("element vertex")).split()[2])
    rec = np.frombuffer(data[end:], dtype=fields)
    assert rec.size == n
    return header, rec


def test_ply_npy_h5_hold_the_same_points(applied):
    """Every format carries the same numbers, sigma_x/sigma_y where the LUT has them."""
    lut, d, _, _, _ = applied
    plain = _read_ply(d / "extra.ply")[0] if (d / "extra.ply").exists() else None
    assert plain is None or not any("sigma" in p for p in plain)  # a LUT without sigma maps
    lut = replace(lut, sigma_x=(lut.loo_x * 0.5).astype(np.float32), sigma_y=(lut.loo_y * 0.5).astype(np.float32))
    save_lut(lut, d / "sigma.lut.h5")
    cloud = lut.points(14.0)
    for ext in ("ply", "npy", "h5"):
        assert main(["apply", str(d / "sigma.lut.h5"), "--z", "14", "--out", str(d / f"same.{ext}")]) == 0
    header, rec = _read_ply(d / "same.ply")
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    assert "comment units mm" in header
    assert [p for p in header if p.startswith("property")] == [
        "property double x", "property double y", "property double z", "property int row", "property int col",
        "property float sigma_x", "property float sigma_y", "property uchar extrapolated"]
    npy = _read_npy(d / "same.npy")
    with h5py.File(d / "same.h5", "r") as f:
        assert f.attrs["format"] == "ptp-points/1" and f.attrs["units"] == "mm"
        assert int(f.attrs["n_invalid"]) == cloud.n_invalid
        h5 = {k: f[k][()] for k in f}
    for name in ("x", "y", "z", "row", "col"):
        want = getattr(cloud, name)
        assert np.array_equal(rec[name], want) and np.array_equal(npy[name], want)
        assert np.array_equal(h5[name], want)
    for name in ("sigma_x", "sigma_y", "extrapolated"):
        want = getattr(cloud, name)
        assert np.array_equal(rec[name], want) and np.array_equal(npy[name], want)
        assert np.array_equal(h5[name], want)
    assert np.all(np.isfinite(cloud.sigma_x)) and cloud.sigma_x.dtype == np.float32


def test_ray_of_a_degree_one_lut(mild_rig):
    vr, samples = mild_rig
    lut = fit_lut(samples, "poly", 1)
    r, c = np.argwhere(lut.valid)[len(np.argwhere(lut.valid)) // 2]
    point, direction = lut.ray(r, c)
    assert point[2] == lut.z_center and direction[2] == 1.0
    for z in (3.0, 17.5, 38.0):
        ev = lut.evaluate(z, extrapolate=True)
        at = point + (z - point[2]) * direction
        assert np.allclose(at, [ev.x[r, c], ev.y[r, c], z], rtol=0, atol=1e-12)
    # The line is the simulator's ray to the LUT's accuracy (slope within a few um over 40 mm).
    truth = vr.truth()
    assert abs(direction[0] - truth.sx[r, c]) < 1e-3 and abs(direction[1] - truth.sy[r, c]) < 1e-3
    with pytest.raises(ValueError, match="degree-1 poly"):
        fit_lut(samples, "poly", 3).ray(r, c)
    with pytest.raises(ValueError, match="degree-1 poly"):
        fit_lut(samples, "linear").ray(r, c)
    bad = np.argwhere(~lut.valid)
    if bad.size:
        with pytest.raises(ValueError, match="no valid LUT"):
            lut.ray(*bad[0])
    with pytest.raises(ValueError, match="outside"):
        lut.ray(lut.shape[0], 0)


def test_points_from_tables_leave_out_nan_gaps(mild_rig):
    """pchip over runs of finite nodes: a height in a NaN gap is 'without a LUT value', not a point."""
    _, samples = mild_rig
    lut = fit_lut(samples, "pchip")
    lut.x[5, :10, :10] = np.nan  # node 5 (z = 20) lost for a corner
    cloud = lut.points(19.0)
    in_corner = lut.valid[:10, :10] & (lut.pixel_z_min[:10, :10] <= 19) & (lut.pixel_z_max[:10, :10] >= 19)
    # Anywhere: 19 mm between nodes 4 (16 mm) and 5 (20 mm), one of them NaN (the corner, or a
    # sample the decoder rejected at one position, e.g. departing from its neighbourhood).
    in_gap = lut.valid & (lut.pixel_z_min <= 19) & (lut.pixel_z_max >= 19) & (np.isnan(lut.x[4]) | np.isnan(lut.x[5]))
    assert in_corner.sum() > 0 and in_gap[:10, :10].sum() == in_corner.sum()
    assert cloud.n_no_value == int(in_gap.sum())
    assert not np.any((cloud.row < 10) & (cloud.col < 10))


@pytest.mark.parametrize("case", ["missing-lut", "not-hdf5", "bad-z", "nan-z", "wrong-shape", "uint16-tiff",
                                  "int-npy", "3d-npy", "bad-suffix", "no-point", "garbage-npy"])
def test_apply_bad_input_exits_2_with_one_line(applied, tmp_path, capsys, case):
    lut, d, _, _, _ = applied
    h, w = lut.shape
    lutf = str(d / "rig.lut.h5")
    out = tmp_path / "out.ply"
    z = "14"
    if case == "missing-lut":
        lutf = str(tmp_path / "nope.lut.h5")
    elif case == "not-hdf5":
        lutf = str(tmp_path / "text.lut.h5")
        (tmp_path / "text.lut.h5").write_text("hello")
    elif case == "bad-z":
        z = "fourteen"
    elif case == "nan-z":
        z = "nan"
    elif case == "wrong-shape":
        z = str(tmp_path / "z.npy")
        np.save(z, np.zeros((h, w + 1)))
    elif case == "uint16-tiff":
        z = str(tmp_path / "z.tif")
        cv2.imwrite(z, np.zeros((h, w), np.uint16))
    elif case == "int-npy":
        z = str(tmp_path / "z.npy")
        np.save(z, np.zeros((h, w), np.int32))
    elif case == "3d-npy":
        z = str(tmp_path / "z.npy")
        np.save(z, np.zeros((h, w, 2)))
    elif case == "garbage-npy":
        z = str(tmp_path / "z.npy")
        (tmp_path / "z.npy").write_bytes(b"\x93NUMPY garbage")
    elif case == "bad-suffix":
        out = tmp_path / "out.xyz"
    elif case == "no-point":
        z = "500"
    assert main(["apply", lutf, "--z", z, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ptp: error: ")
    if case in ("wrong-shape", "uint16-tiff", "int-npy", "3d-npy", "garbage-npy"):
        assert z in err[0]
    assert not out.exists()
    assert not list(tmp_path.glob(".out*"))  # no temporary left behind
