"""``ptp reconstruct``: a scan through the height map and the XY LUT, against the objects' exact surfaces.

Fast tier: a 128 x 96 camera; the XY LUT is the camera's exact rays (so what is tested is the height
map, the scan's decoding and the reconstruction with its sigmas); the height map is fitted to a
decoded sweep. The slow test runs the whole chain from the command line.
"""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ptpcore.cli.main import main
from ptpcore.evaluate.scanner import VDI_LEAVE_OUT, scan_accuracy
from ptpcore.fit.height import fit_height_map
from ptpcore.io.lutfile import load_lut, save_lut
from ptpcore.rig.rigfile import load_scan, scan_to_toml
from ptpcore.run.scanner import decode_projector, reconstruct
from ptpcore.simulate.scanner import (HeightSweepSource, ScannerRig, default_objects, exact_lut, load_scan_truth,
                                      scanner_preset, simulate_scan)

NORMALISED = (0.7, 1.4)  # issue 34: RMS of distance / sigma along the normal


@pytest.fixture(scope="module")
def scanner(tmp_path_factory):
    """A decoded mild sweep at 128 x 96, its height map, an exact XY LUT, and the three scans on disk."""
    folder = tmp_path_factory.mktemp("scanner")
    rig, sim, sc = scanner_preset("scanner-mild", 128, heights=11)
    sr = ScannerRig(rig, sim, sc, seed=4)
    dec = decode_projector(HeightSweepSource(sr))
    hm = fit_height_map(dec.u, dec.sigma_u, dec.z_mm, design=rig.projector.design_attrs)
    hm.camera_noise = (dec.noise.read_var, dec.noise.gain)  # as calibrate_height keeps it
    lut = exact_lut(sr, hm)
    save_lut(lut, folder / "scanner.lut.h5")
    for i, (name, obj) in enumerate(default_objects(rig).items()):
        simulate_scan(folder / name, sr, obj, i)
    return folder, sr, lut


@pytest.mark.parametrize("name", ["sphere", "ballbar", "plane"])
def test_points_lie_on_the_true_surface_within_their_sigma(scanner, name):
    folder, _sr, lut = scanner
    res = reconstruct(folder / name, lut)[0]
    obj, truth = load_scan_truth(folder / name)
    acc = scan_accuracy(res, obj, truth)
    assert acc.n_points >= 20, acc.n_points  # RMS of n normalised errors: relative spread 1/sqrt(2n)
    assert NORMALISED[0] <= acc.rms_normalised <= NORMALISED[1], acc.rms_normalised
    assert acc.n_beyond_4 <= acc.allowed_out, (acc.n_beyond_4, acc.allowed_out)
    # the points' own sigma along Z is the decoded u_p's noise through the map plus the map's sigma
    assert np.all(res.cloud.sigma_z > 0) and np.all(np.isfinite(res.cloud.sigma_x))


def test_scans_decode_within_the_sweeps_noise_model(scanner):
    """A scan's u_p against the exact u_p of the true surface point: within the sigma the height sweep's
    camera noise model predicts (RMS(error / sigma_u) in the honesty band; an object's own few hundred
    pixels measure the noise poorly)."""
    folder, sr, lut = scanner
    for name in ("sphere", "ballbar", "plane"):
        res = reconstruct(folder / name, lut)[0]
        _obj, truth = load_scan_truth(folder / name)
        ok = np.isfinite(res.u)
        err = (res.u - sr.project(truth["xyz"])[0])[ok] / res.sigma_u[ok]
        assert 0.8 <= float(np.sqrt(np.mean(err ** 2))) <= 1.25, name


def test_every_pixel_both_maps_cover_has_a_point(scanner):
    folder, _sr, lut = scanner
    res = reconstruct(folder / "plane", lut)[0]
    ev = lut.height.evaluate(res.u)
    covered = ev.in_range & lut.evaluate(np.where(ev.in_range, ev.z, lut.z_min)).in_range
    assert res.cloud.n_points == int(covered.sum()) > 0
    assert set(zip(res.cloud.row, res.cloud.col)) == set(zip(*np.nonzero(covered)))


def test_outside_the_height_range_is_flagged_never_extrapolated(scanner, tmp_path):
    """A map calibrated on the lower half of the heights: the plane's points above it are left out and
    counted, none extrapolated."""
    folder, sr, lut = scanner
    dec = decode_projector(HeightSweepSource(sr))
    low = np.flatnonzero(dec.z_mm <= 20.0)
    half = fit_height_map(dec.u, dec.sigma_u, dec.z_mm, degree=1, positions=low,
                          design=sr.rig.projector.design_attrs)
    lut_half = exact_lut(sr, half)
    res = reconstruct(folder / "plane", lut_half)[0]
    assert res.cloud.n_out_of_height_range > 100
    # the range is the calibrated u_p's: its edge reads 20 mm to within the samples' noise there
    assert np.all(res.cloud.z <= 20.0 + 5 * res.cloud.sigma_z)


