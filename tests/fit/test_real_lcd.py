"""A real LCD on a real stage (METHOD.md section 8): the simulator's cover glass, carriage pose and bow."""

from dataclasses import replace

import numpy as np
import pytest

from ptpcore.io.dataset import SimulatedSource
from ptpcore.run.pipeline import decode_position
from ptpcore.simulate import VirtualRig, preset, scaled_preset
from ptpcore.simulate.lcd_physics import LcdPhysics, pose_matrix, refraction_offset_mm


def test_plate_offset_is_snell_and_points_to_the_foot_of_the_normal():
    # METHOD section 8: t = 1.1 mm, n = 1.52: 20 um at 3 degrees, 195 um at 25, 225 um at 28.
    tan = np.tan(np.radians([3.0, 25.0, 28.0]))
    got = 1e3 * refraction_offset_mm(tan, 1.1, 1.52)
    assert np.allclose(got, [19.75, 194.54, 227.67], atol=0.01)
    phys = LcdPhysics(1.1, 1.52, 0.0, (192.0, 108.0))
    d = np.array([[0.3, -0.2, -1.0]])
    o = np.array([[10.0, 20.0, 150.0]])
    x, y = phys.hit(o, d)
    air = o[0, :2] + 150.0 * d[0, :2]
    shift = np.array([x[0], y[0]]) - air
    # Toward the foot of the normal (opposite the ray's lateral direction), by the plate offset.
    assert np.allclose(shift, -d[0, :2] / np.hypot(*d[0, :2]) * refraction_offset_mm(np.hypot(0.3, 0.2), 1.1, 1.52),
                       atol=1e-12)


def test_pose_matrix_is_a_small_rotation():
    r = pose_matrix(20.0, -30.0, 10.0)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-15)
    assert np.allclose(r - np.eye(3), [[0, -10e-6, -30e-6], [10e-6, 0, -20e-6], [30e-6, 20e-6, 0]], atol=1e-9)


def test_noise_free_glass_rig_decodes_the_refracted_point():
    """Ideal rig with 1.1 mm glass, tilts, run-out and bow: the decoded LCD point is the exact
    refracted intersection (to the ideal preset's decoding floor), not the ray in air."""
    rig, s = scaled_preset("ideal", 160)
    s = replace(s, cover_glass_mm=1.1, cover_glass_index=1.52, tilt_urad=200.0, roll_urad=100.0,
                runout_um=20.0, bow_um=30.0, stage_error_um=5.0)
    vr = VirtualRig(rig, s, seed=3)
    truth = vr.truth()
    h, w = rig.camera.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    a, b, _ = rig.stage.direction
    for k in (0, rig.stage.n_positions - 1):
        pos = decode_position(SimulatedSource(vr), k)
        u, v = vr._lcd_uv_at(vr.z_true[k], cols, rows, k)
        m = pos.valid
        assert m.mean() > 0.7
        assert np.max(np.abs(pos.u[m] - u[m])) < 0.02
        assert np.max(np.abs(pos.v[m] - v[m])) < 0.02


def test_glass_alone_moves_each_pixel_by_its_plate_offset():
    """Flat glass, perfect stage: the pixel-plane point is the air ray's point at the reading moved
    by the plate offset of that pixel's slope (a constant per pixel, the same at every height)."""
    rig, s = scaled_preset("realistic", 96)
    vr = VirtualRig(rig, replace(s, cover_glass_mm=1.1, cover_glass_index=1.52, stage_error_um=0.0), seed=1)
    truth = vr.truth()
    h, w = rig.camera.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    a, b, _ = rig.stage.direction
    exact = refraction_offset_mm(np.hypot(truth.sx, truth.sy), 1.1, 1.52)
    for z in (0.0, 40.0):
        u, v = vr._lcd_uv_at(z, cols, rows, 0)
        tx, ty = truth.xy(z)
        dx = u * rig.lcd.pitch_mm[0] + a * z - tx
        dy = v * rig.lcd.pitch_mm[1] + b * z - ty
        slope = np.hypot(truth.sx, truth.sy)
        assert np.max(np.abs(np.hypot(dx, dy) - exact)) < 1e-9
        # Toward the foot of the normal: along -(sx, sy), Z growing away from the camera (METHOD 2).
        assert np.max(np.abs(dx + exact * truth.sx / slope)) < 1e-9
        assert np.max(np.abs(dy + exact * truth.sy / slope)) < 1e-9
    assert 0.15 < exact.max() < 0.3  # corners at about 30 degrees


