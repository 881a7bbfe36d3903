"""Lens models beyond Brown plus a smooth field, for the virtual rig (issue 30).

The virtual rig's lens (:class:`ptpcore.simulate.virtual_rig.LensSettings`) is a
pinhole with Brown distortion, a smooth non-parametric field of a few
low-frequency modes and an optional non-central pupil. Three further terms let
a simulated rig leave that family, each off by default (a lens using none of
them renders bit for bit as before):

- ``projection = "equidistant"``: a fisheye-like mapping, image radius
  proportional to the angle off the axis (``r = f * theta``), in place of the
  pinhole's ``r = f * tan(theta)``.
- ``prism = (s1, s2, s3, s4)``: OpenCV's thin-prism terms,
  ``x_d += s1 r^2 + s2 r^4``, ``y_d += s3 r^2 + s4 r^4`` (normalised).
- ``ripple_px, ripple_wavelength_px``: a short-scale distortion field (a sum
  of :data:`RIPPLE_MODES` plane waves of random direction, wavelength within
  a factor two of ``ripple_wavelength_px``, RMS displacement ``ripple_px`` per
  axis), where the existing field varies only over the whole image.

The forward map, from a ray to the pixel that sees it (camera frame: ``x, y``
the ray's tangents ``X/Z, Y/Z``):

1. projection: pinhole ``(x, y)``; equidistant ``(x, y) * atan(r) / r``;
2. Brown plus thin prism in OpenCV's convention (normalised, ``dist`` and
   ``prism``);
3. pixels through ``K``;
4. the image-side fields: the observed pixel ``p`` is the one with
   ``p - F(p) = q``, where ``q`` is step 3's point and ``F`` the smooth field
   plus the ripple, both functions of the observed pixel.

The simulator needs the inverse (pixel -> ray, :func:`image_to_tangent` after
the fields are subtracted: exact, the fields being functions of the observed
pixel); the forward map (:func:`project_world`) is written independently and
checks the simulator's truth rays.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ptpcore.errors import ConfigError
from ptpcore.pinhole.lens import distort_normalised, normalise_dist, undistort_normalised

__all__ = ["PROJECTIONS", "RIPPLE_MODES", "NEW_LENS_KEYS", "uses_extensions", "compact_lens_record",
           "scale_lens_extensions", "distort", "undistort", "equidistant", "equidistant_inverse",
           "tangent_to_image", "image_to_tangent", "RippleField", "project_world"]

PROJECTIONS = ("perspective", "equidistant")
RIPPLE_MODES = 24
"""Plane waves summed in the short-scale field."""

NEW_LENS_KEYS = {"projection": "perspective", "prism": (0.0, 0.0, 0.0, 0.0), "ripple_px": 0.0,
                 "ripple_wavelength_px": 40.0}
"""The lens settings this module adds, with their defaults (off)."""


def uses_extensions(lens) -> bool:
    """Whether a :class:`LensSettings` uses any term of this module."""
    return (lens.projection != "perspective" or any(float(s) != 0.0 for s in lens.prism)
            or lens.ripple_px != 0.0)


def compact_lens_record(record: dict) -> dict:
    """A lens settings record (``asdict``) without this module's keys where they hold their defaults.

    ``truth.h5`` of a lens that uses none of them then stays byte for byte what
    it was before they existed; reading fills in the defaults.
    """
    out = {}
    for key, value in record.items():
        default = NEW_LENS_KEYS.get(key, None)
        if key in NEW_LENS_KEYS and _same(value, default):
            continue
        out[key] = value
    return out


def _same(a, b) -> bool:
    if isinstance(b, tuple):
        return tuple(float(v) for v in a) == b
    return a == b


def scale_lens_extensions(lens, scale: float):
    """``lens`` for a sensor ``scale`` times as wide over the same field of view: the ripple's
    amplitude and wavelength in pixels scale with it (the normalised terms do not change)."""
    return replace(lens, ripple_px=lens.ripple_px * scale, ripple_wavelength_px=lens.ripple_wavelength_px * scale)


# ---- normalised coordinates ---------------------------------------------------------------

def distort(x, y, dist, prism=(0.0, 0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Brown plus thin-prism distortion of normalised coordinates (OpenCV's convention).

    Parameters
    ----------
    x, y : array_like, same shape
        Undistorted normalised coordinates.
    dist : sequence
        ``k1, k2, p1, p2[, k3[, k4, k5, k6]]``.
    prism : (4,) float
        ``s1, s2, s3, s4``.

    Returns
    -------
    xd, yd : ndarray, same shape
    """
    xd, yd = distort_normalised(x, y, dist)
    s1, s2, s3, s4 = (float(s) for s in prism)
    r2 = np.asarray(x, dtype=float) ** 2 + np.asarray(y, dtype=float) ** 2
    return xd + r2 * (s1 + s2 * r2), yd + r2 * (s3 + s4 * r2)


