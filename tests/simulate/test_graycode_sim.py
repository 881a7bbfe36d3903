"""Simulator: Gray-code + phase-shift datasets (ptp-dataset/2, unwrap = "gray") and the
white/black frames' clipping check (issue 13)."""

from dataclasses import replace

import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.decode.graycode import gray_index, gray_to_index
from ptpcore.decode.patterns import gray_bits_needed, gray_code_rig, gray_profile, phase_noise_rad
from ptpcore.decode.phase import Reason
from ptpcore.io.dataset import DatasetSource, SimulatedSource
from ptpcore.io.decodedfile import load_decoded
from ptpcore.io.lutfile import load_lut
from ptpcore.evaluate.accuracy import held_out_accuracy
from ptpcore.rig import load_rig
from ptpcore.run.pipeline import decode_position
from ptpcore.simulate import VirtualRig, scaled_preset
from ptpcore.simulate.virtual_rig import load_truth


def _truth_uv(vr: VirtualRig, k: int):
    h, w = vr.rig.camera.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    return vr._lcd_uv(k, cols, rows)


def test_gray_profile_counts_cycles_of_the_coarsest_period():
    rig, _ = scaled_preset("realistic", 160, positions=3)
    g = gray_code_rig(rig, inverse=True)
    f = g.fringes
    for d in f.directions:
        n = f.bits(d)
        assert n == gray_bits_needed(g, d)
        t0 = float(f.periods(d)[0])
        z = g.stage.z_mm[-1]
        s = f.carrier(d) * z
        extent = g.lcd.width if d == "x" else g.lcd.height
        assert t0 * 2 ** n >= extent - 0.5 + s > t0 * 2 ** (n - 1)
        bits = np.stack([gray_profile(g.lcd, f, d, b, False, z) for b in range(n)])
        inv = np.stack([gray_profile(g.lcd, f, d, b, True, z) for b in range(n)])
        assert set(np.unique(bits)) == {min(bits.ravel()), max(bits.ravel())}  # two levels
        assert np.all(bits != inv)
        index, _c = gray_index(list(bits), list(inv))
        coord = np.arange(extent)
        assert np.array_equal(index, np.floor((coord + s) / t0).astype(int))
        assert np.array_equal(gray_to_index(bits > 127), index)


@pytest.mark.parametrize("inverse,references", [(False, False), (True, False), (False, True)])
def test_gray_decode_equals_the_multi_period_design(inverse, references):
    """The same fine levels unwrapped by a Gray code instead of the coarse periods: the same
    coordinates, bit for bit, on the same pixels (so the plain design's accuracy), with the inverse
    frames, the white/black threshold or the background threshold."""
    rig, settings = scaled_preset("realistic", 160, positions=3)
    plain = decode_position(SimulatedSource(VirtualRig(rig, settings, 4)), 1)
    g = gray_code_rig(rig, inverse=inverse, references=references)
    assert g.fringes.unwrap == "gray" and len(g.fringes.periods("x")) == 2
    pos = decode_position(SimulatedSource(VirtualRig(g, settings, 4)), 1)
    assert np.array_equal(pos.valid, plain.valid)
    assert np.array_equal(pos.u[pos.valid], plain.u[plain.valid])
    assert np.array_equal(pos.v[pos.valid], plain.v[plain.valid])


def _predicted_sigma_px(dec, i, settings, rig, d):
    """Predicted 1-sigma LCD coordinate noise of the decoded direction ``d`` at entry ``i`` (the
    simulator's noise model at the measured background, METHOD.md section 4)."""
    di = "xy".index(d)
    f = rig.fringes
    noise = np.sqrt(settings.noise_dn(rig.camera, dec.background[i, di]) ** 2
                    + (dec.modulation[i, di] / f.amplitude) ** 2 / 12.0)
    return phase_noise_rad(noise, dec.modulation[i, di], f.steps_of(d)[-1]) * float(f.periods(d)[-1]) / (2 * np.pi)