def test_real_preset_has_everything_at_realistic_sizes():
    rig, s = preset("real")
    assert (s.cover_glass_mm, s.cover_glass_index, s.tilt_urad, s.stage_error_um) == (1.1, 1.52, 20.0, 1.0)
    assert s.display_gamma == 1.1 and rig.fringes.gamma == 1.0
    vr = VirtualRig(*scaled_preset("real", 64), seed=0)
    pose = vr.truth().stage_pose
    assert pose.shape == (rig.stage.n_positions, 6)
    assert 3.0 < np.std(pose[:, 3:5]) < 60.0 and np.all(pose[:, 5] == 0)
    # Older presets keep their images bit for bit: no pose, no glass.
    assert not preset("realistic")[1].cover_glass_mm
    assert rig.lcd.cover_glass_mm == 1.1


# ---------------------------------------------------------------- the cover glass removed

def _glass_rigs(width, seed=7, **kw):
    """The `real` rig with and without its glass, same seed (everything else identical)."""
    rig, s = scaled_preset("real", width, **kw)
    return [(VirtualRig(rig, replace(s, cover_glass_mm=t), seed=seed)) for t in (0.0, 1.1)]


def test_glass_correction_is_the_exact_plate_offset_per_pixel():
    from ptpcore.fit.glass import correct_cover_glass, describe_corrections
    from ptpcore.fit.perpixel import fit_lut
    from ptpcore.run.pipeline import collect_samples

    bare, glass = _glass_rigs(64, positions=5)
    truth = glass.truth()
    raw = collect_samples(SimulatedSource(glass))
    fixed, corr = correct_cover_glass(raw, 1.1, 1.52, 0.05, 0.01)
    assert fixed.x is raw.x and np.all(np.isnan(raw.x_ref) == np.isnan(fixed.x_ref))
    exact = 1e3 * refraction_offset_mm(np.hypot(truth.sx, truth.sy), 1.1, 1.52)
    two = raw.valid.sum(axis=0) >= 2
    assert two.mean() > 0.6
    # Each pixel's shift is the simulator's exact refraction offset up to its slope's error: a
    # slope error of 1e-3 moves the offset by about t*(1 - 1/n)*1e-3 = 0.4 um (at 64 px a pixel's
    # samples are tens of um off its centre ray: footprint, bow, tilts).
    diff = np.abs(corr.shift_um[two] - exact[two])
    assert np.median(diff) < 0.3
    assert np.percentile(diff - 0.01 * exact[two], 99) < 1.0
    rec = fixed.corrections["cover_glass"]
    assert abs(rec["median_um"] / np.median(exact[two]) - 1) < 0.01
    assert abs(rec["max_um"] / np.max(exact[two]) - 1) < 0.01
    assert "median" in describe_corrections(fixed.corrections)[0]
    # Tolerances: +-0.05 mm of 1.1 mm is 4.5 % of the shift, the index adds a little.
    assert np.all(corr.sigma[two] > 0.045 * corr.shift_um[two] * 1e-3)
    assert np.all(corr.sigma[two] < 0.06 * corr.shift_um[two] * 1e-3)
    # The corrected LUT sees the air rays as well as the same rig's LUT without glass (at 64 px
    # both are off by the pixel footprint), where the raw one is off by the offset.
    lut_raw, lut_fix = fit_lut(raw, "poly", 2), fit_lut(fixed, "poly", 2)
    lut_bare = fit_lut(collect_samples(SimulatedSource(bare)), "poly", 2)
    ok = lut_fix.valid & two & lut_bare.valid
    ex, ey = truth.xy(20.0)

    def err(lut):
        ev = lut.evaluate(20.0)
        return np.median(1e3 * np.hypot(ev.x - ex, ev.y - ey)[ok])

    assert err(lut_raw) > 30.0
    assert err(lut_fix) < 1.1 * err(lut_bare)


