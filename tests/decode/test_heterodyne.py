"""Heterodyne (multi-frequency) unwrapping, `unwrap = "heterodyne"` (issue 32, FORMATS.md).

Simulated captures of the realistic rig at 160x120 px, decoded and compared with the
simulator's exact LCD coordinates; the noise floor is METHOD.md section 4's
``sqrt(2/N) sigma / B * T1 / 2 pi`` with the simulator's own sigma.
"""

from dataclasses import replace

import math

import h5py
import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.decode.patterns import design_check, heterodyne_rig, phase_noise_rad
from ptpcore.decode.phase import Reason
from ptpcore.errors import ConfigError
from ptpcore.io.dataset import SimulatedSource
from ptpcore.rig import load_rig
from ptpcore.rig.rigfile import heterodyne_beats, rig_from_toml, rig_to_toml
from ptpcore.run.pipeline import decode_position
from ptpcore.simulate import VirtualRig, scaled_preset

L = 4096.0  # the designs are whole numbers of fringes across 4096 px (> the LCD's 3840 plus carrier)
THREE = [L / 27, L / 32, L / 30]  # listed in no order: beats 2048, 1365.3 and 4096 px
TWO = [L / 31, L / 32]  # beat 4096 px
K = 2  # the position decoded (z = 40 mm: the largest carrier shift)


def _truth(vr, k):
    h, w = vr.rig.camera.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    return vr._lcd_uv(k, cols, rows)


def _rig(carrier):
    rig, settings = scaled_preset("realistic", 160, positions=3)
    return replace(rig, fringes=replace(rig.fringes, carrier_px_per_mm=carrier)), settings


@pytest.mark.parametrize("periods,steps,carrier", [
    (THREE, 3, (1.5, 1.0)), (THREE, 8, (0.0, 0.0)), (THREE, 12, (1.5, 1.0)),
    (TWO, 3, (0.0, 0.0)), (TWO, 6, (1.5, 1.0)), (TWO, 12, (0.0, 0.0))])
def test_heterodyne_decodes_to_the_truth_at_the_noise_floor(periods, steps, carrier):
    rig, settings = _rig(carrier)
    het = heterodyne_rig(rig, periods, steps)
    t1 = min(periods)
    assert het.fringes.periods("x")[-1] == pytest.approx(t1)
    vr = VirtualRig(het, settings, 4)
    pos = decode_position(SimulatedSource(vr), K)
    hier = decode_position(SimulatedSource(VirtualRig(rig, settings, 4)), K)  # the rig's own design
    u_t, v_t = _truth(vr, K)
    m = pos.valid
    err = np.concatenate([(pos.u - u_t)[m], (pos.v - v_t)[m]])
    # no valid pixel off by a whole period of the finest level
    assert np.max(np.abs(err)) < 0.5 * t1
    # at least 95 % of the pixels the hierarchical design decodes
    coverage = np.count_nonzero(m & hier.valid) / np.count_nonzero(hier.valid)
    assert coverage >= 0.95, coverage
    # RMS within 1.2x the noise floor of the finest period (the simulator's own noise model)
    floor = []
    for d in "xy":
        fine = pos.directions[d].wrapped[-1]
        sigma = settings.noise_dn(het.camera, fine.background[m])
        floor.append(phase_noise_rad(sigma, fine.modulation[m], steps) * t1 / (2 * np.pi))
    floor = float(np.sqrt(np.mean(np.concatenate(floor) ** 2)))
    rms = float(np.sqrt(np.mean(err ** 2)))
    assert rms <= 1.2 * floor, (rms, floor)
    if periods is TWO and steps == 3:
        # a thin margin (beat x 32): the pixels whose steps disagree are flagged, as unwrapping
        assert np.count_nonzero(pos.reasons & Reason.UNWRAP) > 0


