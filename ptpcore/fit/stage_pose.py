"""Stage pose refinement: each position's six pose errors from the straightness of the rays.

docs/method.md section 8. At stage position ``k`` the LCD may sit off its reading
``z_k`` by a rigid pose error: ``dx, dy`` (run-out, um), ``dz`` (height error,
um) and ``pitch, yaw, roll`` (urad, about the LCD centre). A sample decoded at
LCD-frame point ``(u, v)`` (mm from the LCD centre) then lies, to first order, at

    X = X_obs + dx - roll*v,   Y = Y_obs + dy + roll*u,   Z = z_k + dz + pitch*v - yaw*u,

and every pixel's samples lie on one straight ray ``X = x0 + sx*Z``,
``Y = y0 + sy*Z``. Many pixels over-determine the 6 K pose errors, up to what
no data can tell apart (a choice of world frame): a common offset and a
linear trend in z of ``dx``, ``dy`` and ``dz`` (skew and scale), a common
``pitch``, ``yaw``, ``roll`` (a rotated frame), and a linear trend of the angles
(seen only through products of two ray slopes, second order: too weak to
keep: left free, its sigma is thousands of urad). The fit fixes those twelve
by constraints (``sum_k p_k = 0`` and ``sum_k (z_k - mean z) p_k = 0`` for
each of the six), so the estimates are the true errors minus their
least-squares constant-plus-linear part, up to the small seen part of the
angles' trend (about 1 urad of a 30 urad trend, tests/fit/test_stage_pose.py).

The fit runs over a subsample of pixels by variable projection: for given
poses every pixel's ray is its straight-line fit in closed form, so
:func:`scipy.optimize.least_squares` sees only the 6 K pose errors (and the
gauge constraints as residuals); its Jacobian is that of the projected
residuals. The poses' covariance is ``s2 (J^T J)^-1``: the Schur complement
of the joint problem's normal matrix, i.e. the pose block of its inverse.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from ptpcore.io.samples import SampleStack
from ptpcore.rig.rigfile import Rig

__all__ = ["StagePose", "refine_stage", "apply_stage_pose", "refine_and_correct", "gauge_part_removed",
           "describe_stage_pose", "POSE_NAMES", "N_GAUGE"]

POSE_NAMES = ("dx_um", "dy_um", "dz_um", "pitch_urad", "yaw_urad", "roll_urad")
_GAUGE_WEIGHT = 1e3
N_GAUGE = 12
"""Pose combinations no data can tell apart: a constant and a linear trend in z of each of the six."""


@dataclass
class StagePose:
    """Estimated per-position pose errors.

    Attributes
    ----------
    pose, sigma : (K, 6) float64
        ``dx, dy, dz`` (um), ``pitch, yaw, roll`` (urad) and their 1-sigma
        uncertainties, in the gauge of the module docstring. Positions without
        data hold 0 (and sigma NaN).
    rms_um : float
        RMS residual of the samples to their rays after the fit (um).
    n_pixels : int
        Pixels in the fit.
    """

    pose: np.ndarray
    sigma: np.ndarray
    rms_um: float
    n_pixels: int

    def record(self, shift_um=None) -> dict:
        """JSON-ready summary for ``/provenance`` ``corrections``.

        ``shift_um`` (H, W), optional: each pixel's largest shift (um), summarised as
        ``median_um``, ``max_um`` over the pixels that moved.
        """
        rec = {"kind": "stage_refinement", "n_pixels": self.n_pixels, "rms_um": self.rms_um,
               "max_abs": dict(zip(POSE_NAMES, np.max(np.abs(self.pose), axis=0).tolist())),
               "median_sigma": dict(zip(POSE_NAMES, np.nanmedian(self.sigma, axis=0).tolist()))}
        if shift_um is not None:
            s = shift_um[np.isfinite(shift_um) & (shift_um > 0)]
            rec.update(pixels=int(s.size), median_um=float(np.median(s)) if s.size else 0.0,
                       max_um=float(np.max(s)) if s.size else 0.0)
        return rec


def gauge_part_removed(pose, z) -> np.ndarray:
    """``pose`` (K, 6) minus what no data can tell apart: the least-squares constant + linear trend in ``z`` of each."""
    pose = np.array(pose, dtype=float)
    z = np.asarray(z, dtype=float)
    a = np.stack([np.ones_like(z), z - z.mean()], axis=1)
    for j in range(6):
        pose[:, j] -= a @ np.linalg.lstsq(a, pose[:, j], rcond=None)[0]
    return pose


def _pick_pixels(samples: SampleStack, n_pixels: int, min_valid: int, rng) -> np.ndarray:
    """Flat indices of up to ``n_pixels`` pixels with at least ``min_valid`` valid samples."""
    n_valid = np.asarray(samples.valid).sum(axis=0).ravel()
    good = np.flatnonzero(n_valid >= min_valid)
    if good.size > n_pixels:
        good = np.sort(rng.choice(good, size=n_pixels, replace=False))
    return good


def _observations(samples: SampleStack, rig: Rig, flat: np.ndarray):
    """Observed X, Y (N, K) mm, validity, and LCD-frame u, v from the LCD centre (mm)."""
    h, w = samples.shape
    r, c = np.divmod(flat, w)
    ok = np.asarray(samples.valid[:, r, c]).T
    x = samples.x_ref[r, c][:, None] + np.asarray(samples.x[:, r, c], dtype=float).T
    y = samples.y_ref[r, c][:, None] + np.asarray(samples.y[:, r, c], dtype=float).T
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    z = np.asarray(samples.z, dtype=float)
    u = x - a * z[None] - (rig.lcd.width - 1) / 2 * px
    v = y - b * z[None] - (rig.lcd.height - 1) / 2 * py
    return x, y, ok, np.where(ok, u, 0.0), np.where(ok, v, 0.0)


class _Problem:
    """Residuals (um) of N pixels' samples to their rays, as a function of the K positions' poses only.

    For given poses every pixel's ray is its straight-line fit (closed form), so
    the fit runs over the 6 K pose errors alone (variable projection), with
    the gauge constraints as extra residuals.
    """

    def __init__(self, x, y, ok, u, v, z):
        self.n, self.k = x.shape
        self.i, self.kk = np.nonzero(ok)
        self.x, self.y = x[ok], y[ok]
        self.u, self.v = u[ok], v[ok]
        self.z = z[self.kk]
        self.count = np.bincount(self.i, minlength=self.n).astype(float)
        zc = z - z.mean()
        span = max(float(np.ptp(z)), 1e-9)
        self.gauge = np.zeros((N_GAUGE, 6 * self.k))
        for j in range(6):
            self.gauge[2 * j, j::6] = 1.0 / self.k
            self.gauge[2 * j + 1, j::6] = zc / span / self.k
        self.gauge *= _GAUGE_WEIGHT

    def _line_residual(self, t, vals):
        """``vals`` minus each pixel's least-squares line in ``t`` (both per observation)."""
        n = self.n
        st = np.bincount(self.i, t, n)
        stt = np.bincount(self.i, t * t, n)
        sv = np.bincount(self.i, vals, n)
        stv = np.bincount(self.i, t * vals, n)
        det = self.count * stt - st * st
        slope = (self.count * stv - st * sv) / det
        icpt = (sv - slope * st) / self.count
        return vals - icpt[self.i] - slope[self.i] * t, slope

    def rays(self, p):
        """(N, 4) ``x0, sx, y0, sy`` of every pixel for poses ``p`` (6K,)."""
        q = p.reshape(self.k, 6)[self.kk]
        zt = self.z + 1e-3 * q[:, 2] + 1e-6 * (q[:, 3] * self.v - q[:, 4] * self.u)
        xs = self.x + 1e-3 * q[:, 0] - 1e-6 * q[:, 5] * self.v
        ys = self.y + 1e-3 * q[:, 1] + 1e-6 * q[:, 5] * self.u
        return zt, xs, ys

    def residuals(self, p) -> np.ndarray:
        zt, xs, ys = self.rays(p)
        rx, _ = self._line_residual(zt, xs)
        ry, _ = self._line_residual(zt, ys)
        return np.concatenate([1e3 * rx, 1e3 * ry, self.gauge @ p])


