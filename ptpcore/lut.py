"""Per-pixel look-up tables Z -> (X, Y) (METHOD.md section 5) and ``ptp-lut/1`` files.

Models
------
``poly``
    Least-squares polynomial of degree D in ``t = (z - z_center)/z_scale``.
``linear`` / ``pchip``
    Interpolation of the table of samples between calibrated heights.

Pixels may have any subset of valid positions. Fitting groups pixels by
their pattern of valid positions: all pixels of one pattern share one design
matrix, so each group is one pseudo-inverse and one matrix product, and the
leave-one-out residuals ``r_k / (1 - h_kk)`` come from the same hat matrix.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import h5py
import numpy as np
from scipy.interpolate import PchipInterpolator

from . import __version__
from .atomic import atomic_path
from .errors import FileFormatError

if TYPE_CHECKING:
    from .noise import NoiseModel

__all__ = [
    "LUT_FORMAT",
    "SampleStack",
    "Lut",
    "LutEvaluation",
    "fit_lut",
    "save_lut",
    "load_lut",
    "MODELS",
]

LUT_FORMAT = "ptp-lut/1"
MODELS = ("poly", "pchip", "linear")
_TILE = 1 << 16  # pixels per fitting tile: bounds the float64 working set (~10 MB per array at K = 21)


@dataclass
class SampleStack:
    """Every pixel's samples ``(z_k, X_k, Y_k)`` over all positions.

    Attributes
    ----------
    z : (K,) float64, mm
        Stage readings in capture order.
    x, y : (K, H, W) float32, mm
        World coordinates relative to ``x_ref``/``y_ref`` (float32 offsets keep
        nanometre precision at half the memory of float64). NaN where invalid.
    x_ref, y_ref : (H, W) float64, mm
        Per-pixel reference (first valid sample); NaN for never-valid pixels.
    reasons : (K, H, W) uint8
        :class:`ptpcore.phase.Reason` flags; 0 where valid.
    modulation : (K, H, W) float32 or None
        Finest-period modulation (worse direction), grey levels.
    background : (K, H, W) float32 or None
        Background level A (grey levels).
    noise : ptpcore.noise.NoiseModel or None
        The camera noise measured from the N-step fit residuals.
    """

    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    x_ref: np.ndarray
    y_ref: np.ndarray
    reasons: np.ndarray
    modulation: np.ndarray | None = None
    background: np.ndarray | None = None
    noise: NoiseModel | None = None  # measured from the N-step residuals (ptpcore.noise)

    @classmethod
    def empty(cls, z, shape, with_photometry: bool = True) -> "SampleStack":
        k = len(z)
        full = (k, *shape)
        return cls(
            np.asarray(z, dtype=float),
            np.full(full, np.nan, np.float32), np.full(full, np.nan, np.float32),
            np.full(shape, np.nan), np.full(shape, np.nan),
            np.full(full, 0xFF, np.uint8),
            np.zeros(full, np.float32) if with_photometry else None,
            np.zeros(full, np.float32) if with_photometry else None,
        )

    @property
    def shape(self) -> tuple[int, int]:
        return self.x.shape[1:]

    @property
    def valid(self) -> np.ndarray:
        """(K, H, W) bool."""
        return self.reasons == 0

    def set_position(self, k: int, x: np.ndarray, y: np.ndarray, reasons: np.ndarray,
                     modulation=None, background=None) -> None:
        """Store position ``k``: ``x, y`` (H, W) float64 mm; invalid where ``reasons != 0``."""
        valid = reasons == 0
        new_ref = valid & np.isnan(self.x_ref)
        self.x_ref[new_ref] = x[new_ref]
        self.y_ref[new_ref] = y[new_ref]
        self.x[k] = np.where(valid, x - self.x_ref, np.nan)
        self.y[k] = np.where(valid, y - self.y_ref, np.nan)
        self.reasons[k] = reasons
        if self.modulation is not None and modulation is not None:
            self.modulation[k] = modulation
        if self.background is not None and background is not None:
            self.background[k] = background

    def absolute(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Absolute X, Y (H, W) float64 mm at position ``k`` (NaN where invalid)."""
        return self.x_ref + self.x[k], self.y_ref + self.y[k]

    def subset(self, positions) -> "SampleStack":
        """The stack restricted to some positions (views where possible)."""
        idx = np.asarray(positions)
        return SampleStack(self.z[idx], self.x[idx], self.y[idx], self.x_ref, self.y_ref,
                           self.reasons[idx],
                           None if self.modulation is None else self.modulation[idx],
                           None if self.background is None else self.background[idx], self.noise)


