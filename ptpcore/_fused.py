"""Fused per-tile kernels compiled with numba (optional: ``pip install "ptp-studio[fast]"``).

Imported only through :func:`ptpcore.phase.fused_kernels`, which returns None
when numba is missing or ``PTP_NO_NUMBA=1``; the numpy/OpenCV path then runs
unchanged. Each kernel does one row tile in one pass over its pixels, with the
arithmetic of the numpy path operation for operation (``fastmath=False``), so:

- :func:`nstep_rows`: the N-step sums straight from uint8/uint16 frames
  (``-S``, ``C``, ``sum I``, ``sum I^2``, the maximum for saturation) in float32
  (``sum I^2`` in float64 where float32 is not exact), then modulation,
  background and the noise residual. ``atan2`` stays with numpy
  (:func:`ptpcore.phase._nstep_rows_fused` calls it on the tile right after):
  numpy's float32 ``arctan2`` is SIMD, about 25 times cheaper than the scalar
  libm call numba would make.
- :func:`unwrap_classify_rows`: hierarchical unwrapping of one direction
  (bit-equal to :func:`ptpcore.phase._unwrap_rows`) and the per-pixel reasons
  that need no neighbours (low modulation, saturation, disagreement, outside).
- :func:`near_edge_rows`: the border test by LCD-edge distance (bit-equal to
  :func:`ptpcore.phase._near_edge`: the gradient and ``hypot`` only where a
  per-pixel bound leaves the result in doubt).
- :func:`store_rows`: world coordinates and the sample maps of one position
  (bit-equal to :func:`ptpcore.pipeline._store_rows`).

The kernels release the GIL (``nogil=True``) and run on the engine's tile pool
(:func:`ptpcore.phase.run_tiles`, ``PTP_THREADS``), not on numba's own
threads: a tile's kernel and numpy's ``arctan2`` then share the cache, and
nothing depends on numba's threading layer (which cannot be entered from
several Python threads at once, as the dataset reader and the GUI do).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_OPTS = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

LOW_MODULATION, SATURATED, UNWRAP, OUTSIDE_LCD, BORDER = 1, 2, 4, 8, 16  # ptpcore.phase.Reason


@njit(**_OPTS)
def _sums_lean(row, si, ci, acc_s, acc_c, mx):
    for c in range(row.shape[0]):
        x = row[c]
        v = np.float32(x)
        acc_s[c] += si * v
        acc_c[c] += ci * v
        mx[c] = max(mx[c], x)


@njit(**_OPTS)
def _sums_full(row, si, ci, acc_s, acc_c, acc_a, sq, one_w, mx):
    for c in range(row.shape[0]):
        x = row[c]
        v = np.float32(x)
        acc_s[c] += si * v
        acc_c[c] += ci * v
        acc_a[c] += v
        vw = v * one_w
        sq[c] += vw * vw
        mx[c] = max(mx[c], x)


@njit(**_OPTS)
def _finish_lean(acc_s, acc_c, mx, sat_thr, two_over_n, neg_s, c_out, modulation, saturated):
    for c in range(acc_s.shape[0]):
        s = acc_s[c]
        cc = acc_c[c]
        neg_s[c] = s
        c_out[c] = cc
        modulation[c] = np.float32(math.sqrt(s * s + cc * cc)) * two_over_n
        saturated[c] = np.int64(mx[c]) >= sat_thr


@njit(**_OPTS)
def _finish_full(acc_a, sq, acc_s, acc_c, n, one_w, background, residual_var, want_rv):
    fn = np.float32(n)
    n_w = one_w * n
    two_w = one_w * 2
    zero_w = one_w - one_w
    rv_scale = one_w * (1.0 / (n * (n - 3)) if n > 3 else 0.0)
    for c in range(acc_a.shape[0]):
        background[c] = acc_a[c] / fn
    if want_rv:
        for c in range(acc_a.shape[0]):
            # (N sum I^2 - (sum I)^2 - 2 |Z|^2) / (N (N - 3)), as the numpy path
            a = acc_a[c] * one_w
            s = acc_s[c]
            cc = acc_c[c]
            zw = np.float32(math.sqrt(s * s + cc * cc)) * one_w
            q = sq[c] * n_w
            q -= a * a
            q -= (zw * zw) * two_w
            q = q if q >= zero_w else zero_w
            residual_var[c] = q * rv_scale


@njit(**_OPTS)
def nstep_rows(frames, r0, r1, ws, wc, sat_thr, neg_s, c_out, modulation, saturated,
               photometry, background, want_rv, sq, one_w, residual_var):
    """N-step sums of rows ``[r0, r1)`` of ``frames`` (N, H, W), uint8 or uint16.

    ``ws``/``wc``: float32 weights ``-sin(delta_n)``, ``cos(delta_n)``.
    ``sat_thr``: saturated where the maximum step is ``>= sat_thr`` (an integer).
    ``neg_s``, ``c_out``: (r1 - r0, W) float32, the tile's ``-S`` and ``C``.
    ``modulation``, ``saturated``, ``background``, ``residual_var``: (H, W)
    outputs (the last two only if ``photometry``/``want_rv``). ``sq``: a (W,)
    accumulator of the dtype the numpy path uses for ``sum I^2`` and the residual
    (float32, exact, for uint8 and N <= 16; else float64), ``one_w`` a 1 of that dtype.
    """
    n, _h, w = frames.shape
    acc_s = np.empty(w, np.float32)
    acc_c = np.empty(w, np.float32)
    acc_a = np.empty(w, np.float32)
    mx = np.empty(w, frames.dtype)
    two_over_n = np.float32(2.0 / n)
    for r in range(r0, r1):
        t = r - r0
        acc_s[:] = 0
        acc_c[:] = 0
        acc_a[:] = 0
        sq[:] = 0
        mx[:] = 0
        for i in range(n):
            if photometry:
                _sums_full(frames[i, r], ws[i], wc[i], acc_s, acc_c, acc_a, sq, one_w, mx)
            else:
                _sums_lean(frames[i, r], ws[i], wc[i], acc_s, acc_c, mx)
        _finish_lean(acc_s, acc_c, mx, sat_thr, two_over_n, neg_s[t], c_out[t], modulation[r], saturated[r])
        if photometry:
            _finish_full(acc_a, sq, acc_s, acc_c, n, one_w, background[r], residual_var[r], want_rv)


@njit(**_OPTS)
def unwrap_classify_rows(r0, r1, phases, ratios, scale, shift, modulations, saturateds, min_mod,
                         extent, coord, disagreement, reasons):
    """Unwrap one direction's rows ``[r0, r1)`` into ``coord``/``disagreement`` and OR the
    per-pixel reasons (low modulation and saturation at every level, unwrapping
    disagreement, outside the LCD) into ``reasons``.

    ``phases``, ``modulations``, ``saturateds``: tuples of (H, W) arrays, coarse to fine.
    ``ratios[j] = T_{j-1} / T_j``; ``scale = T_fine / 2 pi``; ``min_mod`` float32.
    Row by row, level by level: every inner loop is over one row (vectorised).
    """
    two_pi = 2.0 * np.pi
    inv_two_pi = 1.0 / two_pi
    half_pi = np.pi / 2
    levels = len(phases)
    w = coord.shape[1]
    hi = extent - 0.5
    u = np.empty(w, np.float64)
    dis = np.empty(w, np.bool_)
    bits = np.empty(w, np.uint8)
    for r in range(r0, r1):
        p0 = phases[0][r]
        odd = False
        for c in range(w):
            x = np.float64(p0[c])
            odd |= not (x >= -two_pi and x < two_pi)
            y = x + two_pi
            x = y if x < 0 else x
            u[c] = x + 0.0  # -0.0 -> +0.0, as np.mod gives
        if odd:  # outside [-2pi, 2pi) (or NaN): np.mod's numbers
            for c in range(w):
                x = np.float64(p0[c])
                if not (x >= -two_pi and x < two_pi):
                    u[c] = x % two_pi
        dis[:] = False
        rs = reasons[r]
        for c in range(w):
            bits[c] = rs[c]
        for j in range(levels):
            mj = modulations[j][r]
            sj = saturateds[j][r]
            for c in range(w):
                b = bits[c]
                b |= LOW_MODULATION if mj[c] < min_mod else 0
                b |= SATURATED if sj[c] else 0
                bits[c] = b
            if j == 0:
                continue
            pj = phases[j][r]
            ratio = ratios[j]
            for c in range(w):
                predicted = u[c] * ratio
                phi = np.float64(pj[c])
                order = np.rint((predicted - phi) * inv_two_pi)
                x = phi + order * two_pi
                u[c] = x
                dis[c] |= abs(x - predicted) > half_pi
        cr = coord[r]
        dr = disagreement[r]
        for c in range(w):
            v = u[c] * scale
            v = v - shift
            cr[c] = v
            dr[c] = dis[c]
            b = bits[c]
            b |= UNWRAP if dis[c] else 0
            b |= 0 if (v >= -0.5 and v <= hi) else OUTSIDE_LCD
            rs[c] = b


@njit(**_OPTS)
def near_edge_rows(r0, r1, coord, extent, margin, reasons):
    """Flag ``BORDER`` in rows ``[r0, r1)`` where ``margin * hypot(*np.gradient(coord))``
    reaches past the LCD edge (pixels inside the LCD only).

    A vectorised first pass bounds the reach per pixel (``hypot(a, b) <= |a| + |b|``,
    and rounding is monotonic: outside the bound the exact test is False); the
    gradient and ``hypot`` are computed only where the bound leaves it in doubt.
    """
    h, w = coord.shape
    hi = extent - 0.5
    doubt = np.empty(w, np.bool_)
    for r in range(r0, r1):
        up = r - 1 if r > 0 else 0
        dn = r + 1 if r < h - 1 else h - 1
        inv_drow = 1.0 / (dn - up)  # 0.5 or 1: exact
        cu = coord[up]
        cd = coord[dn]
        cr = coord[r]
        for c in range(1, w - 1):
            bound = margin * (abs(cd[c] - cu[c]) * inv_drow + abs(cr[c + 1] - cr[c - 1]) * 0.5)
            bound = bound * (1 + 1e-6) + 1e-9
            v = cr[c]
            doubt[c] = (v < -0.5 + bound) | (v > hi - bound)
        doubt[0] = True
        doubt[w - 1] = True
        drow = np.float64(dn - up)
        for c in range(w):
            if not doubt[c]:
                continue
            v = cr[c]
            if not (v >= -0.5 and v <= hi):
                continue
            lf = c - 1 if c > 0 else 0
            rt = c + 1 if c < w - 1 else w - 1
            gr = (cd[c] - cu[c]) / drow
            gc = (cr[rt] - cr[lf]) / np.float64(rt - lf)
            # hypot(a, b) >= max(|a|, |b|): a lower bound that already reaches
            # past the edge decides without hypot (e.g. noise in the bezel).
            low = margin * max(abs(gr), abs(gc)) * (1 - 1e-6) - 1e-9
            if v < -0.5 + low or v > hi - low:
                reasons[r, c] |= BORDER
                continue
            reach = math.hypot(gr, gc) * margin
            if v < -0.5 + reach or v > hi - reach:
                reasons[r, c] |= BORDER


@njit(**_OPTS)
def border_rows(r0, r1, near, reasons):
    """``BORDER`` where the dilated bezel ``near`` reaches a pixel that is not bezel itself."""
    w = reasons.shape[1]
    for r in range(r0, r1):
        for c in range(w):
            if near[r, c] != 0 and (reasons[r, c] & (OUTSIDE_LCD | LOW_MODULATION)) == 0:
                reasons[r, c] |= BORDER


@njit(**_OPTS)
def store_rows(r0, r1, reasons, u, v, px, py, ax, by, x_ref, y_ref, mod_x, mod_y, bg_x, bg_y,
               with_bg, dx, dy, dreasons, dmod, dbg):
    """World coordinates relative to the first valid position, and the sample maps.

    ``ax = a * z``, ``by = b * z`` (mm). NaN where the pixel is invalid.
    """
    w = reasons.shape[1]
    half = np.float32(0.5)
    for r in range(r0, r1):
        for c in range(w):
            rs = reasons[r, c]
            valid = rs == 0
            x = u[r, c] * px
            x += ax
            if valid and np.isnan(x_ref[r, c]):
                x_ref[r, c] = x
            x -= x_ref[r, c]
            dx[r, c] = x if valid else np.nan
            y = v[r, c] * py
            y += by
            if valid and np.isnan(y_ref[r, c]):
                y_ref[r, c] = y
            y -= y_ref[r, c]
            dy[r, c] = y if valid else np.nan
            dreasons[r, c] = rs
            mx = mod_x[r, c]
            my = mod_y[r, c]
            if np.isnan(mx) or np.isnan(my):
                dmod[r, c] = np.nan
            else:
                dmod[r, c] = mx if mx < my else my
            if with_bg:
                dbg[r, c] = (bg_x[r, c] + bg_y[r, c]) * half


@njit(**_OPTS)
def poly_fit_full(pinv, v, loo_scale, with_loo, y, coef, rms, loo):
    """Least squares of every column of ``y`` (K, P) with all K samples valid.

    ``coef = pinv @ y``, ``resid = y - v @ coef``, ``rms = sqrt(sum resid^2 / K)``,
    ``loo = sqrt(sum (resid * loo_scale)^2 / K)`` (if ``with_loo``), as
    :func:`ptpcore.lut._fit_poly_tile_xy` does with ``einsum``, in one pass over
    ``y`` (float32 or float64, each sample taken as float64) in blocks of
    pixels that stay in L1. Equal to the einsum path to a float64 rounding or two.
    """
    n_coef, k = pinv.shape
    p = y.shape[1]
    blk = 256
    c = np.empty((n_coef, blk))
    r = np.empty(blk)
    sq = np.empty(blk)
    sl = np.empty(blk)
    for p0 in range(0, p, blk):
        m = min(blk, p - p0)
        for i in range(n_coef):
            for q in range(m):
                c[i, q] = 0.0
            for j in range(k):
                a = pinv[i, j]
                for q in range(m):
                    c[i, q] += a * np.float64(y[j, p0 + q])
        for q in range(m):
            sq[q] = 0.0
            sl[q] = 0.0
        for j in range(k):
            for q in range(m):
                r[q] = 0.0
            for i in range(n_coef):
                a = v[j, i]
                for q in range(m):
                    r[q] += a * c[i, q]
            s = loo_scale[j]
            for q in range(m):
                e = np.float64(y[j, p0 + q]) - r[q]
                sq[q] += e * e
                e *= s
                sl[q] += e * e
        for q in range(m):
            for i in range(n_coef):
                coef[i, p0 + q] = c[i, q]
            rms[p0 + q] = math.sqrt(sq[q] / k)
            if with_loo:
                loo[p0 + q] = math.sqrt(sl[q] / k)
