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
    vb = VirtualRig(rig_b, moved, 1)
    vb.seed = 101  # another noise stream
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


def test_calibrate_reports_the_drift_of_a_repeated_position(tmp_path, capsys):
    """A ptp-dataset/2 folder whose first position was captured again after the sweep (here: the same
    images, so no drift at all): the summary and /provenance drift say so."""
    import shutil

    from ptpcore.cli import main
    from ptpcore.io import load_lut

    data = tmp_path / "data"
    assert main(["simulate", str(data), "--preset", "mild", "--width", "80", "--positions", "5", "-q"]) == 0
    text = (data / "rig.toml").read_text()
    text = text.replace('format = "ptp-dataset/1"', 'format = "ptp-dataset/2"')
    text = text.replace("[stage]\n", "[stage]\nrepeat_z_mm = [0.0]\n")
    (data / "rig.toml").write_text(text)
    shutil.copytree(data / "z000", data / "z005")
    out = tmp_path / "a.lut.h5"
    assert main(["calibrate", str(data), "--out", str(out), "--model", "poly", "--degree", "1", "-q"]) == 0
    said = capsys.readouterr().out
    assert "drift at z = 0 mm (position 1 again): RMS 0.000" in said and "DRIFT WARNING" not in said
    d = json.loads(load_lut(out).provenance["drift"])
    assert d["repeats"][0]["position"] == 0 and d["repeats"][0]["rms_um"] == 0 and not d["warnings"]