@dataclass
class LutEvaluation:
    """X, Y of every pixel at the requested z.

    Attributes
    ----------
    x, y : (H, W) float64, mm
        NaN where the pixel is invalid, or outside its calibrated range
        unless extrapolation was requested.
    in_range : (H, W) bool
        Valid pixel and z within ``[z_min, z_max]`` of that pixel.
    """

    x: np.ndarray
    y: np.ndarray
    in_range: np.ndarray


@dataclass
class Lut:
    """A per-pixel LUT, in memory exactly what ``ptp-lut/1`` stores.

    Attributes
    ----------
    kind : {"poly", "pchip", "linear"}
    degree : int or None
    z_center, z_scale : float
        Normalisation of z for ``poly``: ``t = (z - z_center)/z_scale``.
    z_min, z_max : float
        The calibrated range over all pixels (mm).
    x, y : (D+1, H, W) or (K, H, W) float64
        Coefficients (lowest power first) or table values at ``z_nodes``.
    z_nodes : (K,) float64 or None
        Ascending calibrated heights (tables only).
    valid : (H, W) bool
    n_positions : (H, W) uint16
    pixel_z_min, pixel_z_max : (H, W) float32
    rms_x, rms_y, loo_x, loo_y : (H, W) float32, mm
    sigma_x, sigma_y : (H, W) float32 or None
        Predicted 1-sigma uncertainty (optional).
    rig_toml : str
    """

    kind: str
    degree: int | None
    z_center: float
    z_scale: float
    z_min: float
    z_max: float
    x: np.ndarray
    y: np.ndarray
    z_nodes: np.ndarray | None
    valid: np.ndarray
    n_positions: np.ndarray
    pixel_z_min: np.ndarray
    pixel_z_max: np.ndarray
    rms_x: np.ndarray
    rms_y: np.ndarray
    loo_x: np.ndarray
    loo_y: np.ndarray
    sigma_x: np.ndarray | None = None
    sigma_y: np.ndarray | None = None
    rig_toml: str = ""
    extra_attrs: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape

    def evaluate(self, z, *, extrapolate: bool = False) -> LutEvaluation:
        """X, Y at height ``z``.

        Parameters
        ----------
        z : float or (H, W) array_like, mm
        extrapolate : bool
            If False (default) pixels whose own calibrated range does not
            contain ``z`` return NaN; ``in_range`` tells them apart either way.
        """
        z = np.asarray(z, dtype=float)
        if z.ndim not in (0, 2) or (z.ndim == 2 and z.shape != self.shape):
            raise ValueError(f"z must be a scalar or a {self.shape} map, got shape {z.shape}")
        eps = 1e-9
        if self.kind == "poly":
            # Row tiles on every core: each tile's Horner steps stay in cache, so
            # the coefficients are read once (the cost floor) instead of once per step.
            from .phase import run_tiles

            h, w = self.shape
            x = np.empty((h, w))
            y = np.empty((h, w))
            in_range = np.empty((h, w), bool)

            def rows(r0: int, r1: int) -> None:
                zr = z if z.ndim == 0 else z[r0:r1]
                ok = self.valid[r0:r1] & (zr >= self.pixel_z_min[r0:r1] - eps) & (zr <= self.pixel_z_max[r0:r1] + eps)
                in_range[r0:r1] = ok
                keep = ok if not extrapolate else self.valid[r0:r1]
                t = (zr - self.z_center) / self.z_scale
                for coeffs, out in ((self.x, x), (self.y, y)):
                    o = out[r0:r1]
                    _horner(coeffs[:, r0:r1], t, o)
                    o[~keep] = np.nan

            run_tiles(rows, h, w)
            return LutEvaluation(x, y, in_range)
        in_range = self.valid & (z >= self.pixel_z_min - eps) & (z <= self.pixel_z_max + eps)
        x = _interp_table(self.z_nodes, self.x, z, self.kind)
        y = _interp_table(self.z_nodes, self.y, z, self.kind)
        keep = in_range if not extrapolate else self.valid
        return LutEvaluation(np.where(keep, x, np.nan), np.where(keep, y, np.nan), in_range)


