"""Shared fixtures: small simulated rigs (seeded) reused across engine tests."""

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import pytest

from ptpcore.io import SimulatedSource
from ptpcore.run import collect_samples
from ptpcore.simulate import VirtualRig, scaled_preset


def _simulated(name: str, width: int = 320, seed: int = 3):
    rig, settings = scaled_preset(name, width)
    vr = VirtualRig(rig, settings, seed)
    samples = collect_samples(SimulatedSource(vr))
    return vr, samples


@pytest.fixture(scope="session")
def rough_rig():
    """(VirtualRig, SampleStack) of the rough preset at 320x240, all 11 positions decoded."""
    return _simulated("rough")


@pytest.fixture(scope="session")
def mild_rig():
    """(VirtualRig, SampleStack) of the mild (Brown-exact lens) preset at 320x240."""
    return _simulated("mild")


def _door_dataset(kind: str, folder):
    """A small dataset of ``kind`` for the one-door tests (tests/run/test_one_door.py and
    tests/gui/test_one_door_gui.py): "realistic", "real" (its cover glass declared) or "scanner"
    (scanner-mild with a 5-height plate sweep); 64 px wide, 5 positions."""
    import numpy as np

    from ptpcore.simulate import simulate_dataset
    from ptpcore.simulate.scanner import scanner_preset, simulate_scanner_dataset

    if kind == "scanner":
        rig, sim, sc = scanner_preset("scanner-mild", 64, heights=5)
        rig = rig.with_z(np.linspace(min(rig.stage.z_mm), max(rig.stage.z_mm), 5))
        return simulate_scanner_dataset(folder, rig, sim, sc, seed=1, objects={})
    rig, sim = scaled_preset(kind, 64, None, 5)
    return simulate_dataset(folder, rig, sim, seed=1)


@pytest.fixture(scope="session")
def door_dataset():
    """``door_dataset(kind, folder) -> folder``: :func:`_door_dataset`."""
    return _door_dataset
