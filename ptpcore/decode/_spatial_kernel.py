"""numba kernels of the spatial-consistency check (:mod:`ptpcore.decode.spatial`).

Optional like :mod:`ptpcore.decode._fused` (loaded only when
:func:`ptpcore.decode.phase.fused_kernels` is not None). Per pixel, the medians of
:func:`ptpcore.decode.spatial.neighbourhood_residual` by an insertion sort of the
(at most 25) non-NaN window values (a selection, not a sort), with the numpy path's arithmetic operation for
operation (``fastmath=False``): the results are bit-equal. The numpy path sorts a
stack of 25 shifted copies of every chunk (four passes), about 6 s per direction at
5 MP; the kernels do it in one pass over the pixels per stage, on the tile pool.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_OPTS = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")


def _batcher(n: int) -> list[tuple[int, int]]:
    """Batcher's odd-even merge sort network for ``n`` (a power of 2) wires: comparators ``(i, j)``,
    ``i < j``, after which wire i holds the smaller value."""
    out = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            for j in range(k % p, n - k, 2 * k):
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        out.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return out


def median_network(m: int) -> tuple[np.ndarray, np.ndarray]:
    """A selection network for the middle value(s) of ``m <= 32`` values.

    Batcher's 32-wire network with the wires ``m..31`` taken as +inf (their comparators are
    no-ops or relabellings), pruned to the comparators the middle wires depend on (113 for 25
    values, 108 for 24). Branch-free, so the kernels run it on whole rows of pixels at once.

    Returns
    -------
    net : (C, 2) int64
        Comparators ``(a, b)``: slot a takes the smaller value, slot b the larger.
    slots : (2,) int64
        Where the lower and upper middle values end (the same slot for odd ``m``).
    """
    n = 32
    inf = [w >= m for w in range(n)]
    phys = list(range(n))
    ops = []
    for i, j in _batcher(n):
        if inf[j]:
            continue
        if inf[i]:  # the +inf moves up: a relabelling, no comparison
            phys[i], phys[j] = phys[j], phys[i]
            inf[i], inf[j] = False, True
            continue
        ops.append((phys[i], phys[j]))
    outs = [(m - 1) // 2, m // 2]
    need = {phys[o] for o in outs}
    keep = []
    for a, b in reversed(ops):
        if a in need or b in need:
            keep.append((a, b))
            need |= {a, b}
    keep.reverse()
    return np.array(keep, np.int64), np.array([phys[o] for o in outs], np.int64)


NET25, SLOTS25 = median_network(25)
NET24, SLOTS24 = median_network(24)


@njit(**_OPTS)
def _median(buf, n):
    """Median of ``buf[:n]`` (reordered in place): the mean of the two middle values, NaN for
    n = 0. Wirth's selection of the lower middle, then the least value above it: the same two
    values a sort would pick, about a third of an insertion sort's work for n = 25."""
    if n == 0:
        return np.nan
    k = (n - 1) // 2
    lo_i = 0
    hi_i = n - 1
    while lo_i < hi_i:
        x = buf[k]
        i = lo_i
        j = hi_i
        while True:
            while buf[i] < x:
                i += 1
            while x < buf[j]:
                j -= 1
            if i <= j:
                t = buf[i]
                buf[i] = buf[j]
                buf[j] = t
                i += 1
                j -= 1
            if i > j:
                break
        if j < k:
            lo_i = i
        if k < i:
            hi_i = j
    lo = buf[k]
    if n % 2 == 1:
        return 0.5 * (lo + lo)
    hi = buf[k + 1]
    for i in range(k + 2, n):
        if buf[i] < hi:
            hi = buf[i]
    return 0.5 * (lo + hi)


@njit(**_OPTS)
def _gather(src, rr, pad, offs, with_centre, w, vals, nan_count):
    """``vals[k, c]``: the window value ``k`` of pixel ``(rr - pad, c)``; ``nan_count[c]``: its NaNs."""
    nk = offs.shape[0]
    for c in range(w):
        nan_count[c] = 0
    for k in range(nk):
        row = src[rr + offs[k, 0]]
        base = pad + offs[k, 1]
        for c in range(w):
            v = row[base + c]
            vals[k, c] = v
            if np.isnan(v):
                nan_count[c] += 1
    if with_centre:
        row = src[rr]
        for c in range(w):
            v = row[pad + c]
            vals[nk, c] = v
            if np.isnan(v):
                nan_count[c] += 1