def _horner(coeffs: np.ndarray, t, out: np.ndarray | None = None) -> np.ndarray:
    """``sum_i coeffs[i] * t**i`` by Horner's rule (coefficients lowest power first), float64."""
    if out is None:
        out = np.array(coeffs[-1], dtype=np.float64, copy=True)
        rest = coeffs[-2::-1]
    elif len(coeffs) > 1:
        np.multiply(coeffs[-1], t, out=out)  # the first step without a copy: same numbers
        out += coeffs[-2]
        rest = coeffs[-3::-1]
    else:
        out[...] = coeffs[-1]
        rest = ()
    for c in rest:
        out *= t
        out += c
    return out


def _runs(mask_1d: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [start, stop) of True in a 1-D bool array."""
    runs, start = [], None
    for i, m in enumerate(mask_1d):
        if m and start is None:
            start = i
        elif not m and start is not None:
            runs.append((start, i))
            start = None
    if start is not None:
        runs.append((start, len(mask_1d)))
    return runs


def _group_by_pattern(mask: np.ndarray):
    """Group columns of a (K, P) bool mask by identical pattern.

    Yields ``(pattern (K,) bool, column indices)``.
    """
    packed = np.ascontiguousarray(np.packbits(mask, axis=0).T)
    keys = packed.view(np.dtype((np.void, packed.shape[1]))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(first) + 1))
    for g, f in enumerate(first):
        yield mask[:, f], order[bounds[g]:bounds[g + 1]]


def _interp_table(z_nodes: np.ndarray, table: np.ndarray, z, kind: str) -> np.ndarray:
    """Per-pixel interpolation of a (K, H, W) table with NaN nodes.

    Each pixel is interpolated over the maximal run of consecutive valid nodes
    that contains ``z``; between a NaN node and its neighbours it is NaN.
    """
    k, h, w = table.shape
    vals = table.reshape(k, -1)
    zq = np.broadcast_to(np.asarray(z, dtype=float), (h, w)).reshape(-1)
    out = np.full(h * w, np.nan)
    for pattern, cols in _group_by_pattern(np.isfinite(vals)):
        for a, b in _runs(pattern):
            if b - a < 2:
                continue
            zn = z_nodes[a:b]
            zc = zq[cols]
            sel = (zc >= zn[0] - 1e-9) & (zc <= zn[-1] + 1e-9)
            if not sel.any():
                continue
            c = cols[sel]
            zc = np.clip(zc[sel], zn[0], zn[-1])
            if kind == "linear" or b - a == 2:
                i = np.clip(np.searchsorted(zn, zc, side="right") - 1, 0, b - a - 2)
                wgt = (zc - zn[i]) / (zn[i + 1] - zn[i])
                v = vals[a:b]
                out[c] = (1 - wgt) * v[i, c] + wgt * v[i + 1, c]
            else:
                if np.ptp(zc) == 0:
                    interp = PchipInterpolator(zn, vals[a:b][:, c], axis=0)
                    out[c] = interp(zc[0])
                else:
                    # Per-pixel z: evaluate each pixel's own curve.
                    interp = PchipInterpolator(zn, vals[a:b][:, c], axis=0)
                    i = np.clip(np.searchsorted(zn, zc, side="right") - 1, 0, b - a - 2)
                    out[c] = _pchip_eval_each(interp, zc, i)
    return out.reshape(h, w)


def _pchip_eval_each(interp: PchipInterpolator, zc: np.ndarray, interval: np.ndarray) -> np.ndarray:
    """Evaluate a vector-valued piecewise polynomial, column j at zc[j]."""
    c = interp.c  # (4, n_intervals, P) local power basis, highest power first
    x0 = interp.x[interval]
    dz = zc - x0
    cols = np.arange(zc.size)
    out = np.zeros(zc.size)
    for p in range(c.shape[0]):
        out = out * dz + c[p, interval, cols]
    return out


# ---------------------------------------------------------------------------
# Fitting

def _z_normalisation(z: np.ndarray) -> tuple[float, float]:
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
    from .fastio import read_block  # file-backed stacks are read block by block, never mapped whole

    k_all = samples.x.shape[0]
    idx = np.arange(k_all) if positions is None else np.asarray(positions)
    if weights is not None:
        weights = np.asarray(weights)[idx]
    z = np.asarray(samples.z, dtype=float)[idx]
    order = np.argsort(z)
    k = len(idx)
    h, w = samples.shape
    z_center, z_scale = _z_normalisation(z)
    if min_positions is None:
        min_positions = degree + 2 if model == "poly" else 2
    p_total = h * w
    # Every tile writes every pixel of its slice (so np.empty: the pages are first
    # touched by the tiles, on every core, not filled here first), in the dtypes of
    # the Lut (no whole-image conversions after; float64 z to float32 rounds alike).
    n_pos = np.empty(p_total, np.uint16)
    pz_min = np.empty(p_total, np.float32)
    pz_max = np.empty(p_total, np.float32)
    valid = np.empty(p_total, bool)
    n_lead = degree + 1 if model == "poly" else k
    coef = {a: np.empty((n_lead, p_total)) for a in "xy"}
    rms = {a: np.empty(p_total, np.float32) for a in "xy"}
    loo = {a: np.empty(p_total, np.float32) for a in "xy"}
    t_all = (z - z_center) / z_scale
    wflat = None if weights is None else np.asarray(weights, dtype=float).reshape(k, -1)
    sel = None if positions is None else idx
    z_sorted = z[order]
    sorted_z = bool(np.all(order == np.arange(k)))

    from .phase import fused_kernels

    kern = fused_kernels()

    def tile(start: int) -> None:
        stop = min(start + _TILE, p_total)
        reasons_t = read_block(samples.reasons, start, stop, sel)
        valid_t = reasons_t == 0
        if kern is not None:  # counts and first/last valid in one pass (argmax on axis 0 is slow)
            n_t, first, last = (np.empty(stop - start, np.int64) for _ in range(3))
            kern.valid_span(np.ascontiguousarray(reasons_t), order, n_t, first, last)
        else:
            n_t = valid_t.sum(axis=0)
            first = last = None
        n_pos[start:stop] = n_t
        usable_t = n_t >= min_positions
        if usable_t.any():
            # The lowest and highest valid z: the first and last valid position in z order
            # (argmax of a bool stack, no (K, P) float temporaries).
            if first is None:
                vs = valid_t if sorted_z else valid_t[order]
                first = vs.argmax(axis=0)
                last = len(z) - 1 - vs[::-1].argmax(axis=0)
            pz_min[start:stop] = np.where(usable_t, z_sorted[first], np.nan)
            pz_max[start:stop] = np.where(usable_t, z_sorted[last], np.nan)
        else:
            pz_min[start:stop] = np.nan
            pz_max[start:stop] = np.nan
        mask = valid_t & usable_t[None, :]
        # Poly fits take the float32 samples as they are (each group converts what it uses,
        # the fused kernel as it reads); tables want float64.
        offs = {a: read_block(getattr(samples, a), start, stop, sel) for a in "xy"}
        if model != "poly":
            offs = {a: o.astype(np.float64) for a, o in offs.items()}
        refs = {a: getattr(samples, f"{a}_ref").reshape(-1)[start:stop] for a in "xy"}
        if model == "poly":
            fits = _fit_poly_tile_xy(t_all, [offs["x"], offs["y"]], mask, degree,
                                     None if wflat is None else wflat[:, start:stop],
                                     np.where(usable_t, n_t, 0))
            for axis_name, (c, r, l) in zip("xy", fits):
                c[0] += refs[axis_name]
                coef[axis_name][:, start:stop] = c
                rms[axis_name][start:stop] = r
                loo[axis_name][start:stop] = l
        else:
            for axis_name in "xy":
                o = offs[axis_name]
                vals = np.where(mask, o + refs[axis_name][None, :], np.nan)
                coef[axis_name][:, start:stop] = vals[order]
                rms[axis_name][start:stop] = np.where(mask.any(axis=0), 0.0, np.nan)
                loo[axis_name][start:stop] = _table_loo(z[order], o[order], mask[order], model)
        # A usable pixel whose fit failed is invalid; invalid pixels hold NaN everywhere.
        cx = coef["x"][:, start:stop]
        ok = usable_t & (np.all(np.isfinite(cx), axis=0) if model == "poly" else np.isfinite(cx).sum(axis=0) >= 2)
        valid[start:stop] = ok
        if not ok.all():
            bad = np.flatnonzero(~ok) + start
            for a in "xy":
                coef[a][:, bad] = np.nan
                rms[a][bad] = np.nan
                loo[a][bad] = np.nan
            pz_min[bad] = np.nan
            pz_max[bad] = np.nan
            n_pos[bad] = 0

    # Pixel tiles on every core (numpy's loops release the GIL); results land in
    # disjoint slices, so the order of completion does not matter.
    from .phase import _pool, tile_workers

    starts = list(range(0, p_total, _TILE))
    done = map(tile, starts) if tile_workers() == 1 or len(starts) == 1 else _pool().map(tile, starts)
    for i, _ in enumerate(done):
        if progress:
            progress(i / len(starts), f"fitting LUT ({model})")
    shape = (h, w)
    if progress:
        progress(1.0, "LUT fitted")
    return Lut(
        kind=model, degree=int(degree) if model == "poly" else None,
        z_center=z_center, z_scale=z_scale, z_min=float(z.min()), z_max=float(z.max()),
        x=coef["x"].reshape(-1, h, w), y=coef["y"].reshape(-1, h, w),
        z_nodes=None if model == "poly" else z[order].astype(float),
        valid=valid.reshape(shape), n_positions=n_pos.reshape(shape),
        pixel_z_min=pz_min.reshape(shape), pixel_z_max=pz_max.reshape(shape),
        rms_x=rms["x"].reshape(shape), rms_y=rms["y"].reshape(shape),
        loo_x=loo["x"].reshape(shape), loo_y=loo["y"].reshape(shape),
        rig_toml=rig_toml,
    )


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
    """``_group_by_pattern`` of the columns with at least ``n_min`` samples.

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
        for pattern, cols in _group_by_pattern(mask[:, rest]):
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
    from .phase import fused_kernels

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
        pred = _interp_table(np.delete(z_sorted, i), dropped[:, None, :], z_sorted[i], kind).ravel()
        ok = has & np.isfinite(pred)
        err = np.where(ok, pred - vals[i], 0.0)
        sq += err * err
        cnt += ok
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.sqrt(sq / cnt), np.nan)


