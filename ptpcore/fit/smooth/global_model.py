"""Step 1 of the smooth fit: the global pinhole + Brown model, and every sample's residual to it.

:func:`global_pinhole` fits the model (:mod:`ptpcore.pinhole`) to a random subset of all calibration
samples; :class:`GlobalRays` holds its rays ``X = x0 + sx z``, ``Y = y0 + sy z`` per pixel. Before a
sample is compared with its ray it loses two physical biases: the display's integer levels
(:func:`remove_level_bias`, :mod:`ptpcore.decode.display`) and the pixel footprint's centroid
(:func:`footprint_bias`). :func:`global_residuals` gives a row block's validity, predicted noise,
weights and residuals: what every later step fits.
"""

from __future__ import annotations

import numpy as np

from ptpcore.decode.display import level_bias_at
from ptpcore.fit.smooth.blocks import row_blocks, run_blocks
from ptpcore.fit.smooth.noise import noise_rows
from ptpcore.io.samples import SampleStack
from ptpcore.pinhole.camera import PinholeModel, fit_pinhole
from ptpcore.rig.rigfile import Rig
from ptpcore.store import read_block, row_store

__all__ = ["global_pinhole", "GlobalRays", "footprint_bias", "FOOTPRINT_M2_MAX_PX2", "remove_level_bias",
           "corrected_samples", "global_residuals"]


