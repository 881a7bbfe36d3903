"""Point clouds from a LUT and a height map: ``Lut.points``, height-map reading, PLY/.npy/.h5 writers.

A scanner measures a height Z per camera pixel (a height map); the LUT turns
each pixel's Z into X, Y (FORMATS.md ``ptp-lut/1``). This module holds the
result, :class:`PointCloud`, and its files. It lives in the I/O layer, beside
the LUT file, because ``Lut.points`` returns it; it never imports the LUT
module (the LUT passes in its evaluation).

Every pixel of the height map ends in exactly one of: a point, or left out
because it has no height (NaN), its LUT is invalid, its height is outside its
own calibrated range (unless extrapolating), or the LUT has no value there
(a table between NaN nodes, or outside its nodes).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ptpcore.atomic import atomic_path
from ptpcore.errors import FileFormatError

__all__ = ["POINTS_FORMAT", "PointCloud", "build_point_cloud", "read_height_map", "write_point_cloud",
           "POINT_CLOUD_SUFFIXES"]

POINTS_FORMAT = "ptp-points/1"
POINT_CLOUD_SUFFIXES = (".ply", ".npy", ".h5")


@dataclass
class PointCloud:
    """The points one height map gives through a LUT.

    Attributes
    ----------
    x, y, z : (N,) float64, mm
        World coordinates of each point (``z`` is the pixel's height).
    row, col : (N,) int32
        The camera pixel of each point.
    sigma_x, sigma_y : (N,) float32 or None, mm
        The LUT's predicted 1-sigma uncertainty of X, Y, where the LUT has it.
    extrapolated : (N,) bool
        True where the height is outside the pixel's calibrated z range (only
        possible when extrapolation was asked for).
    shape : (int, int)
        ``(H, W)`` of the camera.
    n_no_height : int
        Pixels whose height is NaN (no measurement).
    n_invalid : int
        Pixels with a height but no usable LUT.
    n_out_of_range : int
        Pixels left out because their height is outside their calibrated range.
    n_no_value : int
        Pixels with a valid LUT and an allowed height where the LUT gives no
        value (a table between NaN nodes or beyond its nodes).
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    row: np.ndarray
    col: np.ndarray
    sigma_x: np.ndarray | None
    sigma_y: np.ndarray | None
    extrapolated: np.ndarray
    shape: tuple[int, int]
    n_no_height: int = 0
    n_invalid: int = 0
    n_out_of_range: int = 0
    n_no_value: int = 0
    sigma_z: np.ndarray | None = None
    """1-sigma of Z (mm) where the height came with one (``ptp reconstruct``)."""
    n_out_of_height_range: int = 0
    """Pixels left out because their ``u_p`` is outside their height map's calibrated range."""

    @property
    def n_points(self) -> int:
        return int(self.x.size)

    @property
    def n_extrapolated(self) -> int:
        return int(np.count_nonzero(self.extrapolated))

    def summary(self) -> str:
        """One line: points kept and pixels left out, by reason."""
        h, w = self.shape
        parts = [f"{self.n_points} points of {h * w} pixels"]
        if self.n_extrapolated:
            parts.append(f"{self.n_extrapolated} extrapolated")
        left = [f"{n} {why}" for n, why in ((self.n_no_height, "without height"),
                                            (self.n_invalid, "invalid in the LUT"),
                                            (self.n_out_of_range, "outside their calibrated z range"),
                                            (self.n_no_value, "without a LUT value at their height"),
                                            (self.n_out_of_height_range,
                                             "outside their height map's calibrated u_p range"))
                if n]
        return ", ".join(parts) + ("; left out: " + ", ".join(left) if left else "; none left out")


def build_point_cloud(x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray, in_range: np.ndarray,
                      extrapolate: bool, sigma_x=None, sigma_y=None) -> PointCloud:
    """Collect the points of an evaluated LUT (what ``Lut.points`` calls).

    Parameters
    ----------
    x, y : (H, W) float64, mm
        The LUT's X, Y at ``z`` (NaN where it gives none).
    z : (H, W) float64, mm
        The height of every pixel; NaN = no measurement.
    valid, in_range : (H, W) bool
        The LUT's valid pixels; valid pixels whose height is within their range.
    extrapolate : bool
        Keep valid pixels outside their range (flagged ``extrapolated``).
    sigma_x, sigma_y : (H, W) array or None
    """
    has_z = np.isfinite(z)
    has_xy = np.isfinite(x) & np.isfinite(y)
    allowed = valid & has_z & (in_range | extrapolate)
    keep = allowed & has_xy
    rows, cols = np.nonzero(keep)
    n_out = 0 if extrapolate else int(np.count_nonzero(valid & has_z & ~in_range))
    return PointCloud(
        x=x[keep].astype(np.float64), y=y[keep].astype(np.float64), z=z[keep].astype(np.float64),
        row=rows.astype(np.int32), col=cols.astype(np.int32),
        sigma_x=None if sigma_x is None else np.asarray(sigma_x, np.float32)[keep],
        sigma_y=None if sigma_y is None else np.asarray(sigma_y, np.float32)[keep],
        extrapolated=~in_range[keep], shape=tuple(valid.shape),
        n_no_height=int(np.count_nonzero(~has_z)), n_invalid=int(np.count_nonzero(has_z & ~valid)),
        n_out_of_range=n_out, n_no_value=int(np.count_nonzero(allowed & ~has_xy)),
    )


