"""The conventional structured-light calibration: camera and projector as two pinholes (docs/method.md section 9).

The comparison for the per-pixel scanner calibration. Camera and projector are each a pinhole with
Brown distortion (:class:`~ptpcore.pinhole.camera.PinholeModel`, OpenCV's convention) in the stage's
world frame (mm); the projector "sees" a world point at the projector coordinates ``(u_p, v_p)`` a
camera pixel decodes there. Points are measured by intersecting a camera pixel's ray with the
projector's surface of constant ``u_p`` (:meth:`ConventionalCalibration.points_from_up`).

This module is the mathematics only: the fit from feature points (:func:`fit_conventional`) and the
triangulation. Decoding a dataset's sweeps into feature points is
:func:`ptpcore.run.structured_light.calibrate_conventional` (the decoders live above this layer).

Why two separate fits, and where OpenCV's stereo calibration comes in: the feature points' world
coordinates are known (the LCD's decoded coordinates at the stage readings), not estimated, so the
reprojection error of the camera and that of the projector share no parameter. Their joint
minimum, with the projector's pose tied to the camera's (``R``, ``T`` of ``cv2.stereoCalibrate``),
is the pair of separate minima: with one "view" (the sweep's points as one non-coplanar target) the
relative pose is a reparametrisation of the two world poses. Each is fitted by a DLT start and
Levenberg-Marquardt (:func:`~ptpcore.pinhole.camera.fit_pinhole`, as 3DSTC), and
``cv2.stereoCalibrate`` (``CALIB_USE_INTRINSIC_GUESS``, one non-coplanar view) is run on the
projector's points as the independent cross-check (:func:`opencv_stereo_check`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ptpcore.pinhole.camera import PinholeFit, PinholeModel, fit_pinhole
from ptpcore.pinhole.lens import undistort_normalised

__all__ = ["ConventionalCalibration", "fit_conventional", "relative_pose", "opencv_stereo_check"]


@dataclass
class ConventionalCalibration:
    """A camera and a projector calibrated as two pinholes with Brown distortion.

    Attributes
    ----------
    camera : PinholeModel
        World (mm, stage frame) -> camera pixel ``(col, row)``.
    projector : PinholeModel
        World (mm) -> projector pixel ``(u_p, v_p)``.
    camera_fit, projector_fit : PinholeFit or None
        The two fits: ``param_names``, ``param_values``, ``param_std`` (1-sigma standard errors of every
        parameter), ``covariance``, ``residuals_px``, ``n_points``. None in a calibration built from known
        models (:meth:`from_models`: triangulation only).
    rms_camera_px : float
        RMS reprojection error per coordinate of the camera's feature points (camera px).
    rms_projector_px : float
        Same for the projector's (projector px).
    R_proj_cam : (3, 3) float64
        Rotation camera frame -> projector frame (``cv2.stereoCalibrate``'s ``R``).
    T_proj_cam : (3,) float64
        Translation (mm): ``x_proj = R_proj_cam x_cam + T_proj_cam``.
    relative_std : (6,) float64
        1-sigma of the relative pose: its rotation vector (rad) and ``T_proj_cam`` (mm), from the two
        fits' pose covariances (independent: their data's noise is the LCD's and ``u_p``'s).
    opencv_check : dict
        :func:`opencv_stereo_check`'s numbers (empty when not run).
    provenance : dict
        How the feature points were made (grid step, heights, where their X, Y came from, ...).
    """

    camera: PinholeModel
    projector: PinholeModel
    camera_fit: PinholeFit | None
    projector_fit: PinholeFit | None
    rms_camera_px: float
    rms_projector_px: float
    R_proj_cam: np.ndarray
    T_proj_cam: np.ndarray
    relative_std: np.ndarray
    opencv_check: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)

    def to_json_dict(self) -> dict:
        """JSON-ready record: both models, every parameter with its standard error, the relative pose,
        the RMS errors, point counts, the OpenCV check and the provenance."""
        out = {"camera": self.camera.to_dict(), "projector": self.projector.to_dict(),
               "rms_camera_px": self.rms_camera_px, "rms_projector_px": self.rms_projector_px,
               "n_camera_points": self.n_camera_points, "n_projector_points": self.n_projector_points,
               "R_proj_cam": self.R_proj_cam.tolist(), "T_proj_cam": self.T_proj_cam.tolist(),
               "relative_std": self.relative_std.tolist(), "opencv_check": self.opencv_check,
               "provenance": self.provenance}
        for name, fit in (("camera_fit", self.camera_fit), ("projector_fit", self.projector_fit)):
            if fit is not None:
                out[name] = {"param_names": list(fit.param_names), "param_values": fit.param_values.tolist(),
                             "param_std": fit.param_std.tolist()}
        return out

    @classmethod
    def from_models(cls, camera: PinholeModel, projector: PinholeModel) -> "ConventionalCalibration":
        """Known models, no fit (e.g. the simulator's truth): for :meth:`points_from_up`."""
        R, T = relative_pose(camera, projector)
        return cls(camera, projector, None, None, float("nan"), float("nan"), R, T, np.full(6, np.nan))

    @property
    def n_camera_points(self) -> int:
        """Feature points of the camera's fit (0 without a fit)."""
        return self.camera_fit.n_points if self.camera_fit is not None else 0

    @property
    def n_projector_points(self) -> int:
        """Feature points of the projector's fit (0 without a fit)."""
        return self.projector_fit.n_points if self.projector_fit is not None else 0

    def points_from_up(self, cols, rows, u_p, *, max_iter: int = 50, tol_px: float = 1e-9) -> np.ndarray:
        """World points where camera pixels' rays meet the projector's surface of constant ``u_p``.

        The camera pixel is undistorted and its ray cast. With the projector's distortion the set of
        world points lit by projector column ``u_p`` is not a plane: for a guess of ``v_p`` the
        projector point ``(u_p, v_p)`` is undistorted to normalised ``(x_n, y_n)``, the ray meets the
        plane ``x = x_n z`` (projector frame) through the projector's centre, and the point's own
        projection gives the next ``v_p``; at the fixed point the point projects to ``u_p`` exactly.
        Distortion couples ``u`` and ``v`` weakly, so a few iterations reach ``tol_px``.

        Parameters
        ----------
        cols, rows : (N,) array_like
            Camera pixel coordinates (px).
        u_p : (N,) array_like
            Decoded projector coordinate (projector px).
        max_iter : int
            Iteration limit on ``v_p``.
        tol_px : float
            Convergence threshold on ``v_p``'s change (projector px).

        Returns
        -------
        (N, 3) float64
            World points (mm); NaN rows where ``u_p`` is NaN, undistortion fails, the ray meets the
            surface behind either device, or the iteration does not converge.
        """
        cols, rows, u_p = (np.asarray(a, float).ravel() for a in np.broadcast_arrays(cols, rows, u_p))
        origin, direction = _camera_rays(self.camera, cols, rows)
        proj = self.projector
        a = origin @ proj.R.T + proj.tvec  # the ray in the projector's frame: a + t b
        b = direction @ proj.R.T
        K = proj.K
        v_p = np.full(u_p.shape, K[1, 2])
        done = np.zeros(u_p.shape, bool)
        t = np.full(u_p.shape, np.nan)
        points = np.full((u_p.size, 3), np.nan)
        for _ in range(max_iter):
            yd = (v_p - K[1, 2]) / K[1, 1]
            xn, _yn = undistort_normalised((u_p - K[0, 2] - K[0, 1] * yd) / K[0, 0], yd, proj.dist)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (xn * a[:, 2] - a[:, 0]) / (b[:, 0] - xn * b[:, 2])
            points = origin + t[:, None] * direction
            v_new = proj.project(np.where(np.isfinite(points), points, 0.0))[:, 1]
            v_new = np.where(np.isfinite(t), v_new, np.nan)
            done = np.abs(v_new - v_p) < tol_px
            v_p = v_new
            if np.all(done | ~np.isfinite(v_p)):
                break
        depth = a[:, 2] + t * b[:, 2]  # in front of the projector as well as the camera
        good = done & np.isfinite(t) & (t > 0) & (depth > 0)
        return np.where(good[:, None], points, np.nan)


def _camera_rays(camera: PinholeModel, cols: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera pixels' rays in the world: origins (N, 3) mm (the centre) and directions (N, 3), unnormalised
    (camera-frame z component 1); NaN directions where undistortion fails."""
    K = camera.K
    yd = (rows - K[1, 2]) / K[1, 1]
    xd = (cols - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    x, y = undistort_normalised(xd, yd, camera.dist)
    direction = np.stack([x, y, np.ones_like(x)], axis=1) @ camera.R  # R^T d, row-wise
    return np.broadcast_to(camera.centre, direction.shape), direction


def relative_pose(camera: PinholeModel, projector: PinholeModel) -> tuple[np.ndarray, np.ndarray]:
    """The projector's pose relative to the camera: ``x_proj = R x_cam + T``.

    Returns
    -------
    R : (3, 3) float64
    T : (3,) float64, mm
    """
    R = projector.R @ camera.R.T
    return R, projector.tvec - R @ camera.tvec


def _relative_vector(pose_c: np.ndarray, pose_p: np.ndarray) -> np.ndarray:
    """(6,) rotation vector and T of the relative pose from world poses ``(rvec, tvec)`` (6,) each."""
    Rc, Rp = cv2.Rodrigues(pose_c[:3])[0], cv2.Rodrigues(pose_p[:3])[0]
    R = Rp @ Rc.T
    return np.r_[cv2.Rodrigues(R)[0].ravel(), pose_p[3:] - R @ pose_c[3:]]


def _relative_std(camera_fit: PinholeFit, projector_fit: PinholeFit) -> np.ndarray:
    """1-sigma of the relative pose (rotation vector rad, T mm) by linear propagation of the two fits'
    pose covariances (central differences at a tenth of each parameter's own sigma)."""
    pc, pp = camera_fit.param_values[-6:], projector_fit.param_values[-6:]
    cov = np.zeros((12, 12))
    cov[:6, :6] = camera_fit.covariance[-6:, -6:]
    cov[6:, 6:] = projector_fit.covariance[-6:, -6:]
    steps = 0.1 * np.sqrt(np.diag(cov))
    x0 = np.r_[pc, pp]
    jac = np.zeros((6, 12))
    for j in range(12):
        dx = np.zeros(12)
        dx[j] = steps[j]
        hi, lo = x0 + dx, x0 - dx
        jac[:, j] = (_relative_vector(hi[:6], hi[6:]) - _relative_vector(lo[:6], lo[6:])) / (2 * steps[j])
    return np.sqrt(np.diag(jac @ cov @ jac.T))


def fit_conventional(camera_world, camera_pixels, projector_world, projector_pixels, *,
                     camera_fit: PinholeFit | None = None, provenance: dict | None = None) -> ConventionalCalibration:
    """Calibrate camera and projector from their feature points: DLT start and Levenberg-Marquardt each.

    Parameters
    ----------
    camera_world : (M, 3) array_like
        Non-coplanar world points (mm) the camera sees at ``camera_pixels``.
    camera_pixels : (M, 2) array_like
        Camera pixels ``(col, row)``.
    projector_world : (P, 3) array_like
        Non-coplanar world points (mm) the projector lights at ``projector_pixels``.
    projector_pixels : (P, 2) array_like
        Decoded ``(u_p, v_p)`` (projector px).
    camera_fit : PinholeFit, optional
        The camera's fit to these points when the caller has it already (the projector's points may have
        needed its rays).
    provenance : dict, optional
        Stored as :attr:`ConventionalCalibration.provenance`.

    Returns
    -------
    ConventionalCalibration
        Without :attr:`~ConventionalCalibration.opencv_check` (see :func:`opencv_stereo_check`).

    Raises
    ------
    ValueError
        Too few points, or (near-)coplanar ones (:func:`~ptpcore.pinhole.camera.dlt_initial_guess`).
    """
    if camera_fit is None:
        camera_fit = fit_pinhole(camera_world, camera_pixels)
    projector_fit = fit_pinhole(projector_world, projector_pixels)
    R, T = relative_pose(camera_fit.model, projector_fit.model)
    return ConventionalCalibration(
        camera=camera_fit.model, projector=projector_fit.model, camera_fit=camera_fit, projector_fit=projector_fit,
        rms_camera_px=camera_fit.reprojection_rms_px, rms_projector_px=projector_fit.reprojection_rms_px,
        R_proj_cam=R, T_proj_cam=T, relative_std=_relative_std(camera_fit, projector_fit),
        provenance=dict(provenance or {}))


def _intrinsics(K: np.ndarray, dist) -> np.ndarray:
    """(9,) ``fx, fy, cx, cy, k1, k2, p1, p2, k3``: :func:`~ptpcore.pinhole.camera.fit_pinhole`'s first values."""
    return np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.ravel(dist)[:5]]


def opencv_stereo_check(cal: ConventionalCalibration, world, camera_pixels, projector_pixels,
                        camera_size, projector_size) -> dict:
    """Cross-check with ``cv2.stereoCalibrate`` on one non-coplanar view, started from ``cal``'s intrinsics.

    The points seen by both (the height sweep's feature points) are one view; with
    ``CALIB_USE_INTRINSIC_GUESS`` OpenCV fits both intrinsics and distortions, the view's pose and the
    relative ``R``, ``T`` (skew fixed at 0, ``k1, k2, p1, p2, k3``). Each fitted value is compared with
    ``cal``'s in units of ``cal``'s standard error.

    Parameters
    ----------
    cal : ConventionalCalibration
    world : (P, 3) array_like
        The projector's feature points (mm).
    camera_pixels, projector_pixels : (P, 2) array_like
        Where the camera sees them (px) and their decoded ``(u_p, v_p)`` (projector px).
    camera_size, projector_size : (width, height)
        Image sizes (px). OpenCV takes one; it only matters without an intrinsic guess.

    Returns
    -------
    dict
        ``rms_px`` (OpenCV's per-point RMS over both devices), ``projector_max_z`` (largest
        ``|OpenCV - ours| / std`` over the projector's intrinsics and distortion: the same objective,
        so near 0), ``camera_max_z`` (camera intrinsics and distortion: OpenCV's from these points only,
        ours from the LCD sweep's, so within their std where the two sets differ), ``relative_max_z``
        (same over the relative rotation vector and ``T``, which carries OpenCV's camera pose), and
        OpenCV's values.
    """
    obj = [np.asarray(world, np.float32).reshape(-1, 1, 3)]
    img_c = [np.asarray(camera_pixels, np.float32).reshape(-1, 1, 2)]
    img_p = [np.asarray(projector_pixels, np.float32).reshape(-1, 1, 2)]
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_SKEW
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 500, 1e-15)
    rms, Kc, dc, Kp, dp, R, T, _E, _F = cv2.stereoCalibrate(
        obj, img_c, img_p, cal.camera.K.copy(), cal.camera.dist[:5].reshape(-1, 1).copy(), cal.projector.K.copy(),
        cal.projector.dist[:5].reshape(-1, 1).copy(), tuple(int(v) for v in camera_size), flags=flags,
        criteria=criteria)
    z_p = (_intrinsics(Kp, dp) - cal.projector_fit.param_values[:9]) / cal.projector_fit.param_std[:9]
    z_c = (_intrinsics(Kc, dc) - cal.camera_fit.param_values[:9]) / cal.camera_fit.param_std[:9]
    rel = np.r_[cv2.Rodrigues(R)[0].ravel(), np.ravel(T)]
    ours = np.r_[cv2.Rodrigues(cal.R_proj_cam)[0].ravel(), cal.T_proj_cam]
    z_r = (rel - ours) / cal.relative_std
    return {"rms_px": float(rms), "projector_max_z": float(np.max(np.abs(z_p))),
            "relative_max_z": float(np.max(np.abs(z_r))), "camera_max_z": float(np.max(np.abs(z_c))),
            "projector_K": Kp.tolist(), "projector_dist": np.ravel(dp).tolist(), "R": R.tolist(),
            "T": np.ravel(T).tolist(), "projector_size": [int(v) for v in projector_size]}
