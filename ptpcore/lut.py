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
from typing import Callable

import h5py
import numpy as np
from scipy.interpolate import PchipInterpolator

from . import __version__
from .atomic import atomic_path
from .errors import FileFormatError

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
_TILE = 1 << 18  # pixels per fitting tile: bounds the float64 working set


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
    """

    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    x_ref: np.ndarray
    y_ref: np.ndarray
    reasons: np.ndarray
    modulation: np.ndarray | None = None
    background: np.ndarray | None = None

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
                           None if self.background is None else self.background[idx])


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
        in_range = self.valid & (z >= self.pixel_z_min - eps) & (z <= self.pixel_z_max + eps)
        if self.kind == "poly":
            t = (z - self.z_center) / self.z_scale
            x = _horner(self.x, t)
            y = _horner(self.y, t)
        else:
            x = _interp_table(self.z_nodes, self.x, z, self.kind)
            y = _interp_table(self.z_nodes, self.y, z, self.kind)
        keep = in_range if not extrapolate else self.valid
        return LutEvaluation(np.where(keep, x, np.nan), np.where(keep, y, np.nan), in_range)


def _horner(coeffs: np.ndarray, t) -> np.ndarray:
    out = np.array(coeffs[-1], dtype=np.float64, copy=True)
    for c in coeffs[-2::-1]:
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
    if positions is not None:
        samples = samples.subset(positions)
        if weights is not None:
            weights = np.asarray(weights)[np.asarray(positions)]
    z = samples.z
    order = np.argsort(z)
    k, h, w = samples.x.shape
    valid_all = samples.valid.reshape(k, -1)
    n_pos = valid_all.sum(axis=0)
    z_center, z_scale = _z_normalisation(z)
    if min_positions is None:
        min_positions = degree + 2 if model == "poly" else 2
    usable = n_pos >= min_positions
    zk = np.where(valid_all, z[:, None], np.nan)
    with np.errstate(all="ignore"):
        pz_min = np.where(usable, np.nanmin(np.where(valid_all, zk, np.inf), axis=0), np.nan)
        pz_max = np.where(usable, np.nanmax(np.where(valid_all, zk, -np.inf), axis=0), np.nan)
    p_total = h * w
    out = {}
    if model == "poly":
        n_coef = degree + 1
        coef = {a: np.full((n_coef, p_total), np.nan) for a in "xy"}
    else:
        coef = {a: np.full((k, p_total), np.nan) for a in "xy"}
    rms = {a: np.full(p_total, np.nan, np.float32) for a in "xy"}
    loo = {a: np.full(p_total, np.nan, np.float32) for a in "xy"}
    t_all = (z - z_center) / z_scale
    wflat = None if weights is None else np.asarray(weights, dtype=float).reshape(k, -1)
    for start in range(0, p_total, _TILE):
        if progress:
            progress(start / p_total, f"fitting LUT ({model})")
        stop = min(start + _TILE, p_total)
        mask = valid_all[:, start:stop] & usable[None, start:stop]
        for axis_name in "xy":
            offs = getattr(samples, axis_name).reshape(k, -1)[:, start:stop].astype(np.float64)
            ref = getattr(samples, f"{axis_name}_ref").reshape(-1)[start:stop]
            if model == "poly":
                c, r, l = _fit_poly_tile(t_all, offs, mask, degree,
                                         None if wflat is None else wflat[:, start:stop])
                c[0] += ref
                coef[axis_name][:, start:stop] = c
            else:
                vals = np.where(mask, offs + ref[None, :], np.nan)
                coef[axis_name][:, start:stop] = vals[order]
                r = np.where(mask.any(axis=0), 0.0, np.nan)
                l = _table_loo(z[order], offs[order], mask[order], model)
            rms[axis_name][start:stop] = r
            loo[axis_name][start:stop] = l
    valid = usable & np.all(np.isfinite(coef["x"]) | (model != "poly"), axis=0)
    if model != "poly":
        valid &= np.isfinite(coef["x"]).sum(axis=0) >= 2
    for a in "xy":
        if model == "poly":
            coef[a][:, ~valid] = np.nan
        else:
            coef[a][:, ~valid] = np.nan
        rms[a][~valid] = np.nan
        loo[a][~valid] = np.nan
    pz_min = np.where(valid, pz_min, np.nan)
    pz_max = np.where(valid, pz_max, np.nan)
    shape = (h, w)
    if progress:
        progress(1.0, "LUT fitted")
    return Lut(
        kind=model, degree=int(degree) if model == "poly" else None,
        z_center=z_center, z_scale=z_scale, z_min=float(z.min()), z_max=float(z.max()),
        x=coef["x"].reshape(-1, h, w), y=coef["y"].reshape(-1, h, w),
        z_nodes=None if model == "poly" else z[order].astype(float),
        valid=valid.reshape(shape), n_positions=np.where(valid, n_pos, 0).astype(np.uint16).reshape(shape),
        pixel_z_min=pz_min.astype(np.float32).reshape(shape), pixel_z_max=pz_max.astype(np.float32).reshape(shape),
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
    k, p = values.shape
    n_coef = degree + 1
    coef = np.full((n_coef, p), np.nan)
    rms = np.full(p, np.nan)
    loo = np.full(p, np.nan)
    vander = np.vander(t, n_coef, increasing=True)  # (K, D+1)
    if weights is None:
        groups = _group_by_pattern(mask)
    else:
        groups = ((None, np.array([j])) for j in np.flatnonzero(mask.sum(axis=0) >= n_coef))
    for pattern, cols in groups:
        if pattern is None:
            pattern = mask[:, cols[0]]
        n = int(pattern.sum())
        if n < n_coef:
            continue
        v = vander[pattern]
        y = values[pattern][:, cols]
        if weights is not None:
            sw = np.sqrt(weights[pattern][:, cols[0]])
            pinv = np.linalg.pinv(v * sw[:, None]) * sw[None, :]
        else:
            pinv = np.linalg.pinv(v)  # (D+1, n)
        c = pinv @ y
        resid = y - v @ c
        hat = np.einsum("ij,ji->i", v, pinv)  # leverages h_kk
        coef[:, cols] = c
        rms[cols] = np.sqrt(np.mean(resid * resid, axis=0))
        if n > n_coef:
            with np.errstate(divide="ignore", invalid="ignore"):
                loo_r = resid / (1.0 - hat)[:, None]
            loo[cols] = np.sqrt(np.mean(loo_r * loo_r, axis=0))
    return coef, rms, loo


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


def save_lut(lut: Lut, path) -> None:
    """Write ``ptp-lut/1`` (FORMATS.md) atomically."""
    h, w = lut.shape
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = LUT_FORMAT
            f.attrs["software"] = f"ptpcore {__version__}"
            f.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
            f.attrs["units"] = "mm"
            f.create_group("camera").attrs.update({"width": w, "height": h})
            m = f.create_group("model")
            m.attrs.update({"kind": lut.kind, "z_center": lut.z_center, "z_scale": lut.z_scale,
                            "z_min": lut.z_min, "z_max": lut.z_max})
            if lut.kind == "poly":
                m.attrs["degree"] = lut.degree
            for key, val in lut.extra_attrs.items():
                m.attrs[key] = val
            opts = dict(chunks=True, compression="gzip", compression_opts=1, shuffle=True)
            f.create_dataset("x", data=lut.x.astype(np.float64), **opts)
            f.create_dataset("y", data=lut.y.astype(np.float64), **opts)
            if lut.z_nodes is not None:
                f["z_nodes"] = lut.z_nodes.astype(np.float64)
            f.create_dataset("valid", data=lut.valid.astype(np.uint8), **opts)
            q = f.create_group("quality")
            q.create_dataset("n_positions", data=lut.n_positions.astype(np.uint16), **opts)
            q.create_dataset("z_min", data=lut.pixel_z_min.astype(np.float32), **opts)
            q.create_dataset("z_max", data=lut.pixel_z_max.astype(np.float32), **opts)
            for name in ("rms_x", "rms_y", "loo_x", "loo_y", "sigma_x", "sigma_y"):
                val = getattr(lut, name)
                if val is not None:
                    q.create_dataset(name, data=val.astype(np.float32), **opts)
            f.create_group("rig").attrs["toml"] = lut.rig_toml


def load_lut(path) -> Lut:
    """Read and check a ``ptp-lut/1`` file.

    Raises
    ------
    FileFormatError
        Naming the file and the dataset or attribute that is wrong.
    """
    path = Path(path)
    where = str(path)
    try:
        f = h5py.File(path, "r")
    except FileNotFoundError:
        raise FileFormatError(f"{where}: file not found") from None
    except OSError as exc:
        raise FileFormatError(f"{where}: not a readable HDF5 file ({exc})") from None
    with f:
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode()
        if fmt != LUT_FORMAT:
            if isinstance(fmt, str) and fmt.startswith("ptp-lut/"):
                raise FileFormatError(f"{where}: format {fmt!r} is newer than this software reads ({LUT_FORMAT})")
            raise FileFormatError(f"{where}: attribute 'format' is {fmt!r}, expected {LUT_FORMAT!r}")
        try:
            h = int(f["camera"].attrs["height"])
            w = int(f["camera"].attrs["width"])
            m = dict(f["model"].attrs)
            kind = str(m["kind"])
            if kind not in MODELS:
                raise FileFormatError(f"{where}: /model kind {kind!r} is not one of {MODELS}")
            x = f["x"][()]
            y = f["y"][()]
            z_nodes = f["z_nodes"][()] if "z_nodes" in f else None
            valid = f["valid"][()].astype(bool)
            q = f["quality"]
            quality = {n: q[n][()] for n in _QUALITY}
            sig = {n: (q[n][()] if n in q else None) for n in ("sigma_x", "sigma_y")}
            rig_toml = f["rig"].attrs.get("toml", "") if "rig" in f else ""
        except KeyError as exc:
            raise FileFormatError(f"{where}: missing {exc.args[0]!r}") from None
        except OSError as exc:
            raise FileFormatError(f"{where}: truncated or damaged ({exc})") from None
    degree = int(m["degree"]) if kind == "poly" else None
    n_lead = degree + 1 if kind == "poly" else (len(z_nodes) if z_nodes is not None else -1)
    if kind != "poly" and z_nodes is None:
        raise FileFormatError(f"{where}: /z_nodes is required for kind {kind!r}")
    for name, arr, want in (("/x", x, (n_lead, h, w)), ("/y", y, (n_lead, h, w)), ("/valid", valid, (h, w))):
        if arr.shape != want:
            raise FileFormatError(f"{where}: {name} has shape {arr.shape}, expected {want}")
    for name, arr in quality.items():
        if arr.shape != (h, w):
            raise FileFormatError(f"{where}: /quality/{name} has shape {arr.shape}, expected {(h, w)}")
    if kind == "poly" and not np.all(np.isfinite(x[:, valid])) or not np.all(np.isfinite(y[:, valid]) | (kind != "poly")):
        raise FileFormatError(f"{where}: /x or /y holds NaN for pixels marked valid")
    if isinstance(rig_toml, bytes):
        rig_toml = rig_toml.decode()
    return Lut(
        kind=kind, degree=degree, z_center=float(m["z_center"]), z_scale=float(m["z_scale"]),
        z_min=float(m["z_min"]), z_max=float(m["z_max"]), x=x, y=y, z_nodes=z_nodes, valid=valid,
        n_positions=quality["n_positions"], pixel_z_min=quality["z_min"], pixel_z_max=quality["z_max"],
        rms_x=quality["rms_x"], rms_y=quality["rms_y"], loo_x=quality["loo_x"], loo_y=quality["loo_y"],
        sigma_x=sig["sigma_x"], sigma_y=sig["sigma_y"], rig_toml=str(rig_toml),
    )