# ---------------------------------------------------------------------------
# Files

_QUALITY = ("n_positions", "z_min", "z_max", "rms_x", "rms_y", "loo_x", "loo_y")
_MAX_DEGREE = 5


def _lut_root_attrs(obj) -> None:
    """The ``/`` attributes of ``ptp-lut/1`` (also put on a session's ``/lut`` group)."""
    obj.attrs["format"] = LUT_FORMAT
    obj.attrs["software"] = f"ptpcore {__version__}"
    obj.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    obj.attrs["units"] = "mm"


def _write_lut_group(group, lut: Lut) -> None:
    """Write every ``ptp-lut/1`` dataset and group of ``lut`` into an open HDF5 group.

    ``save_lut`` writes into the file's root group; a session file into ``/lut``.
    The format attributes are not written here (see :func:`_lut_root_attrs`).
    """
    h, w = lut.shape
    group.create_group("camera").attrs.update({"width": w, "height": h})
    m = group.create_group("model")
    m.attrs.update({"kind": lut.kind, "z_center": lut.z_center, "z_scale": lut.z_scale,
                    "z_min": lut.z_min, "z_max": lut.z_max})
    if lut.kind == "poly":
        m.attrs["degree"] = lut.degree
    for key, val in lut.extra_attrs.items():
        m.attrs[key] = val
    opts = dict(chunks=True, compression="gzip", compression_opts=1, shuffle=True)
    group.create_dataset("x", data=lut.x.astype(np.float64), **opts)
    group.create_dataset("y", data=lut.y.astype(np.float64), **opts)
    if lut.z_nodes is not None:
        group["z_nodes"] = np.asarray(lut.z_nodes, dtype=np.float64)
    group.create_dataset("valid", data=lut.valid.astype(np.uint8), **opts)
    q = group.create_group("quality")
    q.create_dataset("n_positions", data=lut.n_positions.astype(np.uint16), **opts)
    q.create_dataset("z_min", data=lut.pixel_z_min.astype(np.float32), **opts)
    q.create_dataset("z_max", data=lut.pixel_z_max.astype(np.float32), **opts)
    for name in ("rms_x", "rms_y", "loo_x", "loo_y", "sigma_x", "sigma_y"):
        val = getattr(lut, name)
        if val is not None:
            q.create_dataset(name, data=val.astype(np.float32), **opts)
    group.create_group("rig").attrs["toml"] = lut.rig_toml


