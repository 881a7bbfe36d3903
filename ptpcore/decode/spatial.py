"""Spatial consistency of a decoded coordinate map (docs/method.md section 4).

A pixel whose decoded coordinate departs from a smooth fit over its
neighbourhood by more than ``k`` sigma of its predicted noise is flagged: dust
on the target, dead LCD pixels or printed dots decode many times worse than
their neighbours while their modulation may still pass.

The fit is robust: the local gradient is the median of the central differences
in the window, and the prediction the median of the neighbours carried to the
centre along it; the median of the neighbours' own residuals (what the local
plane misses of a curved map) is then taken off. Neighbours are taken on a sparse grid (every second pixel out
to ``radius``), so a defect a few pixels across cannot take over the median.
"""

from __future__ import annotations

import warnings

import numpy as np

from ptpcore.decode.median_networks import window_offsets

__all__ = ["neighbourhood_residual", "spatial_outliers", "ROBUST_SIGMA"]

ROBUST_SIGMA = 1.4826
"""Median absolute deviation -> standard deviation for normal data."""

MIN_NEIGHBOURS = 8
ROWS_PER_CHUNK = 16
"""Rows per chunk: the 25 neighbours' stacks and their sorted copies are float64 (at 2448 px
wide, 16 rows keep them near 8 MB each; every pixel's median is its own, whatever the chunk)."""


FLAG_ROWS = 256
"""Rows per band of :func:`spatial_outliers`' flagging (a few MB of temporaries at 5 MP)."""


EXACT_MEDIAN_SAMPLE = 1 << 16
"""Values of the sub-sample :func:`median_exact` brackets the median with."""


