"""The LCD's integer levels bias the decoded coordinates; ptpcore.decode.display predicts the bias.

Checked against the simulator: the same noise-free rig rendered twice, once
with the rounded levels a real LCD shows and once with the continuous
(unrounded) profile. The difference of the decoded coordinates is the
rounding's effect alone; the prediction must explain it.
"""

import dataclasses

import numpy as np
import pytest

import ptpcore.simulate.virtual_rig as sim
from ptpcore.io import SimulatedSource
from ptpcore.decode import level_bias_at, level_bias_px, level_phase_errors_px
from ptpcore.decode import fringe_values
from ptpcore.run import collect_samples


def _decode(rig, settings, unrounded, monkeypatch):
    if unrounded:
        def continuous(lcd, design, direction, period, step, n_steps, z_mm, display=None):
            n = lcd.width if direction == "x" else lcd.height
            return np.clip(fringe_values(np.arange(n), design, direction, period, step, n_steps, z_mm), 0, 255)

        monkeypatch.setattr(sim, "fringe_profile", continuous)
    try:
        return collect_samples(SimulatedSource(sim.VirtualRig(rig, settings, 3)))
    finally:
        monkeypatch.undo()


@pytest.fixture(scope="module")
def rounded_and_continuous():
    rig, settings = sim.scaled_preset("mild", 320, positions=3)
    settings = dataclasses.replace(settings, noise=False, stage_error_um=0.0)
    mp = pytest.MonkeyPatch()
    return rig, _decode(rig, settings, False, mp), _decode(rig, settings, True, mp)


def test_predicted_level_bias_explains_the_rounding_shift(rounded_and_continuous):
    rig, rounded, continuous = rounded_and_continuous
    for k, z in enumerate(rig.stage.z_mm):
        m = rounded.valid[k] & continuous.valid[k]
        for i, d in enumerate("xy"):
            pitch = rig.lcd.pitch_mm[i]
            dec = rounded.absolute(k)[i]
            shift = (dec - continuous.absolute(k)[i])[m] / pitch  # LCD px
            pred = level_bias_at(rig.fringes, rig.lcd, d, z, dec[m] / pitch)
            # The shift is real and sizeable against what is left: -0.0015 LCD px on this design.
            assert abs(shift.mean()) > 1e-3
            resid = shift - pred
            # What is left is each pixel's footprint average of eps about the period
            # mean (0.0027 px RMS, correlated over a few pixels): its mean over
            # 60k pixels is ~1e-5 px; 1e-4 px is 10x that and 7 % of the bias.
            assert abs(resid.mean()) < 1e-4, (k, d, resid.mean(), shift.mean())
            # The table follows the period-to-period changes of the bias (ties of
            # the rounding): in bands of LCD coordinate the residual stays small too.
            bands = np.array_split(np.argsort(dec[m]), 8)
            assert max(abs(resid[b].mean()) for b in bands) < 3e-4


def test_no_error_where_the_levels_are_integers_and_nan_stays_nan():
    from ptpcore.rig import FringeDesign, Lcd

    # Period 4, 4 steps, no carrier: every level is 127 + 100 * {1, 0, -1, 0}, an integer.
    design = FringeDesign(("x", "y"), (64, 4), (4, 4), 127.0, 100.0, (0.0, 0.0), 1.0)
    lcd = Lcd(640, 480, (0.05, 0.05))
    eps = level_phase_errors_px(design, lcd, "x", 0.0)
    assert eps.shape == (640,) and np.max(np.abs(eps)) < 1e-12
    assert abs(level_bias_px(design, lcd, "y", 0.0)) < 1e-12
    out = level_bias_at(design, lcd, "x", 0.0, np.array([np.nan, 10.0, 600.0]))
    assert np.isnan(out[0]) and np.all(np.abs(out[1:]) < 1e-12)
