"""Real cameras through their vendors' software: harvesters + the GenTL producer the ``genicam`` package
ships (``viky.cti``: 3 simulated "Viky" devices, 400x400, Mono8 and RGBa8, no exposure control) and Basler's
pypylon with its camera emulation (``PYLON_CAMEMU``). Each SDK's tests skip only when it is not installed.

The conversion of colour frames to grey (the dataset reader's rule) is a unit test: it needs no SDK.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ptpcore.capture import capture
from ptpcore.capture.devices import SimulatedDisplay, SimulatedStage
from ptpcore.capture.devices.camera import FrameError, HarvestersCamera, PylonCamera, camera_from_config, grey_from_colour
from ptpcore.capture.devices.config import capture_config_from_toml
from ptpcore.errors import DeviceError
from ptpcore.io.dataset import luminance, validate_dataset
from ptpcore.simulate import scaled_preset

HAVE_HARVESTERS = importlib.util.find_spec("harvesters") is not None and importlib.util.find_spec("genicam") is not None
HAVE_PYLON = importlib.util.find_spec("pypylon") is not None
needs_harvesters = pytest.mark.skipif(not HAVE_HARVESTERS, reason="harvesters and genicam are not installed"
                                      " (pip install \"ptp-studio[genicam]\")")
needs_pylon = pytest.mark.skipif(not HAVE_PYLON, reason="pypylon is not installed (pip install \"ptp-studio[pylon]\")")


@pytest.fixture(scope="module")
def viky() -> str:
    import genicam

    cti = Path(genicam.__file__).parent / "viky.cti"
    assert cti.is_file(), f"the genicam package no longer ships {cti}"
    return str(cti)


@pytest.fixture
def camemu(monkeypatch):
    """pylon's emulated camera (read by pylon at every device enumeration)."""
    monkeypatch.setenv("PYLON_CAMEMU", "1")


def small_rig(width: int, height: int, bit_depth: int = 8, positions: int = 3):
    """A small simulated rig with the camera's frame size: a capture's plan, not its pixels."""
    rig, _ = scaled_preset("mild", 48, positions=positions)
    return replace(rig, camera=replace(rig.camera, width=width, height=height, bit_depth=bit_depth))


# --------------------------------------------------------------------------- no SDK needed

def test_colour_frames_become_grey_by_the_dataset_readers_rule():
    rng = np.random.default_rng(4)
    rgb = rng.integers(1, 255, (6, 7, 4), dtype=np.uint8)
    rgb[0, 0, :3] = (255, 10, 10)  # one channel saturated: the pixel is saturated
    rgb[0, 1, :3] = (0, 200, 200)  # one channel at black: the pixel is clipped at black
    grey = grey_from_colour(rgb, "RGB")
    want = luminance(np.ascontiguousarray(rgb[:, :, 2::-1]), 255)  # the reader's (BGR) luminance
    assert grey.dtype == np.uint8 and grey.shape == (6, 7)
    assert np.array_equal(grey, np.rint(want).astype(np.uint8))
    assert grey[0, 0] == 255 and grey[0, 1] == 0
    r, g, b = (rgb[2, 3, i].astype(float) for i in range(3))
    assert abs(float(grey[2, 3]) - (0.299 * r + 0.587 * g + 0.114 * b)) <= 0.5 + 1e-4
    assert np.array_equal(grey_from_colour(rgb[:, :, 2::-1], "BGR"), grey)  # channel order honoured


def test_capture_toml_chooses_the_pylon_camera():
    cfg = capture_config_from_toml('format = "ptp-capture-config/1"\n[camera]\nkind = "pylon"\n'
                                   'serial_number = "0815-0000"\npixel_format = "Mono12"\ntimeout_s = 2.0\n')
    cam = camera_from_config(cfg.camera)
    assert isinstance(cam, PylonCamera) and cam.device == "0815-0000" and cam.pixel_format == "Mono12"
    assert cam.timeout_s == 2.0
    cfg = capture_config_from_toml('format = "ptp-capture-config/1"\n[camera]\nkind = "genicam"\n'
                                   'cti = "/opt/p.cti"\ndevice = 2\n')
    cam = camera_from_config(cfg.camera)
    assert isinstance(cam, HarvestersCamera) and cam.cti == "/opt/p.cti" and cam.device == 2


