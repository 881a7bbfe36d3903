"""Phase retrieval, unwrapping and validity (METHOD.md section 4)."""

import numpy as np
import pytest

from ptpcore.io import SimulatedSource
from ptpcore.decode import Reason, unwrap_hierarchical, wrapped_phase
from ptpcore.run import decode_position
from ptpcore.simulate import VirtualRig, scaled_preset


@pytest.mark.parametrize("n", [3, 4, 5, 8])
def test_wrapped_phase_is_exact_on_sinusoids(n):
    rng = np.random.default_rng(n)
    phi = rng.uniform(-np.pi, np.pi, (20, 30))
    a = rng.uniform(50, 150, phi.shape)
    b = rng.uniform(10, 40, phi.shape)
    frames = np.stack([a + b * np.cos(phi + 2 * np.pi * k / n) for k in range(n)])
    w = wrapped_phase(frames)
    assert np.max(np.abs(np.angle(np.exp(1j * (w.phase - phi))))) < 1e-5
    assert np.allclose(w.modulation, b, rtol=1e-5)
    assert np.allclose(w.background, a, rtol=1e-6)
    assert not w.saturated.any()


def test_unwrap_recovers_a_known_coordinate_and_flags_disagreement():
    periods = [1024, 128, 16]
    u = np.linspace(0.0, 1000.0, 5001).reshape(1, -1)
    phases = [np.angle(np.exp(2j * np.pi * u / t)) for t in periods]
    coord, bad = unwrap_hierarchical(phases, periods)
    assert np.max(np.abs(coord - u)) < 1e-9
    assert not bad.any()
    # A coarse phase off by 0.4 rad becomes 3.2 rad at the next level (x 1024/128):
    # the wrong fringe order is chosen and the step disagrees by 2*pi - 3.2 > pi/2.
    phases[0] = phases[0] + np.where(np.arange(u.size) % 7 == 0, 0.4, 0.0)
    coord, bad = unwrap_hierarchical(phases, periods)
    wrong = np.abs(coord - u) > 1.0
    assert wrong.any()
    assert np.all(bad[wrong])


def test_noise_free_unpixelated_decoding_is_exact():
    """Ideal preset: no noise, no LCD pixelation, no blur -> coordinates to 0.02 LCD px."""
    rig, settings = scaled_preset("ideal", 320)
    vr = VirtualRig(rig, settings, seed=5)
    truth = vr.truth()
    src = SimulatedSource(vr)
    a, b, _ = rig.stage.direction
    for k in (0, rig.stage.n_positions - 1):
        pos = decode_position(src, k)
        z = truth.z_true[k]
        tx, ty = truth.xy(z)
        u_true = (tx - a * z) / rig.lcd.pitch_mm[0]
        v_true = (ty - b * z) / rig.lcd.pitch_mm[1]
        m = pos.valid
        assert m.mean() > 0.7
        assert np.max(np.abs(pos.u[m] - u_true[m])) < 0.02
        assert np.max(np.abs(pos.v[m] - v_true[m])) < 0.02
        # Pixels that see the bezel are rejected, each for its own reason.
        outside = (u_true < -0.5) | (u_true > rig.lcd.width - 0.5) | (v_true < -0.5) | (v_true > rig.lcd.height - 0.5)
        assert outside.any()
        assert np.all(pos.reasons[outside] & (Reason.OUTSIDE_LCD | Reason.LOW_MODULATION))


def test_saturation_is_flagged_separately():
    from dataclasses import replace

    rig, settings = scaled_preset("realistic", 160)
    vr = VirtualRig(rig, replace(settings, exposure=1.15, noise=False), seed=1)
    pos = decode_position(SimulatedSource(vr), 5)
    sat = (pos.reasons & Reason.SATURATED) != 0
    assert 0.01 < sat.mean() < 0.9
    # The brightest frames saturate where vignetting is weakest: the centre.
    h, w = rig.camera.shape
    assert sat[h // 2 - 5:h // 2 + 5, w // 2 - 5:w // 2 + 5].mean() > sat.mean()
