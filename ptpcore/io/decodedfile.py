"""``ptp-decoded/1``: the decoded LCD coordinates of some positions (FORMATS.md).

Arrays ``[K, H, W]`` (``[K, 2, H, W]`` per direction x, y) for K positions in
``rig.toml`` order; NaN where invalid or the direction is absent.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import threading
from dataclasses import dataclass
from typing import Iterator

import h5py
import numpy as np

from ptpcore import __version__
from ptpcore.atomic import atomic_path
from ptpcore.io.h5chunks import GZIP_LEVEL, write_compressed

__all__ = ["DECODED_FORMAT", "COMPRESSIONS", "Decoded", "DecodedWriter", "BackgroundWriter", "decoded_writer",
           "save_decoded", "load_decoded"]

DECODED_FORMAT = "ptp-decoded/1"

COMPRESSIONS = {"gzip": dict(compression="gzip", compression_opts=GZIP_LEVEL, shuffle=True), "none": {}}
"""The ``ptp-decoded/1`` file's HDF5 filters by name: ``gzip`` (HDF5's shuffle + deflate at level
:data:`ptpcore.io.h5chunks.GZIP_LEVEL`), ``none`` (no filter). Both are built into every HDF5 reader."""

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
def decoded_writer(path, positions, z_mm, shape, reason_bits: dict, rig_toml: str,
                   compression: str = "none") -> Iterator["DecodedWriter"]:
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
    compression : str
        A key of :data:`COMPRESSIONS`.

    Yields
    ------
    DecodedWriter
    """
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
    opts = COMPRESSIONS[compression]
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
            f.create_dataset(name, dims, np.float32, chunks=chunks, fillvalue=fill, **opts)
        r = f.create_dataset("reasons", (k, 2, h, w), np.uint16, chunks=(1, 1, rows, w), fillvalue=0, **opts)
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


class BackgroundWriter:
    """A sink's ``write(i, *maps)`` on a thread of its own, so that the next position decodes meanwhile.

    At most one position is in flight: :meth:`write` hands the maps over and returns at once, after
    waiting for the previous position's write to end (one position's maps beside the decoder's, 140 MB
    at 5 MP). The maps must not change after they are handed over. An error of the writing thread is
    raised by the next :meth:`write` or by :meth:`close`, which waits for the last write.

    Parameters
    ----------
    sink : object with ``write(i, u, v, modulation, background, reasons)``
    """

    def __init__(self, sink):
        self.sink = sink
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def _run(self, args) -> None:
        try:
            self.sink.write(*args)
        except BaseException as exc:  # noqa: BLE001 - handed to the decoding thread
            self._error = exc

    def _wait(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._error is not None:
            error, self._error = self._error, None
            raise error

    def write(self, i: int, u, v, modulation, background, reasons) -> None:
        """Write position ``i`` in the background (see :meth:`DecodedWriter.write`)."""
        self._wait()
        self._thread = threading.Thread(target=self._run, args=((i, u, v, modulation, background, reasons),),
                                        name="ptp-decoded-writer", daemon=True)
        self._thread.start()

    def close(self, quiet: bool = False) -> None:
        """Wait for the last write; raise its error if it failed (not when ``quiet``: another error is
        on its way and the file will not be kept)."""
        try:
            self._wait()
        except BaseException:
            if not quiet:
                raise


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