def _pose_covariance(jac: np.ndarray, s2: float) -> np.ndarray:
    """(6K, 6K) covariance of the poses: ``s2 * (J^T J)^-1``, J the projected Jacobian with the gauge rows."""
    return s2 * np.linalg.inv(jac.T @ jac)


def refine_stage(samples: SampleStack, rig: Rig, *, n_pixels: int = 3000, seed: int = 0,
                 min_valid: int | None = None, clip_sigma: float = 5.0) -> StagePose:
    """Estimate every position's six pose errors from the straightness of many pixels' rays.

    Parameters
    ----------
    samples : SampleStack
        Decoded samples (cover glass already removed).
    rig : Rig
        For the stage direction and the LCD centre.
    n_pixels : int
        Pixels drawn (at random, seeded) into the joint fit.
    seed : int
    min_valid : int, optional
        Least valid samples of a drawn pixel (default: all but two positions, at least 3).
    clip_sigma : float
        Samples whose residual exceeds this many RMS are dropped and the fit run again.

    Returns
    -------
    StagePose

    Raises
    ------
    ValueError
        Fewer than 4 positions or too few pixels to over-determine the poses.
    """
    k = len(samples.z)
    if k < 4:
        raise ValueError(f"stage refinement needs at least 4 positions, got {k}")
    rng = np.random.default_rng([seed, 14])
    flat = _pick_pixels(samples, n_pixels, min_valid if min_valid is not None else max(3, k - 2), rng)
    if flat.size < 20:
        raise ValueError(f"stage refinement needs at least 20 pixels seen at most positions, got {flat.size}")
    x, y, ok, u, v = _observations(samples, rig, flat)
    z = np.asarray(samples.z, dtype=float)
    p0 = np.zeros(6 * k)
    for _round in range(3):
        prob = _Problem(x, y, ok, u, v, z)
        # Poses only (rays projected out): 6 K unknowns, a dense Jacobian, a few Gauss-Newton steps.
        sol = least_squares(prob.residuals, p0, jac="2-point", method="lm", x_scale=1.0)
        p0 = sol.x
        res = sol.fun[:-N_GAUGE].reshape(2, -1)
        rms = float(np.sqrt(np.mean(res ** 2)))
        bad = np.max(np.abs(res), axis=0) > clip_sigma * rms
        if not bad.any():
            break
        ok = ok.copy()
        ok[prob.i[bad], prob.kk[bad]] = False
        keep = ok.sum(axis=1) >= 3
        x, y, ok, u, v = x[keep], y[keep], ok[keep], u[keep], v[keep]
    dof = max(1, res.size - (4 * prob.n + 6 * k - N_GAUGE))
    s2 = float(np.sum(res ** 2) / dof)
    cov = _pose_covariance(sol.jac, s2)
    sigma = np.sqrt(np.clip(np.diag(cov), 0.0, None)).reshape(k, 6)
    return StagePose(sol.x.reshape(k, 6).copy(), sigma, float(np.sqrt(s2)), int(prob.n))


