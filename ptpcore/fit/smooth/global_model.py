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
    """The rows :func:`_second_differences` reads for rows ``[r0, r1)`` of an ``h``-row map: their neighbours,
    three rows at least (they also cover :func:`_gradients`' rows)."""
    return max(min(r0 - 1, h - 3), 0), min(max(r1 + 1, 3), h)


def _second_differences(a: np.ndarray, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """d2/drow2, d2/dcol2 and d2/drow dcol (per camera px^2) of rows ``[r0, r1)`` of a smooth (H, W) map.

    Second differences at the image's edges repeat the nearest interior one (the block is widened
    to three rows there, so a block of one edge row gives the whole image's value).
    """
    lo, hi = _laplacian_rows(r0, r1, a.shape[0])
    blk = a[lo:hi]
    dcc, drr = np.zeros_like(blk), np.zeros_like(blk)
    if blk.shape[1] >= 3:
        dcc[:, 1:-1] = blk[:, 2:] - 2.0 * blk[:, 1:-1] + blk[:, :-2]
        dcc[:, 0], dcc[:, -1] = dcc[:, 1], dcc[:, -2]
    if blk.shape[0] >= 3:
        drr[1:-1] = blk[2:] - 2.0 * blk[1:-1] + blk[:-2]
        drr[0], drr[-1] = drr[1], drr[-2]
    drc = np.gradient(np.gradient(blk, axis=0), axis=1) if min(blk.shape) >= 2 else np.zeros_like(blk)
    sl = slice(r0 - lo, r0 - lo + (r1 - r0))
    return drr[sl], dcc[sl], drc[sl]


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

    A camera pixel reports the phase of the fringe averaged over its
    footprint on the LCD (the pixel's square plus the lens blur), not the
    phase where its centre ray hits. Where the mapping pixel -> LCD bends
    (lens distortion), the two differ. For a footprint of second moment
    ``m2`` (camera px^2, isotropic; 1/12 for the bare square), gradient
    ``g`` (mm/px) and Hessian ``H`` (mm/px^2) of ``X`` over the image, and
    the finest period's wavenumber ``k``, the phase of the footprint's
    average of ``exp(i k X)`` is, to first order in ``H`` and exactly in
    ``k`` for a Gaussian footprint,

        ``X_decoded - X_centre = m2 / 2 * (tr H - 2 L * g^T H g / |g|^2)``,  ``L = k^2 m2 |g|^2 / 2``

    The first term is the footprint's centroid; the second is the skew the
    bend gives the footprint's spread along ``X``, which a sinusoid weighs
    with ``k^2``: for a footprint wider than a small part of the period it
    is as large as the first and of the other sign (on a fisheye-like lens
    with 0.3 mm pixels on the LCD against a 1.6 mm period, the centroid
    alone over-corrects about 2x: 0.4 um, issue 30). ``L`` is what the same
    footprint takes off the fringe contrast: the finest period's ``B / A``
    against the displayed ``amplitude / offset`` is ``exp(-L)``, which gives
    ``m2`` (``modulation`` is the worse direction's, so from the axis with
    the larger ``k^2 |g|^2``). The derivatives come from the global model
    (smooth, noise-free). The correction is 0.07 um RMS on the harness's
    realistic#1 and 0.45 um on its fisheye#1, growing towards the image's
    edges; on the fisheye's noise-free render it follows the simulator's own
    shift at correlation 0.95 (x), leaving 0.15 um of 0.41.

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
    # X(z) = x0 + slope z per axis: its derivatives are those of the two maps, combined per z.
    maps = [(rays[0], rays[2]), (rays[1], rays[3])]
    grads = [(_gradients(x0, r0, r1), _gradients(slope, r0, r1)) for x0, slope in maps]
    hessians = [(_second_differences(x0, r0, r1), _second_differences(slope, r0, r1)) for x0, slope in maps]
    k2 = (2.0 * np.pi / period_mm) ** 2  # (2,) per axis, 1/mm^2
    out = [np.empty_like(neg_log), np.empty_like(neg_log)]
    for i, zk in enumerate(np.asarray(z, float)):
        g = [(g0r + g1r * zk, g0c + g1c * zk) for (g0r, g0c), (g1r, g1c) in grads]
        g2 = [(gr ** 2 + gc ** 2).ravel() for gr, gc in g]
        with np.errstate(all="ignore"):
            # The stored modulation is the worse direction's: the axis whose fringes the footprint
            # spans most (an isotropic footprint m2 loses k^2 m2 |grad X|^2 / 2 on each axis).
            m2 = np.minimum(2.0 * neg_log[i] / np.maximum(k2[0] * g2[0], k2[1] * g2[1]), FOOTPRINT_M2_MAX_PX2)
            for a in (0, 1):
                gr, gc = g[a]
                hrr, hcc, hrc = (p0 + p1 * zk for p0, p1 in zip(*hessians[a]))
                h_along = (gr * gr * hrr + 2.0 * gr * gc * hrc + gc * gc * hcc).ravel() / g2[a]
                spread = k2[a] * m2 * g2[a] / 2.0  # L of this axis
                out[a][i] = 0.5 * m2 * ((hrr + hcc).ravel() - 2.0 * spread * h_along)
    out = [np.nan_to_num(b, nan=0.0, posinf=0.0, neginf=0.0) for b in out]
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