def save_lut(lut: Lut, path) -> None:
    """Write ``ptp-lut/1`` (FORMATS.md) atomically.

    A process killed during the write leaves the previous file (if any) intact.
    """
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            _lut_root_attrs(f)
            _write_lut_group(f, lut)


def _str_attr(value) -> str | None:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "SUO":
        value = value[()]
        return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)
    return value if isinstance(value, str) else None


def open_hdf5(path) -> tuple[h5py.File, str]:
    """Open an HDF5 file for reading; any failure is a :class:`FileFormatError` naming it.

    Returns the open file and its name for messages.
    """
    where = str(path)
    try:
        return h5py.File(Path(path), "r"), where
    except FileNotFoundError:
        raise FileFormatError(f"{where}: file not found") from None
    except OSError as exc:
        raise FileFormatError(f"{where}: not a readable HDF5 file (truncated or damaged?): {exc}") from None


def check_format(obj, where: str, expected: str) -> None:
    """Check a ``format`` attribute ``"name/N"`` against ``expected``.

    Raises
    ------
    FileFormatError
        Missing or other format; a version newer than this software reads is
        called "too new".
    """
    fmt = _str_attr(obj.attrs.get("format"))
    if fmt == expected:
        return
    family, _, version = expected.rpartition("/")
    if isinstance(fmt, str) and fmt.startswith(family + "/"):
        tail = fmt[len(family) + 1:]
        if tail.isdigit() and int(tail) > int(version):
            raise FileFormatError(f"{where}: format {fmt!r} is newer than this software reads ({expected});"
                                  " update PTP Studio")
        raise FileFormatError(f"{where}: format {fmt!r} is not supported (this software reads {expected})")
    raise FileFormatError(f"{where}: attribute 'format' is {fmt!r}, expected {expected!r}")


