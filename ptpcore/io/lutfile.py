"""The per-pixel LUT Z -> (X, Y) in memory (:class:`Lut`), its evaluation, and ``ptp-lut/1`` files.

Models (docs/method.md section 5)
---------------------------
``poly``
    Polynomial of degree D in ``t = (z - z_center)/z_scale``.
``linear`` / ``pchip``
    Interpolation of the table of samples between calibrated heights.

Fitting lives in :mod:`ptpcore.fit`; this module only holds, evaluates, writes
and reads a LUT, so scanners and tools can use it without the fitting code.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import io
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
from scipy.interpolate import PchipInterpolator

from ptpcore import __version__
from ptpcore.atomic import atomic_path, disk_full_error, write_bytes_atomic
from ptpcore.errors import FileFormatError
from ptpcore.io.h5chunks import create_compressed
from ptpcore.io.heightmap import HeightMap, read_height_group, write_height_group
from ptpcore.io.pointcloud import PointCloud, build_point_cloud

__all__ = [
    "LUT_FORMAT",
    "Lut",
    "LutEvaluation",
    "save_lut",
    "load_lut",
    "MODELS",
]

LUT_FORMAT = "ptp-lut/1"
MODELS = ("poly", "pchip", "linear")


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
        Predicted 1-sigma uncertainty (optional): the propagated noise and the model's own error
        in quadrature.
    rig_toml : str
    extra_attrs : dict
        More ``/model`` attributes (``method``, ``chosen_by``, ...).
    provenance : dict of str
        ``/provenance`` attributes: name -> JSON text (``corrections``: what
        was removed from the samples before fitting; ``model_choice``, ``robust``,
        ``drift``, FORMATS.md).
    stage_pose, stage_pose_sigma : (K, 6) float64 or None
        ``/provenance/stage_pose`` and ``_sigma``: the stage refinement's
        per-position dx, dy, dz (um), pitch, yaw, roll (urad) and 1 sigma.
    n_rejected : (H, W) uint16 or None
        Samples a robust fit left out of each pixel (optional ``/quality/n_rejected``).
    sigma_model_x, sigma_model_y : (H, W) float32 or None
        The model's part of ``sigma_x``, ``sigma_y`` (optional ``/quality/sigma_model_x``, ``_y``;
        ``/provenance`` attribute ``model_error`` says how it was estimated).
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
    provenance: dict = field(default_factory=dict)
    stage_pose: np.ndarray | None = None
    stage_pose_sigma: np.ndarray | None = None
    n_rejected: np.ndarray | None = None
    sigma_model_x: np.ndarray | None = None
    sigma_model_y: np.ndarray | None = None
    height: HeightMap | None = None
    """The scanner's height map ``u_p -> Z`` (optional ``/height``, docs/method.md section 9)."""

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape

    def row_band(self, r0: int, r1: int) -> "Lut":
        """The LUT of image rows ``[r0, r1)``: every per-pixel array a view of this one's rows.

        For work in row blocks on big sensors (the residual diagnostics): evaluating the
        band gives exactly the rows of evaluating the whole image.
        """
        def band(a):
            if a is None:
                return None
            return a[:, r0:r1] if a.ndim == 3 else a[r0:r1]

        per_pixel = ("x", "y", "valid", "n_positions", "pixel_z_min", "pixel_z_max", "rms_x", "rms_y",
                     "loo_x", "loo_y", "sigma_x", "sigma_y", "n_rejected", "sigma_model_x", "sigma_model_y")
        # The height map is not banded: a band has none.
        return dataclasses.replace(self, height=None, **{name: band(getattr(self, name)) for name in per_pixel})

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
        if self.kind == "poly":
            # Row tiles on every core: each tile's Horner steps stay in cache, so
            # the coefficients are read once (the cost floor) instead of once per step.
            from ptpcore.parallel import run_tiles

            h, w = self.shape
            x = np.empty((h, w))
            y = np.empty((h, w))
            in_range = np.empty((h, w), bool)

            def rows(r0: int, r1: int) -> None:
                zr = z if z.ndim == 0 else z[r0:r1]
                ok = _in_range(self.valid[r0:r1], zr, self.pixel_z_min[r0:r1], self.pixel_z_max[r0:r1])
                in_range[r0:r1] = ok
                keep = ok if not extrapolate else self.valid[r0:r1]
                t = (zr - self.z_center) / self.z_scale
                for coeffs, out in ((self.x, x), (self.y, y)):
                    o = out[r0:r1]
                    _horner(coeffs[:, r0:r1], t, o)
                    o[~keep] = np.nan

            run_tiles(rows, h, w)
            return LutEvaluation(x, y, in_range)
        in_range = _in_range(self.valid, z, self.pixel_z_min, self.pixel_z_max)
        x = interp_table(self.z_nodes, self.x, z, self.kind)
        y = interp_table(self.z_nodes, self.y, z, self.kind)
        keep = in_range if not extrapolate else self.valid
        return LutEvaluation(np.where(keep, x, np.nan), np.where(keep, y, np.nan), in_range)

    def points(self, z, *, extrapolate: bool = False) -> PointCloud:
        """The point cloud of a height map (or one height for every pixel).

        Parameters
        ----------
        z : float or (H, W) array_like, mm
            NaN where there is no measurement.
        extrapolate : bool
            Keep valid pixels whose height is outside their own calibrated
            range (flagged ``extrapolated``); tables never extrapolate.

        Returns
        -------
        PointCloud
            One point per pixel with a height, a valid LUT, an allowed height
            and a value there; the others are counted by reason.

        Raises
        ------
        ValueError
            ``z`` is neither a scalar nor an ``(H, W)`` map.
        """
        zz = np.asarray(z, dtype=float)
        ev = self.evaluate(zz, extrapolate=extrapolate)
        return build_point_cloud(ev.x, ev.y, np.broadcast_to(zz, self.shape), self.valid, ev.in_range,
                                 extrapolate, self.sigma_x, self.sigma_y)

    def ray(self, row: int, col: int) -> tuple[np.ndarray, np.ndarray]:
        """A pixel's line in space, for a degree-1 ``poly`` LUT.

        Returns
        -------
        point : (3,) float64, mm
            The pixel's X, Y at ``Z = z_center`` (the middle of the calibrated range).
        direction : (3,) float64
            ``(dX/dZ, dY/dZ, 1)``: the point at height Z is
            ``point + (Z - point[2]) * direction``.

        Raises
        ------
        ValueError
            Another model or degree (their lines are curves: use :meth:`points`),
            a pixel outside the camera or invalid in the LUT.
        """
        if self.kind != "poly" or self.degree != 1:
            what = f"poly degree {self.degree}" if self.kind == "poly" else self.kind
            raise ValueError(f"ray() needs a degree-1 poly LUT, this one is {what}: its pixels' lines are"
                             " not straight; evaluate heights with points() or evaluate()")
        h, w = self.shape
        if not (0 <= int(row) < h and 0 <= int(col) < w):
            raise ValueError(f"pixel (row {row}, col {col}) is outside the {w}x{h} camera")
        if not self.valid[row, col]:
            raise ValueError(f"pixel (row {row}, col {col}) has no valid LUT")
        point = np.array([self.x[0, row, col], self.y[0, row, col], self.z_center])
        direction = np.array([self.x[1, row, col] / self.z_scale, self.y[1, row, col] / self.z_scale, 1.0])
        return point, direction


