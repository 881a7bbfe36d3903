"""Residual diagnostics: per position, the field of (sample - LUT) as arrows, and its RMS.

A magnitude map hides direction: a position whose residuals all point one way (a
stage that moved sideways, a tilted plate) or swirl about the centre (a rotation)
shows a pattern as arrows that a random scatter of noise does not. The field is
the mean residual over square blocks of pixels (one arrow per block); the lists
put the worst positions and the worst pixels first. Arrays only: the GUI draws
them; :func:`residual_png` draws one position with OpenCV for the export.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ptpcore.io.lutfile import Lut
from ptpcore.io.samples import SampleStack
from ptpcore.rig import position_label

from .pngtext import put_text, write_png

__all__ = ["ResidualField", "residual_field", "residual_png"]


@dataclass
class ResidualField:
    """Residuals of a LUT against its samples.

    Attributes
    ----------
    z : (K,) float64, mm
        Stage readings of the positions.
    used : (K,) bool
        Positions the LUT was fitted on (the others are held out).
    rms_um : (K,) float64, µm
        Per position, RMS over valid pixels of the residual length ``|(dX, dY)|``.
    n_pixels : (K,) int64
        Pixels with a residual at each position.
    rows, cols : (Gy,), (Gx,) float64, px
        Block centres.
    dx, dy : (K, Gy, Gx) float64, mm
        Mean residual (sample - LUT) per block; NaN for blocks without a sample.
    pixel_rms_um : (H, W) float64, µm
        Per pixel, RMS over positions of the residual length (NaN without residuals).
    worst_positions : (K,) int64
        Positions by ``rms_um``, largest first.
    worst_pixels : (N, 2) int64
        ``(row, col)`` of the N pixels with the largest ``pixel_rms_um``, largest first.
    block : int
        Block side (px).
    """

    z: np.ndarray
    used: np.ndarray
    rms_um: np.ndarray
    n_pixels: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    pixel_rms_um: np.ndarray
    worst_positions: np.ndarray
    worst_pixels: np.ndarray
    block: int

    def lines(self, n: int = 5) -> list[str]:
        """The worst positions and pixels in words (positions counted from 0, with their height)."""
        out = ["worst positions (residual RMS over X and Y): " + ", ".join(
            f"{position_label(k, self.z[k])}{'' if self.used[k] else ' (held out)'}: {self.rms_um[k]:.3f} µm"
            for k in self.worst_positions[:n] if np.isfinite(self.rms_um[k]))]
        out.append("worst pixels (RMS over positions): " + ", ".join(
            f"({r}, {c}) {self.pixel_rms_um[r, c]:.3f} µm" for r, c in self.worst_pixels[:n]))
        return out

    def merged(self, group: int) -> "ResidualField":
        """The field with ``group x group`` blocks merged into one (fewer, longer-spaced arrows).

        Each merged block's residual is the mean of its blocks' mean residuals (those with a
        value; NaN for none), its centre the mean of their centres; ``block`` is ``group``
        times this one's. A big sensor's field (47 000 blocks of 16 px at 12 MP) drawn whole
        costs the GUI thread 0.1-0.2 s and shows more arrows than a screen can tell apart.
        Everything per position and per pixel stays as it is.
        """
        g = int(group)
        if g < 1:
            raise ValueError(f"group must be at least 1 block, got {group}")
        if g == 1:
            return self
        dx = np.stack([_block_mean(a, g) for a in self.dx])
        dy = np.stack([_block_mean(a, g) for a in self.dy])
        rows, cols = _block_mean(self.rows[:, None], g)[:, 0], _block_mean(self.cols[None, :], g)[0]
        return dataclasses.replace(self, rows=rows, cols=cols, dx=dx, dy=dy, block=self.block * g)


def _block_mean(a: np.ndarray, b: int) -> np.ndarray:
    """(H, W) -> (ceil(H/b), ceil(W/b)) mean of the finite values (NaN for empty blocks)."""
    h, w = a.shape
    gy, gx = -(-h // b), -(-w // b)
    pad = np.full((gy * b, gx * b), np.nan)
    pad[:h, :w] = a
    blocks = pad.reshape(gy, b, gx, b)
    ok = np.isfinite(blocks)
    n = ok.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.where(ok, blocks, 0.0).sum(axis=(1, 3)) / n, np.nan)


BAND_PIXELS = 1 << 19
"""Pixels per row band of :func:`residual_field` (about 0.5 M: its float64 temporaries are a few MB each)."""


def residual_field(lut: Lut, samples: SampleStack, positions=None, *, block: int = 16,
                   n_worst: int = 20) -> ResidualField:
    """The residuals of ``lut`` at every position of ``samples``.

    Worked in row bands (a multiple of ``block`` rows, about :data:`BAND_PIXELS` pixels), the
    samples of each band read from their spill file (:func:`ptpcore.store.read_block`), so
    that a big sensor's stack never comes into memory whole.

    Parameters
    ----------
    lut : Lut
    samples : SampleStack
        Its samples (same camera); all positions are evaluated.
    positions : sequence of int, optional
        The positions the LUT was fitted on (default all), for ``used``.
    block : int
        Block side in px for the arrows.
    n_worst : int
        Pixels listed in ``worst_pixels``.

    Returns
    -------
    ResidualField

    Raises
    ------
    ValueError
        Different camera sizes or a block below 1 px.
    """
    if lut.shape != samples.shape:
        raise ValueError(f"the LUT is {lut.shape} px, the samples {samples.shape}")
    if int(block) < 1:
        raise ValueError(f"block must be at least 1 px, got {block}")
    k_all = samples.z.size
    used = np.zeros(k_all, bool)
    used[np.arange(k_all) if positions is None else np.asarray(positions, dtype=np.int64)] = True
    h, w = samples.shape
    b = int(block)
    acc = _Residuals.empty(k_all, h, w, b)
    band = max(b, BAND_PIXELS // w // b * b)
    for r0 in range(0, h, band):
        acc.add_band(lut.row_band(r0, min(h, r0 + band)), samples, r0, min(h, r0 + band))
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.where(acc.npx > 0, np.sqrt(acc.sum_r2 / np.maximum(acc.npx, 1)) * 1e3, np.nan)
    pix = acc.pixel_rms_um
    flat = np.where(np.isfinite(pix), pix, -1.0).ravel()
    top = np.argsort(flat)[::-1][:int(n_worst)]
    top = top[flat[top] >= 0]
    worst_pos = np.argsort(np.where(np.isfinite(rms), rms, -1.0))[::-1]
    gy, gx = acc.dx.shape[1:]
    rows = np.minimum(np.arange(gy) * b + (b - 1) / 2, h - 1)
    cols = np.minimum(np.arange(gx) * b + (b - 1) / 2, w - 1)
    return ResidualField(samples.z.astype(float).copy(), used, rms, acc.npx, rows, cols,
                         acc.dx, acc.dy, pix, worst_pos.astype(np.int64),
                         np.stack(np.unravel_index(top, (h, w)), axis=1).astype(np.int64), b)


@dataclass
class _Residuals:
    """What :func:`residual_field` gathers band by band.

    Attributes
    ----------
    dx, dy : (K, Gy, Gx) float64, mm
        Block means, filled band by band (a band is a whole number of block rows).
    sum_r2 : (K,) float64, mm^2
        Per position, the sum of squared residual lengths (summed per band, then over bands).
    npx : (K,) int64
    pixel_rms_um : (H, W) float64
    block : int
    """

    dx: np.ndarray
    dy: np.ndarray
    sum_r2: np.ndarray
    npx: np.ndarray
    pixel_rms_um: np.ndarray
    block: int

    @classmethod
    def empty(cls, k_all: int, h: int, w: int, b: int) -> "_Residuals":
        gy, gx = -(-h // b), -(-w // b)
        return cls(np.full((k_all, gy, gx), np.nan), np.full((k_all, gy, gx), np.nan), np.zeros(k_all),
                   np.zeros(k_all, np.int64), np.full((h, w), np.nan), b)

    def add_band(self, lut: Lut, samples: SampleStack, r0: int, r1: int) -> None:
        """Every position's residuals on rows ``[r0, r1)`` (``lut`` is that band's :meth:`Lut.row_band`)."""
        from ptpcore.store import read_block

        w = samples.shape[1]
        start, stop = r0 * w, r1 * w
        x_ref, y_ref = samples.x_ref[r0:r1], samples.y_ref[r0:r1]
        sq, cnt = np.zeros((r1 - r0, w)), np.zeros((r1 - r0, w))
        g0, g1 = r0 // self.block, -(-r1 // self.block)
        for k in range(samples.z.size):
            ev = lut.evaluate(float(samples.z[k]))
            sx = x_ref + read_block(samples.x, start, stop, [k]).reshape(r1 - r0, w)
            sy = y_ref + read_block(samples.y, start, stop, [k]).reshape(r1 - r0, w)
            reasons = read_block(samples.reasons, start, stop, [k]).reshape(r1 - r0, w)
            ok = (reasons == 0) & ev.in_range & lut.valid & np.isfinite(sx)
            rx, ry = np.where(ok, sx - ev.x, np.nan), np.where(ok, sy - ev.y, np.nan)
            r2 = rx * rx + ry * ry
            n = int(ok.sum())
            if n:
                self.npx[k] += n
                self.sum_r2[k] += float(np.sum(r2[ok]))
                self.dx[k, g0:g1], self.dy[k, g0:g1] = _block_mean(rx, self.block), _block_mean(ry, self.block)
            sq += np.where(ok, r2, 0.0)
            cnt += ok
        with np.errstate(invalid="ignore", divide="ignore"):
            self.pixel_rms_um[r0:r1] = np.where(cnt > 0, np.sqrt(sq / cnt) * 1e3, np.nan)


def residual_png(field: ResidualField, k: int, path, size_px: int = 800) -> None:
    """Draw position ``k``'s residual field as arrows (OpenCV) and write it as PNG, atomically.

    The arrows are scaled so the longest is 1.5 blocks long; the scale (µm per block) and the
    position's RMS are written at the top.
    """
    import cv2

    gy, gx = field.dx.shape[1:]
    f = size_px / max(gx, gy) / field.block
    h_img, w_img = int(round(gy * field.block * f)) + 40, int(round(gx * field.block * f))
    img = np.full((h_img, w_img, 3), 255, np.uint8)
    dx, dy = field.dx[k], field.dy[k]
    length = np.hypot(dx, dy)
    longest = float(np.nanmax(length)) if np.isfinite(length).any() else 0.0
    scale = 1.5 * field.block * f / longest if longest > 0 else 0.0
    for i in range(gy):
        for j in range(gx):
            if not np.isfinite(length[i, j]):
                continue
            x0, y0 = field.cols[j] * f, field.rows[i] * f + 40
            p0 = (int(round(x0)), int(round(y0)))
            p1 = (int(round(x0 + dx[i, j] * scale)), int(round(y0 + dy[i, j] * scale)))
            cv2.arrowedLine(img, p0, p1, (178, 114, 0), 1, cv2.LINE_AA, tipLength=0.3)
    text = (f"{position_label(k, field.z[k])}: residual RMS (X and Y) {field.rms_um[k]:.3f} µm;"
            f" longest arrow {longest * 1e3:.3f} µm")
    put_text(img, text, (8, 26))
    write_png(img, path)