def _read_lut_group(group, where: str) -> Lut:
    """Read and check the ``ptp-lut/1`` content of an open HDF5 group.

    Parameters
    ----------
    group : h5py.Group
        The file's root (a ``*.lut.h5``) or a session's ``/lut`` group.
    where : str
        The file name, for messages; dataset names are given in full
        (``/lut/x`` inside a session).

    Raises
    ------
    FileFormatError
        Naming ``where`` and the dataset or attribute that is wrong: missing,
        wrong shape or type, NaN where a valid pixel needs a number, values out
        of range.
    """
    base = "" if group.name == "/" else group.name

    def name(rel):
        return f"{base}/{rel}"

    def fail(msg):
        return FileFormatError(f"{where}: {msg}")

    def array(rel, ndim, kinds="fiub"):
        try:
            obj = group[rel]
        except KeyError:
            raise fail(f"missing dataset {name(rel)}") from None
        if not isinstance(obj, h5py.Dataset):
            raise fail(f"{name(rel)} is not a dataset")
        if obj.dtype.kind not in kinds:
            raise fail(f"{name(rel)} has type {obj.dtype}, expected numbers")
        if obj.ndim != ndim:
            raise fail(f"{name(rel)} has {obj.ndim} dimensions {obj.shape}, expected {ndim}")
        return obj[()]

    def attr(obj_rel, key, kind):
        if obj_rel and obj_rel not in group:
            raise fail(f"missing group {name(obj_rel)}")
        try:
            obj = group[obj_rel] if obj_rel else group
            val = obj.attrs[key]
        except KeyError:
            raise fail(f"missing attribute {key!r} of {name(obj_rel) if obj_rel else base or '/'}") from None
        label = f"attribute {key!r} of {name(obj_rel)}"
        if kind is str:
            s = _str_attr(val)
            if s is None:
                raise fail(f"{label} must be text, got {val!r}")
            return s
        if isinstance(val, np.ndarray) and val.size == 1:
            val = val.reshape(())[()]
        if isinstance(val, (bool, np.bool_)) or not isinstance(val, (int, float, np.integer, np.floating)):
            raise fail(f"{label} must be a number, got {val!r}"[:200])
        if kind is int:
            if float(val) != int(val):
                raise fail(f"{label} must be an integer, got {val!r}")
            return int(val)
        val = float(val)
        if not np.isfinite(val):
            raise fail(f"{label} must be finite, got {val}")
        return val

    try:
        h = attr("camera", "height", int)
        w = attr("camera", "width", int)
        if h < 1 or w < 1:
            raise fail(f"{name('camera')} size {w}x{h} must be positive")
        kind = attr("model", "kind", str)
        if kind not in MODELS:
            raise fail(f"attribute 'kind' of {name('model')} is {kind!r}, not one of {MODELS}")
        degree = attr("model", "degree", int) if kind == "poly" else None
        if degree is not None and not 1 <= degree <= _MAX_DEGREE:
            raise fail(f"attribute 'degree' of {name('model')} must be 1 to {_MAX_DEGREE}, got {degree}")
        mv = {k: attr("model", k, float) for k in ("z_center", "z_scale", "z_min", "z_max")}
        known = {"kind", "degree", "z_center", "z_scale", "z_min", "z_max"}
        extra = {k: v for k, v in group["model"].attrs.items() if k not in known}
        x = array("x", 3, "f")
        y = array("y", 3, "f")
        z_nodes = array("z_nodes", 1, "f") if "z_nodes" in group else None
        valid_raw = array("valid", 2, "uib")
        q = {n: array(f"quality/{n}", 2) for n in _QUALITY}
        sig = {n: (array(f"quality/{n}", 2, "f") if f"quality/{n}" in group else None)
               for n in ("sigma_x", "sigma_y")}
        rig_toml = ""
        if "rig" in group:
            rig_toml = _str_attr(group["rig"].attrs.get("toml", "")) or ""
    except OSError as exc:
        raise fail(f"truncated or damaged ({exc})") from None
    if mv["z_scale"] <= 0:
        raise fail(f"attribute 'z_scale' of {name('model')} must be positive, got {mv['z_scale']}")
    if mv["z_min"] > mv["z_max"]:
        raise fail(f"attributes 'z_min' > 'z_max' of {name('model')} ({mv['z_min']} > {mv['z_max']})")
    if kind != "poly":
        if z_nodes is None:
            raise fail(f"missing dataset {name('z_nodes')} (required for kind {kind!r})")
        if z_nodes.size < 2 or not np.all(np.isfinite(z_nodes)) or np.any(np.diff(z_nodes) <= 0):
            raise fail(f"{name('z_nodes')} must hold at least 2 finite, strictly ascending heights")
    n_lead = degree + 1 if kind == "poly" else len(z_nodes)
    for rel, arr, want in (("x", x, (n_lead, h, w)), ("y", y, (n_lead, h, w)), ("valid", valid_raw, (h, w))):
        if arr.shape != want:
            raise fail(f"{name(rel)} has shape {arr.shape}, expected {want}")
    for rel, arr in [*((f"quality/{n}", a) for n, a in q.items()),
                     *((f"quality/{n}", a) for n, a in sig.items() if a is not None)]:
        if arr.shape != (h, w):
            raise fail(f"{name(rel)} has shape {arr.shape}, expected {(h, w)}")
    if np.any((valid_raw != 0) & (valid_raw != 1)):
        raise fail(f"{name('valid')} must hold only 0 and 1")
    valid = valid_raw.astype(bool)
    for rel, arr in (("x", x), ("y", y)):
        if kind == "poly":
            if not np.all(np.isfinite(arr[:, valid])):
                raise fail(f"{name(rel)} holds NaN or infinite coefficients for pixels marked valid")
        else:
            fin = np.isfinite(arr)
            if np.any(np.isinf(arr)):
                raise fail(f"{name(rel)} holds infinite values")
            if np.any(fin.sum(axis=0)[valid] < 2):
                raise fail(f"{name(rel)} has fewer than 2 finite nodes for pixels marked valid")
    if np.any(q["n_positions"][valid] < 1):
        raise fail(f"{name('quality/n_positions')} is 0 for pixels marked valid")
    pz_min, pz_max = q["z_min"], q["z_max"]
    if not (np.all(np.isfinite(pz_min[valid])) and np.all(np.isfinite(pz_max[valid]))):
        raise fail(f"{name('quality/z_min')} or {name('quality/z_max')} holds NaN for pixels marked valid")
    if np.any(pz_min[valid] > pz_max[valid]):
        raise fail(f"{name('quality/z_min')} exceeds {name('quality/z_max')} for some valid pixels")
    for n in ("rms_x", "rms_y", "loo_x", "loo_y"):
        with np.errstate(invalid="ignore"):
            if np.any(q[n] < 0):
                raise fail(f"{name('quality/' + n)} holds negative values")
    return Lut(
        kind=kind, degree=degree, z_center=mv["z_center"], z_scale=mv["z_scale"],
        z_min=mv["z_min"], z_max=mv["z_max"], x=x, y=y, z_nodes=z_nodes, valid=valid,
        n_positions=q["n_positions"], pixel_z_min=pz_min, pixel_z_max=pz_max,
        rms_x=q["rms_x"], rms_y=q["rms_y"], loo_x=q["loo_x"], loo_y=q["loo_y"],
        sigma_x=sig["sigma_x"], sigma_y=sig["sigma_y"], rig_toml=str(rig_toml), extra_attrs=extra,
    )


def load_lut(path) -> Lut:
    """Read and check a ``ptp-lut/1`` file.

    Raises
    ------
    FileFormatError
        Naming the file and the dataset or attribute that is wrong: not HDF5,
        truncated, another format or a newer version, missing or wrongly shaped
        datasets, NaN where a valid pixel needs a number, values out of range.
    """
    f, where = open_hdf5(path)
    with f:
        check_format(f, where, LUT_FORMAT)
        return _read_lut_group(f, where)