def test_corrections_reach_the_lut_file_and_the_summary(tmp_path):
    import json

    from ptpcore.evaluate import LutReport
    from ptpcore.io.lutfile import load_lut, save_lut
    from ptpcore.fit.glass import correct_samples
    from ptpcore.fit.perpixel import fit_lut
    from ptpcore.run.pipeline import collect_samples

    _bare, glass = _glass_rigs(48, positions=4)
    raw = collect_samples(SimulatedSource(glass))
    rig = glass.rig
    # A rig that declares no glass: a bare panel is assumed, and said.
    rig = replace(rig, lcd=replace(rig.lcd, cover_glass_mm=None))
    same, applied = correct_samples(raw, rig)
    assert not applied and same.x_ref is raw.x_ref
    lut = fit_lut(same, "poly", 1)
    lut.provenance["corrections"] = json.dumps(same.corrections)
    save_lut(lut, tmp_path / "a.lut.h5")
    back = load_lut(tmp_path / "a.lut.h5")
    assert json.loads(back.provenance["corrections"])["cover_glass"]["t_mm"] == 0.0
    assert "bare panel is assumed" in LutReport.of(back).text(width=1000)
    # cover_glass_mm = 0 declared: no glass, said so (not "assumed").
    none, applied = correct_samples(raw, replace(rig, lcd=replace(rig.lcd, cover_glass_mm=0.0)))
    assert not applied and none.x_ref is raw.x_ref
    lut.provenance["corrections"] = json.dumps(none.corrections)
    text = LutReport.of(lut).text(width=1000)
    assert "no cover glass (declared" in text and "assumed" not in text


@pytest.mark.slow
def test_real_rig_with_glass_declared_is_as_good_as_without_glass():
    """Issue 14's Must show: the `real` rig with its glass removed against the same rig without glass."""
    from ptpcore.evaluate import compare
    from ptpcore.fit.glass import correct_cover_glass
    from ptpcore.run.pipeline import collect_samples

    bare, glass = _glass_rigs(160)
    truth = bare.truth()
    r_bare = compare(collect_samples(SimulatedSource(bare)), bare.rig, truth=truth, seed=7)
    raw = collect_samples(SimulatedSource(glass))
    fixed, corr = correct_cover_glass(raw, 1.1, 1.52)
    r_glass = compare(fixed, glass.rig, truth=truth, seed=7)
    r_undeclared = compare(raw, glass.rig, truth=truth, seed=7, with_smooth=False)
    tb, tg = r_bare.references["truth"], r_glass.references["truth"]
    for m, n in (("ptp", "n_ptp"), ("smooth", "n_smooth")):
        assert tg.methods[m].coordinate.rms_um < 1.3 * tb.methods[m].coordinate.rms_um
        assert getattr(r_glass.coverage, n).sum() >= 0.97 * getattr(r_bare.coverage, n).sum()
    # Undeclared, the LUT is off by the glass: tens of um.
    assert r_undeclared.references["truth"].methods["ptp"].coordinate.rms_um > 30.0
    # The report's correction column is the simulator's exact refraction offset.
    exact = 1e3 * refraction_offset_mm(np.hypot(truth.sx, truth.sy), 1.1, 1.52)
    two = raw.valid.sum(axis=0) >= 2
    rec = r_glass.corrections["cover_glass"]
    assert abs(rec["median_um"] / np.median(exact[two]) - 1) < 0.05
    assert abs(rec["max_um"] / np.max(exact[two]) - 1) < 0.05
    # 3DSTC on corrected feature points: the no-glass rig's parameters within 2 of their std.
    pb, pg = r_bare.pinhole, r_glass.pinhole
    std = np.hypot(pb.param_std, pg.param_std) / np.sqrt(2)
    free = std > 0
    assert np.all(np.abs(np.asarray(pg.param_values) - pb.param_values)[free] < 2 * std[free])


def test_glass_tolerances_enter_the_sigma_maps():
    from ptpcore.fit.glass import add_tolerances_to_sigma, correct_cover_glass
    from ptpcore.fit.perpixel import fit_lut
    from ptpcore.run.pipeline import collect_samples

    _bare, glass = _glass_rigs(48, positions=4)
    raw = collect_samples(SimulatedSource(glass))
    fixed, corr = correct_cover_glass(raw, 1.1, 1.52, 0.05, 0.0)
    lut = fit_lut(fixed, "poly", 1)
    lut.sigma_x = np.zeros(lut.shape, np.float32)
    lut.sigma_y = np.zeros(lut.shape, np.float32)
    add_tolerances_to_sigma(lut, {"cover_glass": corr})
    # +-0.05 mm of 1.1 mm: 4.5 % of each pixel's shift (the offset is proportional to t).
    total = np.hypot(lut.sigma_x, lut.sigma_y)
    ok = corr.shift_um > 1.0
    assert np.allclose(1e3 * total[ok], 0.05 / 1.1 * corr.shift_um[ok], rtol=1e-4)
