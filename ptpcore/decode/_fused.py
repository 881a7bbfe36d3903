"""Fused per-tile kernels compiled with numba (optional: ``pip install "ptp-studio[fast]"``).

Imported only through :func:`ptpcore.decode.phase.fused_kernels`, which returns None
when numba is missing or ``PTP_NO_NUMBA=1``; the numpy/OpenCV path then runs
unchanged. Each kernel does one row tile in one pass over its pixels, with the
arithmetic of the numpy path operation for operation (``fastmath=False``), so:

- :func:`nstep_rows`: the N-step sums straight from uint8/uint16 frames (a
  tuple of (H, W) arrays: slices of a stack or files mapped one by one), pixel
  by pixel with the frames in the inner loop (``-S``, ``C``, ``sum I``,
  ``sum I^2``, the maximum for saturation) in float32 (``sum I^2`` in float64
  where float32 is not exact), then modulation, background and the noise
  residual. ``atan2`` stays with numpy
  (:func:`ptpcore.decode.phase._nstep_rows_fused` calls it on the tile right after):
  numpy's float32 ``arctan2`` is SIMD, about 25 times cheaper than the scalar
  libm call numba would make.
- :func:`unwrap_classify_rows`: hierarchical unwrapping of one direction
  (bit-equal to :func:`ptpcore.decode.phase._unwrap_rows`) and the per-pixel reasons
  that need no neighbours (low modulation, saturation, disagreement, outside).
- :func:`near_edge_rows`: the border test by LCD-edge distance (bit-equal to
  :func:`ptpcore.decode.phase._near_edge`: the gradient and ``hypot`` only where a
  per-pixel bound leaves the result in doubt).
- :func:`store_rows`: world coordinates and the sample maps of one position
  (bit-equal to :func:`ptpcore.run.pipeline._store_rows`).
- :func:`poly_fit_full`, :func:`valid_span`: the LUT fit of the pixels valid at
  every position, and each pixel's count and first/last valid position
  (equal to :func:`ptpcore.fit.fit_lut`'s numpy path).

The kernels release the GIL (``nogil=True``) and run on the engine's tile pool
(:func:`ptpcore.parallel.run_tiles`, ``PTP_THREADS``), not on numba's own
threads: a tile's kernel and numpy's ``arctan2`` then share the cache, and
nothing depends on numba's threading layer (which cannot be entered from
several Python threads at once, as the dataset reader and the GUI do).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_OPTS = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")

LOW_MODULATION, SATURATED, UNWRAP, OUTSIDE_LCD, BORDER = 1, 2, 4, 8, 16  # ptpcore.decode.phase.Reason


# Two row kernels on purpose: the coarse periods need only S, C, modulation and saturation, and
# the extra sums of the full kernel (background, noise residual) cost about half its time.
@njit(**_OPTS)
def _row_lean(frames, r, ws, wc, sat_thr, black_thr, two_over_n, ns_row, c_row, mod_row, sat_row, black_row):
    n = len(frames)
    for c in range(ns_row.shape[0]):
        s = np.float32(0.0)
        cc = np.float32(0.0)
        m = frames[0][r, c]
        lo = m
        for i in range(n):
            x = frames[i][r, c]
            v = np.float32(x)
            s += ws[i] * v
            cc += wc[i] * v
            m = max(m, x)
            lo = min(lo, x)
        ns_row[c] = s
        c_row[c] = cc
        mod_row[c] = np.float32(math.sqrt(s * s + cc * cc)) * two_over_n
        sat_row[c] = np.int64(m) >= sat_thr
        black_row[c] = np.int64(lo) <= black_thr


@njit(**_OPTS)
def _row_full(frames, r, ws, wc, sat_thr, black_thr, two_over_n, one_w, ns_row, c_row, mod_row, sat_row, black_row,
              bg_row, rv_row):
    n = len(frames)
    fn = np.float32(n)
    n_w = one_w * n
    two_w = one_w * 2
    zero_w = one_w - one_w
    rv_scale = one_w * (1.0 / (n * (n - 3)) if n > 3 else 0.0)
    for c in range(ns_row.shape[0]):
        s = np.float32(0.0)
        cc = np.float32(0.0)
        a = np.float32(0.0)
        sq = zero_w
        m = frames[0][r, c]
        lo = m
        for i in range(n):
            x = frames[i][r, c]
            v = np.float32(x)
            s += ws[i] * v
            cc += wc[i] * v
            a += v
            vw = v * one_w
            sq += vw * vw
            m = max(m, x)
            lo = min(lo, x)
        ns_row[c] = s
        c_row[c] = cc
        zz = np.float32(math.sqrt(s * s + cc * cc))
        mod_row[c] = zz * two_over_n
        sat_row[c] = np.int64(m) >= sat_thr
        black_row[c] = np.int64(lo) <= black_thr
        bg_row[c] = a / fn
        # (N sum I^2 - (sum I)^2 - 2 |Z|^2) / (N (N - 3)), as the numpy path; computed even
        # when not wanted (then into a scratch row): a branch here stops the loop vectorising
        aw = a * one_w
        zw = zz * one_w
        q = sq * n_w
        q -= aw * aw
        q -= (zw * zw) * two_w
        q = q if q >= zero_w else zero_w
        rv_row[c] = q * rv_scale


@njit(**_OPTS)
def nstep_rows(frames, r0, r1, ws, wc, sat_thr, neg_s, c_out, modulation, saturated,
               photometry, background, one_w, residual_var, rv_r0, black_thr, black, black_r0):
    """N-step sums of rows ``[r0, r1)`` of ``frames``, a tuple of N (H, W) uint8 or uint16 frames.

    ``ws``/``wc``: float32 weights ``-sin(delta_n)``, ``cos(delta_n)``.
    ``sat_thr``: saturated where the maximum step is ``>= sat_thr`` (an integer).
    ``black_thr``: ``black`` row ``r - black_r0`` is True where the minimum step is ``<= black_thr``
    (an integer; the minimum is kept beside the maximum, so the black-clipping check costs no pass
    of its own; an unwanted one goes to a scratch tile, ``black_r0 = r0``).
    ``neg_s``, ``c_out``: (r1 - r0, W) float32, the tile's ``-S`` and ``C``.
    ``modulation``, ``saturated``, ``background``, ``residual_var``: (H, W)
    outputs (the last two only if ``photometry``). ``one_w``: a 1 of the dtype
    the numpy path uses for ``sum I^2`` and the residual (float32, exact, for
    uint8 and N <= 16; else float64). ``residual_var`` row ``r`` is
    ``residual_var[r - rv_r0]``, written whenever ``photometry`` is (an
    unwanted one goes to a scratch tile, ``rv_r0 = r0``).

    Pixel by pixel, the N frames in the inner loop (N is the tuple's length, a
    compile-time constant, so that loop unrolls and the pixel loop vectorises;
    one small function per row kind, so that LLVM does): the sums stay in
    registers, 3-5x cheaper than updating row accumulators frame by frame.
    Every sum still adds its frames in order 0..N-1 in the same precision, so
    the results are those of the row-accumulator form, bit for bit (test).
    """
    n = len(frames)
    two_over_n = np.float32(2.0 / n)
    for r in range(r0, r1):
        t = r - r0
        if photometry:
            _row_full(frames, r, ws, wc, sat_thr, black_thr, two_over_n, one_w, neg_s[t], c_out[t], modulation[r],
                      saturated[r], black[r - black_r0], background[r], residual_var[r - rv_r0])
        else:
            _row_lean(frames, r, ws, wc, sat_thr, black_thr, two_over_n, neg_s[t], c_out[t], modulation[r],
                      saturated[r], black[r - black_r0])


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
def _axpy(a, x, out, m):
    for q in range(m):
        out[q] += a * x[q]


@njit(**_OPTS)
def _to_f64(src, dst, m):
    for q in range(m):
        dst[q] = np.float64(src[q])


@njit(**_OPTS)
def _resid_sums(yv, r, s, sq, sl, m):
    for q in range(m):
        e = yv[q] - r[q]
        sq[q] += e * e
        e *= s
        sl[q] += e * e


@njit(**_OPTS)
def poly_fit_full(pinv, v, loo_scale, with_loo, y, coef, rms, loo):
    """Least squares of every column of ``y`` (K, P) with all K samples valid.

    ``coef = pinv @ y``, ``resid = y - v @ coef``, ``rms = sqrt(sum resid^2 / K)``,
    ``loo = sqrt(sum (resid * loo_scale)^2 / K)`` (if ``with_loo``), as
    :func:`ptpcore.io.lutfile._fit_poly_tile_xy` does with ``einsum``, in one pass over
    ``y`` (float32 or float64, each sample taken as float64) in blocks of
    pixels that stay in L1/L2. Each step is a small loop over the block's
    pixels (an ``axpy``), which LLVM vectorises; every sum runs over the
    positions (or coefficients) in order, so the results do not depend on the
    block size. Equal to the einsum path to a float64 rounding or two.
    """
    n_coef, k = pinv.shape
    p = y.shape[1]
    blk = 512
    c = np.empty((n_coef, blk))
    r = np.empty(blk)
    sq = np.empty(blk)
    sl = np.empty(blk)
    yk = np.empty((k, blk))
    for p0 in range(0, p, blk):
        m = min(blk, p - p0)
        for j in range(k):
            _to_f64(y[j, p0:p0 + m], yk[j], m)
        for i in range(n_coef):
            ci = c[i]
            ci[:] = 0.0
            for j in range(k):
                _axpy(pinv[i, j], yk[j], ci, m)
        sq[:] = 0.0
        sl[:] = 0.0
        for j in range(k):
            r[:] = 0.0
            for i in range(n_coef):
                _axpy(v[j, i], c[i], r, m)
            _resid_sums(yk[j], r, loo_scale[j], sq, sl, m)
        for q in range(m):
            for i in range(n_coef):
                coef[i, p0 + q] = c[i, q]
            rms[p0 + q] = math.sqrt(sq[q] / k)
            if with_loo:
                loo[p0 + q] = math.sqrt(sl[q] / k)


@njit(**_OPTS)
def _span_row(row, jj, n_out, first_out, last_out, seen):
    for q in range(row.shape[0]):
        v = row[q] == 0
        n_out[q] += 1 if v else 0
        first_out[q] = jj if (v and not seen[q]) else first_out[q]
        last_out[q] = jj if v else last_out[q]
        seen[q] |= v


@njit(**_OPTS)
def valid_span(reasons, order, n_out, first_out, last_out):
    """Per pixel of a ``(K, P)`` block of reasons: the number of valid samples (reason 0),
    and the first and last valid one in the order ``order`` (indices into ``order``;
    0 and K-1 when none is valid, like ``argmax`` of an all-false column).
    Branch-free, one row at a time, so the pixel loop vectorises."""
    k, p = reasons.shape
    for q in range(p):
        n_out[q] = 0
        first_out[q] = 0
        last_out[q] = k - 1
    seen = np.zeros(p, np.bool_)
    for jj in range(k):
        _span_row(reasons[order[jj]], jj, n_out, first_out, last_out, seen)


@njit(**_OPTS)
def dft_pairs(frames, transposed, rows, pairs, cos_t, sin_t, re_out, im_out, bg_out):
    """DFT bins and mean of the sampled pixels of one N-step set, straight from its integer frames.

    ``frames``: tuple of N (H, W) uint8/uint16 frames; sample ``(i, j)`` is pixel ``(rows[i], pairs[j])``
    of the image (of its transpose when ``transposed``: pixel ``(pairs[j], rows[i])``). For bin ``b``
    (``cos_t[b]``, ``sin_t[b]``: the N weights), ``re_out[b, i, j] = sum_n I_n cos_n`` and
    ``im_out[b, i, j] = -sum_n I_n sin_n``, ``bg_out[i, j] = sum_n I_n / N``: float64, summed frame by
    frame in order as :func:`ptpcore.decode.harmonics._dft_bin` and ``np.mean`` do (the same bits).
    """
    n = len(frames)
    nb = cos_t.shape[0]
    vals = np.empty(n)
    for i in range(rows.shape[0]):
        r = rows[i]
        for j in range(pairs.shape[0]):
            c = pairs[j]
            for k in range(n):
                vals[k] = np.float64(frames[k][c, r] if transposed else frames[k][r, c])
            for b in range(nb):
                re = vals[0] * cos_t[b, 0]
                im = vals[0] * sin_t[b, 0]
                for k in range(1, n):
                    re += vals[k] * cos_t[b, k]
                    im += vals[k] * sin_t[b, k]
                re_out[b, i, j] = re
                im_out[b, i, j] = -im
            s = vals[0]
            for k in range(1, n):
                s += vals[k]
            bg_out[i, j] = s / n


@njit(**_OPTS)
def coordinate_sigma_rows(bg, mod, read_var, gain, amplitude, n_fine, period, out):
    """:func:`ptpcore.decode.position.coordinate_sigma`'s rows in one pass, numpy's operations in its
    order and precision (``bg``, ``mod`` float32; ``amplitude`` float32, as numpy divides a float32 map
    by a Python float): ``sqrt(2 / n) sqrt(sigma_dn(bg)^2 + (mod / amplitude)^2 / 12) / mod * period / 2 pi``."""
    c = math.sqrt(2.0 / n_fine)
    two_pi = 2 * np.pi
    twelve = np.float32(12.0)
    h, w = out.shape
    for r in range(h):
        for j in range(w):
            lv = np.float64(bg[r, j])
            lv = lv if (lv >= 0.0 or np.isnan(lv)) else 0.0  # np.maximum(lv, 0.0)
            s = math.sqrt(read_var + gain * lv)
            q = mod[r, j] / amplitude
            q = q * q
            q = q / twelve
            var = s * s + np.float64(q)
            out[r, j] = c * math.sqrt(var) / np.float64(mod[r, j]) * period / two_pi