def _jacobian(x, y, dist, prism, eps: float = 1e-7):
    """d(xd, yd)/d(x, y) of :func:`distort`: Brown's part by central differences of the closed form
    (step 1e-7: error ~1e-14 relative, Newton only needs a good direction), the prism's exactly."""
    xp, yp = distort_normalised(x + eps, y, dist)
    xm, ym = distort_normalised(x - eps, y, dist)
    j11, j21 = (xp - xm) / (2 * eps), (yp - ym) / (2 * eps)
    xp, yp = distort_normalised(x, y + eps, dist)
    xm, ym = distort_normalised(x, y - eps, dist)
    j12, j22 = (xp - xm) / (2 * eps), (yp - ym) / (2 * eps)
    s1, s2, s3, s4 = (float(s) for s in prism)
    r2 = x * x + y * y
    gx, gy = (s1 + 2 * s2 * r2) * 2, (s3 + 2 * s4 * r2) * 2
    return j11 + gx * x, j12 + gx * y, j21 + gy * x, j22 + gy * y


def undistort(xd, yd, dist, prism=(0.0, 0.0, 0.0, 0.0), *, max_iter: int = 60,
              tol: float = 1e-15) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort` by Newton's method, to machine precision.

    Without prism terms this is :func:`ptpcore.pinhole.lens.undistort_normalised`
    itself (bit for bit the simulator's inverse before this module).

    Returns
    -------
    x, y : ndarray
        NaN where Newton did not converge (the distortion is not invertible there).
    """
    if not any(float(s) != 0.0 for s in prism):
        return undistort_normalised(xd, yd, dist)
    normalise_dist(dist)  # validates the vector
    xd = np.asarray(xd, dtype=float)
    yd = np.asarray(yd, dtype=float)
    x, y = xd.copy(), yd.copy()
    for _ in range(max_iter):
        fx, fy = distort(x, y, dist, prism)
        ex, ey = fx - xd, fy - yd
        j11, j12, j21, j22 = _jacobian(x, y, dist, prism)
        det = j11 * j22 - j12 * j21
        dx = (j22 * ex - j12 * ey) / det
        dy = (-j21 * ex + j11 * ey) / det
        x, y = x - dx, y - dy
        if x.size == 0 or np.nanmax(np.abs(np.concatenate([np.ravel(dx), np.ravel(dy)]))) < tol:
            break
    fx, fy = distort(x, y, dist, prism)
    bad = ~(np.abs(fx - xd) + np.abs(fy - yd) < 1e-12)
    return np.where(bad, np.nan, x), np.where(bad, np.nan, y)


def equidistant(x, y) -> tuple[np.ndarray, np.ndarray]:
    """Equidistant projection of ray tangents ``(x, y)``: radius ``atan(r)`` in place of ``r``."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    r = np.hypot(x, y)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(r > 0, np.arctan(r) / np.where(r > 0, r, 1.0), 1.0)
    return x * scale, y * scale


def equidistant_inverse(a, b) -> tuple[np.ndarray, np.ndarray]:
    """Ray tangents of equidistant image points ``(a, b)`` (radius ``theta`` < pi/2, radians)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    theta = np.hypot(a, b)
    if np.any(theta >= np.pi / 2):
        raise ConfigError("the equidistant lens sees 90 degrees or more off its axis at some pixel:"
                          " lengthen its focal length")
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(theta > 0, np.tan(theta) / np.where(theta > 0, theta, 1.0), 1.0)
    return a * scale, b * scale


def tangent_to_image(x, y, lens, dist) -> tuple[np.ndarray, np.ndarray]:
    """Forward map, steps 1 and 2: ray tangents -> distorted normalised image coordinates."""
    if lens.projection == "equidistant":
        x, y = equidistant(x, y)
    return distort(x, y, dist, lens.prism)


def image_to_tangent(xd, yd, lens, dist) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`tangent_to_image` (exact to machine precision; NaN where not invertible).

    A lens using none of this module's terms goes through
    :func:`ptpcore.pinhole.lens.undistort_normalised` exactly as before.
    """
    if lens.projection not in PROJECTIONS:
        raise ConfigError(f"lens projection must be one of {PROJECTIONS}, got {lens.projection!r}")
    x, y = undistort(xd, yd, dist, lens.prism)
    if lens.projection == "equidistant":
        lost = ~(np.isfinite(x) & np.isfinite(y))
        x, y = equidistant_inverse(np.where(lost, 0.0, x), np.where(lost, 0.0, y))
        x, y = np.where(lost, np.nan, x), np.where(lost, np.nan, y)
    return x, y


# ---- the short-scale field ----------------------------------------------------------------

class RippleField:
    """A short-scale image-side distortion field (pixels), a seeded sum of plane waves.

    ``dx(p) = A * sum_i a_i cos(k_i . p + phi_i)``, ``dy`` likewise with its own
    amplitudes and phases; ``|k_i| = 2 pi / lambda_i`` with ``lambda_i``
    log-uniform within a factor two around the wavelength, directions uniform.
    ``A`` makes the RMS over random phases of each axis ``amplitude_px``.

    Parameters
    ----------
    amplitude_px : float
        RMS displacement per axis (camera px).
    wavelength_px : float
        Typical wavelength (camera px).
    rng : numpy.random.Generator
        Draws the modes.

    Raises
    ------
    ConfigError
        The field folds the image (its largest gradient reaches 0.5: the
        pixel -> ray map would stop being one to one).
    """

    def __init__(self, amplitude_px: float, wavelength_px: float, rng: np.random.Generator):
        if not (amplitude_px >= 0 and wavelength_px > 0):
            raise ConfigError(f"ripple amplitude must be >= 0 and wavelength > 0 px, got {amplitude_px},"
                              f" {wavelength_px}")
        n = RIPPLE_MODES
        lam = wavelength_px * 2.0 ** rng.uniform(-0.5, 0.5, n)
        ang = rng.uniform(0, 2 * np.pi, n)
        self.k = (2 * np.pi / lam)[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)  # (n, 2), rad/px
        self.phase = rng.uniform(0, 2 * np.pi, (2, n))
        amp = rng.normal(size=(2, n))
        # E[cos^2] = 1/2: RMS of axis a is sqrt(sum amp_a^2 / 2) * A.
        self.amp = amp * (amplitude_px / np.sqrt(0.5 * np.sum(amp ** 2, axis=1, keepdims=True)))
        if self.max_gradient() >= 0.5:
            raise ConfigError(f"ripple of {amplitude_px:g} px at {wavelength_px:g} px folds the image"
                              " (gradient >= 0.5): lower the amplitude or lengthen the wavelength")

    def max_gradient(self) -> float:
        """An upper bound of the field's largest derivative (px per px)."""
        kn = np.hypot(self.k[:, 0], self.k[:, 1])
        return float(max(np.sum(np.abs(self.amp[a]) * kn) for a in range(2)))

    def __call__(self, cols, rows) -> tuple[np.ndarray, np.ndarray]:
        """Displacement ``(dx, dy)`` (px) at image points, same shape as ``cols``/``rows`` broadcast."""
        cols = np.asarray(cols, dtype=float)
        rows = np.asarray(rows, dtype=float)
        shape = np.broadcast(cols, rows).shape
        dx = np.zeros(shape)
        dy = np.zeros(shape)
        for i in range(self.k.shape[0]):
            arg = self.k[i, 0] * cols + self.k[i, 1] * rows
            dx += self.amp[0, i] * np.cos(arg + self.phase[0, i])
            dy += self.amp[1, i] * np.cos(arg + self.phase[1, i])
        return dx, dy


# ---- the direct projection (checks the truth) ----------------------------------------------

def project_world(vr, points, *, iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """The pixel that sees each world point, by the forward map (independent of ``vr.rays``).

    Parameters
    ----------
    vr : VirtualRig
    points : (..., 3) float64, mm
        World points (LCD frame at stage reading 0, docs/method.md section 2).
    iterations : int
        Fixed-point iterations for the non-central pupil and the image-side fields
        (each a contraction: the fields' gradients stay below 0.5).

    Returns
    -------
    cols, rows : (...) float64
        Image coordinates (pixel centres at integers).
    """
    lens = vr.settings.lens
    p_cam = (np.asarray(points, dtype=float) - vr.centre) @ vr.R.T
    x = p_cam[..., 0] / p_cam[..., 2]
    y = p_cam[..., 1] / p_cam[..., 2]
    if lens.pupil_shift_mm:
        for _ in range(iterations):  # the ray leaves the pupil at (0, 0, shift * r^2), r its own tangent
            z0 = lens.pupil_shift_mm * (x * x + y * y)
            x, y = p_cam[..., 0] / (p_cam[..., 2] - z0), p_cam[..., 1] / (p_cam[..., 2] - z0)
    xd, yd = tangent_to_image(x, y, lens, vr.dist)
    qc = vr.K[0, 0] * xd + vr.K[0, 2]
    qr = vr.K[1, 1] * yd + vr.K[1, 2]
    cols, rows = qc.copy(), qr.copy()
    for _ in range(iterations):  # p = q + F(p)
        fx, fy = vr.distortion_field(cols, rows)
        cols, rows = qc + fx, qr + fy
    return cols, rows