def test_cli_writes_a_ply_a_viewer_reads(scanner, tmp_path, capsys):
    folder, _sr, _lut = scanner
    out = tmp_path / "sphere.ply"
    assert main(["reconstruct", str(folder / "sphere"), "--lut", str(folder / "scanner.lut.h5"),
                 "--out", str(out)]) == 0
    data = out.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[:2] == ["ply", "format binary_little_endian 1.0"]
    props = [p.split()[2] for p in header if p.startswith("property ")]
    assert props[:5] == ["x", "y", "z", "row", "col"] and {"sigma_x", "sigma_y", "sigma_z"} <= set(props)
    types = {"double": "<f8", "float": "<f4", "int": "<i4", "uchar": "u1"}
    rec = np.frombuffer(data[end:], dtype=[(p.split()[2], types[p.split()[1]]) for p in header
                                           if p.startswith("property ")])
    n = int(next(p for p in header if p.startswith("element vertex")).split()[2])
    assert rec.size == n > 0 and np.all(np.isfinite(rec["z"]))
    assert f"{n} points" in capsys.readouterr().out


@pytest.mark.parametrize("case", ["no height map", "other periods", "missing frame", "bad suffix", "camera"])
def test_bad_input_exits_2_naming_the_culprit(scanner, tmp_path, capsys, case):
    import shutil

    folder, _sr, lut = scanner
    scan = tmp_path / "scan"
    shutil.copytree(folder / "sphere", scan)
    lut_path, out, expect = folder / "scanner.lut.h5", tmp_path / "out.ply", None
    if case == "no height map":
        lut_path = tmp_path / "xy.lut.h5"
        lut.height, keep = None, lut.height
        try:
            save_lut(lut, lut_path)
        finally:
            lut.height = keep
        expect = "no height map"
    elif case == "other periods":
        spec = load_scan(scan)
        f = spec.projector.fringes
        other = replace(spec.projector, fringes=replace(f, periods_px=f.periods_px[:-1] + (64.0,)))
        (scan / "scan.toml").write_text(scan_to_toml(replace(spec, projector=other)))
        expect = "projector.periods_px"
    elif case == "missing frame":
        victim = sorted(scan.glob("x_T*_n03.png"))[-1]
        victim.unlink()
        expect = victim.name
    elif case == "bad suffix":
        out, expect = tmp_path / "out.xyz", "--out"
    elif case == "camera":
        toml = (scan / "scan.toml").read_text().replace("width = 128", "width = 129", 1)
        (scan / "scan.toml").write_text(toml)
        expect = "camera 129x96"
    assert main(["reconstruct", str(scan), "--lut", str(lut_path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expect in err[0], err


@pytest.mark.slow
def test_the_whole_scanner_from_the_command_line(tmp_path, capsys):
    """simulate -> calibrate (XY LUT and height map) -> reconstruct on scanner-rough at 160 x 120: the
    LUT file has /height, and each scan's points lie on the true surface within their sigma."""
    ds = tmp_path / "ds"
    assert main(["simulate", "--preset", "scanner-rough", "--width", "160", "--seed", "3", "-q", str(ds)]) == 0
    lut_path = tmp_path / "rough.lut.h5"
    assert main(["calibrate", str(ds), "--out", str(lut_path), "-q"]) == 0
    assert "height map" in capsys.readouterr().out
    lut = load_lut(lut_path)
    assert lut.height is not None and lut.height.valid.mean() > 0.99
    for name in ("sphere", "ballbar", "plane"):
        out = tmp_path / f"{name}.ply"
        assert main(["reconstruct", str(ds / "scans" / name), "--lut", str(lut_path), "--out", str(out)]) == 0
        res = reconstruct(ds / "scans" / name, lut)[0]
        obj, truth = load_scan_truth(ds / "scans" / name)
        acc = scan_accuracy(res, obj, truth)
        assert NORMALISED[0] <= acc.rms_normalised <= NORMALISED[1], (name, acc.rms_normalised)
        assert acc.n_beyond_4 <= max(acc.allowed_out, int(VDI_LEAVE_OUT * acc.n_points)), name
        assert Path(out).stat().st_size > 0


def test_a_scan_of_several_views_writes_one_cloud_per_view(scanner, tmp_path, capsys):
    """``{pos}`` in the scan's template: views counted from the files, one cloud each."""
    import shutil

    folder, _sr, _lut = scanner
    scan = tmp_path / "views"
    for pos, name in enumerate(("sphere", "plane")):
        shutil.copytree(folder / name, scan / f"v{pos}", ignore=shutil.ignore_patterns("*.toml", "*.h5"))
    spec = load_scan(folder / "sphere")
    (scan / "scan.toml").write_text(scan_to_toml(replace(spec, template="v{pos}/" + spec.template)))
    assert load_scan(scan).views == 2
    out = tmp_path / "cloud.npy"
    assert main(["reconstruct", str(scan), "--lut", str(folder / "scanner.lut.h5"), "--out", str(out)]) == 0
    sizes = [np.load(tmp_path / f"cloud.view{i:03d}.npy").size for i in range(2)]
    assert 0 < sizes[0] < sizes[1]  # the sphere is smaller than the plane
    assert not out.exists()


def test_inspect_and_diff_report_the_height_map(scanner, capsys):
    folder, _sr, lut = scanner
    path = str(folder / "scanner.lut.h5")
    assert main(["inspect", path]) == 0
    out = capsys.readouterr().out
    assert f"numerator degree {lut.height.degree}" in out and "predicted sigma Z" in out
    assert all(len(line) <= 100 for line in out.splitlines())  # issue 41: a 100-column terminal
    assert main(["diff", path, path, "--tolerance-um", "1"]) == 0
    out = capsys.readouterr().out
    assert f"height map Z        {int(lut.height.valid.sum())} common pixels: RMS 0.000 µm" in out