RANGE_EPS_MM = 1e-9
RANGE_REL = 2.0 ** -23
"""A height is in a pixel's range when ``z_min - tol <= z <= z_max + tol``, ``tol = 1e-9 + |bound| 2**-23``.

The bounds are stored as float32: a reading of 0.1 mm is kept as 0.10000000149. The
relative part (two float32 half-steps) lets that reading itself be in range; the
comparison is made in float64. The C reader (readers/c/ptplut.c) uses the same rule.
"""


def _in_range(valid, z, z_min, z_max) -> np.ndarray:
    """``valid`` and ``z`` within the pixels' calibrated ranges (float64 comparison; bool, shape of ``valid``)."""
    lo = np.asarray(z_min, np.float64)
    hi = np.asarray(z_max, np.float64)
    return valid & (z >= lo - (RANGE_EPS_MM + np.abs(lo) * RANGE_REL)) & (z <= hi + (RANGE_EPS_MM + np.abs(hi) * RANGE_REL))


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


def group_by_pattern(mask: np.ndarray):
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


def interp_table(z_nodes: np.ndarray, table: np.ndarray, z, kind: str) -> np.ndarray:
    """Per-pixel interpolation of a (K, H, W) table with NaN nodes.

    Each pixel is interpolated over the maximal run of consecutive valid nodes
    that contains ``z``; between a NaN node and its neighbours it is NaN.
    """
    k, h, w = table.shape
    vals = table.reshape(k, -1)
    zq = np.broadcast_to(np.asarray(z, dtype=float), (h, w)).reshape(-1)
    out = np.full(h * w, np.nan)
    for pattern, cols in group_by_pattern(np.isfinite(vals)):
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
# Files

