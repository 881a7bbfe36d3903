"""The conventional structured-light calibration (METHOD.md section 9, "The comparison") against the simulator.

``scanner-mild`` at 320x240 (the camera preset ``mild``: a lens Brown describes exactly; projector
k1 = -0.05, no non-parametric field), 6 plate heights on the LCD's readings (0, 8, ..., 40 mm), with
the stage and plate errors switched off as the 3DSTC truth test does (tests/evaluate/test_compare.py):
a stage or plate height error moves every feature point of one height together, correlated noise
that the fits' standard errors (computed for independent residuals) do not cover, and here those
errors are tested against the truth. Every tolerance is a number of reported standard errors or a
noise prediction.
"""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from ptpcore.decode.noise import NoiseModel
from ptpcore.errors import ConfigError
from ptpcore.io.dataset import SimulatedSource
from ptpcore.pinhole import ConventionalCalibration, PinholeModel
from ptpcore.rig.rigfile import save_rig
from ptpcore.run.scanner import decode_projector
from ptpcore.run.structured_light import (calibrate_conventional, calibrate_conventional_from,
                                          reconstruct_conventional)
from ptpcore.simulate.scanner import HeightSweepSource, ScannerRig, ScanSource, default_objects, scanner_preset
from ptpcore.simulate.virtual_rig import VirtualRig

# The 3DSTC truth test's standard (tests/evaluate/test_compare.py::test_3dstc_recovers_brown_exact_lens):
# the truth within 4 reported standard errors, parameter by parameter.
N_STD = 4.0


def _camera_truth(sr: ScannerRig) -> PinholeModel:
    """The simulator's camera in OpenCV's convention (``Xc = R Xw + t``, ``t = -R c``)."""
    vr = sr.camera
    return PinholeModel(K=vr.K, dist=vr.dist, rvec=cv2.Rodrigues(vr.R)[0].ravel(), tvec=-vr.R @ vr.centre)


def _projector_truth(sr: ScannerRig) -> PinholeModel:
    """The simulated projector as a pinhole (exact: ``scanner-mild`` has no non-parametric field)."""
    return PinholeModel(K=sr.K, dist=sr.dist, rvec=cv2.Rodrigues(sr.R)[0].ravel(), tvec=-sr.R @ sr.centre)


def _vector(model: PinholeModel) -> np.ndarray:
    """A model in ``fit_pinhole``'s parameter order (5 distortion coefficients)."""
    K = model.K
    return np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], model.dist[:5], model.rvec, model.tvec]


@pytest.fixture(scope="module")
def mild():
    rig, sim, sc = scanner_preset("scanner-mild", 320, heights=6)
    sim = replace(sim, stage_error_um=0.0)
    sc = replace(sc, plate_tilt_urad=(0.0, 0.0), plate_bow_um=0.0, plate_z_error_um=0.0)
    sr = ScannerRig(rig, sim, sc, seed=7)
    lcd = VirtualRig(replace(rig, projector=None, height=None), sim, 7)  # the LCD sweep: same camera, same seed
    cal = calibrate_conventional_from(rig, SimulatedSource(lcd), HeightSweepSource(sr))
    return SimpleNamespace(rig=rig, sr=sr, cal=cal)


def test_parameters_match_the_truth_within_their_standard_errors(mild):
    """Camera, projector and their relative pose: the truth within 4 reported standard errors each."""
    cal, sr = mild.cal, mild.sr
    for fit, truth in ((cal.camera_fit, _camera_truth(sr)), (cal.projector_fit, _projector_truth(sr))):
        z = (fit.param_values - _vector(truth)) / fit.param_std
        assert np.all(np.abs(z) < N_STD), dict(zip(fit.param_names, np.round(z, 2)))
    # the estimates are informative: far below the parameters' own scales
    std = dict(zip(cal.projector_fit.param_names, cal.projector_fit.param_std))
    assert std["fx"] < 1e-3 * sr.K[0, 0] and std["k1"] < 0.05 * abs(sr.dist[0])
    R, T = _relative_truth(sr)
    rel = np.r_[cv2.Rodrigues(cal.R_proj_cam)[0].ravel(), cal.T_proj_cam]
    z = (rel - np.r_[cv2.Rodrigues(R)[0].ravel(), T]) / cal.relative_std
    assert np.all(np.abs(z) < N_STD), np.round(z, 2)


