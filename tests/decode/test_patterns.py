"""Fringe patterns (METHOD.md section 3) and the design check."""

import numpy as np
import pytest

from ptpcore.decode import design_check, fringe_image, fringe_profile, fringe_values
from ptpcore.rig import FringeDesign, Lcd, Rig


def test_profile_follows_the_formula():
    lcd = Lcd(200, 100, (0.1, 0.1))
    f = FringeDesign(periods_px=(256, 20), steps=(4, 5), carrier_px_per_mm=(1.5, -0.5))
    z = 3.0
    u = np.arange(200)
    want = 127.5 + 100.0 * np.cos(2 * np.pi * (u + 1.5 * z) / 20 + 2 * np.pi * 2 / 5)
    prof = fringe_profile(lcd, f, "x", 20, 2, 5, z)
    assert prof.dtype == np.uint8
    assert np.array_equal(prof, np.rint(want).astype(np.uint8))
    img = fringe_image(lcd, f, "y", 20, 1, 5, z)
    assert img.shape == (100, 200)
    assert np.all(img == img[:, :1])  # y patterns vary along rows only
    want_y = np.rint(fringe_values(np.arange(100), f, "y", 20, 1, 5, z)).astype(np.uint8)
    assert np.array_equal(img[:, 0], want_y)


def test_gamma_precompensation():
    lcd = Lcd(64, 8, (0.1, 0.1))
    f = FringeDesign(periods_px=(128, 16), steps=(4, 4), gamma=2.2)
    prof = fringe_profile(lcd, f, "x", 16, 0, 4, 0.0)
    g = fringe_values(np.arange(64), f, "x", 16, 0, 4, 0.0)
    assert np.array_equal(prof, np.rint(255 * (g / 255) ** (1 / 2.2)).astype(np.uint8))


def test_design_check_flags_an_ambiguous_period_list():
    rig = Rig()
    assert design_check(rig).ok
    bad = Rig(fringes=FringeDesign(periods_px=(2048, 256, 32), steps=(4, 4, 8)))
    report = design_check(bad)
    assert not report.ok
    assert any("unambiguous" in item.name and not item.ok for item in report.items)
    carrier = Rig(fringes=FringeDesign(periods_px=(3900, 512, 64, 16), carrier_px_per_mm=(5.0, 0.0)))
    assert not design_check(carrier).ok  # 3840 px + 5 px/mm * 40 mm > 3900


def test_design_check_noise_floor_formula():
    rig = Rig()
    rep = design_check(rig, modulation_dn=50.0, noise_dn=2.0)
    n, t = rig.fringes.steps[-1], rig.fringes.periods_px[-1]
    want = np.sqrt(2 / n) * 2.0 / 50.0 * t / (2 * np.pi) * 0.05 * 1000
    assert rep.noise_floor_um == pytest.approx(np.full(rig.stage.n_positions, want))
    tight = design_check(rig, modulation_dn=5.0, noise_dn=2.0)
    assert any(item.name.startswith("unwrapping") and not item.ok for item in tight.items)