_QUALITY = ("n_positions", "z_min", "z_max", "rms_x", "rms_y", "loo_x", "loo_y")
_MAX_DEGREE = 5


def write_lut_attrs(obj) -> None:
    """The ``/`` attributes of ``ptp-lut/1`` (also put on a session's ``/lut`` group)."""
    obj.attrs["format"] = LUT_FORMAT
    obj.attrs["software"] = f"ptpcore {__version__}"
    obj.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    obj.attrs["units"] = "mm"


def write_lut_group(group, lut: Lut) -> None:
    """Write every ``ptp-lut/1`` dataset and group of ``lut`` into an open HDF5 group.

    ``save_lut`` writes into the file's root group; a session file into ``/lut``.
    The format attributes are not written here (see :func:`write_lut_attrs`).
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
    # np.asarray, not astype: no copy of a big sensor's maps that already have the stored type.
    create_compressed(group, "x", np.asarray(lut.x, np.float64))
    create_compressed(group, "y", np.asarray(lut.y, np.float64))
    if lut.z_nodes is not None:
        group["z_nodes"] = np.asarray(lut.z_nodes, dtype=np.float64)
    create_compressed(group, "valid", lut.valid.astype(np.uint8))
    q = group.create_group("quality")
    create_compressed(q, "n_positions", np.asarray(lut.n_positions, np.uint16))
    create_compressed(q, "z_min", np.asarray(lut.pixel_z_min, np.float32))
    create_compressed(q, "z_max", np.asarray(lut.pixel_z_max, np.float32))
    for name in ("rms_x", "rms_y", "loo_x", "loo_y", "sigma_x", "sigma_y"):
        val = getattr(lut, name)
        if val is not None:
            create_compressed(q, name, np.asarray(val, np.float32))
    if lut.n_rejected is not None:
        create_compressed(q, "n_rejected", np.minimum(lut.n_rejected, 65535).astype(np.uint16))
    for name in ("sigma_model_x", "sigma_model_y"):
        val = getattr(lut, name)
        if val is not None:
            create_compressed(q, name, np.asarray(val, np.float32))
    group.create_group("rig").attrs["toml"] = lut.rig_toml
    if lut.provenance or lut.stage_pose is not None:
        prov = group.create_group("provenance")
        prov.attrs.update({k: str(v) for k, v in lut.provenance.items()})
        for name in ("stage_pose", "stage_pose_sigma"):
            if getattr(lut, name) is not None:
                prov[name] = np.asarray(getattr(lut, name), dtype=np.float64)
    if lut.height is not None:
        write_height_group(group, lut.height)


def save_lut(lut: Lut, path) -> None:
    """Write ``ptp-lut/1`` (FORMATS.md) atomically.

    A process killed during the write leaves the previous file (if any) intact.
    """
    def fill(f) -> None:
        write_lut_attrs(f)
        write_lut_group(f, lut)

    write_hdf5_atomic(path, fill, arrays_nbytes(lut.x, lut.y, lut.valid, lut.n_positions, lut.rms_x, lut.rms_y,
                                          lut.loo_x, lut.loo_y, lut.sigma_x, lut.sigma_y, lut.sigma_model_x,
                                          lut.sigma_model_y))


IN_MEMORY_MAX = 64 * 2 ** 20
"""HDF5 files estimated larger than this (bytes, uncompressed) are written straight to disk.