def _relative_truth(sr: ScannerRig) -> tuple[np.ndarray, np.ndarray]:
    """True ``R``, ``T`` (mm) with ``x_proj = R x_cam + T``."""
    cam, proj = _camera_truth(sr), _projector_truth(sr)
    R = proj.R @ cam.R.T
    return R, proj.tvec - R @ cam.tvec


def test_residuals_are_the_decoded_noise(mild):
    """The projector's reprojection RMS is the decoded (u_p, v_p)'s predicted noise (the model fits; its
    standard errors, scaled by that RMS, are the right size). The band is the one issue 34 gives a
    point's normalised error, [0.7, 1.4]; the camera's residuals are the LCD decode's micrometres."""
    cal = mild.cal
    ratio = cal.rms_projector_px / cal.provenance["projector_sigma_rms_px"]
    assert 0.7 <= ratio <= 1.4, (cal.rms_projector_px, cal.provenance["projector_sigma_rms_px"])
    assert cal.rms_camera_px < 0.2 * cal.rms_projector_px
    assert cal.n_projector_points == 6 * cal.provenance["n_feature_pixels"]
    assert cal.n_camera_points == 11 * cal.provenance["n_feature_pixels"]
    assert set(cal.provenance["plate_xy_from"].values()) == {"lcd decode"}
    record = json.loads(json.dumps(cal.to_json_dict(), allow_nan=False))  # a report can carry it whole
    assert record["projector_fit"]["param_std"] == cal.projector_fit.param_std.tolist()


def test_opencv_stereo_calibration_lands_on_the_same_minimum(mild):
    """cv2.stereoCalibrate (one non-coplanar view, intrinsic guess) on the projector's points: for the
    projector the same objective as its own fit (no parameter shared with the camera), so the same values
    to a tenth of a standard error; its camera, and so the relative pose, from these points alone (6 of the
    LCD's 11 heights), within 4 standard errors of ours."""
    check = mild.cal.opencv_check
    assert check["projector_max_z"] < 0.1, check
    assert check["camera_max_z"] < N_STD and check["relative_max_z"] < N_STD, check


def test_points_from_up_invert_the_true_projector_exactly(mild):
    """With the true models, a pixel's true u_p on a plane gives back that plane's point (no noise)."""
    sr = mild.sr
    truth = ConventionalCalibration.from_models(_camera_truth(sr), _projector_truth(sr))
    rows, cols = np.mgrid[0:240:17, 0:320:23]
    for z in (0.0, 17.3, 40.0):
        up = sr.true_up(z)[rows, cols]
        p = truth.points_from_up(cols.ravel(), rows.ravel(), up.ravel())
        o, d = sr.camera.rays(cols.astype(float), rows.astype(float))
        t = (z - o[..., 2]) / d[..., 2]
        expected = (o + t[..., None] * d).reshape(-1, 3)
        np.testing.assert_allclose(p, expected, atol=1e-7)
    bad = truth.points_from_up([10.0, 10.0], [10.0, 10.0], [np.nan, 600.0])
    assert np.all(np.isnan(bad[0])) and np.all(np.isfinite(bad[1]))


