"""The live capture of a heterodyne design (issue 32): `ptp capture --rig` shows every frame of an
``unwrap = "heterodyne"`` rig, bit for bit what the simulator renders, and the capture decodes."""

from __future__ import annotations

import filecmp

import h5py
import numpy as np

from ptpcore import cli
from ptpcore.capture import capture_state, frames_per_position
from ptpcore.decode.patterns import heterodyne_rig
from ptpcore.rig import load_rig
from ptpcore.rig.rigfile import save_rig
from ptpcore.simulate import VirtualRig, scaled_preset, simulate_dataset

PERIODS = [4096 / 27, 4096 / 32, 4096 / 30]  # any order; beats 2048, 1365.3 and 4096 px
STEPS = 6
SEED = 7


def test_ptp_capture_of_a_heterodyne_rig_equals_simulate_and_decodes(tmp_path, capsys):
    rig, settings = scaled_preset("realistic", 64, positions=2)
    het = heterodyne_rig(rig, PERIODS, STEPS)
    plan = tmp_path / "plan.toml"
    save_rig(het, plan)
    sim, cap = tmp_path / "sim", tmp_path / "cap"
    simulate_dataset(sim, het, settings, seed=SEED)
    assert cli.main(["capture", "--rig", str(plan), "--preset", "realistic", "--width", "64", "--positions", "2",
                     "--seed", str(SEED), "--out", str(cap), "-q"]) == 0
    captured = load_rig(cap / "rig.toml")
    assert captured.fringes.unwrap == "heterodyne"
    assert sorted(captured.fringes.periods("x")) == sorted(PERIODS)
    # every frame of the design: 2 directions x 3 periods x STEPS steps per position, as the simulator
    names = sorted(p.relative_to(cap) for p in cap.rglob("*.png"))
    assert names == sorted(p.relative_to(sim) for p in sim.rglob("*.png"))
    assert len(names) == 2 * frames_per_position(captured) == 2 * 2 * 3 * STEPS
    assert all(filecmp.cmp(sim / p, cap / p, shallow=False) for p in names)
    st = capture_state(cap)
    assert st["complete"] and st["done"] == st["total"] == 2

    out = tmp_path / "cap.decoded.h5"
    assert cli.main(["decode", str(cap), "--out", str(out), "-q"]) == 0
    vr = VirtualRig(captured, settings, SEED)
    h, w = captured.camera.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    t1 = min(PERIODS)
    with h5py.File(out, "r") as f:
        for k in range(2):
            u_t, v_t = vr._lcd_uv(k, cols, rows)
            for d, truth in ((0, u_t), (1, v_t)):
                valid = f["reasons"][k, d] == 0
                got = f["u" if d == 0 else "v"][k]
                assert valid.mean() > 0.5, (k, d, valid.mean())  # most of the view (64-87 % when written)
                # no valid pixel off by a whole period of T1; the accuracy at the noise floor of the
                # same images (bit for bit the simulator's) is tests/decode/test_heterodyne.py's
                err = np.abs(got[valid] - truth[valid])
                assert err.max() < 0.5 * t1, (k, d, err.max())
