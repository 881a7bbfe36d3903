"""The virtual rig: determinism and a ground truth consistent with OpenCV's camera model."""

from dataclasses import replace

import cv2
import numpy as np

from ptpcore.simulate import VirtualRig, load_truth, scaled_preset, simulate_dataset


def test_rendering_is_seeded_and_order_independent():
    rig, s = scaled_preset("rough", 96)
    a = VirtualRig(rig, s, seed=7)
    b = VirtualRig(rig, s, seed=7)
    later = a.render(3, "y", rig.fringes.periods_px[-1], 2, rig.fringes.steps[-1])
    b.render(0, "x", rig.fringes.periods_px[0], 0, rig.fringes.steps[0])
    assert np.array_equal(later, b.render(3, "y", rig.fringes.periods_px[-1], 2, rig.fringes.steps[-1]))
    c = VirtualRig(rig, s, seed=8)
    assert not np.array_equal(later, c.render(3, "y", rig.fringes.periods_px[-1], 2, rig.fringes.steps[-1]))
    assert later.dtype == np.uint8


def test_truth_rays_project_back_to_their_pixels_with_opencv():
    """On a Brown-exact lens, every pixel's true ray projects onto that pixel (cv2.projectPoints)."""
    rig, s = scaled_preset("mild", 160)
    vr = VirtualRig(rig, s, seed=1)
    truth = vr.truth()
    h, w = rig.camera.shape
    rows, cols = np.mgrid[0:h, 0:w]
    for z in (0.0, 23.0):
        x, y = truth.xy(z)
        pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
        rvec, _ = cv2.Rodrigues(vr.R)
        tvec = -vr.R @ vr.centre
        px, _ = cv2.projectPoints(pts, rvec, tvec, vr.K, vr.dist)
        px = px.reshape(h, w, 2)
        assert np.max(np.abs(px[..., 0] - cols)) < 1e-6
        assert np.max(np.abs(px[..., 1] - rows)) < 1e-6


def test_non_central_pupil_and_field_bend_away_from_the_pinhole():
    rig, s = scaled_preset("rough", 160)
    vr = VirtualRig(rig, s, seed=1)
    truth = vr.truth()
    pinhole = VirtualRig(rig, replace(s, lens=replace(s.lens, pupil_shift_mm=0.0, field_amplitude_px=0.0)), seed=1)
    t2 = pinhole.truth()
    dx = truth.xy(20.0)[0] - t2.xy(20.0)[0]
    assert np.nanmax(np.abs(dx)) > 0.05  # tens of micrometres: what a global model misses


def test_dataset_folder_and_truth_file(tmp_path):
    rig, s = scaled_preset("realistic", 48, positions=2)
    simulate_dataset(tmp_path, rig, s, seed=2)
    assert (tmp_path / "rig.toml").exists()
    n = len(list(tmp_path.rglob("*.png")))
    assert n == 2 * rig.fringes.frames_per_position
    truth, settings, seed = load_truth(tmp_path)
    assert seed == 2 and settings == s
    assert truth.x0.shape == rig.camera.shape