@pytest.mark.slow
def test_ptp_decode_and_calibrate_a_simulated_gray_dataset(tmp_path, capfd):
    """`ptp simulate --gray 2 --references` -> `ptp decode` and `ptp calibrate`: the exact truth
    within the predicted noise, the coverage and LUT of the plain multi-period design."""
    plain, gray = tmp_path / "plain", tmp_path / "gray"
    common = ["--preset", "realistic", "--width", "160", "--positions", "5", "--seed", "3", "-q"]
    assert main(["simulate", str(plain), *common]) == 0
    assert main(["simulate", str(gray), *common, "--gray", "2", "--references"]) == 0
    rig = load_rig(gray)
    assert rig.fringes.unwrap == "gray" and rig.has_references and rig.gray_template
    assert (gray / rig.reference_name(0, "white")).is_file()
    truth, settings, seed = load_truth(gray)
    vr = VirtualRig(rig, settings, seed)
    cover = {}
    for name, ds in (("plain", plain), ("gray", gray)):
        out = tmp_path / f"{name}.decoded.h5"
        assert main(["decode", str(ds), "--out", str(out), "-q"]) == 0
        dec = load_decoded(out)
        cover[name] = float(np.mean(np.isfinite(dec.u) & np.isfinite(dec.v)))
        if name != "gray":
            continue
        for i in range(len(dec.positions)):
            u_t, v_t = _truth_uv(vr, i)
            for d, got, true in (("x", dec.u[i], u_t), ("y", dec.v[i], v_t)):
                m = np.isfinite(got)
                err = (got - true)[m]
                sigma = _predicted_sigma_px(dec, i, settings, rig, d)[m]
                # No cycle slip anywhere: every error within 8 predicted sigma plus the display's
                # pixelation (half an LCD pixel at most, the simulator integrates exact LCD pixels).
                assert np.all(np.abs(err) < 8 * sigma + 0.5), (i, d, np.abs(err).max())
                # and the RMS no more than the predicted noise plus that pixelation's RMS (1/sqrt(12) px)
                assert np.sqrt(np.mean(err ** 2)) < np.hypot(np.sqrt(np.mean(sigma ** 2)), 1 / np.sqrt(12))
    # The same coverage: every pixel the plain design decodes, and a few more (those only its
    # coarse periods' 4-step frames rejected, saturated at their brightest steps, say).
    assert cover["plain"] <= cover["gray"] < cover["plain"] + 0.005, cover
    luts = {}
    for name, ds in (("plain", plain), ("gray", gray)):
        out = tmp_path / f"{name}.lut.h5"
        assert main(["calibrate", str(ds), "--out", str(out), "--model", "poly", "--degree", "2", "-q"]) == 0
        luts[name] = load_lut(out)
    a, b = luts["plain"], luts["gray"]
    assert np.all(b.valid[a.valid]) and b.valid.mean() < a.valid.mean() + 0.005
    # Where both LUTs rest on the same positions, they are the same fit of the same samples.
    same = a.valid & b.valid & (a.n_positions == b.n_positions)
    assert same.mean() > 0.95 * a.valid.mean()
    np.testing.assert_allclose(b.x[:, same], a.x[:, same], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.y[:, same], a.y[:, same], rtol=0, atol=1e-9)
    # and the LUT meets the exact truth as well as the plain design's.
    acc = {n: held_out_accuracy(lut, truth, rig.stage.z_mm, range(5)) for n, lut in luts.items()}
    assert acc["gray"].rms_um < 1.02 * acc["plain"].rms_um, (acc["gray"].rms_um, acc["plain"].rms_um)


def test_white_and_black_frames_flag_clipping():
    """A white frame that saturates and a black frame clipped at 0 give the saturation and the
    black-clipping reasons where they do, and nowhere else."""
    rig, settings = scaled_preset("realistic", 160, positions=3)
    g = gray_code_rig(rig, references=True)
    # The white frame (the fringes' brightest level) saturates the brightest third of the pixels...
    k = 1
    white = VirtualRig(g, settings, 5).reference_frames(k)["white"].astype(float)
    lit = white[white > 0.2 * white.max()]
    settings = replace(settings, exposure=settings.exposure * g.camera.max_level / np.percentile(lit, 67))
    vr = VirtualRig(g, settings, 5)
    refs = vr.reference_frames(k)
    white_sat = refs["white"] >= g.camera.max_level
    assert 0.05 < white_sat.mean() < 0.6
    pos = decode_position(SimulatedSource(vr), k)
    sat = (pos.reasons & Reason.SATURATED) != 0
    assert np.all(sat[white_sat])
    # ... and is the only new source of the flag: the phase frames flag a subset of those pixels.
    assert not np.any(sat & ~white_sat & ~_phase_saturated(vr, k))
    # A black frame clipped at 0 (a region with a black offset): flagged there.
    settings = replace(settings, exposure=0.85 * settings.exposure)
    black = VirtualRig(g, settings, 5).reference_frames(k)["black"].astype(float)
    offset = float(black[30:60, 40:80].max()) + 20.0  # a region whose black falls below the sensor's 0
    settings = replace(settings, black_offset=(40, 30, 80, 60, offset))
    vr = VirtualRig(g, settings, 5)
    refs = vr.reference_frames(k)
    black0 = refs["black"] <= 0
    assert black0[30:60, 40:80].mean() > 0.9 and not black0[:30].any()
    pos = decode_position(SimulatedSource(vr), k)
    clipped = (pos.reasons & Reason.BLACK_CLIPPED) != 0
    assert np.all(clipped[black0])
    assert not clipped[:30].any() and not clipped[60:].any()


