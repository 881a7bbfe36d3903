"""A measured panel flatness applied to the samples' heights (docs/method.md section 8, FORMATS.md ``[lcd]``).

A panel may bow: the pixel plane at LCD point ``(u, v)`` lies ``w(u, v)`` (um,
``+`` = farther from the camera) off the plane the stage reading places it in,
so a sample decoded there was seen at height ``z + w`` along the stage's axis
(docs/method.md section 2: Z grows away from the camera), not at ``z``. Moved back along its
pixel's ray to the reading, its ``X`` changes by ``-dX/dZ * w`` (and ``Y`` by
``-dY/dZ * w``): with ``w`` nearly the same at every position (a ray crosses
the panel at nearly the same point), a constant offset per pixel that no
residual shows and a per-pixel LUT reproduces.

Which way "farther from the camera" runs along Z is read from the data, not
assumed: every pixel's ray passes through the camera's centre, so across
pixels the point ``X_i`` at one position grows with the ray's slope ``B_i``
as ``X_i = P + B_i (z - Z_c)``; the sign of ``z - Z_c`` is the side
(:func:`away_sign`). The cover glass's correction uses the same sign.

``w`` is bilinear in the grid ``flatness_u_px`` x ``flatness_v_px`` (LCD px), held
at its edge value outside the grid.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ptpcore.io.samples import SampleStack
from ptpcore.rig.rigfile import Lcd, Rig

__all__ = ["FlatnessCorrection", "flatness_um", "away_sign", "correct_flatness", "PARALLEL_SPANS"]

PARALLEL_SPANS = 100.0
"""Rays meeting farther than this many stage spans away: nearly parallel, the side cannot be told."""
_MAX_PIXELS = 20000


def flatness_um(lcd: Lcd, u_px, v_px) -> np.ndarray:
    """The declared flatness ``w`` (um) at LCD points ``u_px, v_px`` (LCD px; bilinear, edge values outside).

    Returns
    -------
    ndarray, broadcast shape of ``u_px, v_px``; zeros when no flatness is declared.
    """
    u = np.asarray(u_px, dtype=float)
    v = np.asarray(v_px, dtype=float)
    if not lcd.flatness_um:
        return np.zeros(np.broadcast(u, v).shape)
    gu = np.asarray(lcd.flatness_u_px, dtype=float)
    gv = np.asarray(lcd.flatness_v_px, dtype=float)
    table = np.asarray(lcd.flatness_um, dtype=float)  # [v][u]

    def cell(g, x):
        x = np.clip(x, g[0], g[-1])
        i = np.clip(np.searchsorted(g, x, side="right") - 1, 0, g.size - 2)
        return i, (x - g[i]) / (g[i + 1] - g[i])

    iu, fu = cell(gu, np.nan_to_num(u, nan=gu[0]))
    iv, fv = cell(gv, np.nan_to_num(v, nan=gv[0]))
    top = table[iv, iu] * (1 - fu) + table[iv, iu + 1] * fu
    bottom = table[iv + 1, iu] * (1 - fu) + table[iv + 1, iu + 1] * fu
    out = top * (1 - fv) + bottom * fv
    return np.where(np.isfinite(u) & np.isfinite(v), out, np.nan)


def away_sign(samples: SampleStack, slopes) -> int:
    """+1 when Z grows away from the camera (docs/method.md section 2), -1 when toward it.

    Parameters
    ----------
    samples : SampleStack
    slopes : (2,) tuple of (H, W) float64
        Every pixel's ``dX/dZ``, ``dY/dZ`` (:func:`ptpcore.fit.glass.pixel_slopes`).

    Returns
    -------
    int
        From where the rays converge (at most ~20000 pixels, the position with
        most valid pixels); docs/method.md section 2's +1 when they are nearly parallel (the side
        then moves nothing a flatness or a plate offset could show).
    """
    sx, sy = slopes
    h, w = samples.shape
    step = max(1, int(np.ceil(np.sqrt(h * w / _MAX_PIXELS))))
    k = int(np.argmax([np.count_nonzero(np.asarray(samples.reasons[i, ::step, ::step]) == 0)
                       for i in range(len(samples.z))]))
    xa, ya = samples.absolute(k)
    bx, by = sx[::step, ::step].ravel(), sy[::step, ::step].ravel()
    xa, ya = np.asarray(xa)[::step, ::step].ravel(), np.asarray(ya)[::step, ::step].ravel()
    ok = np.isfinite(bx) & np.isfinite(by) & np.isfinite(xa) & np.isfinite(ya)
    if ok.sum() < 10:
        return 1
    bx, by, xa, ya = bx[ok], by[ok], xa[ok], ya[ok]
    var = np.var(bx) + np.var(by)
    if var <= 0:
        return 1
    # X_i = P + B_i (z_k - Z_c): the regression of X on B across pixels is z_k - Z_c.
    d = (np.mean((xa - xa.mean()) * (bx - bx.mean())) + np.mean((ya - ya.mean()) * (by - by.mean()))) / var
    span = max(float(np.ptp(np.asarray(samples.z, float))), 1e-9)
    if abs(d) > PARALLEL_SPANS * span:
        return 1
    return 1 if d > 0 else -1


@dataclass
class FlatnessCorrection:
    """The flatness correction applied to every sample.

    Attributes
    ----------
    shift_um : (H, W) float64
        Per pixel, the largest length of the shift added to any of its samples
        (um; what ignoring the flatness would have cost); 0 without samples.
    away : int
        :func:`away_sign` used.
    w_range_um : (2,) float
        Smallest and largest declared ``w``.
    """

    shift_um: np.ndarray
    away: int
    w_range_um: tuple[float, float]

    def record(self) -> dict:
        """JSON-ready summary: the grid's range, and the median and max per-pixel shift (um)."""
        s = self.shift_um[np.isfinite(self.shift_um) & (self.shift_um > 0)]
        return {"kind": "flatness", "w_min_um": self.w_range_um[0], "w_max_um": self.w_range_um[1],
                "away_sign": self.away, "pixels": int(s.size),
                "median_um": float(np.median(s)) if s.size else 0.0, "max_um": float(np.max(s)) if s.size else 0.0}


