"""The serial stage against a fake controller on a pseudo-terminal; its protocol comes from capture.toml."""

from __future__ import annotations

import sys
import time

import pytest

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="pseudo-terminals are POSIX")

from fake_stage_controller import FakeController  # noqa: E402

from ptpcore.capture import capture
from ptpcore.capture.devices import SerialStage, SimulatedCamera, SimulatedDisplay  # noqa: E402
from ptpcore.capture.devices.config import capture_config_from_toml  # noqa: E402
from ptpcore.capture.devices.stage import StageTimeout  # noqa: E402
from ptpcore.errors import ConfigError, DeviceError  # noqa: E402
from ptpcore.simulate import VirtualRig, scaled_preset, simulate_dataset

CONFIG = r'''
format = "ptp-capture-config/1"

[stage]
kind = "serial"

[stage.serial]
port = "{port}"
baudrate = 115200
write_ending = "\r"
read_ending = "\r\n"
timeout_s = {timeout}
move_timeout_s = {move_timeout}
poll_interval_s = 0.005
units_per_mm = {units}
home_command = "HOME"
home_reply = "^OK$"
move_command = "{move}"
move_reply = "^OK$"
position_command = "TP"
position_reply = '^TP\s+(?P<z>[-+0-9.]+)$'
{status}
error_reply = '^ERR\s*(?P<message>.*)$'
'''

STATUS = 'status_command = "MD?"\nidle_reply = "^1$"'


def stage_for(ctl, *, status=True, units=1.0, move="MA {z:.4f}", timeout=0.5, move_timeout=5.0) -> SerialStage:
    text = CONFIG.format(port=ctl.port, status=STATUS if status else "", units=units, move=move,
                         timeout=timeout, move_timeout=move_timeout)
    cfg = capture_config_from_toml(text, "capture.toml")
    assert cfg.stage.kind == "serial"
    return SerialStage(cfg.stage.serial)


@pytest.mark.parametrize("status", [True, False], ids=["status-polled", "position-polled"])
def test_moves_wait_until_the_stage_is_there(status):
    with FakeController(speed=200.0) as ctl:
        stage = stage_for(ctl, status=status)
        stage.open()
        try:
            stage.home()
            assert stage.position() == 0.0
            t = time.monotonic()
            stage.move_to(12.5)
            assert time.monotonic() - t >= 12.5 / 200.0 * 0.9  # it waited for the travel
            assert stage.position() == 12.5
        finally:
            stage.close()
        assert ctl.log[0] == "HOME" and "MA 12.5000" in ctl.log
        assert ("MD?" in ctl.log) == status


def test_controller_units_and_integer_steps():
    with FakeController(speed=1e6) as ctl:
        stage = stage_for(ctl, units=1000.0, move="MA {steps}")  # the controller counts µm steps
        stage.open()
        stage.move_to(4.25)
        assert stage.position() == pytest.approx(4.25)
        stage.close()
        assert "MA 4250" in ctl.log


def test_a_stalled_stage_times_out():
    with FakeController(stall=True) as ctl:
        stage = stage_for(ctl, status=False, move_timeout=0.3)
        stage.open()
        with pytest.raises(StageTimeout, match=r"move to z = 8 mm not finished after 0.3 s \(last reading 0 mm\)"):
            stage.move_to(8.0)
        stage.close()


def test_a_silent_controller_times_out():
    with FakeController(mute=True) as ctl:
        stage = stage_for(ctl, timeout=0.2)
        stage.open()
        t = time.monotonic()
        with pytest.raises(StageTimeout, match=r"no reply to 'TP' within 0.2 s"):
            stage.position()
        assert time.monotonic() - t < 2
        stage.close()


def test_controller_errors_reach_the_message():
    with FakeController(limit=50.0) as ctl:
        stage = stage_for(ctl)
        stage.open()
        with pytest.raises(DeviceError, match=r"controller reports an error after 'MA 80.0000': limit 50"):
            stage.move_to(80.0)
        stage.close()


def test_a_missing_port_is_a_device_error(tmp_path):
    cfg = capture_config_from_toml(CONFIG.format(port=tmp_path / "nope", status="", units=1.0, move="MA {z}",
                                                 timeout=0.2, move_timeout=1.0))
    stage = SerialStage(cfg.stage.serial)
    with pytest.raises(DeviceError, match="cannot open the port"):
        stage.open()


@pytest.mark.parametrize("edit, match", [
    (("baudrate = 115200", "baudrate = \"fast\""), "key 'stage.serial.baudrate' must be an integer"),
    (("units_per_mm = 1.0", "units_per_mm = 0.0"), "key 'stage.serial.units_per_mm' must be a positive number"),
    (("move_command = \"MA {z:.4f}\"", "move_command = \"MA {speed}\""), r"key 'stage.serial.move_command'.*\{speed\}"),
    (("(?P<z>[-+0-9.]+)", "([-+0-9.]+)"), "position_reply' must capture the position in a group named z"),
    (("error_reply = '", "error_reply = '(["), "key 'stage.serial.error_reply' is not a valid regular expression"),
    (("baudrate = 115200", "baudrate = 115200\nbaud = 9600"), "unknown key 'stage.serial.baud'"),
    (("[stage]\nkind = \"serial\"", "[stage]\nkind = \"serial\"\nspeed = 3"), "unknown key 'stage.speed'"),
    (("format = \"ptp-capture-config/1\"", "format = \"ptp-capture-config/9\""), "expected \"ptp-capture-config/1\""),
])
def test_bad_protocol_tables_name_the_key(edit, match):
    text = CONFIG.format(port="/dev/null", status="", units=1.0, move="MA {z:.4f}", timeout=1, move_timeout=5)
    assert edit[0] in text
    with pytest.raises(ConfigError, match=match):
        capture_config_from_toml(text.replace(edit[0], edit[1]), "capture.toml")


def test_a_capture_through_the_serial_stage(tmp_path):
    """The whole capture with the stage on the pty: same images as `ptp simulate` (readings are exact)."""
    rig, settings = scaled_preset("mild", 32, positions=3)
    simulate_dataset(tmp_path / "sim", rig, settings, seed=2)
    with FakeController(speed=2000.0) as ctl:
        stage = stage_for(ctl)
        display = SimulatedDisplay(rig.lcd.width, rig.lcd.height)
        camera = SimulatedCamera(VirtualRig(rig, settings, 2), display, stage)
        result = capture(tmp_path / "cap", rig, camera, stage, display)
    assert result.rig.stage.z_mm == rig.stage.z_mm
    for p in (tmp_path / "sim").rglob("*.png"):
        assert p.read_bytes() == (tmp_path / "cap" / p.relative_to(tmp_path / "sim")).read_bytes()