def global_pinhole(samples: SampleStack, positions, n_points: int = 20000, seed: int = 0,
                   rig: Rig | None = None, full: bool = False):
    """Fit the pinhole + Brown model to a random subset of valid calibration samples.

    With ``rig``, the samples lose the display's level bias first (:mod:`ptpcore.decode.display`).
    Returns the :class:`PinholeModel`, or with ``full`` the whole
    :class:`ptpcore.pinhole.camera.PinholeFit` (with its parameter covariance).
    """
    rng = np.random.default_rng(seed)
    h, w = samples.shape
    pts, pix = [], []
    positions = list(positions)
    per = max(n_points // len(positions), 10)
    for k in positions:
        idx = np.flatnonzero(read_block(samples.reasons, 0, h * w, [k])[0] == 0)
        if idx.size == 0:
            continue
        pick = rng.choice(idx, size=min(per, idx.size), replace=False)
        r, c = np.divmod(pick, w)
        x = samples.x_ref.ravel()[pick] + read_block(samples.x, 0, h * w, [k])[0][pick]
        y = samples.y_ref.ravel()[pick] + read_block(samples.y, 0, h * w, [k])[0][pick]
        if rig is not None:
            x = remove_level_bias(x[None], rig, "x", [samples.z[k]], _lcd_shift(samples, 0, pick))[0]
            y = remove_level_bias(y[None], rig, "y", [samples.z[k]], _lcd_shift(samples, 1, pick))[0]
        pts.append(np.stack([x, y, np.full(pick.size, samples.z[k])], 1))
        pix.append(np.stack([c, r], 1).astype(float))
    fit = fit_pinhole(np.concatenate(pts), np.concatenate(pix))
    return fit if full else fit.model


def remove_level_bias(values: np.ndarray, rig: Rig, axis: str, z, shift=0.0) -> np.ndarray:
    """Absolute world X or Y samples minus the display's level bias (:mod:`ptpcore.decode.display`), in place.

    Parameters
    ----------
    values : (K, n) float64, mm
        Absolute ``X`` (``axis = "x"``) or ``Y`` of ``n`` pixels at the heights ``z`` (K,).
    shift : (n,) float64 or float, mm
        What corrections added to these pixels since decoding (``SampleStack.lcd_shift``).
    """
    d = "xy".index(axis)
    slope, pitch = rig.stage.direction[d], rig.lcd.pitch_mm[d]
    for i, zk in enumerate(np.asarray(z, dtype=float)):
        coord = (values[i] - shift - slope * zk) / pitch  # the decoded LCD coordinate
        values[i] -= level_bias_at(rig.fringes, rig.lcd, axis, zk, coord) * pitch
    return values


def _lcd_shift(samples: SampleStack, axis: int, flat):
    """``samples.lcd_shift[axis]`` at flat pixel indices ``flat`` (0.0 as decoded)."""
    shift = getattr(samples, "lcd_shift", None)
    return 0.0 if shift is None else np.asarray(shift[axis]).reshape(-1)[flat]


class GlobalRays:
    """The global model's rays ``X = x0 + sx z``, ``Y = y0 + sy z``: four (H, W) float64 maps read by rows.

    Above :data:`ptpcore.store.SPILL_PIXELS` pixels they wait in a temporary file (a row store) and each
    row block reads its rows: at 12 MP the four maps (380 MB) are not held beside the pixel fits
    through the smoothing and every leave-one-out refit. The values are the same either way.
    """

    def __init__(self, model: PinholeModel, shape):
        h, w = self.shape = tuple(shape)
        self._maps = row_store((4, h, w))

        def block(r0, r1):
            rr, cc = np.mgrid[r0:r1, 0:w].astype(float)
            a0, b0 = model.pixel_to_world_at_z(cc, rr, 0.0)
            a1, b1 = model.pixel_to_world_at_z(cc, rr, 1.0)
            self._maps[:, r0:r1] = np.stack((a0, b0, a1 - a0, b1 - b0))

        run_blocks(block, row_blocks(h, w))

    def rows(self, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``x0, y0, sx, sy`` of rows ``[r0, r1)``: four ``(r1 - r0, W)`` maps."""
        return tuple(self._maps.row_block(r0, r1))

    def window(self, r0: int, r1: int) -> tuple[tuple, int]:
        """The rows :func:`footprint_bias` reads for rows ``[r0, r1)`` (their neighbours, three rows
        at least) and the first one's index: pass ``(rays, r0 - first, r1 - first)`` to it."""
        lo, hi = _laplacian_rows(r0, r1, self.shape[0])
        return self.rows(lo, hi), lo


#: Largest footprint second moment (camera px^2) the correction believes: a blur sigma of 2 px.
#: Ambient light or a camera black level lower the contrast like blur does; this bounds the damage.
FOOTPRINT_M2_MAX_PX2 = 4.0


def _laplacian_rows(r0: int, r1: int, h: int) -> tuple[int, int]:
    """The rows :func:`_laplacian` reads for rows ``[r0, r1)`` of an ``h``-row map: their neighbours,
    three rows at least (they also cover :func:`_gradients`' rows)."""
    return max(min(r0 - 1, h - 3), 0), min(max(r1 + 1, 3), h)


def _laplacian(a: np.ndarray, r0: int, r1: int) -> np.ndarray:
    """Laplacian (per camera px^2) of rows ``[r0, r1)`` of a smooth (H, W) map.

    Second differences at the image's edges repeat the nearest interior one (the block is widened
    to three rows there, so a block of one edge row gives the whole image's value).
    """
    lo, hi = _laplacian_rows(r0, r1, a.shape[0])
    blk = a[lo:hi]
    d2 = np.zeros_like(blk)
    if blk.shape[1] >= 3:
        d2[:, 1:-1] = blk[:, 2:] - 2.0 * blk[:, 1:-1] + blk[:, :-2]
        d2[:, 0], d2[:, -1] = d2[:, 1], d2[:, -2]
    if blk.shape[0] >= 3:
        d2r = np.empty_like(blk)
        d2r[1:-1] = blk[2:] - 2.0 * blk[1:-1] + blk[:-2]
        d2r[0], d2r[-1] = d2r[1], d2r[-2]
        d2 += d2r
    sl = slice(r0 - lo, r0 - lo + (r1 - r0))
    return d2[sl]


def _gradients(a: np.ndarray, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
    """d/drow and d/dcol (per camera px) of rows ``[r0, r1)`` of an (H, W) map (central differences)."""
    lo, hi = max(r0 - 1, 0), min(r1 + 1, a.shape[0])
    blk = a[lo:hi]
    gr = np.gradient(blk, axis=0) if blk.shape[0] >= 2 else np.zeros_like(blk)
    gc = np.gradient(blk, axis=1) if blk.shape[1] >= 2 else np.zeros_like(blk)
    sl = slice(r0 - lo, r0 - lo + (r1 - r0))
    return gr[sl], gc[sl]


def footprint_bias(rays, rig: Rig, z: np.ndarray, modulation: np.ndarray, background: np.ndarray,
                   r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
    """How far each decoded sample sits from its pixel's centre ray: the footprint's curvature term.

    A camera pixel reports the phase averaged over its footprint on the LCD
    (the pixel's square plus the lens blur), i.e. the footprint's centroid,
    not the point its centre ray hits. Where the mapping pixel -> LCD bends
    (lens distortion), the two differ by ``m2 / 2 * laplacian(X)`` with
    ``m2`` the footprint's second moment (camera px^2; 1/12 for the bare
    square). The same footprint lowers the fringe contrast: the finest
    period's contrast ``B / A`` against the displayed ``amplitude / offset``
    is ``exp(-2 pi^2 m2_X / (T pitch)^2)``, which gives ``m2_X`` on the LCD
    (mm^2) and ``m2 = m2_X / |grad X|^2``. The derivatives come from the
    global model (smooth, noise-free). On the presets this removes a
    0.001 LCD px (0.05 um) bias that grows towards the image's edges.

    Parameters
    ----------
    rays : (x0, y0, sx, sy) float64 maps of the global model: the whole image, or rows of it
        (:meth:`GlobalRays.window`) with ``r0``, ``r1`` counted from their first
    rig : Rig
    z : (K,) heights (mm)
    modulation, background : (K, n) finest-period ``B`` and ``A`` of rows ``[r0, r1)`` (n = rows * W)
    r0, r1 : int

    Returns
    -------
    bias_x, bias_y : (K, n) float64, mm
        To subtract from the samples; 0 where the contrast says nothing.
    """
    f = rig.fringes
    period_mm = f.periods_px[-1] * np.asarray(rig.lcd.pitch_mm, float)
    c0 = f.amplitude / f.offset  # the emitted contrast when the display follows the pre-compensated gamma
    with np.errstate(all="ignore"):
        neg_log = -np.log(np.clip(modulation / background / c0, 0.05, 1.0))  # (K, n)
    out = []
    for a, (x0, slope) in enumerate(((rays[0], rays[2]), (rays[1], rays[3]))):
        # X(z) = x0 + slope z: its Laplacian and gradient are those of the two maps, combined per z.
        lap0 = _laplacian(x0, r0, r1)
        lap1 = _laplacian(slope, r0, r1)
        g0r, g0c = _gradients(x0, r0, r1)
        g1r, g1c = _gradients(slope, r0, r1)
        bias = np.empty_like(neg_log)
        for i, zk in enumerate(np.asarray(z, float)):
            g2 = ((g0r + g1r * zk) ** 2 + (g0c + g1c * zk) ** 2).ravel()
            with np.errstate(all="ignore"):
                m2 = np.minimum(neg_log[i] * period_mm[a] ** 2 / (2.0 * np.pi ** 2) / g2, FOOTPRINT_M2_MAX_PX2)
                bias[i] = 0.5 * m2 * (lap0 + lap1 * zk).ravel()
        out.append(np.nan_to_num(bias, nan=0.0, posinf=0.0, neginf=0.0))
    return out[0], out[1]


def corrected_samples(samples: SampleStack, rig: Rig, axis: int, s: int, e: int, sel, z,
                      level_bias: bool, footprint) -> np.ndarray:
    """Absolute X (``axis`` 0) or Y (1) of flat pixels ``[s, e)`` at positions ``sel``, corrected.

    Returns
    -------
    (K, e - s) float64, mm: minus the level bias if ``level_bias``, minus
    ``footprint[axis]`` (from :func:`footprint_bias`) unless it is None.
    """
    name = "xy"[axis]
    values = getattr(samples, f"{name}_ref").reshape(-1)[s:e][None] + read_block(
        getattr(samples, name), s, e, sel).astype(np.float64)
    if level_bias:
        remove_level_bias(values, rig, name, z, _lcd_shift(samples, axis, slice(s, e)))
    if footprint is not None:
        values -= footprint[axis]
    return values


def global_residuals(samples: SampleStack, rig: Rig, sel, z, r0: int, r1: int, rays: GlobalRays,
                     level_bias: bool = False, footprint: bool = False, corrected: bool = False):
    """Rows ``[r0, r1)`` of the chosen positions: validity, sample sigma, weights and residuals to the global model.

    Returns
    -------
    valid : (K, n) bool ; sigma : (K, n) float64 (NaN where invalid) ; wts : (K, n) float64
    (0 where invalid or off the global model) ; resid : (rx, ry) (K, n) float64, mm ;
    with ``corrected`` also the corrected samples themselves (:func:`corrected_samples`, X and Y)
    """
    w = samples.shape[1]
    s, e = r0 * w, r1 * w
    valid, mod, bg, sig = noise_rows(samples, rig, sel, s, e)
    wts = np.where(np.isfinite(sig) & (sig > 0), 1.0 / np.square(sig), 0.0)
    near, lo = rays.window(r0, r1)
    g = [r[r0 - lo:r1 - lo].reshape(-1) for r in near]
    wts[:, ~(np.isfinite(g[0]) & np.isfinite(g[1]))] = 0.0
    fb = footprint_bias(near, rig, z, mod, bg, r0 - lo, r1 - lo) if footprint else None
    values = [corrected_samples(samples, rig, a, s, e, sel, z, level_bias, fb) for a in (0, 1)]
    resid = [v - (g0[None] + gs[None] * z[:, None]) for v, (g0, gs) in zip(values, ((g[0], g[2]), (g[1], g[3])))]
    return (valid, sig, wts, resid, values) if corrected else (valid, sig, wts, resid)
