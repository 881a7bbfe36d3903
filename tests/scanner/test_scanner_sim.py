"""The scanner in the simulator (issue 34): the rig file's [projector] and [height], exact truth, and
decoded projector coordinates against it within their predicted noise."""

from dataclasses import replace

import numpy as np
import pytest

from ptpcore.errors import ConfigError
from ptpcore.rig.rigfile import load_rig, load_scan, rig_from_toml, rig_to_toml
from ptpcore.run.scanner import decode_projector
from ptpcore.simulate.scanner import HeightSweepSource, ScannerRig, default_objects, scanner_preset

# The honesty band of a predicted sigma (the trust issue): RMS of error / sigma.
HONEST = (0.8, 1.25)


@pytest.fixture(scope="module")
def mild():
    rig, sim, sc = scanner_preset("scanner-mild", 96, heights=11)
    return ScannerRig(rig, sim, sc, seed=5)


def test_rig_toml_round_trips_projector_and_height():
    rig, _sim, _sc = scanner_preset("scanner-rough", 96)
    text = rig_to_toml(rig)
    assert 'format = "ptp-dataset/2"' in text
    back = rig_from_toml(text)
    assert back.projector == rig.projector and back.height == rig.height
    h = back.height_rig()
    assert (h.lcd.width, h.lcd.height) == (1280, 800) and h.fringes.carrier_px_per_mm == (0.0, 0.0)
    assert h.stage.z_mm == rig.height.z_mm


@pytest.mark.parametrize("edit, key", [
    (lambda t: t.replace("[height]", "[unused]"), "height"),
    (lambda t: t.replace("[projector]\n", "[projector]\ncarrier_px_per_mm = [1.0, 0.0]\n"),
     "projector.carrier_px_per_mm"),
    (lambda t: t.replace("[projector]\n", '[projector]\nunwrap = "gray"\ngray_bits = 4\n'), "projector.unwrap"),
    # the preset's projector shows x and y: a [projector] showing y alone is refused
    (lambda t: t.replace('height = 800\ndirections = [\n    "x",\n    "y",\n]', 'height = 800\ndirections = [\n    "y",\n]'),
     "projector.directions"),
    (lambda t: t.replace("width = 1280", "width = 4000"), "projector.periods_px"),
])
def test_bad_scanner_tables_name_their_key(edit, key):
    rig, _sim, _sc = scanner_preset("scanner-mild", 96)
    text = edit(rig_to_toml(rig))
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        rig_from_toml(text)


def test_too_few_heights_is_refused():
    rig, _sim, _sc = scanner_preset("scanner-mild", 96)
    rig = replace(rig, height=replace(rig.height, z_mm=(0.0, 4.0)))
    with pytest.raises(ConfigError, match=r"height\.z_mm"):
        rig_from_toml(rig_to_toml(rig))


def test_truth_is_exact_both_ways(mild):
    """true_z inverts true_up to machine precision, and u_p changes monotonically with height."""
    for z in (0.0, 13.7, 40.0):
        up = mild.true_up(z)
        assert np.all(np.isfinite(up))
        assert np.max(np.abs(mild.true_z(up) - z)) < 1e-9
    slope = mild.true_up(21.0) - mild.true_up(20.0)
    assert np.all(np.sign(slope) == np.sign(slope[0, 0])) and np.min(np.abs(slope)) > 0.5


def test_plate_truth_includes_tilt_and_bow(mild):
    """The plate's tilt and bow move what a pixel sees by their height times the slope du_p/dz."""
    k = 3
    flat = mild.true_up(mild.plate_z_true[k])
    real = mild.plate_up(k)
    o, d = mild.pixel_rays()
    p = mild.plate_point(o, d, k)
    dz = p[..., 2] - mild.plate_z_true[k]
    slope = mild.true_up(mild.plate_z_true[k] + 1e-3) - flat
    assert np.max(np.abs(dz)) > 0.0005  # microns of bow and tilt are there
    np.testing.assert_allclose(real - flat, slope * dz * 1e3, atol=1e-6)


