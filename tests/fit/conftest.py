"""Fixtures of the fit tests."""

import pytest

from ptpcore.fit import fit_smooth_lut
from ptpcore.io import SimulatedSource
from ptpcore.run import collect_samples
from ptpcore.simulate import VirtualRig, scaled_preset


@pytest.fixture(scope="session")
def even_split_smooth_fit():
    """``fit(rig, **options)``: ``fit_smooth_lut`` of degree 1 on the even positions of a shared rig.

    ``rig`` is a session fixture's ``(VirtualRig, SampleStack)`` (``rough_rig``, ``mild_rig``). Several
    tests judge the same fit from different sides and a smooth fit of a 320x240 rig is one of the
    suite's slowest steps, so each (rig, options) is fitted once per session. The fit is deterministic
    (``seed`` 0); the returned ``(Lut, SmoothInfo)`` is shared: read it, never modify it.
    """
    fits = {}

    def fit(rig, **options):
        vr, samples = rig
        key = (id(samples), tuple(sorted(options.items())))
        if key not in fits:
            cal = list(range(0, samples.z.size, 2))
            fits[key] = fit_smooth_lut(samples, vr.rig, 1, cal, **options)
        return fits[key]

    return fit


@pytest.fixture(scope="session")
def mild_21_positions():
    """(VirtualRig, SampleStack) of the mild preset at 160x120, 21 positions, seed 1, all decoded.

    The robust fits' and the model choice's tests judge this one rig; shared, so read it, never modify
    it (copy what a test corrupts).
    """
    rig, settings = scaled_preset("mild", 160, positions=21)
    vr = VirtualRig(rig, settings, 1)
    return vr, collect_samples(SimulatedSource(vr))
