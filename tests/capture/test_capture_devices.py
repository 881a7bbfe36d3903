"""The other devices and the capture configuration: OpenCV camera, GenICam without harvesters, the CLI prompt."""

from __future__ import annotations

import builtins

import cv2
import numpy as np
import pytest

from ptpcore import cli
from ptpcore.capture.devices import HarvestersCamera, OpenCVCamera, SimulatedDisplay
from ptpcore.capture.devices.config import capture_config_from_toml, load_capture_config
from ptpcore.errors import ConfigError, DeviceError
from ptpcore.rig import load_rig


def test_opencv_camera_reads_an_image_sequence(tmp_path):
    rng = np.random.default_rng(1)
    frames = [rng.integers(0, 256, (24, 32), dtype=np.uint8) for _ in range(3)]
    for i, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"img_{i:03d}.png"), cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    cam = OpenCVCamera(str(tmp_path / "img_%03d.png"), api=cv2.CAP_IMAGES, warmup=0)
    cam.open()
    try:
        got = [cam.grab() for _ in range(4)]
    finally:
        cam.close()
    assert [g.shape for g in got[:3]] == [(24, 32)] * 3 and got[0].dtype == np.uint8
    assert all(np.array_equal(g, f) for g, f in zip(got, frames))  # colour frames come back grey
    assert got[3] is None  # the sequence is over: a dropped frame, not an exception
    cam.close()


def test_opencv_camera_that_is_not_there(tmp_path):
    cam = OpenCVCamera(str(tmp_path / "missing_%03d.png"), api=cv2.CAP_IMAGES)
    with pytest.raises(DeviceError, match="cannot open"):
        cam.open()
    with pytest.raises(DeviceError, match="before open"):
        cam.grab()


def test_genicam_without_harvesters_says_how_to_install(monkeypatch):
    real_import = builtins.__import__

    def no_harvesters(name, *args, **kwargs):
        if name.startswith("harvesters"):
            raise ImportError("no harvesters here")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_harvesters)
    with pytest.raises(DeviceError, match=r"optional 'harvesters' package: pip install \"ptp-studio\[genicam\]\""):
        HarvestersCamera("/opt/producer.cti").open()


def test_display_refuses_wrong_images():
    d = SimulatedDisplay(8, 4)
    d.open()
    with pytest.raises(ValueError, match=r"expected a \(4, 8\) uint8 image"):
        d.show(np.zeros((4, 9), np.uint8))
    d.show(np.zeros((4, 8), np.uint8))
    assert d.shown == 1


def test_capture_config_file(tmp_path):
    path = tmp_path / "capture.toml"
    path.write_text('format = "ptp-capture-config/1"\n[camera]\nkind = "opencv"\nsource = 1\nexposure_us = 8000\n'
                    '[display]\nscreen = 1\nsettle_ms = 150\n[exposure_check]\nmax_saturated = 0.01\n')
    cfg = load_capture_config(path)
    assert (cfg.camera.kind, cfg.camera.source, cfg.camera.exposure_us) == ("opencv", 1, 8000.0)
    assert (cfg.display.screen, cfg.display.settle_ms) == (1, 150.0)
    assert cfg.stage.kind == "sim" and cfg.exposure_check == {"max_saturated": 0.01}
    for text, match in [
        ('[camera]\nkind = "sim"', "missing key 'format'"),
        ('format = "ptp-capture-config/1"\n[camera]\nkind = "webcam"', "'camera.kind' must be one of sim, opencv"),
        ('format = "ptp-capture-config/1"\n[stage]\nkind = "serial"', r"no \[stage.serial\] table"),
        ('format = "ptp-capture-config/1"\n[display]\nsettle = 3', "unknown key 'display.settle'"),
        ('format = "ptp-capture-config/1"\n[exposure_check]\nmax_dark = 3.0', "'max_dark' must be a fraction"),
        ('format = "ptp-capture-config/1"\n[lcd]\nwidth = 3', "unknown key 'lcd'"),
    ]:
        with pytest.raises(ConfigError, match=match):
            capture_config_from_toml(text, "capture.toml")
    with pytest.raises(ConfigError, match="file not found"):
        load_capture_config(tmp_path / "nope.toml")


def test_cli_manual_stage_prompts_for_readings(tmp_path, monkeypatch, capsys):
    answers = iter(["", "20.004", "oops", "40"])  # Enter takes the planned value; a typo is asked again
    monkeypatch.setattr(builtins, "input", lambda prompt: next(answers))
    out = tmp_path / "cap"
    assert cli.main(["capture", "--stage", "manual", "--out", str(out), "--preset", "mild", "--width", "32",
                     "--positions", "3", "-q"]) == 0
    assert load_rig(out).stage.z_mm == (0.0, 20.004, 40.0)
    assert "type the reading in mm" in capsys.readouterr().err


def test_cli_refuses_what_it_cannot_do(tmp_path, capsys):
    assert cli.main(["capture", "--camera", "opencv", "--out", str(tmp_path / "x")]) == 2
    assert "only the GUI shows" in capsys.readouterr().err
    assert cli.main(["capture", "--stage", "serial", "--out", str(tmp_path / "x")]) == 2
    assert "--stage serial needs --config FILE" in capsys.readouterr().err
