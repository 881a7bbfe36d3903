"""Rig hardware behind small interfaces, each with a simulated implementation.

- :mod:`~ptpcore.capture.devices.camera` — :class:`Camera`: simulated, OpenCV, GenICam (harvesters);
- :mod:`~ptpcore.capture.devices.stage` — :class:`Stage`: simulated, manual, serial (pyserial);
- :mod:`~ptpcore.capture.devices.display` — :class:`Display`: simulated (the real LCD
  window is Qt and lives in the GUI, ``ptp_studio.lcd_window``);
- :mod:`~ptpcore.capture.devices.config` — the capture configuration file (``capture.toml``).

:func:`simulated_devices` builds the three simulated devices for a rig, wired
together so the camera photographs what the display shows where the stage is.
"""

from __future__ import annotations

from ptpcore.capture.devices.camera import Camera, FrameError, HarvestersCamera, OpenCVCamera, SimulatedCamera
from ptpcore.capture.devices.display import Display, SimulatedDisplay
from ptpcore.capture.devices.stage import (ManualStage, SerialProtocol, SerialStage, SimulatedStage, Stage,
    StageTimeout)

__all__ = [
    "Camera", "FrameError", "SimulatedCamera", "OpenCVCamera", "HarvestersCamera",
    "Display", "SimulatedDisplay",
    "Stage", "StageTimeout", "SimulatedStage", "ManualStage", "SerialProtocol", "SerialStage",
    "simulated_devices", "simulated_meta", "describe",
]


def simulated_devices(rig, settings, seed: int = 0, *, settle_s: float = 0.0, camera_faults=None,
                      stage_faults=None):
    """``(camera, stage, display)`` simulating ``rig`` with the virtual rig.

    Parameters
    ----------
    rig : Rig
    settings : SimSettings
    seed : int
    settle_s : float
        Display settle time (seconds).
    camera_faults, stage_faults : optional
        Injected faults (see :class:`SimulatedCamera`, :class:`SimulatedStage`).
    """
    from ptpcore.simulate.virtual_rig import VirtualRig

    display = SimulatedDisplay(rig.lcd.width, rig.lcd.height, settle_s)
    stage = SimulatedStage(faults=stage_faults)
    camera = SimulatedCamera(VirtualRig(rig, settings, seed), display, stage, faults=camera_faults)
    return camera, stage, display


def simulated_meta(preset_name: str, seed: int, settings) -> dict:
    """What a capture with the simulated camera must keep when resumed (``capture(meta=...)``)."""
    import json
    from dataclasses import asdict

    return {"camera": "sim", "preset": preset_name, "seed": int(seed),
            "sim_settings": json.loads(json.dumps(asdict(settings)))}


def describe(device) -> str:
    """A device's own description, else its class name."""
    fn = getattr(device, "describe", None)
    if callable(fn):
        try:
            return str(fn())
        except Exception:  # noqa: BLE001 - a description must never fail
            pass
    return type(device).__name__
