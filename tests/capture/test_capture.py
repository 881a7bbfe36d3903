"""Live capture with the simulated devices: same dataset as `ptp simulate`, faults, kills and resumes."""

from __future__ import annotations

import filecmp
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ptpcore import cli
from ptpcore.capture import (STATE_FILE, ExposureError, ExposureLimits, capture, capture_state,
    exposure_report, pattern_image)
from ptpcore.capture.devices import ManualStage, SimulatedCamera, SimulatedDisplay, SimulatedStage, simulated_devices
from ptpcore.capture.devices.camera import FrameError
from ptpcore.capture.devices.stage import StageTimeout
from ptpcore.errors import Cancelled, CaptureError, ConfigError, DeviceError
from ptpcore.io import load_lut
from ptpcore.simulate import VirtualRig, scaled_preset, simulate_dataset

ARGS = ["--preset", "mild", "--width", "48", "--positions", "5", "--seed", "3"]


def small(name="mild", positions=5, width=48):
    return scaled_preset(name, width, positions=positions)


def images(folder: Path) -> list[Path]:
    return sorted(p.relative_to(folder) for p in folder.rglob("*.png"))


def assert_same_images(a: Path, b: Path) -> None:
    """Every image of dataset ``a`` is in ``b`` with the same bytes, and nothing else is."""
    ia, ib = images(a), images(b)
    assert ia == ib and ia
    different = [str(p) for p in ia if not filecmp.cmp(a / p, b / p, shallow=False)]
    assert not different, f"{len(different)} images differ, e.g. {different[:3]}"
    assert (a / "rig.toml").read_text() == (b / "rig.toml").read_text()


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """`ptp simulate` of the small mild rig: the dataset every capture must reproduce."""
    out = tmp_path_factory.mktemp("ref") / "sim"
    assert cli.main(["simulate", str(out), *ARGS, "-q"]) == 0
    return out


def snapshot(folder: Path, positions) -> dict:
    """inode, mtime and bytes of every image of ``positions``: what "not touched" means."""
    snap = {}
    for p in images(folder):
        if int(p.parts[0][1:]) in positions:
            st = (folder / p).stat()
            snap[p] = (st.st_ino, st.st_mtime_ns, (folder / p).read_bytes())
    return snap


# --------------------------------------------------------------------------- the main promise