def median_exact(x: np.ndarray) -> float:
    """``np.median(x)`` of a 1-D array without NaN, the same number, without partitioning it all.

    A regular sub-sample of :data:`EXACT_MEDIAN_SAMPLE` values brackets the median (its order
    statistics 4.5 standard errors either side); one pass counts the values below the bracket and
    gathers those inside, whose partition gives the two middle values of the whole. Should the
    bracket miss (a tie-heavy or adversarial order), the whole array is partitioned. About 4x
    cheaper than ``np.median`` on the millions of residuals of a 5 MP map.
    """
    n = x.size
    if n <= 4 * EXACT_MEDIAN_SAMPLE:
        return float(np.median(x))
    sample = np.sort(x[::n // EXACT_MEDIAN_SAMPLE])
    m = sample.size
    d = int(4.5 * 0.5 * np.sqrt(m)) + 1
    lo, hi = sample[max(m // 2 - d, 0)], sample[min(m // 2 + d, m - 1)]
    k1, k2 = (n - 1) // 2, n // 2
    below = int(np.count_nonzero(x < lo))
    inside = x[(x >= lo) & (x <= hi)]
    if not below <= k1 or not below + inside.size > k2:
        return float(np.median(x))
    part = np.partition(inside, [k1 - below, k2 - below])
    return float(np.mean(part[[k1 - below, k2 - below]]))


def _nanmedian0(stack: np.ndarray) -> np.ndarray:
    """``np.nanmedian(stack, axis=0)`` by one sort (NaN sort last): many times faster."""
    s = np.sort(stack, axis=0)
    n = np.count_nonzero(~np.isnan(stack), axis=0)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[None], axis=0)[0]
    hi = np.take_along_axis(s, (n // 2)[None], axis=0)[0] if s.shape[0] else lo
    out = 0.5 * (lo + hi)
    out[n == 0] = np.nan
    return out


def neighbourhood_residual(coord: np.ndarray, valid: np.ndarray, *, radius: int = 4, step: int = 2
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Decoded coordinate minus its robust local prediction.

    Parameters
    ----------
    coord : (H, W) float
        LCD coordinate map (px).
    valid : (H, W) bool
        Pixels that may serve as neighbours (and be judged).

    Returns
    -------
    residual : (H, W) float64
        NaN where the pixel is invalid or has too few valid neighbours.
    n_neighbours : (H, W) int16
        0 where the pixel is not valid (its residual is NaN whatever its neighbours).
    """
    h, w = coord.shape
    pad = radius
    kern = _kernels()
    if kern is not None and window_offsets(radius, step) == window_offsets():
        # The kernels' row functions are written out for the default window.
        return _residual_fused(kern, coord, valid, pad)
    cp, gcp, grp, rp = _padded_maps(coord, valid, pad)
    c, resid = cp[pad:pad + h, pad:pad + w], rp[pad:pad + h, pad:pad + w]
    offs = window_offsets(radius, step)
    count = np.zeros((h, w), np.int16)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
        for r0 in range(0, h, ROWS_PER_CHUNK):
            r1 = min(h, r0 + ROWS_PER_CHUNK)
            sl = [(r0 + pad + dr, r1 + pad + dr, pad + dc, pad + dc + w) for dr, dc in offs]
            centre = (r0 + pad, r1 + pad, pad, pad + w)
            g_c = _nanmedian0(np.stack([gcp[a:b, e:f] for a, b, e, f in sl + [centre]]))
            g_r = _nanmedian0(np.stack([grp[a:b, e:f] for a, b, e, f in sl + [centre]]))
            carried = np.stack([cp[a:b, e:f] - g_c * dc - g_r * dr
                                for (a, b, e, f), (dr, dc) in zip(sl, offs)])
            n = np.count_nonzero(np.isfinite(carried), axis=0)
            pred = _nanmedian0(carried)
            res = c[r0:r1] - pred
            res[n < MIN_NEIGHBOURS] = np.nan
            resid[r0:r1] = res
            n[np.isnan(c[r0:r1])] = 0
            count[r0:r1] = n
        # What a plane leaves of a curved map is smooth too: take the neighbours' residuals
        # (their median) off, so only what stands out from its surroundings remains.
        out = np.full((h, w), np.nan)
        for r0 in range(0, h, ROWS_PER_CHUNK):
            r1 = min(h, r0 + ROWS_PER_CHUNK)
            around = _nanmedian0(np.stack([rp[r0 + pad + dr:r1 + pad + dr, pad + dc:pad + dc + w]
                                           for dr, dc in offs]))
            out[r0:r1] = resid[r0:r1] - np.where(np.isfinite(around), around, 0.0)
    return out, count


def _kernels():
    """:mod:`ptpcore.decode._spatial_kernel` when the numba kernels are on, else None."""
    from ptpcore.decode.phase import fused_kernels

    if fused_kernels() is None:
        return None
    from ptpcore.decode import _spatial_kernel

    return _spatial_kernel


def _padded_maps(coord: np.ndarray, valid: np.ndarray, pad: int, lo: int = 0, hi: int | None = None
                 ) -> tuple[np.ndarray, ...]:
    """The coordinate (NaN where not valid), its central differences along columns and rows, and
    room for the residual, of image rows ``[lo, hi)`` (default all), each inside a NaN border of ``pad``
    pixels: (hi - lo + 2 pad, W + 2 pad) float64. The border rows are the image's own where it has them.

    Written in place (no padded copy of an unpadded map: 40 MB less to touch per map at 5 MP).
    """
    h, w = coord.shape
    hi = h if hi is None else hi
    a0, a1 = max(lo - pad, 0), min(hi + pad, h)  # the image rows the padded maps hold
    g0, g1 = max(a0 - 1, 0), min(a1 + 1, h)  # and the rows their row differences read
    maps = []
    i0, i1 = a0 - lo + pad, a1 - lo + pad  # the padded rows of image rows [a0, a1)
    first, last = max(a0, 1), min(a1, h - 1)  # the rows with a row difference
    for i in range(4):
        # NaN only where nothing is written below (the border; all of the residual's room but
        # what the residual fills): np.full wrote every value twice.
        a = np.empty((hi - lo + 2 * pad, w + 2 * pad))
        a[:, :pad], a[:, pad + w:] = np.nan, np.nan
        top, bottom = (i0, i1) if i < 2 else (first - a0 + i0, last - a0 + i0) if i == 2 else (pad, pad + hi - lo)
        a[:top], a[max(bottom, top):] = np.nan, np.nan
        maps.append(a)
    inner = slice(i0, i1), slice(pad, pad + w)
    c, gc, gr = (m[inner] for m in maps[:3])
    near = np.full((g1 - g0, w), np.nan)  # the coordinate of rows [g0, g1), NaN where not valid
    np.copyto(near, coord[g0:g1], where=valid[g0:g1])
    c[...] = near[a0 - g0:a1 - g0]
    gc[:, :1], gc[:, w - 1:] = np.nan, np.nan
    if w > 2:
        np.subtract(c[:, 2:], c[:, :-2], out=gc[:, 1:-1])
        gc[:, 1:-1] *= 0.5
    # Row differences of rows [a0, a1), NaN at the image's first and last rows.
    if last > first:
        out = gr[first - a0:last - a0]
        np.subtract(near[first + 1 - g0:last + 1 - g0], near[first - 1 - g0:last - 1 - g0], out=out)
        out *= 0.5
    return tuple(maps)


SPATIAL_BAND_PIXELS = 1 << 20
"""Pixels per band of the fused residual: its four padded float64 maps are held for one band (35 MB at
4000 px wide) instead of the whole image (390 MB at 12 MP); a band recomputes the residuals of the
``2 pad`` rows around it that its neighbours' medians read (3 % more at 4000 px wide)."""


def _residual_fused(kern, coord: np.ndarray, valid: np.ndarray, pad: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`neighbourhood_residual` by the numba kernels, band by band of rows (bit-equal: every pixel's
    numbers come from the same neighbours whatever the band)."""
    from ptpcore.parallel import run_tiles

    h, w = coord.shape
    offs = np.array(window_offsets(), np.int64).reshape(-1, 2)
    out = np.empty((h, w))
    count = np.empty((h, w), np.int16)
    rows = max(4 * pad, SPATIAL_BAND_PIXELS // max(w, 1))
    for b0 in range(0, h, rows):
        b1 = min(h, b0 + rows)
        lo, hi = max(b0 - pad, 0), min(b1 + pad, h)  # the rows whose residuals the band's medians read
        cp, gcp, grp, rp = _padded_maps(coord, valid, pad, lo, hi)
        resid = rp[pad:pad + hi - lo, pad:pad + w]
        band_count = np.empty((hi - lo, w), np.int16)
        run_tiles(lambda r0, r1: kern.residual_rows(cp, gcp, grp, offs, pad, MIN_NEIGHBOURS, r0, r1, resid,
                                                    band_count), hi - lo, w)
        del cp, gcp, grp
        count[b0:b1] = band_count[b0 - lo:b1 - lo]
        band_out = out[lo:hi]  # row r of the band's maps is image row lo + r
        run_tiles(lambda r0, r1: kern.around_rows(rp, offs, pad, r0 + b0 - lo, r1 + b0 - lo, band_out), b1 - b0, w)
        del rp
    return out, count


def spatial_outliers(coord: np.ndarray, valid: np.ndarray, sigma, k: float = 5.0, **kwargs
                     ) -> tuple[np.ndarray, float]:
    """Pixels departing from their neighbourhood by more than ``k`` sigma.

    Parameters
    ----------
    coord, valid : see :func:`neighbourhood_residual`
    sigma : float, (H, W) array, callable or None
        Predicted 1-sigma noise of ``coord`` (px). A callable ``sigma(r0, r1)`` gives rows
        ``[r0, r1)`` as an ``(r1 - r0, W)`` array (the map is never made whole: 96 MB of
        float64 at 12 MP, at the decoder's peak). None: estimated from the residuals
        themselves (robust spread over the valid pixels).
    k : float

    Returns
    -------
    flagged : (H, W) bool
    sigma_used : float
        The median sigma used: the predicted one, but never below the robust
        spread of the residuals over the map (the fit's own floor).
    """
    resid, n = neighbourhood_residual(coord, valid, **kwargs)
    finite = np.isfinite(resid)
    if not finite.any():
        return np.zeros(coord.shape, bool), float("nan")
    magnitude = resid[finite]  # a copy, made absolute in place
    np.abs(magnitude, out=magnitude)
    spread = ROBUST_SIGMA * median_exact(magnitude)
    del magnitude
    if sigma is None:
        sigma = spread
    if not callable(sigma):
        sigma_map = np.asarray(sigma, np.float64)
        if not sigma_map.ndim:
            flagged = _flag_rows(resid, n, finite, lambda r0, r1: sigma_map, spread, k)
            return flagged, float(np.maximum(sigma_map, spread))
        sigma = lambda r0, r1: sigma_map[r0:r1]  # noqa: E731 - the map's rows
    # Where the map is less smooth than the noise (noise-free data, structure the
    # local plane does not follow), the robust spread of the residuals is the floor.
    # The median of max(sigma, spread) is taken over the pixels where sigma is defined
    # (NaN stays NaN), gathered band by band (np.empty: only the pages written count).
    defined = np.empty(resid.size)
    kern = _kernels()
    if kern is not None:  # each band in one pass (the same bits as _flag_rows)
        flagged = np.empty(resid.shape, bool)
        end = 0
        for r0 in range(0, resid.shape[0], FLAG_ROWS):
            r1 = min(resid.shape[0], r0 + FLAG_ROWS)
            sig = np.ascontiguousarray(sigma(r0, r1), np.float64)
            end = kern.flag_band(resid[r0:r1], n[r0:r1], sig, spread, float(k), np.pi / 2.0, flagged[r0:r1],
                                 defined, end)
        return flagged, (median_exact(defined[:end]) if end else float("nan"))
    count = [0]

    def sigma_rows(r0, r1):
        sig = np.asarray(sigma(r0, r1), np.float64)
        kept = sig[~np.isnan(sig)]
        np.maximum(kept, spread, out=kept)
        defined[count[0]:count[0] + kept.size] = kept
        count[0] += kept.size
        return sig

    flagged = _flag_rows(resid, n, finite, sigma_rows, spread, k)
    defined = defined[:count[0]]
    return flagged, (median_exact(defined) if defined.size else float("nan"))


def _flag_rows(resid, n, finite, sigma_rows, spread: float, k: float) -> np.ndarray:
    """``|resid| > k max(sigma, spread) sqrt(1 + pi / 2 / n)`` band by band of rows (no whole-map temporaries)."""
    flagged = np.empty(resid.shape, bool)
    for r0 in range(0, resid.shape[0], FLAG_ROWS):
        r1 = min(resid.shape[0], r0 + FLAG_ROWS)
        sig = np.maximum(sigma_rows(r0, r1), spread)
        # The median prediction has its own noise, about sqrt(pi / 2 / n) of one pixel's.
        scale = np.sqrt(1.0 + np.pi / 2.0 / np.maximum(n[r0:r1], 1))
        with np.errstate(invalid="ignore"):
            flagged[r0:r1] = finite[r0:r1] & (np.abs(resid[r0:r1]) > k * sig * scale)
    return flagged
