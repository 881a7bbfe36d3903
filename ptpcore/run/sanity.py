"""Checks of the decoded samples against what the geometry allows, before a LUT is fitted.

Two mistakes give a LUT that looks fine and is wrong:

- ``z_mm`` listed in reverse (readings that shrink as the screen moves away
  from the camera). Every pixel's ray is a straight line ``X = A + B z``; the
  rays of all pixels meet at the camera's centre, ``Z_c = -cov(A, B) / var(B)``
  (``A_i + B_i Z_c`` is the same point for every pixel). The camera is on one
  side of every screen position (:data:`CAMERA_SIDE`); readings in reverse put
  ``Z_c`` on the other side (``Z_c' = z_min + z_max - Z_c``). That is an error
  naming ``z_mm``.
- two positions whose decoded maps agree although their readings differ (a
  stuck stage, images copied twice). Across the image their samples move far
  less differently than the rays' slopes say they must: a
  :class:`~ptpcore.errors.DataWarning` naming both.

:func:`check_samples` runs both on a subsample of the pixels (fast on any sensor).
"""

from __future__ import annotations

import warnings

import numpy as np

from ptpcore.errors import ConfigError, DataWarning
from ptpcore.io.samples import SampleStack

__all__ = ["check_samples", "convergence_z", "STUCK_RATIO", "CAMERA_SIDE"]

CAMERA_SIDE = -1
"""The side of the screen positions the camera's centre is on: -1 below the smallest reading, +1 above the largest.

docs/method.md section 2: the camera at Z < 0, readings growing as the screen moves
away from it. The engine's virtual rig (``ptpcore.simulate``) follows it.
"""

STUCK_RATIO = 0.1
"""Two positions are 'the same' when their maps' difference varies by less than this fraction of the expected."""

_MAX_PIXELS = 20000
_PARALLEL = 100.0  # rays converging farther than this many z ranges away: nearly parallel, sense not judged


