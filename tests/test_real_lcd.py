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
        # Toward the foot of the normal: along +(sx, sy), the slope dX/dZ of a ray seen going down.
        assert np.max(np.abs(dx - exact * truth.sx / slope)) < 1e-9
        assert np.max(np.abs(dy - exact * truth.sy / slope)) < 1e-9
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
    if hasattr(rig.lcd, "cover_glass_mm"):
        assert rig.lcd.cover_glass_mm == 1.1
