"""Brown-Conrady lens distortion in OpenCV's convention, vectorised.

Normalised image coordinates ``(x, y)`` are ``(X/Z, Y/Z)`` in the camera frame.
The distortion vector follows OpenCV: ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``.

Both the simulator (pixel -> ray) and the 3DSTC pinhole model (projection and
its inverse) use these functions, so the two can never disagree on the
convention.
"""

from __future__ import annotations

import numpy as np

__all__ = ["normalise_dist", "distort_normalised", "undistort_normalised"]


def normalise_dist(dist) -> np.ndarray:
    """Return the distortion vector padded to 8 coefficients (float64).

    Parameters
    ----------
    dist : sequence of 0, 4, 5 or 8 floats
        ``k1, k2, p1, p2[, k3[, k4, k5, k6]]``.

    Returns
    -------
    (8,) float64
    """
    d = np.zeros(8)
    arr = np.asarray(dist if dist is not None else [], dtype=float).ravel()
    if arr.size not in (0, 4, 5, 8):
        raise ValueError(f"distortion vector must have 4, 5 or 8 coefficients, got {arr.size}")
    d[: arr.size] = arr
    return d


def _radial(r2: np.ndarray, d: np.ndarray):
    """Radial factor R(r2) and its derivative dR/d(r2)."""
    k1, k2, _, _, k3, k4, k5, k6 = d
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
    return num / den, (dnum * den - num * dden) / (den * den)


def distort_normalised(x: np.ndarray, y: np.ndarray, dist) -> tuple[np.ndarray, np.ndarray]:
    """Apply distortion to undistorted normalised coordinates.

    Parameters
    ----------
    x, y : array_like, same shape
        Undistorted normalised coordinates (dimensionless).
    dist : sequence
        OpenCV distortion vector.

    Returns
    -------
    xd, yd : ndarray
        Distorted normalised coordinates, same shape as ``x``.
    """
    d = normalise_dist(dist)
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    p1, p2 = d[2], d[3]
    r2 = x * x + y * y
    radial, _ = _radial(r2, d)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def _jacobian(x, y, d):
    p1, p2 = d[2], d[3]
    r2 = x * x + y * y
    radial, dradial = _radial(r2, d)
    rx = 2.0 * x * dradial
    ry = 2.0 * y * dradial
    j11 = radial + x * rx + 2.0 * p1 * y + 6.0 * p2 * x
    j12 = x * ry + 2.0 * p1 * x + 2.0 * p2 * y
    j21 = y * rx + 2.0 * p1 * x + 2.0 * p2 * y
    j22 = radial + y * ry + 6.0 * p1 * y + 2.0 * p2 * x
    return j11, j12, j21, j22


def undistort_normalised(xd, yd, dist, *, max_iter: int = 50, tol: float = 1e-14):
    """Invert :func:`distort_normalised` by Newton's method.

    Written by hand because ``cv2.undistortPoints`` uses a fixed-point
    iteration with a fixed iteration count that does not reach machine
    precision (or diverges) for strong distortion, and the simulator's
    ground truth must be exact. Each point is an independent 2x2 system, so
    the Newton step is solved in closed form for all points at once.

    Parameters
    ----------
    xd, yd : array_like, same shape
        Distorted normalised coordinates.
    dist : sequence
        OpenCV distortion vector.
    max_iter : int
        Iteration limit.
    tol : float
        Convergence threshold on the largest step (normalised units).

    Returns
    -------
    x, y : ndarray
        Undistorted normalised coordinates; NaN where Newton did not
        converge (outside the region where the distortion is invertible).
    """
    d = normalise_dist(dist)
    xd = np.asarray(xd, dtype=float)
    yd = np.asarray(yd, dtype=float)
    x = xd.copy()
    y = yd.copy()
    if not np.any(d):
        return x, y
    step = np.inf
    for _ in range(max_iter):
        fx, fy = distort_normalised(x, y, d)
        ex, ey = fx - xd, fy - yd
        j11, j12, j21, j22 = _jacobian(x, y, d)
        det = j11 * j22 - j12 * j21
        dx = (j22 * ex - j12 * ey) / det
        dy = (-j21 * ex + j11 * ey) / det
        x = x - dx
        y = y - dy
        step = np.nanmax(np.abs(np.concatenate([np.ravel(dx), np.ravel(dy)]))) if x.size else 0.0
        if step < tol:
            break
    fx, fy = distort_normalised(x, y, d)
    bad = ~(np.abs(fx - xd) + np.abs(fy - yd) < 1e-9)
    if np.any(bad):
        x = np.where(bad, np.nan, x)
        y = np.where(bad, np.nan, y)
    return x, y
