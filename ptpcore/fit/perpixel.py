"""Per-pixel LUT fitting (docs/method.md section 5): ``poly``, ``pchip`` and ``linear``.

Pixels may have any subset of valid positions. Fitting groups pixels by
their pattern of valid positions: all pixels of one pattern share one design
matrix, so each group is one pseudo-inverse and one matrix product, and the
leave-one-out residuals ``r_k / (1 - h_kk)`` come from the same hat matrix.
Rows are fitted in tiles on the shared pool (:mod:`ptpcore.parallel`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ptpcore.io.lutfile import MODELS, Lut, group_by_pattern, interp_table
from ptpcore.io.samples import SampleStack

__all__ = ["fit_lut"]

_TILE = 1 << 16  # pixels per fitting tile: bounds the float64 working set (~10 MB per array at K = 21)



def z_normalisation(z: np.ndarray) -> tuple[float, float]:
    lo, hi = float(np.min(z)), float(np.max(z))
    return 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-12)


def fit_lut(samples: SampleStack, model: str = "poly", degree: int = 3,
            positions=None, *, min_positions: int | None = None, weights: np.ndarray | None = None,
            rig_toml: str = "", progress: Callable[[float, str], None] | None = None) -> Lut:
    """Fit a LUT to every pixel's valid samples.

    Parameters
    ----------
    samples : SampleStack
    model : {"poly", "pchip", "linear"}
    degree : int
        Polynomial degree (1 to 5), ``poly`` only.
    positions : sequence of int, optional
        Use only these positions (e.g. the calibration half of a split).
    min_positions : int, optional
        Fewest valid positions a pixel needs; default ``degree + 2`` for
        ``poly`` (one more than the unknowns, so a residual exists) and 2 for tables.
    weights : (K, H, W) array_like, optional
        Per-sample least-squares weights (``poly`` only), e.g. inverse variances.
    rig_toml : str
        Stored in the file's ``/rig`` attributes.
    progress : callable, optional
        ``progress(fraction, message)``; may raise to cancel.

    Returns
    -------
    Lut
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if model == "poly" and not 1 <= int(degree) <= 5:
        raise ValueError(f"poly degree must be 1 to 5, got {degree}")
    from ptpcore.decode.phase import fused_kernels
    from ptpcore.parallel import tile_workers, worker_pool

    k_all = samples.x.shape[0]
    idx = np.arange(k_all) if positions is None else np.asarray(positions)
    if weights is not None:
        weights = np.asarray(weights)[idx]
    z = np.asarray(samples.z, dtype=float)[idx]
    h, w = samples.shape
    if min_positions is None:
        min_positions = degree + 2 if model == "poly" else 2
    plan = _FitPlan(samples, model, int(degree), z, None if positions is None else idx, min_positions,
                    None if weights is None else np.asarray(weights, dtype=float).reshape(len(idx), -1),
                    fused_kernels())
    out = _LutArrays.empty(h * w, degree + 1 if model == "poly" else len(idx))
    # Pixel tiles on every core (numpy's loops release the GIL); results land in
    # disjoint slices, so the order of completion does not matter.
    starts = list(range(0, h * w, _TILE))
    tile = lambda start: plan.fit_tile(out, start, min(start + _TILE, h * w))  # noqa: E731
    done = map(tile, starts) if tile_workers() == 1 or len(starts) == 1 else worker_pool().map(tile, starts)
    for i, _ in enumerate(done):
        if progress:
            progress(i / len(starts), f"fitting LUT ({model})")
    if progress:
        progress(1.0, "LUT fitted")
    return out.to_lut(plan, (h, w), rig_toml)