@njit(**_OPTS)
def _row_medians(vals, m, nan_count, net, slots, w, work, buf, out):
    """``out[c]``: the NaN-ignoring median of ``vals[:m, c]`` (the network where no value is NaN,
    a selection of the others)."""
    for k in range(m):
        for c in range(w):
            work[k, c] = vals[k, c]
    for q in range(net.shape[0]):
        ra = work[net[q, 0]]
        rb = work[net[q, 1]]
        for c in range(w):
            x = ra[c]
            y = rb[c]
            ra[c] = x if x < y else y
            rb[c] = y if x < y else x
    lo = work[slots[0]]
    hi = work[slots[1]]
    for c in range(w):
        if nan_count[c] == 0:
            out[c] = 0.5 * (lo[c] + hi[c])
        else:
            n = 0
            for k in range(m):
                v = vals[k, c]
                if not np.isnan(v):
                    buf[n] = v
                    n += 1
            out[c] = _median(buf, n)


@njit(**_OPTS)
def residual_rows(cp, gcp, grp, offs, pad, min_n, r0, r1, resid, count):
    """Rows ``r0:r1``: the residual from the median-carried neighbours (before the
    neighbours' residual is taken off) and the count of neighbours. ``cp``, ``gcp``,
    ``grp``: the coordinate and its column/row gradients, NaN-padded by ``pad``."""
    nk = offs.shape[0]
    w = resid.shape[1]
    vals = np.empty((nk + 1, w))
    work = np.empty((nk + 1, w))
    nan_count = np.empty(w, np.int64)
    buf = np.empty(nk + 1)
    g_c = np.empty(w)
    g_r = np.empty(w)
    pred = np.empty(w)
    fin = np.empty(w, np.int64)
    for r in range(r0, r1):
        rr = r + pad
        _gather(gcp, rr, pad, offs, True, w, vals, nan_count)
        _row_medians(vals, nk + 1, nan_count, NET25, SLOTS25, w, work, buf, g_c)
        _gather(grp, rr, pad, offs, True, w, vals, nan_count)
        _row_medians(vals, nk + 1, nan_count, NET25, SLOTS25, w, work, buf, g_r)
        for c in range(w):
            nan_count[c] = 0
            fin[c] = 0
        for k in range(nk):
            dr = offs[k, 0]
            dc = offs[k, 1]
            row = cp[rr + dr]
            base = pad + dc
            for c in range(w):
                v = row[base + c] - g_c[c] * dc - g_r[c] * dr
                vals[k, c] = v
                if np.isnan(v):
                    nan_count[c] += 1
                if np.isfinite(v):
                    fin[c] += 1
        _row_medians(vals, nk, nan_count, NET24, SLOTS24, w, work, buf, pred)
        centre = cp[rr]
        for c in range(w):
            res = centre[pad + c] - pred[c]
            if fin[c] < min_n:
                res = np.nan
            resid[r, c] = res
            count[r, c] = fin[c]


@njit(**_OPTS)
def around_rows(rp, offs, pad, r0, r1, out):
    """Rows ``r0:r1``: the residual minus the median of its neighbours' residuals (``rp``: the
    residuals NaN-padded by ``pad``)."""
    nk = offs.shape[0]
    w = out.shape[1]
    vals = np.empty((nk, w))
    work = np.empty((nk, w))
    nan_count = np.empty(w, np.int64)
    buf = np.empty(nk)
    around = np.empty(w)
    for r in range(r0, r1):
        rr = r + pad
        _gather(rp, rr, pad, offs, False, w, vals, nan_count)
        _row_medians(vals, nk, nan_count, NET24, SLOTS24, w, work, buf, around)
        centre = rp[rr]
        for c in range(w):
            a = around[c]
            if not np.isfinite(a):
                a = 0.0
            out[r, c] = centre[pad + c] - a
