"""The comparison's statistics: error statistics, point pairs and distance curves, the verdict.

Coordinate error of a pixel: the vector ``(dX, dY)`` = method minus reference;
its statistics are those of the length ``|(dX, dY)|``. Distance error of a
point pair: the method's 3D distance minus the reference's, with the pair's
points at their held-out heights (same height, or two different heights held
out by the same calibration); pairs are stratified so their distances spread
evenly over the field. Lengths in arrays are mm; statistics are µm (``*_um``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["COMPARE_FORMAT", "SPLITS", "METHODS", "METHOD_LABELS", "REFERENCES", "PAIR_KINDS", "ErrorStats",
           "CoordinateStats", "DistanceCurve", "PairSet", "DistanceErrors", "Verdict", "error_stats",
           "coordinate_stats", "CoordinateAccumulator"]

COMPARE_FORMAT = "ptp-compare/1"
SPLITS = ("alternate", "loo")
#: Every method the comparison knows, in display order (a result holds these or a subset:
#: :attr:`CompareResult.methods`).
METHODS = ("ptp", "smooth", "3dstc")
REFERENCES = ("measured", "truth")
PAIR_KINDS = ("same_height", "across_heights")
METHOD_LABELS = {"ptp": "PTP", "smooth": "PTP smooth", "3dstc": "3DSTC"}


@dataclass
class ErrorStats:
    """Summary of a set of errors ``e`` (µm).

    Attributes
    ----------
    n : int
        Number of errors.
    rms_um : float
        ``sqrt(mean(e**2))``.
    mean_um : float
        ``mean(e)``: the bias for signed errors (distances), the mean length for
        coordinate errors.
    p95_um, max_um : float
        95th percentile and maximum of ``|e|``.

    All values are NaN when ``n == 0``.
    """

    n: int
    rms_um: float
    mean_um: float
    p95_um: float
    max_um: float

    def to_json_dict(self) -> dict:
        return {k: jsonable(v) for k, v in self.__dict__.items()}


@dataclass
class CoordinateStats(ErrorStats):
    """Coordinate errors: :class:`ErrorStats` of the length ``|(dX, dY)|`` plus per-axis values.

    Attributes
    ----------
    rms_x_um, rms_y_um : float
        RMS of ``dX`` and of ``dY`` (``rms_um**2 = rms_x_um**2 + rms_y_um**2``).
    mean_x_um, mean_y_um : float
        Mean signed ``dX``, ``dY`` (bias).
    """

    rms_x_um: float
    rms_y_um: float
    mean_x_um: float
    mean_y_um: float


def error_stats(e) -> ErrorStats:
    """:class:`ErrorStats` of errors ``e`` (any shape, mm; NaN entries ignored)."""
    e = np.asarray(e, dtype=float).ravel()
    e = e[np.isfinite(e)]
    if e.size == 0:
        return ErrorStats(0, math.nan, math.nan, math.nan, math.nan)
    a = np.abs(e)
    return ErrorStats(int(e.size), float(np.sqrt(np.mean(e * e)) * 1e3), float(np.mean(e) * 1e3),
                      float(np.percentile(a, 95) * 1e3), float(a.max() * 1e3))


def coordinate_stats(dx, dy) -> CoordinateStats:
    """:class:`CoordinateStats` of coordinate errors.

    Parameters
    ----------
    dx, dy : array_like, same shape, mm
        Method minus reference; entries where either is NaN are ignored.
    """
    dx = np.asarray(dx, dtype=float).ravel()
    dy = np.asarray(dy, dtype=float).ravel()
    ok = np.isfinite(dx) & np.isfinite(dy)
    dx, dy = dx[ok], dy[ok]
    base = error_stats(np.hypot(dx, dy))
    if base.n == 0:
        return CoordinateStats(**base.__dict__, rms_x_um=math.nan, rms_y_um=math.nan,
                               mean_x_um=math.nan, mean_y_um=math.nan)
    return CoordinateStats(**base.__dict__,
                           rms_x_um=float(np.sqrt(np.mean(dx * dx)) * 1e3),
                           rms_y_um=float(np.sqrt(np.mean(dy * dy)) * 1e3),
                           mean_x_um=float(np.mean(dx) * 1e3), mean_y_um=float(np.mean(dy) * 1e3))


@dataclass
class DistanceCurve:
    """Distance error against distance, in bins of the reference distance.

    Attributes
    ----------
    edges_mm : (B+1,) float64
        Bin edges of the reference distance (mm).
    count : (B,) int64
        Pairs per bin.
    rms_um, mean_um, p95_um : (B,) float64
        As :class:`ErrorStats`, per bin; NaN for empty bins.
    """

    edges_mm: np.ndarray
    count: np.ndarray
    rms_um: np.ndarray
    mean_um: np.ndarray
    p95_um: np.ndarray

    def to_json_dict(self) -> dict:
        return {k: jsonable(v) for k, v in self.__dict__.items()}


def distance_curve(distance_mm: np.ndarray, error_mm: np.ndarray, edges: np.ndarray) -> DistanceCurve:
    nb = max(len(edges) - 1, 0)
    b = np.clip(np.searchsorted(edges, distance_mm, side="right") - 1, 0, max(nb - 1, 0))
    out = {k: np.full(nb, np.nan) for k in ("rms", "mean", "p95")}
    count = np.zeros(nb, np.int64)
    for i in range(nb):
        s = error_stats(error_mm[b == i])
        count[i] = s.n
        out["rms"][i], out["mean"][i], out["p95"][i] = s.rms_um, s.mean_um, s.p95_um
    return DistanceCurve(np.asarray(edges, float), count, out["rms"], out["mean"], out["p95"])


@dataclass
class PairSet:
    """Point pairs for distance errors.

    Attributes
    ----------
    kind : {"same_height", "across_heights"}
    held_a, held_b : (P,) int64
        Indices into :attr:`CompareResult.held_positions` of each end's height.
    row_a, col_a, row_b, col_b : (P,) int64
        Camera pixels of the two ends.
    edges_mm : (B+1,) float64
        Bins of the measured distance used to spread the pairs over the field
        (equal quotas per bin); also the bins of the error-vs-distance curves.
    """

    kind: str
    held_a: np.ndarray
    held_b: np.ndarray
    row_a: np.ndarray
    col_a: np.ndarray
    row_b: np.ndarray
    col_b: np.ndarray
    edges_mm: np.ndarray

    def __len__(self) -> int:
        return int(self.held_a.size)


@dataclass
class DistanceErrors:
    """Distance errors of one method against one reference over one :class:`PairSet`.

    Attributes
    ----------
    kind, method, reference : str
    reference_mm : (P,) float64
        The reference's 3D distance of every pair (mm).
    error_mm : (P,) float64
        Method's distance minus the reference's (mm).
    stats : ErrorStats
    curve : DistanceCurve
    """

    kind: str
    method: str
    reference: str
    reference_mm: np.ndarray
    error_mm: np.ndarray
    stats: ErrorStats
    curve: DistanceCurve


@dataclass
class Verdict:
    """Who is ahead against one reference, and by how much.

    Attributes
    ----------
    reference : str
    coordinate_ahead : {"ptp", "smooth", "3dstc", "tie"}
        Method with the smallest coordinate RMS ("tie" when the best two are equal).
    coordinate_ratio : float
        RMS of the runner-up over RMS of the method ahead (>= 1); with two
        methods, of the method behind.
    distance_ahead : {"ptp", "smooth", "3dstc", "tie"} or None
        Method with the smallest RMS distance error over all pairs of both
        kinds; None without pairs.
    distance_ratio : float
        As ``coordinate_ratio`` for distances (NaN without pairs).
    text : str
        One sentence stating the above, with every method's RMS.
    coordinate_rms_um, distance_rms_um : dict of str to float
        Every method's coordinate RMS and RMS distance error (µm), for
        pairwise ratios (:meth:`ratio`).
    """

    reference: str
    coordinate_ahead: str
    coordinate_ratio: float
    distance_ahead: str | None
    distance_ratio: float
    text: str
    coordinate_rms_um: dict = field(default_factory=dict)
    distance_rms_um: dict = field(default_factory=dict)

    def ratio(self, behind: str, ahead: str, kind: str = "coordinate") -> float:
        """RMS of method ``behind`` over RMS of method ``ahead`` (``kind``: "coordinate" or "distance")."""
        rms = {"coordinate": self.coordinate_rms_um, "distance": self.distance_rms_um}[kind]
        a, b = rms[ahead], rms[behind]
        return b / a if a > 0 else (math.inf if b > 0 else 1.0)


def draw_pairs(mask_at, sizes, shape, groups, kind: str, n_pairs: int, n_bins: int, rng: np.random.Generator,
                measured_xyz) -> PairSet:
    """Random point pairs whose measured distances spread over the field.

    Candidates: a random compared pixel, and a second one at a random offset
    (length uniform up to the image diagonal, random direction), at the same
    height or at another height of the same fold. They are binned by measured
    3D distance into ``n_bins`` equal bins and each bin keeps at most
    ``n_pairs // n_bins`` of them.

    Parameters
    ----------
    mask_at : callable
        ``mask_at(e)``: (H, W) bool, the compared pixels of held-out position ``e``
        (read one position at a time: the whole ``(E, H, W)`` mask is never needed).
    sizes : (E,) int64
        Compared pixels per held-out position (``mask_at(e).sum()``).
    shape : (H, W)
    groups : list of (n,) int64
        Held-out positions of each fold.
    measured_xyz : callable
        ``measured_xyz(e, row, col)``: (P, 3) measured points, mm.
    """
    sizes = np.asarray(sizes, dtype=np.int64)
    e_n, (h, w) = len(sizes), shape
    if kind == "same_height":
        combos = [(e, e) for e in range(e_n) if sizes[e] >= 2]
    else:
        combos = [(a, b) for g in groups for a in g for b in g if a < b and sizes[a] and sizes[b]]
    empty = np.zeros(0, np.int64)
    if not combos or n_pairs < 1:
        return PairSet(kind, empty, empty, empty, empty, empty, empty, np.zeros(0))
    combos = np.asarray(combos, dtype=np.int64)
    diag = math.hypot(h - 1, w - 1)
    want = 10 * n_pairs
    got = []
    n_got = 0
    for _ in range(50):
        m = 2 * want
        c = combos[rng.integers(len(combos), size=m)]
        swap = rng.random(m) < 0.5  # either end may be the higher one
        ea = np.where(swap, c[:, 1], c[:, 0])
        eb = np.where(swap, c[:, 0], c[:, 1])
        pa = _nth_compared(mask_at, ea, (rng.random(m) * sizes[ea]).astype(np.int64))
        ra, ca = np.divmod(pa, w)
        length = rng.random(m) * diag
        theta = rng.random(m) * 2 * np.pi
        cb = np.rint(ca + length * np.cos(theta)).astype(np.int64)
        rb = np.rint(ra + length * np.sin(theta)).astype(np.int64)
        ok = (cb >= 0) & (cb < w) & (rb >= 0) & (rb < h)
        ok[ok] = _mask_lookup(mask_at, eb[ok], rb[ok], cb[ok])
        ok &= ~((ea == eb) & (ra == rb) & (ca == cb))
        got.append((ea[ok], eb[ok], ra[ok], ca[ok], rb[ok], cb[ok]))
        n_got += int(ok.sum())
        if n_got >= want:
            break
    ea, eb, ra, ca, rb, cb = (np.concatenate(a) for a in zip(*got))
    pa = measured_xyz(ea, ra, ca)
    pb = measured_xyz(eb, rb, cb)
    d = np.linalg.norm(pa - pb, axis=1)
    edges = np.linspace(d.min(), d.max(), n_bins + 1) if d.size else np.zeros(0)
    if d.size == 0:
        keep = np.zeros(0, np.int64)
    else:
        b = np.clip(np.searchsorted(edges, d, side="right") - 1, 0, n_bins - 1)
        quota = max(1, n_pairs // n_bins)
        keep = np.concatenate([np.flatnonzero(b == i)[:quota] for i in range(n_bins)])
        keep.sort()
    return PairSet(kind, ea[keep], eb[keep], ra[keep], ca[keep], rb[keep], cb[keep], edges)


def _nth_compared(mask_at, e: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Flat pixel index of the ``j``-th compared pixel (row-major order) of held-out position ``e``.

    One position's index list at a time (int64, H x W at most), instead of every
    position's at once: the same pixels as indexing the concatenated lists.
    """
    out = np.empty(e.shape, np.int64)
    for ei in np.unique(e):
        sel = e == ei
        out[sel] = np.flatnonzero(mask_at(int(ei)))[j[sel]]
    return out