@dataclass
class _LutArrays:
    """The flat (P = H*W pixels) arrays of a LUT being fitted, written tile by tile.

    Every tile writes every pixel of its slice (so ``np.empty``: the pages are first
    touched by the tiles, on every core, not filled here first), in the dtypes of
    the Lut (no whole-image conversions after; float64 z to float32 rounds alike).
    """

    n_pos: np.ndarray    # (P,) uint16
    pz_min: np.ndarray   # (P,) float32, mm
    pz_max: np.ndarray   # (P,) float32, mm
    valid: np.ndarray    # (P,) bool
    coef: dict           # "x", "y" -> (D+1 or K, P) float64, mm
    rms: dict            # "x", "y" -> (P,) float32, mm
    loo: dict            # "x", "y" -> (P,) float32, mm

    @classmethod
    def empty(cls, p_total: int, n_lead: int) -> "_LutArrays":
        return cls(np.empty(p_total, np.uint16), np.empty(p_total, np.float32), np.empty(p_total, np.float32),
                   np.empty(p_total, bool), {a: np.empty((n_lead, p_total)) for a in "xy"},
                   {a: np.empty(p_total, np.float32) for a in "xy"}, {a: np.empty(p_total, np.float32) for a in "xy"})

    def clear(self, bad: np.ndarray) -> None:
        """Invalid pixels (flat indices ``bad``) hold NaN everywhere and no positions."""
        for a in "xy":
            self.coef[a][:, bad] = np.nan
            self.rms[a][bad] = np.nan
            self.loo[a][bad] = np.nan
        self.pz_min[bad] = np.nan
        self.pz_max[bad] = np.nan
        self.n_pos[bad] = 0

    def to_lut(self, plan: "_FitPlan", shape, rig_toml: str) -> Lut:
        h, w = shape
        poly = plan.model == "poly"
        return Lut(
            kind=plan.model, degree=plan.degree if poly else None,
            z_center=plan.z_center, z_scale=plan.z_scale, z_min=float(plan.z.min()), z_max=float(plan.z.max()),
            x=self.coef["x"].reshape(-1, h, w), y=self.coef["y"].reshape(-1, h, w),
            z_nodes=None if poly else plan.z_sorted.astype(float),
            valid=self.valid.reshape(shape), n_positions=self.n_pos.reshape(shape),
            pixel_z_min=self.pz_min.reshape(shape), pixel_z_max=self.pz_max.reshape(shape),
            rms_x=self.rms["x"].reshape(shape), rms_y=self.rms["y"].reshape(shape),
            loo_x=self.loo["x"].reshape(shape), loo_y=self.loo["y"].reshape(shape),
            rig_toml=rig_toml,
        )


