"""Drift within a sweep (issue 16): a repeat of the first position judged against the predicted noise."""

import json
from dataclasses import replace

import numpy as np
import pytest

from ptpcore.fit.drift import Drift, RepeatSource, sweep_drift
from ptpcore.io import SimulatedSource
from ptpcore.run import collect_samples
from ptpcore.simulate import VirtualRig, scaled_preset


@pytest.fixture(scope="module")
def sweep():
    rig, settings = scaled_preset("mild", 160, positions=11)
    vr = VirtualRig(rig, settings, 1)
    return rig, settings, collect_samples(SimulatedSource(vr))


def _repeat(rig, settings, shift_mm=0.0):
    """The first position captured again (other noise; the same stage error: the first draw of the
    same seed), the camera moved sideways by ``shift_mm`` in between."""
    z = rig.stage.z_mm
    rig_b = replace(rig, stage=replace(rig.stage, z_mm=(z[0], z[-1])))  # same z range: same pose
    moved = replace(settings, offset_mm=(settings.offset_mm[0] + shift_mm, settings.offset_mm[1]))
    vb = VirtualRig(rig_b, moved, 1, noise_seed=101)  # another noise stream
    return collect_samples(SimulatedSource(vb), positions=[0]).subset([0])


def test_a_repeat_without_drift_is_within_the_predicted_noise(sweep):
    rig, settings, samples = sweep
    d = sweep_drift(samples, _repeat(rig, settings), rig)
    assert d.matched.tolist() == [0] and not d.warnings
    assert 0.8 <= d.rms_um[0] / d.predicted_rms_um[0] <= 1.25, d.lines()
    assert np.all(np.abs(d.mean_um[0]) < 5 * d.mean_se_um[0])


def test_a_camera_that_moved_is_a_named_warning(sweep):
    """The camera moved 0.5 um sideways (far below one pixel's noise): the mean drift finds it."""
    rig, settings, samples = sweep
    d = sweep_drift(samples, _repeat(rig, settings, 0.0005), rig)
    assert d.warnings and "moved" in d.warnings[0]
    # the scene moves the other way in the camera's world coordinates
    se = np.asarray(d.mean_se_um[0])  # the mean's standard error from the predicted noise, per axis
    assert abs(abs(d.mean_um[0][0]) - 0.5) < 4 * se[0] and abs(d.mean_um[0][1]) < 4 * se[1], (d.mean_um, se)
    assert se.max() < 0.125  # the 0.5 um shift is at least 4 standard errors: the test can tell
    assert d.lines()[0].startswith("DRIFT WARNING")
    j = json.loads(d.to_json())
    assert j["warnings"] == d.warnings and j["repeats"][0]["position"] == 0
    assert isinstance(d, Drift)


def test_repeat_source_maps_positions_after_the_sweep():
    class Fake:
        rig = replace(scaled_preset("mild", 80)[0])

        def frames(self, k):
            return k

    src = Fake()
    src.rig = replace(src.rig, stage=replace(src.rig.stage, repeat_z_mm=(src.rig.stage.z_mm[0],)))
    rep = RepeatSource(src)
    assert rep.rig.stage.z_mm == (src.rig.stage.z_mm[0],) and rep.frames(0) == src.rig.stage.n_positions
    with pytest.raises(ValueError):
        RepeatSource(type("S", (), {"rig": scaled_preset("mild", 80)[0]})())


def test_calibrate_reports_the_drift_of_the_simulators_repeat(tmp_path, capsys):
    """``ptp simulate --repeat`` shows the first position again after the sweep (its own noise and stage
    error, ptp-dataset/2 ``[stage] repeat_z_mm``): calibrate finds it within the predicted noise; with
    ``--drift-um`` the camera moved sideways before the repeat: a named warning and the mean shift."""
    from ptpcore.cli import main
    from ptpcore.io import load_lut
    from ptpcore.rig import load_rig

    found = []
    for name, extra in (("still", []), ("moved", ["--drift-um", "3", "0"])):
        data = tmp_path / name
        assert main(["simulate", str(data), "--preset", "mild", "--width", "80", "--positions", "5", "--repeat",
                     *extra, "-q"]) == 0
        rig = load_rig(data / "rig.toml")
        assert rig.stage.repeat_z_mm == (0.0,) and rig.stage.n_positions == 5
        assert (data / "z005").is_dir() and not (data / "z006").exists()
        out = tmp_path / f"{name}.lut.h5"
        assert main(["calibrate", str(data), "--out", str(out), "--model", "poly", "--degree", "1", "-q"]) == 0
        found.append((capsys.readouterr().out, json.loads(load_lut(out).provenance["drift"])))
    (said, d), (said_moved, d_moved) = found
    r = d["repeats"][0]
    assert "drift at z = 0 mm (position 0 again)" in said and "DRIFT WARNING" not in said and not d["warnings"]
    assert r["position"] == 0 and 0.8 <= r["rms_um"] / r["predicted_rms_um"] <= 1.25, r
    assert all(abs(m) < 5 * se for m, se in zip(r["mean_um"], r["mean_se_um"]))
    # Moved 3 um in X (a tenth of a pixel's noise at 80 px): the mean drift finds it, X only.
    rm = d_moved["repeats"][0]
    assert d_moved["warnings"] and "DRIFT WARNING" in said_moved
    assert abs(abs(rm["mean_um"][0]) - 3.0) < 5 * rm["mean_se_um"][0] and abs(rm["mean_um"][1]) < 5 * rm["mean_se_um"][1]


def test_simulate_drift_needs_repeat(tmp_path):
    from ptpcore.cli import main

    assert main(["simulate", str(tmp_path / "d"), "--preset", "mild", "--width", "40", "--positions", "3",
                 "--drift-um", "1", "0", "-q"]) == 2