def apply_stage_pose(samples: SampleStack, rig: Rig, pose: StagePose, slopes) -> SampleStack:
    """Samples moved from each position's true pose to its reading, along every pixel's ray.

    Parameters
    ----------
    samples : SampleStack
    rig : Rig
    pose : StagePose
    slopes : (2,) tuple of (H, W) float64
        Every pixel's ``dX/dZ``, ``dY/dZ`` (:func:`ptpcore.fit.glass.pixel_slopes`).

    Returns
    -------
    SampleStack
        New ``x, y`` arrays (in memory); ``corrections`` gains ``stage_refinement``
        (with each pixel's largest shift summarised: median and max, um).
    """
    sx, sy = (np.nan_to_num(s) for s in slopes)
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    xs = np.empty(samples.x.shape, np.float32)
    ys = np.empty(samples.y.shape, np.float32)
    longest = np.zeros(samples.shape)
    for k, zk in enumerate(np.asarray(samples.z, dtype=float)):
        xa, ya = samples.absolute(k)
        u = xa - a * zk - (rig.lcd.width - 1) / 2 * px
        v = ya - b * zk - (rig.lcd.height - 1) / 2 * py
        q = pose.pose[k]
        dzt = 1e-3 * q[2] + 1e-6 * (q[3] * v - q[4] * u)
        ddx = 1e-3 * q[0] - 1e-6 * q[5] * v - sx * dzt
        ddy = 1e-3 * q[1] + 1e-6 * q[5] * u - sy * dzt
        xs[k] = samples.x[k] + ddx
        ys[k] = samples.y[k] + ddy
        longest = np.fmax(longest, np.where(np.asarray(samples.reasons[k]) == 0, 1e3 * np.hypot(ddx, ddy), 0.0))
    return replace(samples, x=xs, y=ys,
                   corrections={**samples.corrections, "stage_refinement": pose.record(longest)})


def refine_and_correct(samples: SampleStack, rig: Rig, *, seed: int = 0,
                       n_pixels: int = 1500) -> tuple[SampleStack, StagePose]:
    """:func:`refine_stage`, then :func:`apply_stage_pose` with every pixel's own slopes.

    Returns
    -------
    corrected : SampleStack
    pose : StagePose
    """
    from ptpcore.fit.glass import pixel_slopes

    est = refine_stage(samples, rig, n_pixels=n_pixels, seed=seed)
    return apply_stage_pose(samples, rig, est, pixel_slopes(samples)), est


def describe_stage_pose(pose: np.ndarray, sigma: np.ndarray, z_mm) -> list[str]:
    """One line per position: its six estimates ± 1 sigma (um, urad)."""
    lines = []
    for k, zk in enumerate(np.asarray(z_mm, dtype=float)):
        cells = "  ".join(f"{n.split('_')[0]} {pose[k, j]:+.2f}±{sigma[k, j]:.2f}" for j, n in enumerate(POSE_NAMES))
        lines.append(f"z={zk:g}: {cells}")
    return lines