class _FitPlan:
    """What every tile of one :func:`fit_lut` call shares: the samples, the model and the positions used.

    Attributes
    ----------
    z : (K,) float64, mm
        The readings of the positions used, in the order given.
    order : (K,) int
        Their ascending order; ``z_sorted = z[order]``.
    t : (K,) float64
        ``(z - z_center) / z_scale``.
    sel : (K,) int or None
        The positions used (None: all).
    weights : (K, P) float64 or None
    """

    def __init__(self, samples: SampleStack, model: str, degree: int, z: np.ndarray, sel, min_positions: int,
                 weights, kern):
        self.samples, self.model, self.degree, self.z, self.sel = samples, model, degree, z, sel
        self.min_positions, self.weights, self.kern = min_positions, weights, kern
        self.order = np.argsort(z)
        self.z_sorted = z[self.order]
        self.sorted_z = bool(np.all(self.order == np.arange(z.size)))
        self.z_center, self.z_scale = z_normalisation(z)
        self.t = (z - self.z_center) / self.z_scale

    def fit_tile(self, out: _LutArrays, start: int, stop: int) -> None:
        """Fit pixels ``[start, stop)`` (flat indices) into ``out``."""
        from ptpcore.store import read_block

        valid_t, n_t, usable_t = self._z_span(out, start, stop, read_block(self.samples.reasons, start, stop, self.sel))
        mask = valid_t & usable_t[None, :]
        if self.model == "poly":
            self._fit_poly(out, start, stop, mask, usable_t, n_t)
        else:
            self._fill_table(out, start, stop, mask)
        # A usable pixel whose fit failed is invalid; invalid pixels hold NaN everywhere.
        cx = out.coef["x"][:, start:stop]
        ok = usable_t & (np.all(np.isfinite(cx), axis=0) if self.model == "poly"
                         else np.isfinite(cx).sum(axis=0) >= 2)
        out.valid[start:stop] = ok
        if not ok.all():
            out.clear(np.flatnonzero(~ok) + start)

    def _z_span(self, out: _LutArrays, start: int, stop: int, reasons_t: np.ndarray):
        """Valid positions of a tile, their count, and each pixel's lowest and highest valid z (into ``out``)."""
        valid_t = reasons_t == 0
        if self.kern is not None:  # counts and first/last valid in one pass (argmax on axis 0 is slow)
            n_t, first, last = (np.empty(stop - start, np.int64) for _ in range(3))
            self.kern.valid_span(np.ascontiguousarray(reasons_t), self.order, n_t, first, last)
        else:
            n_t = valid_t.sum(axis=0)
            first = last = None
        out.n_pos[start:stop] = n_t
        usable_t = n_t >= self.min_positions
        if usable_t.any():
            # The lowest and highest valid z: the first and last valid position in z order
            # (argmax of a bool stack, no (K, P) float temporaries).
            if first is None:
                vs = valid_t if self.sorted_z else valid_t[self.order]
                first = vs.argmax(axis=0)
                last = len(self.z) - 1 - vs[::-1].argmax(axis=0)
            out.pz_min[start:stop] = np.where(usable_t, self.z_sorted[first], np.nan)
            out.pz_max[start:stop] = np.where(usable_t, self.z_sorted[last], np.nan)
        else:
            out.pz_min[start:stop] = np.nan
            out.pz_max[start:stop] = np.nan
        return valid_t, n_t, usable_t

    def _offsets(self, start: int, stop: int):
        from ptpcore.store import read_block

        offs = {a: read_block(getattr(self.samples, a), start, stop, self.sel) for a in "xy"}
        refs = {a: getattr(self.samples, f"{a}_ref").reshape(-1)[start:stop] for a in "xy"}
        return offs, refs

    def _fit_poly(self, out: _LutArrays, start: int, stop: int, mask, usable_t, n_t) -> None:
        # Poly fits take the float32 samples as they are (each group converts what it uses,
        # the fused kernel as it reads).
        offs, refs = self._offsets(start, stop)
        fits = _fit_poly_tile_xy(self.t, [offs["x"], offs["y"]], mask, self.degree,
                                 None if self.weights is None else self.weights[:, start:stop],
                                 np.where(usable_t, n_t, 0))
        for axis_name, (c, r, l) in zip("xy", fits):
            c[0] += refs[axis_name]
            out.coef[axis_name][:, start:stop] = c
            out.rms[axis_name][start:stop] = r
            out.loo[axis_name][start:stop] = l

    def _fill_table(self, out: _LutArrays, start: int, stop: int, mask) -> None:
        # Tables want float64.
        offs, refs = self._offsets(start, stop)
        order = self.order
        for axis_name in "xy":
            o = offs[axis_name].astype(np.float64)
            vals = np.where(mask, o + refs[axis_name][None, :], np.nan)
            out.coef[axis_name][:, start:stop] = vals[order]
            out.rms[axis_name][start:stop] = np.where(mask.any(axis=0), 0.0, np.nan)
            out.loo[axis_name][start:stop] = _table_loo(self.z_sorted, o[order], mask[order], self.model)


def _fit_poly_tile(t: np.ndarray, values: np.ndarray, mask: np.ndarray, degree: int,
                   weights: np.ndarray | None):
    """Least-squares polynomials for a tile of pixels.

    Parameters
    ----------
    t : (K,) normalised heights
    values : (K, P) float64 samples (NaN where invalid)
    mask : (K, P) bool usable samples
    degree : int
    weights : (K, P) or None

    Returns
    -------
    coef : (D+1, P) ; rms : (P,) ; loo : (P,)
    """
    return _fit_poly_tile_xy(t, [values], mask, degree, weights)[0]


def _pattern_groups(mask: np.ndarray, n_min: int, counts: np.ndarray | None = None):
    """``group_by_pattern`` of the columns with at least ``n_min`` samples.

    The common pattern "every position valid" is found without sorting.
    ``counts``: ``mask.sum(axis=0)`` if the caller has it.
    """
    if counts is None:
        counts = mask.sum(axis=0)
    full = counts == mask.shape[0]
    if full.any():
        yield np.ones(mask.shape[0], bool), np.flatnonzero(full)
    rest = np.flatnonzero(~full & (counts >= n_min))
    if rest.size:
        for pattern, cols in group_by_pattern(mask[:, rest]):
            yield pattern, rest[cols]