def test_pylon_missing_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pypylon", None)  # import pypylon -> ImportError
    with pytest.raises(DeviceError, match=r"optional 'pypylon' package: pip install \"ptp-studio\[pylon\]\""):
        PylonCamera().open()


# --------------------------------------------------------------------------- harvesters + viky.cti

@pytest.mark.slow
@needs_harvesters
def test_genicam_grabs_real_frames_from_the_shipped_producer(viky):
    for device in (0, "2", {"serial_number": "1"}):
        cam = HarvestersCamera(viky, device, timeout_s=2.0, pixel_format="Mono8")
        cam.open()
        try:
            assert cam.model == "Viky" and cam.bit_depth == 8 and not cam.triggered  # no trigger node
            frames = [cam.grab() for _ in range(3)]
        finally:
            cam.close()
        cam.close()  # twice is fine
        for f in frames:
            assert f.shape == (400, 400) and f.dtype == np.uint8
        assert "Viky (serial" in cam.describe()
    cam = HarvestersCamera(viky, 0, pixel_format="RGBa8")  # colour, converted to grey
    cam.open()
    try:
        nm = cam.node_map
        grey = cam.grab()
        assert grey.shape == (400, 400) and grey.dtype == np.uint8 and cam.bit_depth == 8
        with pytest.raises(DeviceError, match=r"Viky \(serial 0\).*has no exposure control"):
            cam.set_exposure(5000)
        assert str(nm.PixelFormat.value) == "RGBa8"
    finally:
        cam.close()


@pytest.mark.slow
@needs_harvesters
def test_genicam_frame_rate_below_the_timeout_is_a_dropped_frame(viky):
    cam = HarvestersCamera(viky, 0, timeout_s=0.2, pixel_format="Mono8", features={"AcquisitionFrameRate": 1.0})
    cam.open()
    try:
        with pytest.raises(FrameError, match=r"Viky \(serial 0\).*no frame within 0.2 s"):
            cam.grab()
    finally:
        cam.close()


@pytest.mark.slow
@needs_harvesters
def test_genicam_errors_name_the_producer_device_and_setting(viky, tmp_path):
    with pytest.raises(DeviceError, match=r"GenTL producer .*nope\.cti: no such file"):
        HarvestersCamera(str(tmp_path / "nope.cti")).open()
    bad = tmp_path / "bad.cti"
    bad.write_bytes(b"not a shared library")
    with pytest.raises(DeviceError, match=r"GenTL producer .*bad\.cti: cannot be loaded"):
        HarvestersCamera(str(bad)).open()
    with pytest.raises(DeviceError, match=r"no camera number 7 \(the producer lists 3: 0: Viky \(serial 0\)"):
        HarvestersCamera(viky, 7).open()
    with pytest.raises(DeviceError, match=r"no camera with \{'serial_number': '9'\}"):
        HarvestersCamera(viky, "9").open()
    with pytest.raises(DeviceError, match=r"Viky \(serial 0\).*pixel format 'Mono12' is not offered \(it offers"):
        HarvestersCamera(viky, 0, pixel_format="Mono12").open()
    with pytest.raises(DeviceError, match=r"has no software trigger"):
        HarvestersCamera(viky, 0, trigger="software").open()
    cam = HarvestersCamera(viky, 0, pixel_format="Mono8")  # after all those, the producer still opens
    cam.open()
    cam.close()


@pytest.mark.slow
@needs_harvesters
def test_genicam_capture_writes_a_dataset_the_reader_validates(viky, tmp_path):
    rig = small_rig(400, 400, positions=2)
    cam = HarvestersCamera(viky, 0, timeout_s=2.0, pixel_format="Mono8")
    out = tmp_path / "viky"
    display = SimulatedDisplay(rig.lcd.width, rig.lcd.height)
    result = capture(out, rig, cam, SimulatedStage(), display, check=False)
    assert len(result.captured) == 2
    report = validate_dataset(out, full=True)  # raises on a missing, mis-sized or wrong-depth image
    assert report.decoded and report.n_images == len(list(out.rglob("*.png"))) > 0 and not report.colour
    assert (report.rig.camera.width, report.rig.camera.height, report.rig.camera.bit_depth) == (
        rig.camera.width, rig.camera.height, rig.camera.bit_depth)