def _phase_saturated(vr, k):
    out = np.zeros(vr.rig.camera.shape, bool)
    for _spec, img in vr.frames(k):
        out |= img >= vr.rig.camera.max_level
    return out


def test_capture_of_a_gray_code_rig_equals_simulate(tmp_path):
    """The capture sequence shows the Gray-code and reference frames the simulator renders:
    the same images, bit for bit, as `simulate_dataset`."""
    from ptpcore.capture import capture, frames_per_position
    from ptpcore.capture.devices import simulated_devices
    from ptpcore.simulate import simulate_dataset

    rig, settings = scaled_preset("mild", 40, positions=2)
    g = gray_code_rig(rig, inverse=True, references=True)
    simulate_dataset(tmp_path / "sim", g, settings, seed=7)
    result = capture(tmp_path / "cap", g, *simulated_devices(g, settings, 7))
    assert result.captured == [0, 1]
    sim = sorted(p.relative_to(tmp_path / "sim") for p in (tmp_path / "sim").rglob("*.png"))
    cap = sorted(p.relative_to(tmp_path / "cap") for p in (tmp_path / "cap").rglob("*.png"))
    assert sim == cap and len(sim) == 2 * frames_per_position(g)
    assert any("_G00_1" in str(p) for p in sim) and any("white" in str(p) for p in sim)
    for p in sim:
        assert (tmp_path / "sim" / p).read_bytes() == (tmp_path / "cap" / p).read_bytes(), p


def test_ptp_decode_warns_about_measured_display_harmonics(tmp_path, capfd):
    """A display response far from the gamma pre-compensation: `ptp decode` says so, with the design
    check's advice, from the harmonics measured at the first position (the Fringes page shows the same)."""
    from ptpcore.simulate import simulate_dataset

    rig, settings = scaled_preset("realistic", 160, positions=2)
    rig = replace(rig, fringes=replace(rig.fringes, steps=(8, 8, 8, 8), gamma=2.2))
    bad = replace(settings, display_gamma=1.3, pixelated=False, supersample=1)
    for name, s, expect in (("bad", bad, True), ("good", settings, False)):
        ds = simulate_dataset(tmp_path / name, rig, s, seed=3)
        capfd.readouterr()
        assert main(["decode", str(ds), "--out", str(tmp_path / f"{name}.decoded.h5"), "--positions", "0",
                     "-q"]) == 0
        err = capfd.readouterr().err
        assert ("harmonics" in err and "more steps" in err) == expect, err


def test_repeat_source_passes_gray_and_reference_frames_on():
    """Drift's repeats of a Gray-code dataset: their Gray-code and reference frames are the source's
    at positions K, K+1, ... (like their phase frames)."""
    from ptpcore.fit.drift import RepeatSource

    rig, _ = scaled_preset("mild", 40, positions=3)
    rig = replace(rig, stage=replace(rig.stage, repeat_z_mm=(0.0, 8.0)))

    class Source:
        def __init__(self):
            self.rig = rig

        def frames(self, k):
            return k

        def gray_frames(self, k):
            return ("gray", k)

    rep = RepeatSource(Source())
    assert rep.frames(1) == 4 and rep.gray_frames(1) == ("gray", 4)
    assert not hasattr(rep, "reference_frames")  # the source has none
