"""Tests for ptpcore.pinhole.camera: the 3DSTC pinhole + Brown baseline."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from ptpcore.pinhole import PinholeFit, PinholeModel, dlt_initial_guess, fit_pinhole, opencv_calibrate

W, H = 640, 480
SIGMA = 0.05  # px
M = 2000


def _values(model: PinholeModel) -> np.ndarray:
    """Parameter vector in fit_pinhole order (5-coefficient model)."""
    K = model.K
    return np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], model.dist[:5], model.rvec, model.tvec]


@pytest.fixture(scope="module")
def cam():
    """640x480 camera, fx~1200, strong distortion, 300 mm above a 160x120x40 mm volume."""
    K = np.array([[1200.0, 0.0, 322.5], [0.0, 1195.0, 236.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.25, 0.1, 1e-3, -5e-4, 0.0])
    R = cv2.Rodrigues(np.array([np.pi - 0.1, 0.08, 0.05]))[0]  # looking down -Z, slightly tilted
    true = PinholeModel(K=K, dist=dist, rvec=cv2.Rodrigues(R)[0].ravel(), tvec=-R @ [0.0, 0.0, 300.0])
    rng = np.random.default_rng(20240601)
    pw = rng.uniform([-80, -60, 0], [80, 60, 40], (3 * M, 3))
    px = true.project(pw)
    inside = (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
    pw, px = pw[inside][:M], px[inside][:M]
    assert len(pw) == M
    noisy = px + rng.normal(0.0, SIGMA, px.shape)
    return {"true": true, "pw": pw, "px": px, "noisy": noisy}


@pytest.fixture(scope="module")
def fit(cam) -> PinholeFit:
    return fit_pinhole(cam["pw"], cam["noisy"])


# ----------------------------------------------------------------------------- model

def test_project_matches_opencv(cam):
    m = cam["true"]
    ref = cv2.projectPoints(cam["pw"], m.rvec, m.tvec, m.K, m.dist)[0].reshape(-1, 2)
    assert np.max(np.abs(m.project(cam["pw"]) - ref)) < 1e-9
    m8 = PinholeModel(K=m.K, dist=np.r_[m.dist, 0.02, -0.01, 0.005], rvec=m.rvec, tvec=m.tvec)
    ref8 = cv2.projectPoints(cam["pw"], m8.rvec, m8.tvec, m8.K, m8.dist)[0].reshape(-1, 2)
    assert np.max(np.abs(m8.project(cam["pw"]) - ref8)) < 1e-9


def test_pixel_to_world_inverts_project(cam):
    m, pw, px = cam["true"], cam["pw"], cam["px"]
    X, Y = m.pixel_to_world_at_z(px[:, 0], px[:, 1], pw[:, 2])
    assert np.max(np.abs(X - pw[:, 0])) < 1e-9
    assert np.max(np.abs(Y - pw[:, 1])) < 1e-9
    # broadcasting: pixel grid against a scalar plane, and a column of planes
    cols, rows = np.meshgrid(np.arange(0, W, 64.0), np.arange(0, H, 48.0))
    X, Y = m.pixel_to_world_at_z(cols, rows, 20.0)
    assert X.shape == cols.shape and np.all(np.isfinite(X))
    back = m.project(np.c_[X.ravel(), Y.ravel(), np.full(X.size, 20.0)])
    assert np.max(np.abs(back - np.c_[cols.ravel(), rows.ravel()])) < 1e-9
    X3, _ = m.pixel_to_world_at_z(cols[None], rows[None], np.array([0.0, 20.0, 40.0])[:, None, None])
    assert X3.shape == (3,) + cols.shape
    assert np.allclose(X3[1], X, atol=1e-12)
    # the plane behind the camera (camera at Z=300 looking down) has no intersection
    Xb, Yb = m.pixel_to_world_at_z(320.0, 240.0, 400.0)
    assert np.isnan(Xb) and np.isnan(Yb)


def test_dict_roundtrip(cam):
    m = cam["true"]
    d = json.loads(json.dumps(m.to_dict()))
    assert set(d) == {"K", "dist", "rvec", "tvec"} and len(d["K"]) == 3
    m2 = PinholeModel.from_dict(d)
    for a in ("K", "dist", "rvec", "tvec"):
        np.testing.assert_array_equal(getattr(m2, a), getattr(m, a))


# ----------------------------------------------------------------------------- DLT

def test_dlt_noise_free_undistorted(cam):
    t = cam["true"]
    pinhole = PinholeModel(K=t.K, dist=np.zeros(5), rvec=t.rvec, tvec=t.tvec)
    m = dlt_initial_guess(cam["pw"], pinhole.project(cam["pw"]))
    np.testing.assert_allclose(m.K, t.K, atol=1e-6)
    np.testing.assert_allclose(m.R, t.R, atol=1e-9)
    assert np.linalg.det(m.R) == pytest.approx(1.0)
    np.testing.assert_allclose(m.tvec, t.tvec, atol=1e-6)
    np.testing.assert_array_equal(m.dist, np.zeros(5))


def test_dlt_distorted_is_reasonable_start(cam):
    t = cam["true"]
    m = dlt_initial_guess(cam["pw"], cam["noisy"])
    assert m.K[0, 1] == 0.0 and np.all(np.diag(m.K) > 0)
    np.testing.assert_allclose(np.diag(m.K)[:2], np.diag(t.K)[:2], rtol=0.05)
    np.testing.assert_allclose(m.K[:2, 2], t.K[:2, 2], atol=40.0)
    assert np.linalg.norm(m.centre - t.centre) < 10.0  # mm, camera ~300 mm away
    assert np.sqrt(np.mean((m.project(cam["pw"]) - cam["noisy"]) ** 2)) < 5.0  # px, distortion ignored


# ----------------------------------------------------------------------------- LM fit

def test_fit_recovers_parameters_within_reported_std(cam, fit):
    assert fit.param_names == ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3",
                               "rx", "ry", "rz", "tx", "ty", "tz"]
    assert fit.n_points == M and fit.residuals_px.shape == (M, 2)
    np.testing.assert_allclose(fit.param_values, _values(fit.model), rtol=0, atol=0)
    z = (fit.param_values - _values(cam["true"])) / fit.param_std
    assert np.all(np.abs(z) < 4.0), dict(zip(fit.param_names, np.round(z, 2)))
    n = len(fit.param_names)
    expected = SIGMA * np.sqrt((2 * M - n) / (2 * M))
    assert fit.reprojection_rms_px == pytest.approx(expected, rel=0.10)
    np.testing.assert_allclose(fit.residuals_px, fit.model.project(cam["pw"]) - cam["noisy"], atol=1e-9)


def test_fit_std_is_honest(cam):
    """Scatter of estimates over noise draws matches the reported 1-sigma."""
    rng = np.random.default_rng(7)
    fits = [fit_pinhole(cam["pw"], cam["px"] + rng.normal(0.0, SIGMA, cam["px"].shape)) for _ in range(30)]
    values = np.array([f.param_values for f in fits])
    reported = np.array([f.param_std for f in fits]).mean(axis=0)
    ratio = values.std(axis=0, ddof=1) / reported
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), dict(zip(fits[0].param_names, np.round(ratio, 2)))


def test_fit_from_given_init_and_rational(cam, fit):
    f2 = fit_pinhole(cam["pw"], cam["noisy"], init=cam["true"])
    np.testing.assert_allclose(f2.param_values, fit.param_values, atol=1e-3 * fit.param_std.min())
    fr = fit_pinhole(cam["pw"], cam["noisy"], rational=True)
    assert fr.param_names[4:12] == ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]
    assert fr.model.dist.shape == (8,)
    # k1..k6 are poorly separable when the truth has no rational part, but the mapping is not
    assert fr.reprojection_rms_px <= fit.reprojection_rms_px
    assert np.sqrt(np.mean((fr.model.project(cam["pw"]) - cam["px"]) ** 2)) < SIGMA


# ----------------------------------------------------------------------------- OpenCV cross-check

def test_opencv_agrees_with_fit(cam, fit):
    init = dlt_initial_guess(cam["pw"], cam["noisy"])
    m = opencv_calibrate(cam["pw"], cam["noisy"], (W, H), init)
    assert m.dist.shape == (5,) and m.K[0, 1] == 0.0
    z = (_values(m) - fit.param_values) / fit.param_std
    assert np.all(np.abs(z[:9]) < 1.0), dict(zip(fit.param_names[:9], np.round(z[:9], 3)))  # intrinsics, dist
    assert np.all(np.abs(z[9:]) < 1.0)  # pose as well
    mr = opencv_calibrate(cam["pw"], cam["noisy"], (W, H), init, rational=True)
    assert mr.dist.shape == (8,)


# ----------------------------------------------------------------------------- bad input

def test_bad_input_raises(cam):
    pw, px = cam["pw"], cam["noisy"]
    with pytest.raises(ValueError, match=r"points_world must have shape \(M, 3\)"):
        dlt_initial_guess(pw[:, :2], px)
    with pytest.raises(ValueError, match=r"pixels must have shape \(M, 2\)"):
        fit_pinhole(pw, px.T)
    with pytest.raises(ValueError, match="same length"):
        fit_pinhole(pw, px[:-1])
    bad = px.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_pinhole(pw, bad)
    with pytest.raises(ValueError, match="at least 6"):
        dlt_initial_guess(pw[:5], px[:5])
    with pytest.raises(ValueError, match="at least 8"):
        fit_pinhole(pw[:7], px[:7])
    planar = pw.copy()
    planar[:, 2] = 10.0 + 1e-6 * planar[:, 0]
    with pytest.raises(ValueError, match="non-coplanar"):
        dlt_initial_guess(planar, px)
    with pytest.raises(ValueError, match="image_size"):
        opencv_calibrate(pw, px, (640,), cam["true"])
    with pytest.raises(ValueError, match="points_world"):
        cam["true"].project(pw[:, :2])
    t = cam["true"]
    with pytest.raises(ValueError, match="dist must have 5 or 8"):
        PinholeModel(K=t.K, dist=[0.1, 0.2, 0.3], rvec=t.rvec, tvec=t.tvec)
    with pytest.raises(ValueError, match="K must have 9"):
        PinholeModel(K=np.eye(2), dist=t.dist, rvec=t.rvec, tvec=t.tvec)
    with pytest.raises(ValueError, match="rvec contains NaN"):
        PinholeModel(K=t.K, dist=t.dist, rvec=[np.nan, 0, 0], tvec=t.tvec)
    with pytest.raises(ValueError, match="missing keys"):
        PinholeModel.from_dict({"K": t.K.tolist()})
    with pytest.raises(ValueError, match="rational=False"):
        fit_pinhole(pw, px, init=PinholeModel(K=t.K, dist=np.r_[t.dist, 0.1, 0, 0], rvec=t.rvec, tvec=t.tvec))