def _subsample(samples: SampleStack, positions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``z (K,)`` and world ``X, Y (K, P)`` (float64, NaN where invalid) on at most ~20000 pixels."""
    ks = np.arange(len(samples.z)) if positions is None else np.asarray(list(positions), int)
    h, w = samples.x_ref.shape
    step = max(1, int(np.ceil(np.sqrt(h * w / _MAX_PIXELS))))
    xr = np.asarray(samples.x_ref[::step, ::step], np.float64).reshape(-1)
    yr = np.asarray(samples.y_ref[::step, ::step], np.float64).reshape(-1)
    # One map at a time with a file read (SampleStack.plane): strided indexing of a spilled stack's
    # memory map faulted in nearly every page of x, y and reasons (1.4 GB resident at 5 MP x 31).
    xs = np.stack([samples.plane("x", k)[::step, ::step].astype(np.float64).reshape(-1) for k in ks]) + xr
    ys = np.stack([samples.plane("y", k)[::step, ::step].astype(np.float64).reshape(-1) for k in ks]) + yr
    bad = np.stack([samples.plane("reasons", k)[::step, ::step].reshape(-1) != 0 for k in ks])
    xs[bad] = np.nan
    ys[bad] = np.nan
    return np.asarray(samples.z, float)[ks], xs, ys


def _lines(z: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel least-squares lines ``v = A + B z`` over the finite samples (NaN with fewer than 2)."""
    ok = np.isfinite(v)
    zz = np.where(ok, z[:, None], 0.0)
    vv = np.where(ok, v, 0.0)
    n = ok.sum(axis=0)
    sz, szz, sv, szv = zz.sum(0), (zz * zz).sum(0), vv.sum(0), (zz * vv).sum(0)
    den = n * szz - sz * sz
    with np.errstate(invalid="ignore", divide="ignore"):
        b = np.where((n >= 2) & (den > 1e-12), (n * szv - sz * sv) / den, np.nan)
        a = (sv - b * sz) / n
    return a, b


def convergence_z(z: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> float | None:
    """Where the pixels' rays meet along Z (mm), or None when it cannot be told.

    Parameters
    ----------
    z : (K,) float
        Stage readings.
    xs, ys : (K, P) float
        World X and Y of P pixels at every position (NaN where invalid).

    Returns
    -------
    float or None
        ``Z_c = -(cov(Ax, Bx) + cov(Ay, By)) / (var(Bx) + var(By))`` over the
        pixels, from their lines ``X = Ax + Bx z`` and ``Y = Ay + By z``.
    """
    if np.ptp(z) <= 0:
        return None
    ax, bx = _lines(z, xs)
    ay, by = _lines(z, ys)
    ok = np.isfinite(ax) & np.isfinite(bx) & np.isfinite(ay) & np.isfinite(by)
    if ok.sum() < 10:
        return None
    ax, bx, ay, by = ax[ok], bx[ok], ay[ok], by[ok]
    var = np.var(bx) + np.var(by)
    if var <= 0:
        return None
    cov = np.mean((ax - ax.mean()) * (bx - bx.mean())) + np.mean((ay - ay.mean()) * (by - by.mean()))
    return float(-cov / var)


def _check_sense(z: np.ndarray, xs: np.ndarray, ys: np.ndarray, source: str) -> None:
    zc = convergence_z(z, xs, ys)
    span = float(np.ptp(z))
    if zc is None or abs(zc - float(np.mean(z))) > _PARALLEL * span:
        return
    wrong = zc < z.min() if CAMERA_SIDE > 0 else zc > z.max()
    if wrong:
        want = "toward" if CAMERA_SIDE > 0 else "away from"
        raise ConfigError(
            f"{source}: stage.z_mm runs the wrong way: the rays converge at Z = {zc:.1f} mm, on the far side"
            f" of the screen (readings {z.min():g} .. {z.max():g} mm); the readings must grow as the screen"
            f" moves {want} the camera (list them reversed, or negate them)")


def _stuck_pairs(z: np.ndarray, xs: np.ndarray, ys: np.ndarray, ks) -> list[str]:
    """Pairs of positions whose maps agree where their readings say they must differ.

    Between two heights every pixel moves by its ray's slope times ``dz``: a
    move that differs from pixel to pixel (the rays diverge). What is compared
    is that variation, not the move itself, so a shift common to every pixel
    (a pattern offset changed between positions, a stage's sideways run-out)
    does not hide a stuck stage or a duplicated set of images.
    """
    _, bx = _lines(z, xs)
    _, by = _lines(z, ys)
    spread = float(np.nanmedian(np.hypot(bx - np.nanmedian(bx), by - np.nanmedian(by))))
    found = []
    for i in range(len(z)):
        for j in range(i + 1, len(z)):
            expected = spread * abs(z[j] - z[i])
            dx, dy = xs[j] - xs[i], ys[j] - ys[i]
            ok = np.isfinite(dx) & np.isfinite(dy)
            if not expected > 0 or ok.sum() < 10:
                continue
            dx, dy = dx[ok], dy[ok]
            moved = float(np.median(np.hypot(dx - np.median(dx), dy - np.median(dy))))
            if moved < STUCK_RATIO * expected:
                found.append(f"positions {ks[i]} (z = {z[i]:g} mm) and {ks[j]} (z = {z[j]:g} mm): decoded"
                             f" maps agree (they vary by {1e3 * moved:.2f} µm across the image where the rays'"
                             f" slopes say {1e3 * expected:.1f} µm): a stuck stage or duplicated images?")
    return found


def check_samples(samples: SampleStack, *, positions=None, source: str = "rig.toml",
                  warn: bool = True) -> list[str]:
    """Check decoded samples before a fit: the readings' sense and stuck positions.

    Parameters
    ----------
    samples : SampleStack
    positions : sequence of int, optional
        The positions to judge (default all).
    source : str
        What to name in the messages (the dataset's ``rig.toml``).
    warn : bool
        Issue each finding as a :class:`~ptpcore.errors.DataWarning` too.

    Returns
    -------
    list of str
        One message per pair of positions that look stuck.

    Raises
    ------
    ConfigError
        ``z_mm`` contradicts where the rays converge (listed in reverse).
    """
    ks = list(range(len(samples.z))) if positions is None else [int(p) for p in positions]
    if len(ks) < 2:
        return []
    z, xs, ys = _subsample(samples, ks)
    _check_sense(z, xs, ys, source)
    found = _stuck_pairs(z, xs, ys, ks)
    if warn:
        for msg in found:
            warnings.warn(msg, DataWarning, stacklevel=2)
    return found
