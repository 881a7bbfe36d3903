"""Accuracy against the simulator's exact truth, with tolerances from the predicted noise."""

import numpy as np
import pytest

from ptpcore.evaluate import held_out_accuracy
from ptpcore.fit import predicted_poly_sigma, sample_sigma
from ptpcore.fit import fit_lut


def _prediction(vr, samples, degree, cal, held):
    rig, s = vr.rig, vr.settings
    f = rig.fringes
    truth = vr.truth()
    sig = sample_sigma(samples, lambda level: s.noise_dn(rig.camera, level), f.steps[-1], f.periods_px[-1],
                       rig.lcd.pitch_mm[0], s.stage_error_um * 1e-3, truth.sx - rig.stage.direction[0])
    return truth, predicted_poly_sigma(samples, sig, degree, cal, samples.z[held])


@pytest.mark.parametrize("degree", [1, 3])
def test_rough_preset_held_out_error_matches_the_predicted_noise_floor(rough_rig, degree):
    """Between calibrated heights the LUT agrees with the true rays to 1.5x the predicted noise.

    The prediction propagates each sample's phase noise, sqrt(2/N) sigma / B with sigma
    from the camera's shot, read and quantisation noise at the sample's background level,
    through the pixel's own least-squares fit, plus the stage position error.
    """
    vr, samples = rough_rig
    k = samples.z.size
    cal, held = list(range(0, k, 2)), list(range(1, k, 2))
    lut = fit_lut(samples, "poly", degree, positions=cal)
    truth, pred = _prediction(vr, samples, degree, cal, held)
    acc = held_out_accuracy(lut, truth, vr.rig.stage.z_mm, held, pred)
    assert lut.valid.mean() > 0.6
    assert acc.rms_um <= 1.5 * acc.predicted_rms_um
    # The prediction is not merely pessimistic: it explains the error.
    assert acc.rms_um >= acc.predicted_rms_um / 1.5
    # Per pixel too: normalised errors behave like unit Gaussians.
    zscore = np.concatenate([(acc.error_x / pred)[np.isfinite(acc.error_x)],
                             (acc.error_y / pred)[np.isfinite(acc.error_y)]])
    assert np.mean(np.abs(zscore) > 4) < 1e-3


def test_linear_table_on_rough_preset(rough_rig):
    """Tables interpolate the noisy samples: the error is about the sample noise itself."""
    vr, samples = rough_rig
    k = samples.z.size
    cal, held = list(range(0, k, 2)), list(range(1, k, 2))
    lut = fit_lut(samples, "linear", positions=cal)
    truth, _ = _prediction(vr, samples, 1, cal, held)
    rig, s = vr.rig, vr.settings
    f = rig.fringes
    sig = sample_sigma(samples, lambda level: s.noise_dn(rig.camera, level), f.steps[-1], f.periods_px[-1],
                       rig.lcd.pitch_mm[0], s.stage_error_um * 1e-3, truth.sx - rig.stage.direction[0])
    # Midway between two nodes the linear interpolant averages two samples: var = (s1^2 + s2^2)/4.
    pred = np.stack([0.5 * np.hypot(sig[c - 1], sig[c + 1]) for c in held])
    acc = held_out_accuracy(lut, truth, rig.stage.z_mm, held, pred)
    assert acc.predicted_rms_um / 1.5 <= acc.rms_um <= 1.5 * acc.predicted_rms_um