# --------------------------------------------------------------------------- pylon emulation

@pytest.mark.slow
@needs_pylon
def test_pylon_emulation_grabs_mono8_mono12_mono16_with_exposure_and_trigger(camemu):
    for fmt, bits, dtype, top in (("Mono8", 8, np.uint8, 255), ("Mono12", 12, np.uint16, 4095),
                                  ("Mono16", 16, np.uint16, 65535), ("RGB8Packed", 8, np.uint8, 255)):
        cam = PylonCamera("0815-0000", timeout_s=2.0, pixel_format=fmt, features={"Width": 160, "Height": 120})
        cam.open()
        try:
            assert cam.model == "Emulation" and cam.triggered and cam.bit_depth == bits
            cam.set_exposure(2500.0)
            assert cam.node_map.ExposureTime.value == pytest.approx(2500.0)
            f = cam.grab()
            assert f.shape == (120, 160) and f.dtype == dtype and int(f.max()) <= top and f.max() > f.min()
        finally:
            cam.close()
    cam = PylonCamera(0, trigger="off", features={"Width": 160, "Height": 120})  # free running, flushed
    cam.open()
    try:
        assert not cam.triggered and cam.grab().shape == (120, 160)
        with pytest.raises(DeviceError, match=r"Emulation \(serial 0815-0000\): exposure 1e\+09 µs is outside"):
            cam.set_exposure(1e9)
    finally:
        cam.close()


@pytest.mark.slow
@needs_pylon
def test_pylon_errors_name_the_camera_and_setting(camemu):
    with pytest.raises(DeviceError, match=r"no camera number 3 \(pylon finds 0: Emulation \(serial 0815-0000\)\)"):
        PylonCamera(3).open()
    with pytest.raises(DeviceError, match=r"no camera with serial number 'x'"):
        PylonCamera("x").open()
    with pytest.raises(DeviceError, match=r"pixel format 'Mono14' is not offered"):
        PylonCamera(pixel_format="Mono14").open()
    with pytest.raises(DeviceError, match=r"pixel format 'BayerRG8' is not one PTP Studio reads;.*Mono8, Mono10"):
        PylonCamera(pixel_format="BayerRG8").open()
    with pytest.raises(DeviceError, match=r"Emulation \(serial 0815-0000\): has no feature 'Nope'"):
        PylonCamera(features={"Nope": 1}).open()


@pytest.mark.slow
@needs_pylon
def test_pylon_without_a_camera_says_so():
    code = ("import os; os.environ.pop('PYLON_CAMEMU', None)\n"
            "from ptpcore.capture.devices.camera import PylonCamera\n"
            "try:\n    PylonCamera().open()\nexcept Exception as e:\n    print(e)\n")
    env = {k: v for k, v in __import__("os").environ.items() if k != "PYLON_CAMEMU"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert "pylon finds no camera" in out.stdout and "PYLON_CAMEMU=1" in out.stdout, out.stdout + out.stderr


@pytest.mark.slow
@needs_pylon
def test_pylon_capture_at_12_bits_writes_a_dataset_the_reader_validates(camemu, tmp_path):
    rig = small_rig(160, 120, bit_depth=12, positions=2)
    cam = PylonCamera(0, timeout_s=2.0, pixel_format="Mono12", features={"Width": 160, "Height": 120})
    out = tmp_path / "pylon"
    display = SimulatedDisplay(rig.lcd.width, rig.lcd.height)
    result = capture(out, rig, cam, SimulatedStage(), display, check=False, exposure_us=4000.0)
    assert len(result.captured) == 2
    report = validate_dataset(out, full=True)  # raises on a missing, mis-sized or wrong-depth image
    assert report.decoded and report.n_images == len(list(out.rglob("*.png"))) > 0 and not report.colour
    assert (report.rig.camera.width, report.rig.camera.height, report.rig.camera.bit_depth) == (
        rig.camera.width, rig.camera.height, rig.camera.bit_depth)