Building a file in memory costs up to twice its size (the growing buffer, then the
write): 64 MB keeps that small beside a big sensor's LUT (about 450 MB at 5 MP)."""


def write_hdf5_atomic(path, fill, size_hint: int | None = None) -> None:
    """Write an HDF5 file atomically, so that a full disk is one clean error.

    HDF5 writing straight to a disk that fills leaves the library in a state
    that prints tracebacks from finalizers and can crash the interpreter at
    exit. Up to :data:`IN_MEMORY_MAX` the file is built in memory and reaches
    the disk as one plain write: a full disk is one
    :class:`~ptpcore.atomic.DiskFullError` naming the file and its size, the
    temporary file removed. A bigger file (a session of a large sensor) is
    written to disk directly, after checking that the disk has room for its
    uncompressed size (refused up front otherwise: the same error).

    Parameters
    ----------
    path : path
        The file to write.
    fill : callable
        Called with the open, empty ``h5py.File``.
    size_hint : int, optional
        The data's uncompressed size in bytes (default: small).
    """
    if size_hint is not None and size_hint > IN_MEMORY_MAX:
        need = int(size_hint) + 2 ** 20
        folder = Path(path).parent
        if shutil.disk_usage(folder if str(folder) else ".").free < need:
            raise disk_full_error(path, need)
        with atomic_path(path, need_bytes=need) as tmp:
            with h5py.File(tmp, "w") as f:
                fill(f)
        return
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        fill(f)
    write_bytes_atomic(path, buf.getbuffer())


def arrays_nbytes(*arrays) -> int:
    """Total bytes of the arrays given (None skipped): a file's uncompressed size."""
    return sum(int(a.nbytes) for a in arrays if a is not None)


def str_attr(value) -> str | None:
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
    fmt = str_attr(obj.attrs.get("format"))
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


def read_lut_group(group, where: str) -> Lut:
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
    rd = _GroupReader(group, where)
    try:
        lut, camera_shape = _read_lut_arrays(rd)
    except (OSError, RuntimeError) as exc:  # h5py raises RuntimeError for some damaged structures
        raise rd.fail(f"truncated or damaged ({exc})") from None
    _check_lut_model(rd, lut)
    _check_lut_shapes(rd, lut, camera_shape)
    _check_lut_values(rd, lut)
    if "height" in group:
        try:
            lut.height = read_height_group(rd, camera_shape)
        except (OSError, RuntimeError) as exc:
            raise rd.fail(f"/height truncated or damaged ({exc})") from None
    return lut


class _GroupReader:
    """Typed, checked reads of one HDF5 group's datasets and attributes; errors name the file and the path."""

    def __init__(self, group, where: str):
        self.group, self.where = group, where
        self.base = "" if group.name == "/" else group.name

    def name(self, rel: str) -> str:
        return f"{self.base}/{rel}"

    def fail(self, msg: str) -> FileFormatError:
        return FileFormatError(f"{self.where}: {msg}")

    def array(self, rel: str, ndim: int, kinds: str = "fiub") -> np.ndarray:
        """The dataset ``rel`` read whole, checked to hold numbers of ``kinds`` in ``ndim`` dimensions."""
        try:
            obj = self.group[rel]
        except KeyError:
            raise self.fail(f"missing dataset {self.name(rel)}") from None
        if not isinstance(obj, h5py.Dataset):
            raise self.fail(f"{self.name(rel)} is not a dataset")
        if obj.dtype.kind not in kinds:
            raise self.fail(f"{self.name(rel)} has type {obj.dtype}, expected numbers")
        if obj.ndim != ndim:
            raise self.fail(f"{self.name(rel)} has {obj.ndim} dimensions {obj.shape}, expected {ndim}")
        return obj[()]

    def attr(self, obj_rel: str, key: str, kind):
        """Attribute ``key`` of the group ``obj_rel`` ('' = this group) as ``kind`` (str, int or float, finite)."""
        if obj_rel and obj_rel not in self.group:
            raise self.fail(f"missing group {self.name(obj_rel)}")
        try:
            obj = self.group[obj_rel] if obj_rel else self.group
            val = obj.attrs[key]
        except KeyError:
            where = self.name(obj_rel) if obj_rel else self.base or "/"
            raise self.fail(f"missing attribute {key!r} of {where}") from None
        label = f"attribute {key!r} of {self.name(obj_rel)}"
        if kind is str:
            s = str_attr(val)
            if s is None:
                raise self.fail(f"{label} must be text, got {val!r}")
            return s
        if isinstance(val, np.ndarray) and val.size == 1:
            val = val.reshape(())[()]
        if isinstance(val, (bool, np.bool_)) or not isinstance(val, (int, float, np.integer, np.floating)):
            raise self.fail(f"{label} must be a number, got {val!r}"[:200])
        if kind is int:
            if float(val) != int(val):
                raise self.fail(f"{label} must be an integer, got {val!r}")
            return int(val)
        val = float(val)
        if not np.isfinite(val):
            raise self.fail(f"{label} must be finite, got {val}")
        return val