def test_sphere_scan_within_its_predicted_noise(mild):
    """A simulated sphere scan through the conventional calibration: the RMS radial distance from the true
    sphere within [0.7, 1.4] of what the decoded u_p's noise predicts (issue 34's band for a point's
    normalised error). Every pixel the decoder keeps on the lit sphere counts: its border margin already
    leaves out the pixels near the silhouette, whose footprint averages sphere and dark background."""
    cal, sr = mild.cal, mild.sr
    obj = default_objects(mild.rig)["sphere"]
    noise = NoiseModel(*cal.provenance["camera_noise"], source="height sweep")
    dec = decode_projector(ScanSource(sr, obj), noise=noise)
    truth = sr.scan_truth(obj)
    use = truth["lit"] & np.isfinite(dec.u[0])
    rows, cols = np.nonzero(use)
    u, sig = dec.u[0][use].astype(float), dec.sigma_u[0][use].astype(float)
    p = cal.points_from_up(cols, rows, u)
    radial = obj.distance(p)
    # the radial distance's sensitivity to u_p (mm per projector px), by central differences
    step = 0.01  # projector px: the map is smooth on this scale
    hi, lo = cal.points_from_up(cols, rows, u + step), cal.points_from_up(cols, rows, u - step)
    dr = (obj.distance(hi) - obj.distance(lo)) / (2 * step)
    predicted = float(np.sqrt(np.mean((dr * sig) ** 2)))
    rms = float(np.sqrt(np.mean(radial ** 2)))
    assert use.sum() > 0.5 * truth["lit"].sum() and np.all(np.isfinite(radial))
    assert 0.7 <= rms / predicted <= 1.4, (rms, predicted, float(np.mean(radial)))


def test_dataset_without_a_height_sweep_or_its_y_direction_is_refused(tmp_path, mild):
    """One clear line naming the rig.toml and the table or key; before anything is decoded."""
    no_sweep = tmp_path / "no_sweep"
    no_sweep.mkdir()
    save_rig(replace(mild.rig, projector=None, height=None), no_sweep / "rig.toml")
    with pytest.raises(ConfigError, match=r"rig\.toml: no height sweep") as err:
        calibrate_conventional(no_sweep)
    assert "\n" not in str(err.value)
    x_only = tmp_path / "x_only"
    x_only.mkdir()
    proj = mild.rig.projector
    save_rig(replace(mild.rig, projector=replace(proj, fringes=replace(proj.fringes, directions=("x",)))),
             x_only / "rig.toml")
    with pytest.raises(ConfigError, match=r"rig\.toml: key 'projector\.directions' is \['x'\]") as err:
        calibrate_conventional(x_only)
    assert "\n" not in str(err.value)


def test_a_dataset_folder_calibrates_as_its_frames_rendered_on_demand(tmp_path):
    """``calibrate_conventional(folder)`` (the frames read from the PNGs of ``ptp-dataset/2``) gives the very
    numbers of :func:`calibrate_conventional_from` on the same frames rendered in memory."""
    from ptpcore.simulate.scanner import simulate_scanner_dataset

    rig, sim, sc = scanner_preset("scanner-mild", 96, heights=6)
    sphere = default_objects(rig)["sphere"]
    folder = simulate_scanner_dataset(tmp_path / "ds", rig, sim, sc, seed=3, objects={"sphere": sphere})
    read = calibrate_conventional(folder)
    sr = ScannerRig(rig, sim, sc, seed=3)
    lcd = VirtualRig(replace(rig, projector=None, height=None), sim, 3)
    rendered = calibrate_conventional_from(rig, SimulatedSource(lcd), HeightSweepSource(sr))
    for a, b in ((read.camera_fit, rendered.camera_fit), (read.projector_fit, rendered.projector_fit)):
        np.testing.assert_array_equal(a.param_values, b.param_values)
    assert read.provenance == rendered.provenance
    # a caller that decoded the height sweep already (x and y) passes it in: the same calibration
    from ptpcore.io.dataset import DatasetSource

    h_source = DatasetSource(folder, rig=rig.height_rig())
    again = calibrate_conventional(folder, decoded=decode_projector(h_source, directions=("x", "y")))
    np.testing.assert_array_equal(again.projector_fit.param_values, read.projector_fit.param_values)
    with pytest.raises(ValueError, match="without v_p"):
        calibrate_conventional(folder, decoded=decode_projector(h_source))
    # the scan folder's cloud: its decoded u_p through points_from_up, each point with |dP/du_p| sigma_u
    (cloud,) = reconstruct_conventional(folder / "scans" / "sphere", read)
    noise = NoiseModel(*read.provenance["camera_noise"], source="height sweep")
    dec = decode_projector(ScanSource(sr, sphere), noise=noise)
    assert cloud.x.size == np.count_nonzero(np.isfinite(dec.u[0])) > 20
    p = read.points_from_up(cloud.col, cloud.row, dec.u[0][cloud.row, cloud.col])
    np.testing.assert_array_equal(np.stack([cloud.x, cloud.y, cloud.z], axis=1), p)
    assert np.all(cloud.sigma_z > 0) and np.all(np.isfinite(cloud.sigma_x))