def test_decoded_projector_coordinate_within_its_predicted_noise(mild):
    """Every pixel decodes u_p on the plate; (u - truth) / sigma_u has RMS in the honesty band and no
    mean bias beyond 5 standard errors."""
    dec = decode_projector(HeightSweepSource(mild))
    truth = np.stack([mild.plate_up(k) for k in range(len(dec.z_mm))])
    ok = np.isfinite(dec.u)
    assert ok.mean() > 0.99
    zs = ((dec.u - truth) / dec.sigma_u)[ok]
    rms = float(np.sqrt(np.mean(zs ** 2)))
    assert HONEST[0] <= rms <= HONEST[1], rms
    assert abs(float(np.mean(zs))) < 5 * rms / np.sqrt(zs.size) + 0.05, np.mean(zs)


def test_objects_have_exact_truth(mild):
    """Each object's per-pixel truth lies on its surface, and its lit pixels face the projector."""
    for name, obj in default_objects(mild.rig).items():
        t = mild.scan_truth(obj)
        assert t["lit"].sum() > 50, name
        assert np.all(t["hit"][t["lit"]])
        assert np.max(np.abs(obj.distance(t["xyz"][t["hit"]]))) < 1e-9, name


def test_cli_simulate_writes_a_scanner_dataset(tmp_path):
    from ptpcore.cli.main import main

    out = tmp_path / "ds"
    assert main(["simulate", "--preset", "scanner-mild", "--width", "48", "-q", str(out)]) == 0
    rig = load_rig(out)
    assert rig.projector is not None and len(rig.height.z_mm) == 21
    assert (out / "scanner_truth.h5").is_file()
    for name in ("sphere", "ballbar", "plane"):
        spec = load_scan(out / "scans" / name)
        # a scan shows x alone (the height sweep x and y), otherwise the sweep's design (FORMATS.md)
        assert spec.views == 1 and spec.projector.fringes.directions == ("x",)
        assert rig.projector.fringes.directions == ("x", "y")
        shown = replace(spec.projector, fringes=replace(spec.projector.fringes, directions=("x", "y")))
        assert shown == rig.projector
        assert (out / "scans" / name / "truth.h5").is_file()
    assert main(["simulate", "--preset", "scanner-mild", "--gray", "2", "--force", "-q", str(out)]) == 2


def test_calibrate_names_a_missing_height_frame_before_decoding(tmp_path, capsys):
    from ptpcore.cli.main import main

    out = tmp_path / "ds"
    assert main(["simulate", "--preset", "scanner-mild", "--width", "48", "-q", str(out)]) == 0
    victim = sorted((out / "h007").glob("x_T*_n05.png"))[0]
    victim.unlink()
    capsys.readouterr()
    assert main(["calibrate", str(out), "--out", str(tmp_path / "a.lut.h5"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "h007/" + victim.name in err[0], err
    assert not (tmp_path / "a.lut.h5").exists()


def test_a_spilled_decode_equals_the_one_in_memory(mild):
    """The big-sensor path (the (K, H, W) arrays in a temporary file) decodes and fits bit for bit alike."""
    from ptpcore.fit.height import fit_height_map

    a = decode_projector(HeightSweepSource(mild), spill=False)
    b = decode_projector(HeightSweepSource(mild), spill=True)
    assert isinstance(b.u, np.memmap) and not isinstance(a.u, np.memmap)
    np.testing.assert_array_equal(a.u, b.u)
    np.testing.assert_array_equal(a.sigma_u, b.sigma_u)
    ha = fit_height_map(a.u, a.sigma_u, a.z_mm, degree=1, positions=[0, 2, 4, 6, 8, 10])
    hb = fit_height_map(b.u, b.sigma_u, b.z_mm, degree=1, positions=[0, 2, 4, 6, 8, 10])
    np.testing.assert_array_equal(ha.p, hb.p)
    np.testing.assert_array_equal(ha.sigma_z, hb.sigma_z)