def _read_lut_arrays(rd: _GroupReader) -> tuple[Lut, tuple[int, int]]:
    """Every attribute and dataset of a LUT group, each checked for its type (not yet for consistency),
    and the camera's ``(height, width)`` from ``/camera``."""
    group, name = rd.group, rd.name
    h = rd.attr("camera", "height", int)
    w = rd.attr("camera", "width", int)
    if h < 1 or w < 1:
        raise rd.fail(f"{name('camera')} size {w}x{h} must be positive")
    kind = rd.attr("model", "kind", str)
    if kind not in MODELS:
        raise rd.fail(f"attribute 'kind' of {name('model')} is {kind!r}, not one of {MODELS}")
    degree = rd.attr("model", "degree", int) if kind == "poly" else None
    if degree is not None and not 1 <= degree <= _MAX_DEGREE:
        raise rd.fail(f"attribute 'degree' of {name('model')} must be 1 to {_MAX_DEGREE}, got {degree}")
    mv = {k: rd.attr("model", k, float) for k in ("z_center", "z_scale", "z_min", "z_max")}
    known = {"kind", "degree", "z_center", "z_scale", "z_min", "z_max"}
    extra = {k: v for k, v in group["model"].attrs.items() if k not in known}
    x = rd.array("x", 3, "f")
    y = rd.array("y", 3, "f")
    z_nodes = rd.array("z_nodes", 1, "f") if "z_nodes" in group else None
    valid_raw = rd.array("valid", 2, "uib")
    q = {n: rd.array(f"quality/{n}", 2) for n in _QUALITY}
    sig = {n: (rd.array(f"quality/{n}", 2, "f") if f"quality/{n}" in group else None)
           for n in ("sigma_x", "sigma_y", "sigma_model_x", "sigma_model_y")}
    n_rejected = rd.array("quality/n_rejected", 2, "ui") if "quality/n_rejected" in group else None
    rig_toml = ""
    if "rig" in group:
        rig_toml = str_attr(group["rig"].attrs.get("toml", "")) or ""
    provenance, poses = {}, {}
    if "provenance" in group:
        provenance = {str(k): str(str_attr(v)) for k, v in group["provenance"].attrs.items()}
        poses = {n: rd.array(f"provenance/{n}", 2, "f") for n in ("stage_pose", "stage_pose_sigma")
                 if f"provenance/{n}" in group}
    # valid stays as stored until _check_lut_values has seen it hold only 0 and 1.
    lut = Lut(
        kind=kind, degree=degree, z_center=mv["z_center"], z_scale=mv["z_scale"],
        z_min=mv["z_min"], z_max=mv["z_max"], x=x, y=y, z_nodes=z_nodes, valid=valid_raw,
        n_positions=q["n_positions"], pixel_z_min=q["z_min"], pixel_z_max=q["z_max"],
        rms_x=q["rms_x"], rms_y=q["rms_y"], loo_x=q["loo_x"], loo_y=q["loo_y"],
        sigma_x=sig["sigma_x"], sigma_y=sig["sigma_y"], rig_toml=str(rig_toml), extra_attrs=extra,
        provenance=provenance, stage_pose=poses.get("stage_pose"), stage_pose_sigma=poses.get("stage_pose_sigma"),
        n_rejected=n_rejected, sigma_model_x=sig["sigma_model_x"], sigma_model_y=sig["sigma_model_y"],
    )
    return lut, (h, w)


