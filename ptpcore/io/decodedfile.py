"""``ptp-decoded/1``: the decoded LCD coordinates of some positions (FORMATS.md).

Arrays ``[K, H, W]`` (``[K, 2, H, W]`` per direction x, y) for K positions in
``rig.toml`` order; NaN where invalid or the direction is absent.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
from dataclasses import dataclass
from typing import Iterator

import h5py
import numpy as np

from ptpcore import __version__
from ptpcore.atomic import atomic_path
from ptpcore.io.h5chunks import write_compressed

__all__ = ["DECODED_FORMAT", "Decoded", "DecodedWriter", "decoded_writer", "save_decoded", "load_decoded"]

DECODED_FORMAT = "ptp-decoded/1"

_OPTS = dict(compression="gzip", compression_opts=1, shuffle=True)

_CHUNK_PIXELS = 1 << 18
"""About this many pixels per chunk (1 MB of float32): a chunk holds whole rows of one position."""


@dataclass
class Decoded:
    """The content of a ``ptp-decoded/1`` file.

    Attributes
    ----------
    positions : (K,) int32
        Index of each decoded position in the dataset.
    z_mm : (K,) float64
    u, v : (K, H, W) float32
        LCD coordinates (px, carrier removed); NaN where invalid or the direction is absent.
    modulation, background : (K, 2, H, W) float32
        At the finest level, per direction (x, y), camera DN.
    reasons : (K, 2, H, W) uint16
        Per direction: 0 valid, else bit flags named by ``reason_bits``.
    reason_bits : dict of str -> int
    rig_toml : str
    """

    positions: np.ndarray
    z_mm: np.ndarray
    u: np.ndarray
    v: np.ndarray
    modulation: np.ndarray
    background: np.ndarray
    reasons: np.ndarray
    reason_bits: dict
    rig_toml: str


def save_decoded(path, dec: Decoded) -> None:
    """Write a ``ptp-decoded/1`` file atomically (all positions in memory; see :func:`decoded_writer`)."""
    with decoded_writer(path, dec.positions, dec.z_mm, dec.u.shape[1:], dec.reason_bits, dec.rig_toml) as out:
        for i in range(len(dec.positions)):
            out.write(i, dec.u[i], dec.v[i], dec.modulation[i], dec.background[i], dec.reasons[i])


@contextlib.contextmanager
def decoded_writer(path, positions, z_mm, shape, reason_bits: dict, rig_toml: str) -> Iterator["DecodedWriter"]:
    """A ``ptp-decoded/1`` file written one position at a time, atomically.

    A big sensor's positions never need to be in memory together (5 MP x 21 positions
    of maps is about 3 GB). The file appears under its name only when the ``with`` block
    ends without an exception (:func:`ptpcore.atomic.atomic_path`); positions never
    written keep the fill values (NaN coordinates, reasons 0).

    Parameters
    ----------
    path : path
    positions : (K,) int
    z_mm : (K,) float64
    shape : (H, W)
    reason_bits : dict of str -> int
    rig_toml : str

    Yields
    ------
    DecodedWriter
    """
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = DECODED_FORMAT
        f.attrs["software"] = f"ptpcore {__version__}"
        f.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        f.create_group("rig").attrs["toml"] = rig_toml
        f["positions"] = np.asarray(positions, np.int32)
        f["z_mm"] = np.asarray(z_mm, np.float64)
        (h, w), k = shape, len(positions)
        rows = int(min(h, max(1, _CHUNK_PIXELS // w)))  # a chunk: rows of one position, written whole
        for name, per_dir, fill in (("u", False, np.nan), ("v", False, np.nan), ("modulation", True, 0.0),
                                    ("background", True, 0.0)):
            dims, chunks = ((k, 2, h, w), (1, 1, rows, w)) if per_dir else ((k, h, w), (1, rows, w))
            f.create_dataset(name, dims, np.float32, chunks=chunks, fillvalue=fill, **_OPTS)
        r = f.create_dataset("reasons", (k, 2, h, w), np.uint16, chunks=(1, 1, rows, w), fillvalue=0, **_OPTS)
        for key, bit in reason_bits.items():
            r.attrs[key] = np.uint16(bit)
        yield DecodedWriter(f)


class DecodedWriter:
    """Writes the positions of an open ``ptp-decoded/1`` file (:func:`decoded_writer`)."""

    def __init__(self, f: h5py.File):
        self.file = f

    def write(self, i: int, u, v, modulation, background, reasons) -> None:
        """Position ``i`` (index into the file's ``positions``): ``u, v`` (H, W) px; the others (2, H, W)."""
        f = self.file
        # Compressed on all cores (h5py would deflate the 24 MB of a 5 MP position on one).
        for name, values in (("u", u), ("v", v), ("modulation", modulation), ("background", background),
                             ("reasons", reasons)):
            write_compressed(f[name], i, values)


def load_decoded(path) -> Decoded:
    """Read a ``ptp-decoded/1`` file."""
    with h5py.File(path, "r") as f:
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode()
        if fmt != DECODED_FORMAT:
            raise ValueError(f"{path}: not a {DECODED_FORMAT} file (format {fmt!r})")
        toml = f["rig"].attrs["toml"]
        return Decoded(f["positions"][()], f["z_mm"][()], f["u"][()], f["v"][()], f["modulation"][()],
                       f["background"][()], f["reasons"][()], {k: int(v) for k, v in f["reasons"].attrs.items()},
                       toml.decode() if isinstance(toml, bytes) else str(toml))
