"""The rig room after its split: one refraction formula for the fit and the simulator, and the old
``ptpcore.rig.rigfile`` names still there."""

import numpy as np

import ptpcore.rig as rig
from ptpcore.rig import rigfile
from ptpcore.rig.refraction import plate_offset_mm


def test_fit_and_simulator_share_the_formula():
    from ptpcore.fit import glass
    from ptpcore.simulate import lcd_physics

    assert glass.plate_offset_mm is plate_offset_mm
    assert lcd_physics.refraction_offset_mm is plate_offset_mm
    assert rig.plate_offset_mm is plate_offset_mm


def test_plate_offset_is_snells_law():
    """``t (tan(theta) - tan(theta'))`` against the angles themselves; shape and dtype kept."""
    tan = np.linspace(-2.0, 2.0, 81).reshape(9, 9)
    for t_mm, n in ((1.1, 1.52), (0.5, 1.0), (2.0, 2.4)):
        theta = np.arctan(tan)
        inside = np.arcsin(np.sin(theta) / n)
        got = plate_offset_mm(tan, t_mm, n)
        assert got.shape == tan.shape and got.dtype == np.float64
        assert np.allclose(got, t_mm * (tan - np.tan(inside)), rtol=1e-12, atol=1e-15)
    assert plate_offset_mm(0.0, 1.1, 1.52) == 0.0
    assert np.allclose(plate_offset_mm(tan, 1.1, 1.0), 0.0, rtol=0, atol=1e-14)  # no glass index, no offset


def test_the_old_module_keeps_its_names():
    for name in rigfile.__all__:
        assert getattr(rigfile, name) is getattr(rig, name), name
    for name in ("DEFAULT_TEMPLATE", "TEMPLATE_FIELDS", "GRAY_TEMPLATE_FIELDS", "REFERENCE_TEMPLATE_FIELDS",
                 "MAX_POSITIONS", "MAX_PERIOD_PX", "MAX_STEPS", "MAX_GRAY_BITS"):
        assert hasattr(rigfile, name), name