def _check_lut_model(rd: _GroupReader, lut: Lut) -> None:
    """The z normalisation, range and (for tables) the nodes."""
    name = rd.name
    if lut.z_scale <= 0:
        raise rd.fail(f"attribute 'z_scale' of {name('model')} must be positive, got {lut.z_scale}")
    if lut.z_min > lut.z_max:
        raise rd.fail(f"attributes 'z_min' > 'z_max' of {name('model')} ({lut.z_min} > {lut.z_max})")
    if lut.kind != "poly":
        z_nodes = lut.z_nodes
        if z_nodes is None:
            raise rd.fail(f"missing dataset {name('z_nodes')} (required for kind {lut.kind!r})")
        if z_nodes.size < 2 or not np.all(np.isfinite(z_nodes)) or np.any(np.diff(z_nodes) <= 0):
            raise rd.fail(f"{name('z_nodes')} must hold at least 2 finite, strictly ascending heights")


def _check_lut_shapes(rd: _GroupReader, lut: Lut, camera_shape: tuple[int, int]) -> None:
    """Every array has the camera's shape (and the model's leading size)."""
    h, w = camera_shape
    n_lead = lut.degree + 1 if lut.kind == "poly" else len(lut.z_nodes)
    for rel, arr, want in (("x", lut.x, (n_lead, h, w)), ("y", lut.y, (n_lead, h, w)),
                           ("valid", lut.valid, (h, w))):
        if arr.shape != want:
            raise rd.fail(f"{rd.name(rel)} has shape {arr.shape}, expected {want}")
    quality = {"n_positions": lut.n_positions, "z_min": lut.pixel_z_min, "z_max": lut.pixel_z_max,
               "rms_x": lut.rms_x, "rms_y": lut.rms_y, "loo_x": lut.loo_x, "loo_y": lut.loo_y,
               "sigma_x": lut.sigma_x, "sigma_y": lut.sigma_y, "n_rejected": lut.n_rejected,
               "sigma_model_x": lut.sigma_model_x, "sigma_model_y": lut.sigma_model_y}
    for n, arr in quality.items():
        if arr is not None and arr.shape != (h, w):
            raise rd.fail(f"{rd.name('quality/' + n)} has shape {arr.shape}, expected {(h, w)}")


def _check_lut_values(rd: _GroupReader, lut: Lut) -> None:
    """Numbers where a valid pixel needs them, ranges in order, no negative RMS; makes ``valid`` bool."""
    name = rd.name
    if np.any((lut.valid != 0) & (lut.valid != 1)):
        raise rd.fail(f"{name('valid')} must hold only 0 and 1")
    valid = lut.valid = lut.valid.astype(bool)
    for rel, arr in (("x", lut.x), ("y", lut.y)):
        if lut.kind == "poly":
            if not np.all(np.isfinite(arr[:, valid])):
                raise rd.fail(f"{name(rel)} holds NaN or infinite coefficients for pixels marked valid")
        else:
            fin = np.isfinite(arr)
            if np.any(np.isinf(arr)):
                raise rd.fail(f"{name(rel)} holds infinite values")
            if np.any(fin.sum(axis=0)[valid] < 2):
                raise rd.fail(f"{name(rel)} has fewer than 2 finite nodes for pixels marked valid")
    if np.any(lut.n_positions[valid] < 1):
        raise rd.fail(f"{name('quality/n_positions')} is 0 for pixels marked valid")
    pz_min, pz_max = lut.pixel_z_min, lut.pixel_z_max
    if not (np.all(np.isfinite(pz_min[valid])) and np.all(np.isfinite(pz_max[valid]))):
        raise rd.fail(f"{name('quality/z_min')} or {name('quality/z_max')} holds NaN for pixels marked valid")
    if np.any(pz_min[valid] > pz_max[valid]):
        raise rd.fail(f"{name('quality/z_min')} exceeds {name('quality/z_max')} for some valid pixels")
    for n in ("rms_x", "rms_y", "loo_x", "loo_y"):
        with np.errstate(invalid="ignore"):
            if np.any(getattr(lut, n) < 0):
                raise rd.fail(f"{name('quality/' + n)} holds negative values")


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
        return read_lut_group(f, where)
