"""``ptp diff``: two LUTs of one camera against the difference their sigma maps predict (issue 16)."""

import json
from dataclasses import replace

import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.evaluate.diff import diff_luts
from ptpcore.fit import fit_model
from ptpcore.io import SimulatedSource, load_lut, save_lut
from ptpcore.run import collect_samples
from ptpcore.simulate import VirtualRig, scaled_preset


@pytest.fixture(scope="module")
def two_sweeps(tmp_path_factory):
    """Two sweeps of one simulated rig (mild lens, 160x120): other noise seed, the second sweep at
    the midpoints between the first one's heights (plus the same ends, so the rig is the same).
    Plain poly degree 3 LUTs (their sigma maps are the honest ones today)."""
    rig, s = scaled_preset("mild", 160)
    z = np.asarray(rig.stage.z_mm)
    zb = np.concatenate([[z[0]], z[:-1] + (z[1] - z[0]) / 2, [z[-1]]])
    rig_b = replace(rig, stage=replace(rig.stage, z_mm=tuple(float(v) for v in zb)))
    va, vb = VirtualRig(rig, s, 1), VirtualRig(rig_b, s, 1)
    vb.seed = 101  # same lens and modes (drawn at construction), another noise stream
    luts = [fit_model(collect_samples(SimulatedSource(v)), v.rig, "poly", 3) for v in (va, vb)]
    d = tmp_path_factory.mktemp("diff")
    paths = [d / "a.lut.h5", d / "b.lut.h5"]
    for lut, p in zip(luts, paths):
        save_lut(lut, p)
    return luts, paths


def test_two_sweeps_of_one_rig_are_consistent(two_sweeps, tmp_path):
    (a, b), (pa, pb) = two_sweeps
    r = diff_luts(a, b)
    assert 0.7 <= r.ratio <= 1.4, r.summary()
    assert r.consistent and r.fraction_beyond <= 0.01
    assert r.n_pixels > 0.8 * a.valid.sum()
    out_json, out_png = tmp_path / "d.json", tmp_path / "d.png"
    assert main(["diff", str(pa), str(pb), "--json", str(out_json), "--png", str(out_png)]) == 0
    d = json.loads(out_json.read_text())
    assert d["verdict"] == "consistent" and abs(d["ratio"] - r.ratio) < 1e-6
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_shifted_lut_differs_and_the_map_shows_the_shift(two_sweeps, tmp_path):
    """A rig moved by 5 predicted sigmas in X: exit 1, and the signed map equals the shift."""
    (a, b), (pa, _pb) = two_sweeps
    shift = 5 * float(np.sqrt(np.nanmean(a.sigma_x[a.valid] ** 2)))
    moved = replace(b, x=b.x.copy())
    moved.x[0] += shift  # the constant coefficient: every height
    r = diff_luts(a, moved)
    assert not r.consistent
    m = r.common
    assert abs(np.median(-r.signed_x[m]) - shift) < 0.1 * shift
    p = tmp_path / "moved.lut.h5"
    save_lut(moved, p)
    assert main(["diff", str(pa), str(p)]) == 1


def test_bad_input_exits_2(two_sweeps, tmp_path):
    (a, _b), (pa, _pb) = two_sweeps
    other = tmp_path / "small.lut.h5"
    small = replace(a, x=a.x[:, :10, :10], y=a.y[:, :10, :10], valid=a.valid[:10, :10],
                    n_positions=a.n_positions[:10, :10], pixel_z_min=a.pixel_z_min[:10, :10],
                    pixel_z_max=a.pixel_z_max[:10, :10], rms_x=a.rms_x[:10, :10], rms_y=a.rms_y[:10, :10],
                    loo_x=a.loo_x[:10, :10], loo_y=a.loo_y[:10, :10], sigma_x=a.sigma_x[:10, :10],
                    sigma_y=a.sigma_y[:10, :10])
    save_lut(small, other)
    assert main(["diff", str(pa), str(other)]) == 2
    assert main(["diff", str(pa), str(tmp_path / "missing.lut.h5")]) == 2
    assert main(["diff", str(pa), str(pa), "--max-fraction", "2"]) == 2