def test_beats_and_their_margins_in_the_design_check():
    b = heterodyne_beats(THREE)
    assert b["periods"] == sorted(THREE)
    assert b["steps"][1][1] == pytest.approx(2048.0) and b["t23"] == pytest.approx(L / 3)
    assert b["absolute"] == pytest.approx(L)
    rig, _ = _rig((1.5, 1.0))
    for periods, steps in ((TWO, 12), (THREE, 4)):
        het = heterodyne_rig(rig, periods, steps)
        report = design_check(het, noise_dn=2.0, modulation_dn=80.0)
        rng = [i for i in report.items if i.name == "unambiguous range x"][0]
        assert rng.ok and rng.value == pytest.approx(L) and "T12 = " in rng.message
        s = phase_noise_rad(2.0, 80.0, steps)
        margins = {i.name: i for i in report.items if i.name.startswith("unwrapping")}
        if periods is TWO:
            # the beat multiplies the phase noise (sqrt 2 s) by T12 / T1 = 32
            assert margins["unwrapping T12 -> T1"].value == pytest.approx(
                (math.pi / 2) / math.hypot(math.sqrt(2) * s * 32, s))
        else:
            assert set(margins) == {"unwrapping T123 -> T12", "unwrapping T12 -> T1"}
            assert margins["unwrapping T123 -> T12"].value == pytest.approx(
                (math.pi / 2) / math.hypot(math.sqrt(6) * s * 2, math.sqrt(2) * s))
    thin = design_check(heterodyne_rig(rig, TWO, 3), noise_dn=8.0, modulation_dn=60.0)
    item = [i for i in thin.items if i.name == "unwrapping T12 -> T1"][0]
    assert not item.ok and "too small" in item.message


def test_beats_that_do_not_cover_the_field_are_refused_naming_the_periods(tmp_path, capfd):
    rig, _ = _rig((1.5, 1.0))
    short = [128, L / 30]  # beat 2048 px < the LCD's 3840
    with pytest.raises(ConfigError, match=r"128, 136\.533"):
        heterodyne_rig(rig, short)
    with pytest.raises(ConfigError, match="equal beats"):
        heterodyne_rig(rig, [L / 32, L / 30, L / 28])
    # the same in rig.toml, periods in any order
    good = rig_to_toml(heterodyne_rig(rig, THREE))
    assert 'unwrap = "heterodyne"' in good
    assert rig_from_toml(good).fringes.periods("y") == tuple(sorted(THREE, reverse=True))
    het = heterodyne_rig(rig, THREE)
    bad = rig_to_toml(replace(het, fringes=replace(het.fringes, periods_px=(128, L / 30), steps=(8, 8))))
    with pytest.raises(ConfigError, match=r"key 'fringes.periods_px'.*136\.533.*does not cover"):
        rig_from_toml(bad)
    capfd.readouterr()
    assert main(["simulate", str(tmp_path / "s"), "--width", "64", "--positions", "2",
                 "--heterodyne", "128,136.533", "-q"]) == 2
    err = capfd.readouterr().err
    assert "128, 136.533" in err and "does not cover" in err


def test_ptp_simulate_heterodyne_then_ptp_decode(tmp_path):
    out = tmp_path / "het"
    assert main(["simulate", str(out), "--width", "64", "--positions", "2", "--heterodyne",
                 ",".join(str(t) for t in THREE), "--heterodyne-steps", "5", "-q"]) == 0
    rig = load_rig(out)
    assert rig.fringes.unwrap == "heterodyne" and rig.fringes.steps == (5, 5, 5)
    assert main(["decode", str(out), "--out", str(tmp_path / "het.decoded.h5"), "-q"]) == 0
    with h5py.File(tmp_path / "het.decoded.h5", "r") as f:
        u = f["u"][()]
    assert np.mean(np.isfinite(u)) > 0.5


@pytest.mark.parametrize("cycles", [(32, 30, 27), (32, 29, 27), (32, 31)])
def test_analytic_phases_unwrap_exactly_whichever_beat_is_longer(cycles):
    """Noise-free phases of u over [0, 4000) px: the cascade returns u (float32 phases: 1e-5 px)."""
    from ptpcore.decode.phase import WrappedPhase, decode_direction

    periods = sorted((L / c for c in cycles), reverse=True)
    u = np.linspace(0.0, 4000.0, 2001)[None, :].repeat(3, axis=0)
    wrapped = [WrappedPhase(np.angle(np.exp(2j * np.pi * (u + 7.0) / t)).astype(np.float32), None, None, None)
               for t in periods]
    dec = decode_direction(wrapped, periods, 7.0, heterodyne=True)
    assert not dec.disagreement.any()
    assert np.max(np.abs(dec.coord - u)) < 1e-5 * L