def test_cli_capture_calibrates_exactly_like_simulate(reference, tmp_path):
    out = tmp_path / "cap"
    assert cli.main(["capture", "--camera", "sim", "--stage", "sim", "--out", str(out), *ARGS, "-q"]) == 0
    assert_same_images(reference, out)
    luts = []
    for ds in (reference, out):
        lut_file = tmp_path / f"{ds.name}.lut.h5"
        assert cli.main(["calibrate", str(ds), "--out", str(lut_file), "-q"]) == 0
        luts.append(load_lut(lut_file))
    a, b = luts
    assert a.valid.any()
    for name in ("x", "y", "valid", "n_positions", "pixel_z_min", "pixel_z_max", "rms_x", "rms_y", "loo_x", "loo_y"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
    assert (a.z_center, a.z_scale, a.z_min, a.z_max, a.rig_toml) == (b.z_center, b.z_scale, b.z_min, b.z_max,
                                                                     b.rig_toml)
    st = capture_state(out)
    assert st["complete"] and st["done"] == st["total"] == 5
    assert (out / "truth.h5").is_file()


def test_capture_can_end_the_sweep_at_its_first_position_again(tmp_path, capsys):
    """``ptp capture --repeat-first`` visits the first position again after the sweep ([stage] repeat_z_mm):
    bit for bit ``ptp simulate --repeat`` (the repeat has its own noise), and calibrate reports the drift."""
    sim, cap = tmp_path / "sim", tmp_path / "cap"
    assert cli.main(["simulate", str(sim), *ARGS, "--repeat", "-q"]) == 0
    assert cli.main(["capture", "--out", str(cap), *ARGS, "--repeat-first", "-q"]) == 0
    assert_same_images(sim, cap)
    first = sorted((cap / "z000").iterdir())[0].name
    assert not filecmp.cmp(cap / "z000" / first, cap / "z005" / first, shallow=False)  # its own noise
    st = capture_state(cap)
    assert st["complete"] and st["done"] == st["total"] == 6
    capsys.readouterr()
    assert cli.main(["calibrate", str(cap), "--out", str(tmp_path / "a.lut.h5"), "--model", "poly", "--degree", "1",
                     "-q"]) == 0
    said = capsys.readouterr().out
    assert "drift at z = 0 mm (position 0 again)" in said and "DRIFT WARNING" not in said


@pytest.mark.parametrize("name", ["ideal", "realistic", "rough"])
def test_every_preset_captures_bit_for_bit(name, tmp_path):
    rig, settings = small(name, positions=3, width=40)
    simulate_dataset(tmp_path / "sim", rig, settings, seed=7)
    result = capture(tmp_path / "cap", rig, *simulated_devices(rig, settings, 7))
    assert_same_images(tmp_path / "sim", tmp_path / "cap")
    assert result.captured == [0, 1, 2] and result.kept == [] and result.exposure.ok


# --------------------------------------------------------------------------- the simulated camera

def test_the_simulated_camera_photographs_what_is_shown_where_the_stage_is():
    rig, settings = small(positions=3)
    vr = VirtualRig(rig, settings, 3)
    camera, stage, display = simulated_devices(rig, settings, 3)
    for dev in (display, camera, stage):
        dev.open()
    spec = ("x", 2, rig.fringes.periods_px[2], 1, rig.fringes.steps[2])
    z = rig.stage.z_mm
    stage.move_to(z[2])
    display.show(pattern_image(rig, spec[0], spec[2], spec[3], spec[4], z[2]))
    assert np.array_equal(camera.grab(), vr.render(2, "x", spec[2], spec[3], spec[4]))
    # The pattern of position 1 (its carrier) shown while the stage is at position 2: another picture.
    display.show(pattern_image(rig, spec[0], spec[2], spec[3], spec[4], z[1]))
    wrong = camera.grab()
    assert not np.array_equal(wrong, vr.render(2, "x", spec[2], spec[3], spec[4]))
    assert not np.array_equal(wrong, vr.render(1, "x", spec[2], spec[3], spec[4]))
    # The right pattern with the stage elsewhere: not the frame of that position either.
    display.show(pattern_image(rig, spec[0], spec[2], spec[3], spec[4], z[2]))
    stage.move_to(z[1])
    assert not np.array_equal(camera.grab(), vr.render(2, "x", spec[2], spec[3], spec[4]))


def test_a_capture_that_grabs_before_showing_gets_other_frames(reference, tmp_path):
    """If the display did not change before the grab, the dataset is not the reference (the test would see it)."""
    rig, settings = small()

    class LateDisplay(SimulatedDisplay):
        def show(self, image):  # shows the previous image: one pattern late
            previous, self._pending = getattr(self, "_pending", None), image
            super().show(previous if previous is not None else image)

    display = LateDisplay(rig.lcd.width, rig.lcd.height)
    stage = SimulatedStage()
    camera = SimulatedCamera(VirtualRig(rig, settings, 3), display, stage)
    capture(tmp_path / "late", rig, camera, stage, display, check=False)
    same = [p for p in images(reference) if filecmp.cmp(reference / p, tmp_path / "late" / p, shallow=False)]
    assert len(same) < len(images(reference)) // 2


# --------------------------------------------------------------------------- exposure

def test_exposure_report_verdicts():
    rng = np.random.default_rng(0)
    dark = np.full((40, 50), 20, np.uint8)
    bright = rng.integers(150, 200, (40, 50)).astype(np.uint8)
    assert exposure_report(bright, dark, 255).verdict == "ok"
    hot = bright.copy()
    hot[:5] = 255
    r = exposure_report(hot, dark, 255, exposure_us=10000)
    assert r.verdict == "overexposed" and not r.ok and "saturate" in r.message
    assert r.suggested_exposure_us < 10000
    r = exposure_report((bright // 8).astype(np.uint8), (dark // 8).astype(np.uint8), 255, exposure_us=1000)
    assert r.verdict == "underexposed" and r.suggested_exposure_us > 1000 and "lengthen" in r.message
    r = exposure_report(np.full((40, 50), 3, np.uint8), dark * 0, 255)
    assert r.verdict == "no signal"
    r = exposure_report(bright, np.zeros_like(dark), 255)
    assert r.verdict == "black clipped"
    with pytest.raises(ConfigError, match="max_saturated"):
        ExposureLimits(max_saturated=2.0).validate()


def test_an_overexposed_camera_stops_before_the_long_run(tmp_path):
    rig, settings = small()
    camera, stage, display = simulated_devices(rig, settings, 3)
    seen = []
    with pytest.raises(ExposureError, match="overexposed.*shorten the exposure"):
        capture(tmp_path / "hot", rig, camera, stage, display, exposure_us=40_000, on_exposure=seen.append)
    assert seen and seen[0].verdict == "overexposed" and seen[0].saturated_fraction > 0.01
    assert images(tmp_path / "hot") == []  # not one frame of the long run
    state = json.loads((tmp_path / "hot" / STATE_FILE).read_text())
    assert state["exposure"]["verdict"] == "overexposed"
    # Accepting the verdict captures anyway; a resume with the nominal exposure passes the check.
    camera, stage, display = simulated_devices(rig, settings, 3)
    result = capture(tmp_path / "hot", rig, camera, stage, display, resume=True)
    assert result.exposure.ok and result.captured == list(range(5))
    camera, stage, display = simulated_devices(rig, settings, 3)
    dim = capture(tmp_path / "dim", rig, camera, stage, display, exposure_us=1500, accept_exposure=True)
    assert dim.exposure.verdict == "underexposed" and dim.exposure.suggested_exposure_us > 1500


# --------------------------------------------------------------------------- faults

def test_a_stage_timeout_leaves_a_resumable_capture(reference, tmp_path):
    rig, settings = small()
    out = tmp_path / "cap"
    with pytest.raises(StageTimeout) as info:
        capture(out, rig, *simulated_devices(rig, settings, 3, stage_faults={2: "timeout"}))
    msg = str(info.value)
    assert "simulated stage: move to z = 20 mm did not finish in time" in msg
    assert "2 of 5 positions are saved" in msg and "resume" in msg
    assert not (out / "rig.toml").exists()
    assert capture_state(out)["done"] == 2
    before = snapshot(out, {0, 1})
    assert len(before) == 2 * rig.fringes.frames_per_position
    result = capture(out, rig, *simulated_devices(rig, settings, 3), resume=True)
    assert result.kept == [0, 1] and result.captured == [2, 3, 4]
    assert snapshot(out, {0, 1}) == before  # kept positions were not touched
    assert_same_images(reference, out)


def test_a_dropped_frame_is_grabbed_again(reference, tmp_path):
    rig, settings = small()
    out = tmp_path / "cap"
    faults = {3: "none", 50: "raise", 51: "none", 120: "raise"}  # 3: in the exposure check
    camera, stage, display = simulated_devices(rig, settings, 3, camera_faults=faults)
    capture(out, rig, camera, stage, display)
    assert camera.grabs == 2 + 5 * rig.fringes.frames_per_position + len(faults)
    assert_same_images(reference, out)


def test_a_camera_that_stops_delivering_leaves_a_resumable_capture(reference, tmp_path):
    rig, settings = small()
    out = tmp_path / "cap"
    n = 2 + 3 * rig.fringes.frames_per_position + 7  # in the 4th position
    camera, stage, display = simulated_devices(rig, settings, 3, camera_faults=lambda i: "none" if i >= n else None)
    with pytest.raises(FrameError, match=r"no frame for position 3, .* after 3 tries .*3 of 5 positions are saved"):
        capture(out, rig, camera, stage, display)
    assert capture_state(out)["done"] == 3
    assert len(images(out)) == 3 * rig.fringes.frames_per_position + 7  # the partial position stays until resumed
    camera, stage, display = simulated_devices(rig, settings, 3, camera_faults={0: "error"})
    with pytest.raises(DeviceError, match="camera disconnected"):
        capture(out, rig, camera, stage, display, resume=True)
    result = capture(out, rig, *simulated_devices(rig, settings, 3), resume=True)
    assert result.kept == [0, 1, 2] and result.captured == [3, 4]
    assert_same_images(reference, out)


def test_wrong_frames_are_refused(tmp_path):
    rig, settings = small(positions=3)

    class SmallCamera(SimulatedCamera):
        def grab(self):
            return super().grab()[:-1]

    display = SimulatedDisplay(rig.lcd.width, rig.lcd.height)
    stage = SimulatedStage()
    camera = SmallCamera(VirtualRig(rig, settings, 3), display, stage)
    with pytest.raises(DeviceError, match=r"shape \(35, 48\), but rig.toml says camera 48x36"):
        capture(tmp_path / "cap", rig, camera, stage, display)


def test_cancel_and_resume(reference, tmp_path):
    rig, settings = small()
    out = tmp_path / "cap"
    calls = []

    def progress(fraction, message):
        calls.append(message)
        if fraction > 0.5:
            raise Cancelled("cancelled")

    with pytest.raises(Cancelled):
        capture(out, rig, *simulated_devices(rig, settings, 3), progress=progress)
    done = capture_state(out)["done"]
    assert 1 <= done < 5
    result = capture(out, rig, *simulated_devices(rig, settings, 3), resume=True)
    assert result.kept == list(range(done))
    assert_same_images(reference, out)


def test_resume_verifies_what_exists_by_reading_it(reference, tmp_path):
    rig, settings = small()
    out = tmp_path / "cap"
    with pytest.raises(StageTimeout):
        capture(out, rig, *simulated_devices(rig, settings, 3, stage_faults={3: "timeout"}))
    victim = out / rig.image_name(1, "y", rig.fringes.periods_px[1], 2, rig.fringes.steps[1])
    victim.write_bytes(victim.read_bytes()[:200])  # truncated behind the capture's back
    (out / "z002" / ".x_T4096_n00.png.abc123.part").write_bytes(b"half")  # a write killed mid-way
    result = capture(out, rig, *simulated_devices(rig, settings, 3), resume=True)
    assert result.kept == [0, 2] and result.captured == [1, 3, 4]
    assert not list(out.rglob("*.part"))
    assert_same_images(reference, out)


def test_the_folder_and_the_plan_are_checked(tmp_path):
    rig, settings = small(positions=3)
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(CaptureError, match="not empty"):
        capture(tmp_path / "busy", rig, *simulated_devices(rig, settings, 3))
    out = tmp_path / "cap"
    with pytest.raises(StageTimeout):
        capture(out, rig, *simulated_devices(rig, settings, 3, stage_faults={1: "timeout"}))
    with pytest.raises(CaptureError, match=r"partial capture \(1 of 3 positions\); resume it"):
        capture(out, rig, *simulated_devices(rig, settings, 3))
    other = rig.with_z([0.0, 15.0, 40.0])
    with pytest.raises(CaptureError, match="started with another rig"):
        capture(out, other, *simulated_devices(other, settings, 3), resume=True)
    with pytest.raises(CaptureError, match="other settings"):
        capture(out, rig, *simulated_devices(rig, settings, 3), resume=True, meta={"seed": 4})
    capture(out, rig, *simulated_devices(rig, settings, 3), resume=True)
    with pytest.raises(CaptureError, match="complete capture; choose another folder"):
        capture(out, rig, *simulated_devices(rig, settings, 3))


def test_a_manual_stage_records_the_engineers_readings(tmp_path):
    rig, settings = small(positions=3)
    asked = []
    offsets = [0.002, -0.001, 0.0]

    def ask(z, prompt):
        asked.append(prompt)
        return z + offsets[len(asked) - 1] if len(asked) <= 3 else None

    display = SimulatedDisplay(rig.lcd.width, rig.lcd.height)
    stage = ManualStage(ask)
    camera = SimulatedCamera(VirtualRig(rig, settings, 3), display, stage)
    result = capture(tmp_path / "cap", rig, camera, stage, display)
    assert asked[0] == "Move the stage to z = 0 mm, then enter its reading (mm)."
    assert result.rig.stage.z_mm == pytest.approx([0.002, 19.999, 40.0], abs=1e-12)
    from ptpcore.rig import load_rig

    assert load_rig(tmp_path / "cap").stage.z_mm == result.rig.stage.z_mm

    def far(z, prompt):
        return z + 7.0

    stage = ManualStage(far)
    with pytest.raises(DeviceError, match="reads z = 7 mm after the move to 0 mm"):
        capture(tmp_path / "far", rig, SimulatedCamera(VirtualRig(rig, settings, 3), display, stage), stage, display)
    stage = ManualStage(lambda z, p: None)
    with pytest.raises(Cancelled, match="cancelled"):
        capture(tmp_path / "stop", rig, SimulatedCamera(VirtualRig(rig, settings, 3), display, stage), stage, display)


# --------------------------------------------------------------------------- killed for real

def test_a_capture_killed_mid_way_resumes_with_nothing_lost(reference, tmp_path):
    out = tmp_path / "cap"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "ptpcore.cli", "capture", "--out", str(out), *ARGS, "--settle-ms", "10", "-q"]
    log = tmp_path / "stderr.txt"
    with open(log, "wb") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env=env)
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and proc.poll() is None:
                if (out / "z002").is_dir() and any((out / "z002").glob("*.png")):
                    break  # the first image of position 3 is written
                time.sleep(0.002)
            assert proc.poll() is None, log.read_text()
            proc.send_signal(signal.SIGKILL)
        finally:
            proc.wait(30)
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "rig.toml").exists()
    st = capture_state(out)
    assert st["done"] == 2 and not st["complete"]
    partial = [p for p in images(out) if p.parts[0] == "z002"]
    assert 0 < len(partial) < 40  # killed inside position 3
    kept = snapshot(out, {0, 1})
    assert len(kept) == 80
    assert cli.main(["capture", "--out", str(out), *ARGS, "--resume", "-q"]) == 0
    assert snapshot(out, {0, 1}) == kept
    assert not list(out.rglob("*.part"))
    assert_same_images(reference, out)
