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
    # Same lens and modes (drawn from the seed), another noise stream.
    va, vb = VirtualRig(rig, s, 1), VirtualRig(rig_b, s, 1, noise_seed=101)
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


@pytest.mark.slow
def test_two_sweeps_of_one_rig_with_default_luts_are_consistent(tmp_path):
    """Must show (issue 16): two sweeps of one rig (other noise seed, the second at the midpoints),
    each calibrated with the default model (auto: the smooth LUT on this lens) and the stage's declared
    1-sigma error, are consistent: exit 0 and RMS difference / predicted within [0.7, 1.4]."""
    rig, s = scaled_preset("mild", 160)
    z = np.asarray(rig.stage.z_mm)
    zb = np.concatenate([[z[0]], z[:-1] + (z[1] - z[0]) / 2, [z[-1]]])
    rig_b = replace(rig, stage=replace(rig.stage, z_mm=tuple(float(v) for v in zb)))
    va, vb = VirtualRig(rig, s, 1), VirtualRig(rig_b, s, 1, noise_seed=101)
    paths = []
    for name, v in (("a", va), ("b", vb)):
        lut = fit_model(collect_samples(SimulatedSource(v)), v.rig, "auto", stage_sigma_mm=s.stage_error_um * 1e-3)
        assert lut.extra_attrs["method"] == "smooth"
        paths.append(tmp_path / f"{name}.lut.h5")
        save_lut(lut, paths[-1])
    out = tmp_path / "d.json"
    assert main(["diff", str(paths[0]), str(paths[1]), "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    print(d)
    assert d["verdict"] == "consistent" and 0.7 <= d["ratio"] <= 1.4


def test_with_and_without_the_cover_glass_declared_the_luts_differ_by_the_refraction_offset(tmp_path):
    """Must show (issue 16): one simulated rig behind 1.1 mm of cover glass (``real`` preset) calibrated with
    the glass declared in rig.toml and without: exit 1, and the difference map is the simulator's exact
    refraction offset ``t (tan theta - tan theta')`` along each pixel's ray, within 5 % (RMS over the pixels)."""
    from ptpcore.rig import load_rig
    from ptpcore.simulate.lcd_physics import refraction_offset_mm
    from ptpcore.simulate.virtual_rig import TRUTH_FILE, load_truth

    data = tmp_path / "data"
    assert main(["simulate", str(data), "--preset", "real", "--width", "64", "--positions", "5", "-q"]) == 0
    rig = load_rig(data / "rig.toml")
    assert (rig.lcd.cover_glass_mm, rig.lcd.cover_glass_index) == (1.1, 1.52)
    luts = []
    for name in ("declared", "bare"):
        if name == "bare":  # the same images, the glass left out of rig.toml
            text = (data / "rig.toml").read_text()
            (data / "rig.toml").write_text("\n".join(line for line in text.splitlines()
                                                     if not line.startswith("cover_glass_")) + "\n")
            assert not load_rig(data / "rig.toml").lcd.cover_glass_mm  # None: not declared
        luts.append(tmp_path / f"{name}.lut.h5")
        assert main(["calibrate", str(data), "--out", str(luts[-1]), "--model", "poly", "--degree", "2", "-q"]) == 0
    out = tmp_path / "d.json"
    assert main(["diff", str(luts[0]), str(luts[1]), "--json", str(out)]) == 1
    assert json.loads(out.read_text())["verdict"] == "differ"
    r = diff_luts(load_lut(luts[0]), load_lut(luts[1]))
    truth = load_truth(data / TRUTH_FILE)[0]
    exact = refraction_offset_mm(np.hypot(truth.sx, truth.sy), 1.1, 1.52)
    m = r.common
    shown = np.hypot(r.signed_x, r.signed_y)  # the same shift at every height: its length
    err_um, exact_um = 1e3 * np.sqrt(np.mean((shown[m] - exact[m]) ** 2)), 1e3 * np.sqrt(np.mean(exact[m] ** 2))
    print(f"glass diff: {r.summary()}; |signed| - exact RMS {err_um:.3f} um of {exact_um:.3f} um")
    assert err_um <= 0.05 * exact_um, (err_um, exact_um)
    # ...and along each pixel's ray: the glass shows the pixel plane nearer the foot of the ray's normal.
    along = (r.signed_x * truth.sx + r.signed_y * truth.sy) / np.hypot(truth.sx, truth.sy)
    assert np.mean(np.abs(along[m]) >= 0.95 * shown[m]) > 0.95


def _synthetic_diff(h=60, w=80):
    """A LutDiff whose difference rises left to right from 0 to 3 tolerances (tolerance 3 x 1 µm), a
    corner outside the common pixels."""
    from ptpcore.evaluate.diff import LutDiff

    predicted = np.full((h, w), 1e-3)  # mm: 1 µm
    diff = np.tile(np.linspace(0, 9e-3, w), (h, 1))  # up to 9 µm = 3 tolerances
    common = np.ones((h, w), bool)
    common[:10, :10] = False
    zero = np.zeros((h, w))
    return LutDiff(np.array([0.0, 40.0]), zero, zero, zero, zero, diff, predicted, diff > 3e-3, common,
                   int(common.sum()), 1.0, 2.0, 9.0, 1.0, 1.0, float((diff > 3e-3).mean()), 3.0, 0.0, 0.01, False)


def test_diff_png_has_a_title_a_colour_bar_and_its_scale(tmp_path):
    import cv2

    from ptpcore.evaluate.diff import diff_png

    r = _synthetic_diff()
    diff_png(r, tmp_path / "d.png")
    page = cv2.imread(str(tmp_path / "d.png"))
    f = 5  # 80 px wide: enlarged to 400
    inferno = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_INFERNO)[:, 0]
    # The map: where the page shows it (below the title), the colour of |d| / (2 tol), grey outside.
    grey = (page == 128).all(axis=2)  # the map's grey corner (10 x 10 camera pixels) is its top left
    top, left = np.argmax(grey.sum(axis=1) >= 10 * f), np.argmax(grey.sum(axis=0) >= 10 * f)
    shown = page[top:top + 60 * f, left:left + 80 * f]
    level = np.clip(r.diff / (3 * r.predicted) / 2, 0, 1)
    want = inferno[np.nan_to_num(level * 255).astype(np.uint8)]
    want[~r.common] = 128
    np.testing.assert_array_equal(shown, np.repeat(np.repeat(want, f, axis=0), f, axis=1))
    assert top >= 40 and (page[:top - 5] < 100).any()  # the title and the note above the map
    # The colour bar right of the map: bright (2 tolerances and beyond) at the top, dark (0) at the bottom,
    # its ticks and labels beside it.
    right = page[top:top + 60 * f, left + 80 * f:]
    bar_cols = [j for j in range(right.shape[1]) if (right[:, j] == inferno[255]).all(axis=1)[0]
                and (right[:, j] == inferno[0]).all(axis=1)[-1]]
    assert len(bar_cols) >= 15, "no colour bar"
    bar = right[:, bar_cols[len(bar_cols) // 2]]
    np.testing.assert_array_equal(bar[0], inferno[255])
    assert np.all(np.diff(bar.astype(int).sum(axis=1)) <= 3)  # darker downwards (inferno: brightness falls)
    labels = right[:, bar_cols[-1] + 8:]
    assert labels.shape[1] > 80 and (labels < 100).any()
    assert (page[top + 60 * f:] < 100).any()  # the scale line under the map


def test_common_mode_standard_error_holds_on_correlated_noise():
    """The common-mode t of an unchanged pair: difference fields of Gaussian-smoothed white noise
    (scale 2 px, as a smooth LUT's) with a corner left out. If the block-mean standard error accounts
    for the correlation, t is Student's with 23 degrees of freedom (24 blocks of 30 px, the side capped at
    a quarter of the image): std(t) = sqrt(23 / 21) = 1.05 within 4 standard errors of its estimate over
    200 fields (+- 0.2), and at most 6 of 200 beyond the 1 % critical value
    (expected 2; 7 or more has chance 0.004 when the rate is right). Assuming independent
    pixels instead gives std(t) about 2 sqrt(pi) * 2 = 7 (checked below too)."""
    import cv2

    from ptpcore.evaluate.diff import block_side, common_mode_shift

    rng = np.random.default_rng(5)
    h, w, scale = 120, 160, 2.0
    common = np.ones((h, w), bool)
    common[:20, :30] = False
    side = block_side(scale, (h, w))
    ts, naive = [], []
    for _ in range(200):
        f = cv2.GaussianBlur(rng.standard_normal((h, w)), (0, 0), scale, borderType=cv2.BORDER_REFLECT)
        c = common_mode_shift(f, common, side, 0.01)
        ts.append(c.t)
        v = f[common]
        naive.append(v.mean() / (v.std() / np.sqrt(v.size)))
    ts = np.array(ts)
    assert c.n_blocks == 24 and side == 30
    assert 0.85 <= ts.std() <= 1.25, ts.std()
    assert np.sum(np.abs(ts) > c.critical) <= 6
    assert np.std(naive) > 3  # the independent-pixel standard error would cry wolf


def test_a_rigid_shift_far_below_one_pixels_noise_is_flagged_by_the_common_mode(two_sweeps):
    """A shift of 0.2 predicted sigmas in X: the per-pixel test cannot see it (consistent per pixel),
    the common mode flags X (its standard error is about 1/100 of a pixel's sigma at 160x120 px), and the
    unchanged pair is not flagged; the shift is measured within 3 standard errors."""
    (a, b), _ = two_sweeps
    r0 = diff_luts(a, b)
    assert not r0.common_flagged and r0.consistent
    assert r0.like_with_like and "unlike" not in r0.verdict_words()
    shift = 0.2 * float(np.sqrt(np.nanmean(a.sigma_x[a.valid] ** 2)))
    moved = replace(b, x=b.x.copy())
    moved.x[0] += shift
    r = diff_luts(a, moved)
    assert r.pixels_consistent and r.common_x.flagged and not r.consistent
    assert "common mode" in r.verdict_words() and "per pixel" not in r.verdict_words()
    measured = -(r.common_x.shift_um - r0.common_x.shift_um)
    assert abs(measured - shift * 1e3) < 3 * r.common_x.se_um
    s = r.summary()
    assert s["common_mode"]["x"]["flagged"] and s["common_mode_verdict"] == "differ"
    assert abs(s["pixel_false_alarm_rate"] - 0.0027) < 1e-4


def test_luts_of_different_models_say_they_are_unlike(two_sweeps, tmp_path, capsys):
    (a, _b), (pa, _pb) = two_sweeps
    lower = replace(a, x=a.x[:3], y=a.y[:3], degree=2)  # the same data's first coefficients: another model
    r = diff_luts(a, lower)
    assert not r.like_with_like and r.models == ("poly degree 3", "poly degree 2")
    assert "unlike models" in r.verdict_words()
    p = tmp_path / "deg2.lut.h5"
    save_lut(lower, p)
    main(["diff", str(pa), str(p), "--json", str(tmp_path / "d.json")])
    assert "UNLIKE" in capsys.readouterr().out
    assert json.loads((tmp_path / "d.json").read_text())["like_with_like"] is False


def test_the_common_mode_is_not_assessed_where_the_image_cannot_hold_its_blocks(two_sweeps, capsys):
    """A smooth LUT at a 64 px scale on a 160x120 image: blocks of 8 correlation lengths (733 px) do not
    fit 4 x 4 times, cut smaller they under-estimate the error (the slow two-sweep test was flagged at
    t = 5.5 on an unchanged rig so): no t, never flagged, the mean shift still reported, and said so."""
    from ptpcore.evaluate.diff import needed_block_side

    (a, b), (pa, pb) = two_sweeps
    big = {**(a.extra_attrs or {}), "smoothing_scale_px": 64.0}
    r = diff_luts(replace(a, extra_attrs=big), b)
    assert needed_block_side(64.0) > min(a.x.shape[1:]) // 4
    for c in (r.common_x, r.common_y):
        assert not c.assessed and not c.flagged and np.isfinite(c.shift_um) and c.block_px == needed_block_side(64.0)
    assert r.consistent == r.pixels_consistent
    assert r.summary()["common_mode"]["x"]["t"] is None
