"""Selection networks for the spatial check's window medians, and the source of their row kernels.

The spatial-consistency check (:mod:`ptpcore.decode.spatial`) takes four medians per pixel
and direction over a 5 x 5 window sampled every second pixel: 25 values (the column and
row gradients, centre included) or 24 (the carried neighbours, the neighbours' residuals).
A comparator network finds the middle values without branches. Run on one pixel's values
held in registers, across a row of pixels at once (one SIMD lane a pixel), it is about 2.5x
faster than the same network run pass by pass over a stack of rows in memory, which is
bound by the stores of every pass.

numba compiles a function of fixed straight-line code but has no way to unroll a loop over a
network into one, so :func:`render_module` writes the row kernels out as Python source: the
module ``_median_rows.py`` beside this one is its output, checked in and compared with it by
``tests/decode/test_spatial_kernel.py``. Regenerate it after changing the window or the networks::

    python -m ptpcore.decode.median_networks > ptpcore/decode/_median_rows.py
"""

from __future__ import annotations

import numpy as np

__all__ = ["median_network", "window_offsets", "render_module", "NET25", "SLOTS25", "NET24", "SLOTS24"]

RADIUS = 4
STEP = 2


def window_offsets(radius: int = RADIUS, step: int = STEP) -> list[tuple[int, int]]:
    """``(d_row, d_col)`` of a pixel's neighbours: every ``step`` pixels out to ``radius``, the centre left out."""
    r = range(-radius, radius + 1, step)
    return [(dr, dc) for dr in r for dc in r if (dr, dc) != (0, 0)]


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
    values, 108 for 24). Branch-free.

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

_HEADER = '''"""Row kernels of the spatial check's window medians: GENERATED, do not edit.

Written by ``python -m ptpcore.decode.median_networks`` (see that module); the test
``tests/decode/test_spatial_kernel.py`` fails when this file and the generator disagree.
Each kernel takes the pixels ``(rr - pad, c)``, ``c < w``, of a NaN-padded map (``col0`` = the
padding): ``out[c]`` the mean of the two middle values of the window by the network (meaningful
only where ``nans[c] == 0``: the caller takes a NaN-ignoring median elsewhere; ``nans[c]`` is 1 where
the window holds a NaN (the carried kernel: the count of values not finite)).
"""

from numba import njit

_OPTS = dict(nogil=True, cache=True, fastmath=False, error_model="numpy")
'''


def _network_lines(net: np.ndarray, slots: np.ndarray, indent: str) -> list[str]:
    lines = []
    for a, b in net:
        lines.append(f"{indent}lo = a{a} if a{a} < a{b} else a{b}")
        lines.append(f"{indent}a{b} = a{b} if a{a} < a{b} else a{a}")
        lines.append(f"{indent}a{a} = lo")
    lines.append(f"{indent}out[c] = 0.5 * (a{slots[0]} + a{slots[1]})")
    return lines


def _kernel(name: str, doc: str, m: int, with_centre: bool, carried: bool) -> list[str]:
    net, slots = (NET25, SLOTS25) if m == 25 else (NET24, SLOTS24)
    args = "src, rr, col0, w, g_c, g_r, out, nans, fin" if carried else "src, rr, col0, w, out, nans"
    lines = ["", "", "@njit(**_OPTS)", f"def {name}({args}):", f'    """{doc}"""', "    for c in range(w):"]
    ind = " " * 8
    if carried:
        lines += [f"{ind}gc = g_c[c]", f"{ind}gr = g_r[c]"]
    values = list(enumerate(window_offsets()))
    if with_centre:
        values.append((len(values), (0, 0)))
    for k, (dr, dc) in values:
        load = f"src[{_plus('rr', dr)}, {_plus('col0 + c', dc)}]"
        # The same operations in the same order as the numpy path: v - g_c * dc - g_r * dr.
        lines.append(f"{ind}a{k} = {load} - gc * {float(dc)!r} - gr * {float(dr)!r}" if carried else f"{ind}a{k} = {load}")
    if carried:
        lines += _sum_lines(f"{ind}fin[c] = ", [f"(abs(a{k}) < _INF)" for k in range(m)], ind)
        lines.append(f"{ind}nans[c] = {m} - fin[c]")  # NaN (and infinite: the fall-back takes them alike)
    else:
        # Any NaN, by the sum (one add a value where counting took a compare, a convert and an add;
        # +inf and -inf together also make NaN: the fall-back's median is then the network's).
        lines += _sum_lines(f"{ind}t = ", [f"a{k}" for k in range(m)], ind)
        lines.append(f"{ind}nans[c] = t != t")
    return lines + _network_lines(net, slots, ind)


def _plus(name: str, d: int) -> str:
    return name if d == 0 else f"{name} {'+' if d > 0 else '-'} {abs(d)}"


def _sum_lines(head: str, terms: list[str], ind: str, per_line: int = 5) -> list[str]:
    """``head (t0 + t1 + ...)`` over lines of ``per_line`` terms."""
    rows = [" + ".join(terms[i:i + per_line]) for i in range(0, len(terms), per_line)]
    pad = " " * (len(head) - len(ind) + 1)
    return [head + "(" + rows[0]] + [f"{ind}{pad}+ {r}" for r in rows[1:-1]] + [f"{ind}{pad}+ {rows[-1]})"]


def render_module() -> str:
    """The source text of ``ptpcore/decode/_median_rows.py``."""
    parts = [_HEADER, "_INF = float(\"inf\")"]
    parts += _kernel("median25_row", "Median of the 25 window values, centre included (the gradients).", 25, True, False)
    parts += _kernel("median24_row", "Median of the 24 neighbours (the neighbours' residuals).", 24, False, False)
    parts += _kernel("carried_median24_row", "Median of the 24 neighbours carried to the centre along the\n"
                     "    gradients ``g_c``, ``g_r`` (w,); ``fin[c]``: how many are finite.", 24, False, True)
    return "\n".join(parts) + "\n"


if __name__ == "__main__":
    print(render_module(), end="")
