"""Pinhole camera with Brown distortion: the "3DSTC" baseline (docs/method.md section 6).

The model follows OpenCV exactly: world points ``Xw`` (mm) go to the camera frame
by ``Xc = R(rvec) Xw + tvec``, to normalised coordinates ``(Xc/Zc, Yc/Zc)``, are
distorted with :mod:`ptpcore.pinhole.lens` (``k1, k2, p1, p2, k3[, k4, k5, k6]``) and
mapped to pixels ``(col, row)`` by ``K`` (``fx, fy, cx, cy``; no skew is fitted).

Calibration from M non-coplanar 3D points with known pixels: normalised DLT for
the initial guess (:func:`dlt_initial_guess`), then Levenberg-Marquardt over all
parameters minimising the reprojection error in pixels (:func:`fit_pinhole`).
:func:`opencv_calibrate` runs ``cv2.calibrateCamera`` on the same data as an
independent cross-check.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.linalg import rq
from scipy.optimize import least_squares

from ptpcore.pinhole.lens import distort_normalised, normalise_dist, undistort_normalised

__all__ = ["PinholeModel", "PinholeFit", "dlt_initial_guess", "fit_pinhole", "opencv_calibrate"]

_INTRINSIC_NAMES = ["fx", "fy", "cx", "cy"]
_DIST_NAMES = ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]
_POSE_NAMES = ["rx", "ry", "rz", "tx", "ty", "tz"]


# ----------------------------------------------------------------------------- validation

def _vector(a, n, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.size != n:
        raise ValueError(f"{name} must have {n} elements, got shape {arr.shape}")
    arr = arr.reshape(n).copy()
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def _points(a, ncols: int, name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != ncols:
        raise ValueError(f"{name} must have shape (M, {ncols}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def _correspondences(points_world, pixels, min_points: int = 6) -> tuple[np.ndarray, np.ndarray]:
    pw = _points(points_world, 3, "points_world")
    px = _points(pixels, 2, "pixels")
    if pw.shape[0] != px.shape[0]:
        raise ValueError(f"points_world and pixels must have the same length, got {pw.shape[0]} and {px.shape[0]}")
    if pw.shape[0] < min_points:
        raise ValueError(f"need at least {min_points} point correspondences, got {pw.shape[0]}")
    return pw, px


# ----------------------------------------------------------------------------- model

@dataclass
class PinholeModel:
    """Pinhole camera with Brown distortion, OpenCV convention.

    Attributes
    ----------
    K : (3, 3) float64
        Camera matrix in pixels, ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` (``s`` is 0 for fitted models).
    dist : (5,) or (8,) float64
        ``k1, k2, p1, p2, k3[, k4, k5, k6]`` (dimensionless).
    rvec : (3,) float64
        Rodrigues rotation vector, world -> camera (rad).
    tvec : (3,) float64
        Translation world -> camera (mm).
    """

    K: np.ndarray
    dist: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray

    def __post_init__(self):
        self.K = _vector(self.K, 9, "K").reshape(3, 3)
        if self.K[2, 0] != 0 or self.K[2, 1] != 0 or self.K[1, 0] != 0 or self.K[2, 2] != 1:
            raise ValueError("K must be upper triangular with K[2, 2] == 1")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise ValueError("K must have positive focal lengths fx, fy")
        d = np.asarray(self.dist, dtype=float).ravel()
        if d.size not in (5, 8):
            raise ValueError(f"dist must have 5 or 8 coefficients, got {d.size}")
        self.dist = _vector(d, d.size, "dist")
        self.rvec = _vector(self.rvec, 3, "rvec")
        self.tvec = _vector(self.tvec, 3, "tvec")

    @property
    def R(self) -> np.ndarray:
        """(3, 3) rotation matrix world -> camera."""
        return cv2.Rodrigues(self.rvec)[0]

    @property
    def centre(self) -> np.ndarray:
        """(3,) camera centre in world coordinates (mm)."""
        return -self.R.T @ self.tvec

    def project(self, points_world) -> np.ndarray:
        """Project world points to distorted pixel coordinates (same as ``cv2.projectPoints``).

        Parameters
        ----------
        points_world : (M, 3) array_like
            World points (mm).

        Returns
        -------
        (M, 2) float64
            Pixel coordinates ``(col, row)``.
        """
        pw = _points(points_world, 3, "points_world")
        pc = pw @ self.R.T + self.tvec
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
        xd, yd = distort_normalised(x, y, self.dist)
        K = self.K
        return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=-1)

    def pixel_to_world_at_z(self, cols, rows, z) -> tuple[np.ndarray, np.ndarray]:
        """Back-project pixels onto the world plane ``Z = z``.

        The pixel is undistorted (Newton, :func:`ptpcore.pinhole.lens.undistort_normalised`),
        the ray from the camera centre is cast and intersected with the plane.

        Parameters
        ----------
        cols, rows : array_like
            Pixel coordinates (px); broadcast together with ``z``.
        z : array_like
            World plane height (mm).

        Returns
        -------
        X, Y : ndarray
            World coordinates (mm) of the intersection, broadcast shape. NaN where
            undistortion fails, the ray is parallel to the plane, or the plane is
            behind the camera.
        """
        u, v, z = np.broadcast_arrays(np.asarray(cols, float), np.asarray(rows, float), np.asarray(z, float))
        K = self.K
        yd = (v - K[1, 2]) / K[1, 1]
        xd = (u - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        x, y = undistort_normalised(xd, yd, self.dist)
        Rt = self.R.T  # camera -> world
        dx = Rt[0, 0] * x + Rt[0, 1] * y + Rt[0, 2]
        dy = Rt[1, 0] * x + Rt[1, 1] * y + Rt[1, 2]
        dz = Rt[2, 0] * x + Rt[2, 1] * y + Rt[2, 2]
        c = self.centre
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (z - c[2]) / dz
        lam = np.where(np.isfinite(lam) & (lam > 0), lam, np.nan)
        return c[0] + lam * dx, c[1] + lam * dy

    def to_dict(self) -> dict:
        """JSON-friendly dict: ``{"K": 3x3 lists, "dist": [...], "rvec": [3], "tvec": [3]}``."""
        return {"K": self.K.tolist(), "dist": self.dist.tolist(), "rvec": self.rvec.tolist(), "tvec": self.tvec.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "PinholeModel":
        """Inverse of :meth:`to_dict`."""
        missing = {"K", "dist", "rvec", "tvec"} - set(d)
        if missing:
            raise ValueError(f"PinholeModel dict is missing keys {sorted(missing)}")
        return cls(K=d["K"], dist=d["dist"], rvec=d["rvec"], tvec=d["tvec"])


@dataclass
class PinholeFit:
    """Result of :func:`fit_pinhole`.

    Attributes
    ----------
    model : PinholeModel
        Fitted camera.
    reprojection_rms_px : float
        RMS reprojection error per coordinate, ``sqrt(SSR / (2 M))`` (px). OpenCV's
        ``calibrateCamera`` reports the per-point value, larger by ``sqrt(2)``.
    param_names : list of str
        ``fx, fy, cx, cy, k1, k2, p1, p2, k3[, k4, k5, k6], rx, ry, rz, tx, ty, tz``.
    param_values : (n,) float64
        Fitted values in ``param_names`` order (px, dimensionless, rad, mm).
    param_std : (n,) float64
        1-sigma uncertainties: ``cov = s^2 (J^T J)^-1``, ``s^2 = SSR / (2 M - n)``.
    n_points : int
        Number of correspondences M.
    residuals_px : (M, 2) float64
        Projected minus observed pixels.
    """

    model: PinholeModel
    reprojection_rms_px: float
    param_names: list[str]
    param_values: np.ndarray
    param_std: np.ndarray
    n_points: int
    residuals_px: np.ndarray
    covariance: np.ndarray = field(default=None, repr=False)  # (n, n), same order as param_names


# ----------------------------------------------------------------------------- DLT

def _hartley(p: np.ndarray) -> np.ndarray:
    """Similarity T (homogeneous) moving the centroid to 0 and the mean distance to sqrt(dim)."""
    dim = p.shape[1]
    c = p.mean(axis=0)
    s = np.sqrt(dim) / np.mean(np.linalg.norm(p - c, axis=1))
    T = np.eye(dim + 1)
    T[:dim, :dim] *= s
    T[:dim, dim] = -s * c
    return T


def dlt_initial_guess(points_world, pixels) -> PinholeModel:
    """Initial camera by the normalised direct linear transform (no distortion).

    Parameters
    ----------
    points_world : (M, 3) array_like
        Non-coplanar world points (mm), M >= 6.
    pixels : (M, 2) array_like
        Observed pixels ``(col, row)``.

    Returns
    -------
    PinholeModel
        ``K`` with positive diagonal and zero skew, ``det(R) = +1``, ``dist`` zeros (5,).

    Raises
    ------
    ValueError
        Bad shapes, NaN, fewer than 6 points or (near-)coplanar world points.
    """
    pw, px = _correspondences(points_world, pixels)
    centred = pw - pw.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[0] == 0 or sv[2] / sv[0] < 1e-3:
        raise ValueError(
            "DLT needs non-coplanar world points: the point cloud is (near-)planar "
            f"(singular value ratio {sv[2] / sv[0] if sv[0] else 0:.2e} < 1e-3)"
        )
    T3, T2 = _hartley(pw), _hartley(px)
    Xn = np.c_[pw, np.ones(len(pw))] @ T3.T
    un = (np.c_[px, np.ones(len(px))] @ T2.T)[:, :2]
    M = len(pw)
    A = np.zeros((2 * M, 12))
    A[0::2, 0:4] = Xn
    A[0::2, 8:12] = -un[:, :1] * Xn
    A[1::2, 4:8] = Xn
    A[1::2, 8:12] = -un[:, 1:] * Xn
    P = np.linalg.inv(T2) @ np.linalg.svd(A, full_matrices=False)[2][-1].reshape(3, 4) @ T3
    if np.linalg.det(P[:, :3]) < 0:  # P is defined up to sign; this choice gives det(R) = +1
        P = -P
    K, R = rq(P[:, :3])
    D = np.diag(np.sign(np.diag(K)))
    K, R = K @ D, D @ R
    t = np.linalg.solve(K, P[:, 3])
    K = K / K[2, 2]
    K[0, 1] = 0.0
    return PinholeModel(K=K, dist=np.zeros(5), rvec=cv2.Rodrigues(R)[0].ravel(), tvec=t)


# ----------------------------------------------------------------------------- LM fit

def fit_pinhole(points_world, pixels, *, rational: bool = False, init: PinholeModel | None = None) -> PinholeFit:
    """Calibrate a pinhole + Brown camera by Levenberg-Marquardt on the reprojection error.

    Parameters
    ----------
    points_world : (M, 3) array_like
        World points (mm), non-coplanar unless ``init`` is given.
    pixels : (M, 2) array_like
        Observed pixels ``(col, row)``.
    rational : bool
        Also fit ``k4, k5, k6`` (OpenCV rational model).
    init : PinholeModel, optional
        Starting point; default :func:`dlt_initial_guess`. Its skew is dropped.

    Returns
    -------
    PinholeFit

    Notes
    -----
    The residuals and the analytic Jacobian come from ``cv2.projectPoints``
    (identical to :meth:`PinholeModel.project`); ``x_scale="jac"`` copes with the
    very different parameter scales.
    """
    nd = 8 if rational else 5
    names = _INTRINSIC_NAMES + _DIST_NAMES[:nd] + _POSE_NAMES
    n = len(names)
    pw, px = _correspondences(points_world, pixels, min_points=max(6, n // 2 + 1))
    if init is None:
        init = dlt_initial_guess(pw, px)
    d0 = normalise_dist(init.dist)
    if not rational and np.any(d0[5:]):
        raise ValueError("init has non-zero k4..k6 but rational=False")
    K0 = init.K
    p0 = np.concatenate([[K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]], d0[:nd], init.rvec, init.tvec])
    obs = px.ravel()
    order = np.r_[6:10, 10:10 + nd, 0:6]  # cv2 jacobian columns: r, t, fx, fy, cx, cy, dist

    def unpack(p):
        K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
        return K, p[4:4 + nd], p[4 + nd:7 + nd], p[7 + nd:10 + nd]

    cache = {}

    def proj(p):
        key = p.tobytes()
        if key not in cache:
            K, d, r, t = unpack(p)
            ip, J = cv2.projectPoints(pw, r, t, K, d)
            cache.clear()
            cache[key] = (ip.ravel() - obs, J[:, order])
        return cache[key]

    sol = least_squares(lambda p: proj(p)[0], p0, jac=lambda p: proj(p)[1], method="lm",
                        x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=2000)
    if not sol.success:
        warnings.warn(f"fit_pinhole: Levenberg-Marquardt did not converge ({sol.message})", RuntimeWarning, stacklevel=2)
    p = sol.x
    res, J = proj(p)
    ssr = float(res @ res)
    s2 = ssr / (2 * len(pw) - n)
    norms = np.linalg.norm(J, axis=0)
    norms[norms == 0] = 1.0
    cov = s2 * np.linalg.pinv((J / norms).T @ (J / norms)) / np.outer(norms, norms)
    K, d, r, t = unpack(p)
    return PinholeFit(
        model=PinholeModel(K=K, dist=d, rvec=r, tvec=t),
        reprojection_rms_px=float(np.sqrt(ssr / res.size)),
        param_names=names,
        param_values=p.copy(),
        param_std=np.sqrt(np.diag(cov)),
        n_points=len(pw),
        residuals_px=res.reshape(-1, 2),
        covariance=cov,
    )


# ----------------------------------------------------------------------------- OpenCV cross-check

def opencv_calibrate(points_world, pixels, image_size, init: PinholeModel, *, rational: bool = False) -> PinholeModel:
    """Cross-check: ``cv2.calibrateCamera`` on one view holding all M points.

    Non-planar object points require ``CALIB_USE_INTRINSIC_GUESS``, so ``init``
    (e.g. from :func:`dlt_initial_guess`) supplies K and the distortion; OpenCV
    finds the pose itself (``solvePnP``). Skew is fixed at zero.

    Parameters
    ----------
    points_world : (M, 3) array_like
        World points (mm); passed to OpenCV as float32.
    pixels : (M, 2) array_like
        Observed pixels ``(col, row)``; passed as float32.
    image_size : (width, height)
        Image size in pixels.
    init : PinholeModel
        Initial intrinsics and distortion.
    rational : bool
        Use ``CALIB_RATIONAL_MODEL`` (8 coefficients).

    Returns
    -------
    PinholeModel
    """
    pw, px = _correspondences(points_world, pixels)
    size = np.asarray(image_size).ravel()
    if size.size != 2 or not np.all(size > 0):
        raise ValueError(f"image_size must be (width, height) > 0, got {image_size!r}")
    nd = 8 if rational else 5
    d0 = normalise_dist(init.dist)[:nd].reshape(-1, 1)
    K0 = init.K.copy()
    K0[0, 1] = 0.0
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_SKEW
    if rational:
        flags |= cv2.CALIB_RATIONAL_MODEL
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 500, 1e-15)
    _, K, d, rvecs, tvecs = cv2.calibrateCamera(
        [pw.astype(np.float32).reshape(-1, 1, 3)], [px.astype(np.float32).reshape(-1, 1, 2)],
        (int(size[0]), int(size[1])), K0, d0, flags=flags, criteria=criteria)
    return PinholeModel(K=K, dist=np.ravel(d)[:nd], rvec=np.ravel(rvecs[0]), tvec=np.ravel(tvecs[0]))