def test_plate_heights_on_the_lcd_readings_use_its_decode_alone():
    """The presets' 21 plate heights hold the LCD's 11: the projector uses those 11 (X, Y decoded); with
    fewer than 3 on the LCD's readings every height is used, X, Y from the camera's rays."""
    from ptpcore.run.structured_light import _plate_heights

    lcd = SimpleNamespace(z=np.arange(0.0, 41.0, 4.0))
    heights, position = _plate_heights(lcd, np.arange(0.0, 41.0, 2.0))
    np.testing.assert_array_equal(heights, np.arange(0, 21, 2))
    np.testing.assert_array_equal(position, np.arange(11))
    heights, position = _plate_heights(lcd, np.linspace(0.0, 40.0, 4))  # 0 and 40 only: too few
    np.testing.assert_array_equal(heights, np.arange(4))
    assert np.all(position == -1)


def test_plate_points_from_the_camera_model_when_heights_are_off_the_lcd():
    """4 plate heights (0, 13.3, 26.7, 40 mm): X, Y from the fitted camera's rays at every height; on the
    Brown-exact camera the projector's residuals are still its decoded noise (issue 34's band)."""
    rig, sim, sc = scanner_preset("scanner-mild", 96, heights=4)
    sim = replace(sim, stage_error_um=0.0)
    sc = replace(sc, plate_tilt_urad=(0.0, 0.0), plate_bow_um=0.0, plate_z_error_um=0.0)
    sr = ScannerRig(rig, sim, sc, seed=4)
    lcd = VirtualRig(replace(rig, projector=None, height=None), sim, 4)
    cal = calibrate_conventional_from(rig, SimulatedSource(lcd), HeightSweepSource(sr))
    assert list(cal.provenance["plate_xy_from"].values()) == ["camera model"] * 4
    assert cal.n_projector_points == 4 * cal.provenance["n_feature_pixels"]
    ratio = cal.rms_projector_px / cal.provenance["projector_sigma_rms_px"]
    assert 0.7 <= ratio <= 1.4, ratio


class _PlainSource:
    """A frame source with nothing but ``rig`` and ``frames`` (decode_projector filters its frames)."""

    def __init__(self, source):
        self.rig, self.frames = source.rig, source.frames


def test_decode_projector_reads_the_directions_asked_for():
    """x alone by default (the height map's decode, whatever else the sweep shows; a plain source's other
    frames are skipped alike); x and y: v_p against the simulator's truth within its predicted sigma
    (issue 34's band); y from a sweep without it: a ConfigError naming the key."""
    rig, sim, sc = scanner_preset("scanner-mild", 64, heights=3)
    sr = ScannerRig(rig, sim, sc, seed=1)
    a = decode_projector(HeightSweepSource(sr))
    b = decode_projector(_PlainSource(HeightSweepSource(sr)))
    np.testing.assert_array_equal(a.u, b.u)
    assert a.v is None and b.v is None
    both = decode_projector(HeightSweepSource(sr), directions=("x", "y"))
    assert np.array_equal(np.isfinite(both.u), np.isfinite(both.v)) and np.isfinite(both.v).mean() > 0.5
    o, d = sr.pixel_rays()
    v_true = np.stack([sr.project(sr.plate_point(o, d, k))[1] for k in range(3)])
    ok = np.isfinite(both.v)
    normalised = (both.v[ok] - v_true[ok]) / both.sigma_v[ok]
    assert 0.7 <= np.sqrt(np.mean(normalised ** 2)) <= 1.4
    spilled = decode_projector(HeightSweepSource(sr), directions=("x", "y"), spill=True)  # a big sensor's path
    for name in ("u", "v", "sigma_u", "sigma_v"):
        np.testing.assert_array_equal(getattr(spilled, name), getattr(both, name))
    with pytest.raises(ConfigError, match=r"projector\.directions"):
        decode_projector(HeightSweepSource(sr, ("x",)), directions=("x", "y"))