# --------------------------------------------------------------------------- height maps

def read_height_map(path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a height map: a 32-bit float TIFF or a ``.npy`` array.

    Parameters
    ----------
    path : path
        ``*.tif``/``*.tiff`` (single channel, 32-bit float) or ``*.npy``
        (2-D, floating point).
    shape : (H, W), optional
        The camera's size; the map must have it.

    Returns
    -------
    (H, W) float64, mm; NaN where there is no measurement.

    Raises
    ------
    FileFormatError
        Naming the file: missing, unreadable, another kind of file, wrong
        shape or type.
    """
    path = Path(path)
    where = str(path)
    if not path.is_file():
        raise FileFormatError(f"{where}: height map not found")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise FileFormatError(f"{where}: not a readable .npy array ({exc})") from None
        if not isinstance(arr, np.ndarray) or arr.dtype.kind != "f":
            raise FileFormatError(f"{where}: height map must be floating point (mm), got {arr.dtype}")
    elif suffix in (".tif", ".tiff"):
        import cv2

        arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if arr is None:
            raise FileFormatError(f"{where}: not a readable TIFF image")
        if arr.dtype != np.float32:
            raise FileFormatError(f"{where}: height map must be a 32-bit float TIFF (mm), got {arr.dtype}"
                                  + (f" with {arr.shape[2]} channels" if arr.ndim == 3 else ""))
    else:
        raise FileFormatError(f"{where}: height map must be a 32-bit float TIFF (.tif, .tiff) or a .npy array")
    if arr.ndim != 2:
        raise FileFormatError(f"{where}: height map must be 2-D (H, W), got shape {arr.shape}")
    if shape is not None and arr.shape != tuple(shape):
        raise FileFormatError(f"{where}: height map is {arr.shape[1]}x{arr.shape[0]} px (shape {arr.shape}),"
                              f" the LUT's camera is {shape[1]}x{shape[0]}")
    arr = arr.astype(np.float64)
    if np.any(np.isinf(arr)):
        raise FileFormatError(f"{where}: height map holds infinite values (use NaN for no measurement)")
    return arr


# --------------------------------------------------------------------------- writers

def _records(cloud: PointCloud) -> np.ndarray:
    """The points as one structured array (little-endian; the field order of every file)."""
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("row", "<i4"), ("col", "<i4")]
    if cloud.sigma_x is not None and cloud.sigma_y is not None:
        fields += [("sigma_x", "<f4"), ("sigma_y", "<f4")]
    if cloud.sigma_z is not None:
        fields.append(("sigma_z", "<f4"))
    fields.append(("extrapolated", "u1"))
    rec = np.empty(cloud.n_points, dtype=fields)
    for name, _ in fields:
        rec[name] = getattr(cloud, name)
    return rec


_PLY_TYPES = {"<f8": "double", "<f4": "float", "<i4": "int", "|u1": "uchar"}


def _write_ply(cloud: PointCloud, tmp: Path, comment: str) -> None:
    rec = _records(cloud)
    lines = ["ply", "format binary_little_endian 1.0", "comment units mm"]
    lines += [f"comment {c}" for c in comment.splitlines() if c]
    lines.append(f"element vertex {rec.size}")
    lines += [f"property {_PLY_TYPES[rec.dtype[name].str]} {name}" for name in rec.dtype.names]
    lines.append("end_header")
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(lines) + "\n").encode("ascii"))
        fh.write(rec.tobytes())


def _write_h5(cloud: PointCloud, tmp: Path, comment: str) -> None:
    """``ptp-points/1`` built in memory, then written as one plain write (a full disk: one error)."""
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        f.attrs["format"] = POINTS_FORMAT
        f.attrs["units"] = "mm"
        f.attrs["comment"] = comment
        f.attrs["camera_height"], f.attrs["camera_width"] = cloud.shape
        for key in ("n_no_height", "n_invalid", "n_out_of_range", "n_no_value"):
            f.attrs[key] = getattr(cloud, key)
        if cloud.n_out_of_height_range:
            f.attrs["n_out_of_height_range"] = cloud.n_out_of_height_range
        rec = _records(cloud)
        for name in rec.dtype.names:
            f.create_dataset(name, data=rec[name], chunks=True if rec.size else None,
                             compression="gzip" if rec.size else None)
    tmp.write_bytes(buf.getbuffer())


def write_point_cloud(cloud: PointCloud, path, comment: str = "") -> Path:
    """Write ``cloud`` atomically; the format follows the suffix.

    ``.ply``: binary little-endian PLY, one vertex per point with ``x, y, z``
    (double, mm), ``row, col`` (int), ``sigma_x, sigma_y`` (float, mm, where
    the LUT has them) and ``extrapolated`` (uchar 0/1). ``.npy``: the same
    fields as one structured array. ``.h5``: ``ptp-points/1``, one dataset per
    field plus the counts of left-out pixels as attributes (docs/formats.md).

    Raises
    ------
    ValueError
        Another suffix.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in POINT_CLOUD_SUFFIXES:
        raise ValueError(f"{path}: output must end in {', '.join(POINT_CLOUD_SUFFIXES)}")
    with atomic_path(path) as tmp:
        if suffix == ".ply":
            _write_ply(cloud, tmp, comment)
        elif suffix == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, _records(cloud), allow_pickle=False)
        else:
            _write_h5(cloud, tmp, comment)
    return path
