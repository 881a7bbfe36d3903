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