def correct_flatness(samples: SampleStack, rig: Rig, slopes, away: int | None = None,
                     ) -> tuple[SampleStack, FlatnessCorrection]:
    """Every sample moved along its pixel's ray from its true height ``z + w(u, v)`` to the reading ``z``.

    Parameters
    ----------
    samples : SampleStack
        Not modified; ``lcd_shift`` (the cover glass) is taken off to find the
        decoded LCD point ``(u, v)``.
    rig : Rig
        ``[lcd] flatness_*`` (must be declared), pitch and the stage direction.
    slopes : (2,) tuple of (H, W) float64
        Every pixel's ``dX/dZ``, ``dY/dZ``.
    away : int, optional
        :func:`away_sign` (computed when not given).

    Returns
    -------
    corrected : SampleStack
        New ``x, y`` arrays (in memory, float32); ``corrections`` gains ``flatness``.
    correction : FlatnessCorrection
    """
    lcd = rig.lcd
    if not lcd.flatness_um:
        raise ValueError("no flatness declared ([lcd] flatness_um)")
    away = away_sign(samples, slopes) if away is None else int(away)
    sx, sy = (np.nan_to_num(s) for s in slopes)
    a, b, _ = rig.stage.direction
    px, py = lcd.pitch_mm
    sh = samples.lcd_shift if samples.lcd_shift is not None else (0.0, 0.0)
    xs = np.empty(samples.x.shape, np.float32)
    ys = np.empty(samples.y.shape, np.float32)
    longest = np.zeros(samples.shape)
    for k, zk in enumerate(np.asarray(samples.z, dtype=float)):
        xa, ya = samples.absolute(k)
        w = flatness_um(lcd, (xa - sh[0] - a * zk) / px, (ya - sh[1] - b * zk) / py)
        dz = np.where(np.isfinite(w), away * 1e-3 * w, 0.0)  # mm along Z
        xs[k] = samples.x[k] - sx * dz
        ys[k] = samples.y[k] - sy * dz
        longest = np.fmax(longest, np.where(np.asarray(samples.reasons[k]) == 0, 1e3 * np.hypot(sx, sy) * np.abs(dz), 0.0))
    table = np.asarray(lcd.flatness_um, dtype=float)
    corr = FlatnessCorrection(longest, away, (float(table.min()), float(table.max())))
    out = replace(samples, x=xs, y=ys, corrections={**samples.corrections, "flatness": corr.record()})
    return out, corr