def _mask_lookup(mask_at, e: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``mask[e, r, c]`` (bool, same shape as ``e``), one held-out position's mask at a time."""
    out = np.zeros(e.shape, bool)
    for ei in np.unique(e):
        sel = e == ei
        out[sel] = mask_at(int(ei))[r[sel], c[sel]]
    return out


class CoordinateAccumulator:
    """:func:`coordinate_stats` over values that arrive in blocks (one held-out position at a time).

    Counts, sums, the maximum and a histogram of the lengths' float32 bit patterns
    are kept; the 95th percentile is selected exactly afterwards (:meth:`result`)
    by reading the blocks again. Memory: a 65 536-bin histogram, never the values.

    ``n``, ``max_um`` and ``p95_um`` equal :func:`coordinate_stats` of the
    concatenated blocks exactly; ``rms_*`` and ``mean_*`` are sums of per-block
    sums and may differ from it in the last bits (summation order).
    """

    _TOP = 16  # the histogram's key: a float32 length's upper 16 bits (sign, exponent, 7 mantissa bits)

    def __init__(self):
        self.n = 0
        self.sums = np.zeros(6)  # length, length**2, dx, dy, dx**2, dy**2 (mm, mm**2)
        self.max = -math.inf
        self.hist = np.zeros(1 << (32 - self._TOP), np.int64)

    def add(self, dx, dy) -> None:
        """One block's coordinate errors: dx, dy (n,) mm (entries where either is NaN are ignored)."""
        dx, dy = _finite_pairs(dx, dy)
        length = _finite(np.hypot(dx, dy))
        if length.size == 0:
            return
        self.n += length.size
        self.sums += [np.sum(length), np.sum(length * length), np.sum(dx), np.sum(dy), np.sum(dx * dx),
                      np.sum(dy * dy)]
        self.max = max(self.max, float(length.max()))
        self.hist += np.bincount(_bits(length) >> self._TOP, minlength=self.hist.size)

    def result(self, lengths, n_blocks: int) -> CoordinateStats:
        """The statistics; ``lengths(i)``: block ``i``'s ``np.hypot(dx, dy)`` again, (n,) mm, as added."""
        if self.n == 0:
            return coordinate_stats([], [])
        n = self.n
        s_len, s_len2, s_x, s_y, s_x2, s_y2 = self.sums
        p95 = _linear_percentile(lambda ranks: _select_ranks(lengths, n_blocks, self.hist, self._TOP, ranks), n, 95)
        return CoordinateStats(n, float(math.sqrt(s_len2 / n) * 1e3), float(s_len / n * 1e3), float(p95 * 1e3),
                               float(self.max * 1e3), rms_x_um=float(math.sqrt(s_x2 / n) * 1e3),
                               rms_y_um=float(math.sqrt(s_y2 / n) * 1e3), mean_x_um=float(s_x / n * 1e3),
                               mean_y_um=float(s_y / n * 1e3))


def _finite_pairs(dx, dy) -> tuple[np.ndarray, np.ndarray]:
    """Flat float64 ``dx, dy`` where both are finite (as :func:`coordinate_stats` keeps them)."""
    dx = np.asarray(dx, dtype=float).ravel()
    dy = np.asarray(dy, dtype=float).ravel()
    ok = np.isfinite(dx) & np.isfinite(dy)
    return dx[ok], dy[ok]


def _finite(e: np.ndarray) -> np.ndarray:
    return e[np.isfinite(e)]


def _bits(length: np.ndarray) -> np.ndarray:
    """Lengths (>= 0) as the uint32 bit patterns of their float32 values: ordered as the lengths are.

    Rounding to float32 never reverses two lengths' order, and non-negative
    float32 values sort as their bit patterns do.
    """
    return length.astype(np.float32).view(np.uint32)


def _select_ranks(lengths, n_blocks: int, hist: np.ndarray, top: int, ranks) -> dict:
    """The values of ranks ``ranks`` (0 = smallest) of every block's lengths, exactly.

    ``hist`` counts the lengths by ``_bits >> top``. The ranks' bins are found
    from it; a pass over the blocks keeps only the lengths of those bins (about
    1 % of them near the 95th percentile), which are sorted. When those are too
    many (lengths crowding into few float32 values), a second histogram on the
    lower bits narrows the range first.
    """
    cum = np.cumsum(hist)
    bins = [int(np.searchsorted(cum, r, side="right")) for r in ranks]
    lo, hi = min(bins), max(bins)
    below = int(cum[lo - 1]) if lo else 0
    if int(cum[hi]) - below <= _SELECT_LIMIT:
        return _select_ranks_in(lengths, n_blocks, hist, ranks, 0, top)
    fine = np.zeros((hi - lo + 1) << top, np.int64)  # the lower bits within the ranks' bins
    for i in range(n_blocks):
        b = _bits(_finite(lengths(i))).astype(np.int64)
        b = b[(b >> top >= lo) & (b >> top <= hi)] - (lo << top)
        fine += np.bincount(b, minlength=fine.size)
    return _select_ranks_in(lengths, n_blocks, fine, ranks, lo << top, 0, base=below)


_SELECT_LIMIT = 4_000_000  # lengths kept for the exact selection (32 MB)


def _select_ranks_in(lengths, n_blocks: int, hist: np.ndarray, ranks, offset: int, shift: int,
                     base: int = 0) -> dict:
    """Ranks' values from the lengths whose key ``(_bits - offset) >> shift`` is in the ranks' bins.

    ``hist`` counts the keys from 0 up; ``base`` lengths lie below key 0 (their ranks come first).
    """
    cum = base + np.cumsum(hist)
    bins = [int(np.searchsorted(cum, r, side="right")) for r in ranks]
    lo, hi = min(bins), max(bins)
    below = int(cum[lo - 1]) if lo else base
    kept = []
    for i in range(n_blocks):
        v = _finite(lengths(i))
        key = (_bits(v).astype(np.int64) - offset) >> shift
        kept.append(v[(key >= lo) & (key <= hi)])
    kept = np.sort(np.concatenate(kept))
    return {r: float(kept[r - below]) for r in ranks}


def _linear_percentile(select, n: int, q: float) -> float:
    """``np.percentile(a, q)`` (method "linear") of ``n`` values from their order statistics, bit for bit.

    ``select(ranks)`` gives ``{rank: value}`` of the sorted values (rank 0 the
    smallest). numpy's steps: virtual index ``(n - 1) * q / 100``, its floor and
    the next index (both the last one past the end), then ``_lerp``.
    """
    virtual = (n - 1) * (np.float64(q) / 100)
    if virtual >= n - 1:
        return select([n - 1])[n - 1]
    prev = int(np.floor(virtual))
    gamma = virtual - np.float64(prev)
    v = select([prev, prev + 1])
    a, b = np.float64(v[prev]), np.float64(v[prev + 1])
    diff = b - a
    if gamma >= 0.5:
        return float(b - diff * (1 - gamma))
    return float(a + diff * gamma)


def _rank(values: dict) -> tuple[str | None, float, list]:
    """(method ahead or "tie" or None, runner-up over best, methods best first) of RMS values."""
    if len(values) < 2 or not all(math.isfinite(v) for v in values.values()):
        return None, math.nan, []
    order = sorted(values, key=lambda m: values[m])  # stable: METHODS order breaks ties
    a, b = values[order[0]], values[order[1]]
    if f"{a:.3g}" == f"{b:.3g}":  # equal as the summary prints them (3 significant digits): no one is ahead
        return "tie", 1.0, order
    return order[0], (b / a if a > 0 else math.inf), order


def _versus(values: dict, order: list) -> str:
    """ "b µm (r x)" with two methods, else "b µm for B (r x) and c µm for C (s x)" against the first."""
    best = values[order[0]]

    def ratio(m):
        return values[m] / best if best > 0 else math.inf

    if len(order) == 2:
        return f"{values[order[1]]:.3g} µm ({ratio(order[1]):.3g}x)"
    parts = [f"{values[m]:.3g} µm for {METHOD_LABELS[m]} ({ratio(m):.3g}x)" for m in order[1:]]
    return ", ".join(parts[:-1]) + " and " + parts[-1]


def comparison_verdict(reference: str, coord: dict, dist: dict) -> Verdict:
    """The verdict from every method's coordinate RMS and RMS distance error (µm, keyed by method)."""
    c_ahead, c_ratio, c_order = _rank(coord)
    d_ahead, d_ratio, d_order = _rank(dist)
    where = {"truth": "against the exact truth", "measured": "against the measured held-out samples"}[reference]
    if c_ahead is None:
        text = f"no pixels to compare {where}"
        c_ahead = "tie"
    elif c_ahead == "tie":
        best = coord[c_order[0]]
        tied = [m for m in c_order if f"{coord[m]:.3g}" == f"{best:.3g}"]
        text = f"tie {where}: {' and '.join(METHOD_LABELS[m] for m in tied)} at coordinate RMS {best:.3g} µm"
        rest = [m for m in c_order if m not in tied]
        if rest:
            text += "; " + ", ".join(f"{METHOD_LABELS[m]} {coord[m]:.3g} µm" for m in rest)
    else:
        text = (f"{METHOD_LABELS[c_ahead]} is ahead {where}: coordinate RMS {coord[c_ahead]:.3g} µm against "
                + _versus(coord, c_order))
    if d_ahead is not None:
        if d_ahead == "tie":
            text += f"; distances: tie ({dist[d_order[0]]:.3g} µm RMS)"
        else:
            text += (f"; distances: {METHOD_LABELS[d_ahead]} ahead, RMS {dist[d_ahead]:.3g} µm against "
                     + _versus(dist, d_order))
    return Verdict(reference, c_ahead, c_ratio, d_ahead, d_ratio, text, dict(coord), dict(dist))


def block_rms(img: np.ndarray, block: int) -> np.ndarray:
    """RMS of the finite values of ``img`` (H, W) in ``block`` x ``block`` tiles (NaN where none)."""
    h, w = img.shape
    hb, wb = -(-h // block), -(-w // block)
    pad = np.full((hb * block, wb * block), np.nan)
    pad[:h, :w] = img
    t = pad.reshape(hb, block, wb, block)
    ok = np.isfinite(t)
    n = ok.sum(axis=(1, 3))
    ms = np.full((hb, wb), np.nan)
    np.divide(np.where(ok, t * t, 0.0).sum(axis=(1, 3)), n, out=ms, where=n > 0)
    return np.sqrt(ms)


def jsonable(v):
    """Plain JSON value: numpy scalars and arrays to Python, NaN/inf to None."""
    if isinstance(v, np.ndarray):
        return [jsonable(x) for x in v.tolist()] if v.ndim else jsonable(v.item())
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v