def _fit_poly_tile_xy(t: np.ndarray, values_list, mask: np.ndarray, degree: int,
                      weights: np.ndarray | None, counts: np.ndarray | None = None):
    """:func:`_fit_poly_tile` of several value arrays sharing one mask (X and Y):
    one grouping and one pseudo-inverse per pattern serve them all.
    ``counts``: ``mask.sum(axis=0)`` if the caller has it."""
    k, p = mask.shape
    n_coef = degree + 1
    out = [(np.full((n_coef, p), np.nan), np.full(p, np.nan), np.full(p, np.nan)) for _ in values_list]
    vander = np.vander(t, n_coef, increasing=True)  # (K, D+1)
    from ptpcore.decode.phase import fused_kernels

    kern = fused_kernels()
    if weights is None:
        groups = _pattern_groups(mask, n_coef, counts)
    else:
        groups = ((None, np.array([j])) for j in np.flatnonzero(mask.sum(axis=0) >= n_coef))
    for pattern, cols in groups:
        if pattern is None:
            pattern = mask[:, cols[0]]
        n = int(pattern.sum())
        if n < n_coef:
            continue
        rows = np.flatnonzero(pattern)
        v = vander[rows]
        if weights is not None:
            sw = np.sqrt(weights[rows][:, cols[0]])
            pinv = np.linalg.pinv(v * sw[:, None]) * sw[None, :]
        else:
            pinv = np.linalg.pinv(v)  # (D+1, n)
        hat = np.einsum("ij,ji->i", v, pinv)  # leverages h_kk
        with np.errstate(divide="ignore", invalid="ignore"):
            loo_scale = (1.0 / (1.0 - hat))[:, None] if n > n_coef else None
        all_cols = cols.size == p
        if kern is not None and n == k and weights is None:
            # Every position valid (most pixels): one compiled pass over the whole tile
            # (columns of other patterns are computed too, and dropped).
            scale = np.zeros(k) if loo_scale is None else np.ascontiguousarray(loo_scale[:, 0])
            for values, (coef, rms, loo) in zip(values_list, out):
                if all_cols:
                    kern.poly_fit_full(pinv, v, scale, loo_scale is not None, values, coef, rms, loo)
                else:
                    tc, tr, tl = np.empty((n_coef, p)), np.empty(p), np.full(p, np.nan)
                    kern.poly_fit_full(pinv, v, scale, loo_scale is not None, values, tc, tr, tl)
                    coef[:, cols] = tc[:, cols]
                    rms[cols] = tr[cols]
                    loo[cols] = tl[cols]
            continue
        for values, (coef, rms, loo) in zip(values_list, out):
            if all_cols:
                y = values if n == k else values[rows]
            else:
                y = values[np.ix_(rows, cols)]
            y = y.astype(np.float64, copy=False)
            # einsum, not BLAS: (D+1, K) x (K, P) is too thin for BLAS's threads,
            # which on a busy machine cost ten times the arithmetic.
            c = np.einsum("ij,jk->ik", pinv, y)
            resid = np.einsum("ij,jk->ik", v, c)
            np.subtract(y, resid, out=resid)
            coef[:, cols] = c
            sq = np.einsum("ij,ij->j", resid, resid)
            rms[cols] = np.sqrt(sq / n)
            if loo_scale is not None:
                resid *= loo_scale
                loo[cols] = np.sqrt(np.einsum("ij,ij->j", resid, resid) / n)
    return out


def _table_loo(z_sorted: np.ndarray, values: np.ndarray, mask: np.ndarray, kind: str) -> np.ndarray:
    """Leave-one-position-out RMS of a table: drop each interior node, interpolate it back."""
    k, p = values.shape
    sq = np.zeros(p)
    cnt = np.zeros(p)
    vals = np.where(mask, values, np.nan)
    for i in range(1, k - 1):
        has = mask[i]
        if not has.any():
            continue
        # Remove node i (not NaN it: a NaN node would split the run around z_i).
        dropped = np.delete(vals, i, axis=0)
        pred = interp_table(np.delete(z_sorted, i), dropped[:, None, :], z_sorted[i], kind).ravel()
        ok = has & np.isfinite(pred)
        err = np.where(ok, pred - vals[i], 0.0)
        sq += err * err
        cnt += ok
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.sqrt(sq / cnt), np.nan)
