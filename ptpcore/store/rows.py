"""Image-shaped float64 arrays ``(*lead, H, W)`` read and written by row ranges, in memory or on disk.

The smooth fit keeps several maps per pixel (its pixel fits, the global model's rays, the
leave-one-out's sums, the smoothing weights); at 5-12 MP they do not all fit in memory beside each
other, so above :data:`SPILL_PIXELS` pixels each waits in a temporary file. Both kinds answer the
same few methods, so the estimator never asks where its maps are:

- ``store[i, ..., r0:r1] = values`` writes rows (leading indices ints or ``:``, then a row slice);
- :meth:`rows` ``(index, r0, r1)`` reads rows of one plane, :meth:`row_block` ``(r0, r1)`` rows of
  every plane, :meth:`plane` ``(index)`` one whole plane, :meth:`plane_rows` ``(index)`` one plane
  as a map read by row slices (:class:`PlaneRows`);
- :meth:`add_rows` ``(index, r0, values)`` adds to rows (the same bits as ``+=``);
- :meth:`load` (or :func:`load`) brings the whole array into memory (and closes a file); :func:`park`
  sends an array to a file until then.

In memory (:class:`MemoryRows`) the reads are views; from a file (:class:`FileRows`) they are
copies read with plain file reads (no memory map), so the file's pages stay out of the process.
"""

from __future__ import annotations

import itertools
import os
import tempfile
import threading
import weakref

import numpy as np

__all__ = ["SPILL_PIXELS", "FileRows", "MemoryRows", "PlaneRows", "row_store", "park", "load", "spills"]

SPILL_PIXELS = 320_000
"""Above this many pixels (a plane's ``H * W``) :func:`row_store` and :func:`park` put the array in a
temporary file (at 5 MP and degree 3: 560 MB of the smooth fit's float64 maps not held beside the
folds' statistics)."""


def spills(shape) -> bool:
    """Whether an array of this shape goes to a file (planes over :data:`SPILL_PIXELS` pixels)."""
    return shape[-2] * shape[-1] > SPILL_PIXELS


def row_store(shape, zeros: bool = False) -> "FileRows | MemoryRows":
    """A float64 ``shape`` array for row-range access: in a file above :data:`SPILL_PIXELS` pixels.

    ``zeros``: start as zeros (a file always does); else uninitialised in memory.
    """
    if spills(shape):
        return FileRows(shape)
    return (np.zeros(shape) if zeros else np.empty(shape)).view(MemoryRows)


def park(array: np.ndarray) -> "FileRows | MemoryRows":
    """``array`` (float64 ``(*lead, H, W)``) as a row store until :meth:`load`: a file copy above
    :data:`SPILL_PIXELS` pixels, else the array itself."""
    if isinstance(array, (FileRows, MemoryRows)):
        return array
    return FileRows.park(array) if spills(array.shape) else array.view(MemoryRows)


class MemoryRows(np.ndarray):
    """A float64 ndarray with the row-store methods (reads are views of it)."""

    def rows(self, index: int, r0: int, r1: int) -> np.ndarray:
        """Rows ``[r0, r1)`` of one plane (flat index over the leading axes): ``(r1 - r0, W)``, a view."""
        return self._planes()[int(index), r0:r1]

    def row_block(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``[r0, r1)`` of every plane: ``(*lead, r1 - r0, W)``, a view."""
        return self.view(np.ndarray)[..., r0:r1, :]

    def plane(self, index: int) -> np.ndarray:
        """One ``(H, W)`` plane (flat index over the leading axes), a view."""
        return self._planes()[int(index)]

    def plane_rows(self, index: int) -> np.ndarray:
        """One plane as an ``(H, W)`` map read by row slices: here the plane itself."""
        return self.plane(index)

    def add_rows(self, index: int, r0: int, values: np.ndarray) -> None:
        """Add ``values`` ``(r1 - r0, W)`` to rows ``[r0, r0 + len(values))`` of one plane, in place."""
        self._planes()[int(index), r0:r0 + len(values)] += values

    def load(self) -> np.ndarray:
        """The array itself (a plain ndarray view)."""
        return self.view(np.ndarray)

    def _planes(self) -> np.ndarray:
        return self.view(np.ndarray).reshape(-1, *self.shape[-2:])


class FileRows:
    """A float64 ``(*lead, H, W)`` array in a temporary file, written by row ranges.

    Plain file reads and writes (no memory map; one at a time, under a lock), so its pages stay out of the
    process's resident memory; writes of disjoint rows may come from several threads.
    The file is in ``PTP_SPILL_DIR`` (default the system's temporary folder) and
    disappears when closed.
    """

    def __init__(self, shape):
        self.shape = tuple(int(n) for n in shape)
        self._row_bytes = self.shape[-1] * 8
        self._plane = self.shape[-2] * self._row_bytes
        self._file = tempfile.TemporaryFile(prefix="ptp-fits-", dir=os.environ.get("PTP_SPILL_DIR") or None)
        self._file.truncate(int(np.prod(self.shape)) * 8)
        self._lock = threading.Lock()
        # A spill dropped unread closes its file when collected, without a ResourceWarning
        # ("unclosed file" at the end of `ptp calibrate`, when the refits' own_var, own_diag were spilled).
        self.close = weakref.finalize(self, self._file.close)

    def __setitem__(self, key, values) -> None:
        """``spill[i, ..., r0:r1] = values``: leading indices (int or ``:``), then a row slice."""
        key = key if isinstance(key, tuple) else (key,)
        lead, rows = key[:-1], key[-1]
        nlead = len(self.shape) - 2
        lead = lead + (slice(None),) * (nlead - len(lead))
        r0, r1, _ = rows.indices(self.shape[-2])
        ranges = [[k] if isinstance(k, (int, np.integer)) else range(*k.indices(n)) for k, n in zip(lead, self.shape)]
        sel_shape = tuple(len(r) for k, r in zip(lead, ranges) if not isinstance(k, (int, np.integer)))
        vals = np.broadcast_to(np.asarray(values, dtype=np.float64), sel_shape + (r1 - r0, self.shape[-1]))
        vals = vals.reshape(-1, r1 - r0, self.shape[-1])
        for i, idx in enumerate(itertools.product(*ranges)):
            plane = int(np.ravel_multi_index(idx, self.shape[:-2])) if idx else 0
            data = np.ascontiguousarray(vals[i])
            with self._lock:
                self._file.seek(plane * self._plane + r0 * self._row_bytes)
                self._file.write(data.data.cast("B"))

    def plane(self, index: int) -> np.ndarray:
        """One ``(H, W)`` plane (flat index over the leading axes), read into memory."""
        return self._read(int(index) * self._plane, np.empty(self.shape[-2:]))

    def rows(self, index: int, r0: int, r1: int) -> np.ndarray:
        """Rows ``[r0, r1)`` of one plane (flat index over the leading axes): ``(r1 - r0, W)``, read into memory."""
        return self._read(int(index) * self._plane + int(r0) * self._row_bytes, np.empty((r1 - r0, self.shape[-1])))

    def row_block(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``[r0, r1)`` of every plane: ``(*lead, r1 - r0, W)``, read into memory."""
        n = int(np.prod(self.shape[:-2]))
        out = np.stack([self.rows(i, r0, r1) for i in range(n)]) if n else np.empty((0, r1 - r0, self.shape[-1]))
        return out.reshape(*self.shape[:-2], r1 - r0, self.shape[-1])

    def plane_rows(self, index: int) -> "PlaneRows":
        """One plane as a read-only ``(H, W)`` map whose row slices are read from the file."""
        return PlaneRows(self, int(index))

    def add_rows(self, index: int, r0: int, values: np.ndarray) -> None:
        """Add ``values`` to rows ``[r0, r0 + len(values))`` of one plane: ``old + new`` read back from the
        file gives the very bits the in-memory ``+=`` gives (blocks of disjoint rows may come from
        several threads)."""
        index, r1 = int(index), r0 + len(values)
        lead = np.unravel_index(index, self.shape[:-2]) if len(self.shape) > 2 else ()
        self[tuple(int(i) for i in lead) + (slice(r0, r1),)] = self.rows(index, r0, r1) + values

    def _read(self, offset: int, out: np.ndarray) -> np.ndarray:
        buf, done = out.data.cast("B"), 0
        with self._lock:
            self._file.seek(offset)
            while done < len(buf):
                n = self._file.readinto(buf[done:])
                if not n:
                    raise OSError("the pixel fits' temporary file ended early")
                done += n
        return out

    @classmethod
    def park(cls, array: np.ndarray) -> "FileRows":
        """A copy of a float64 ``(*lead, H, W)`` array in a new spill (:meth:`load` brings it back)."""
        spill = cls(array.shape)
        spill[(slice(None),) * (array.ndim - 2) + (slice(0, array.shape[-2]),)] = array
        return spill

    def load(self) -> np.ndarray:
        """The whole array, read into memory; the file is closed."""
        out = self._read(0, np.empty(self.shape))
        self.close()
        return out


class PlaneRows:
    """A :class:`FileRows` plane where an ``(H, W)`` map is read by rows: ``shape``, ``plane[r0:r1]``
    (a file read) and ``np.asarray(plane)`` (the whole plane). The smoothing's binning reads its
    weights so, band by band: the leak variance's two weight maps (190 MB at 12 MP) stay in their file."""

    def __init__(self, spill: FileRows, index: int):
        self.spill, self.index = spill, index
        self.shape = spill.shape[-2:]

    def __getitem__(self, rows: slice) -> np.ndarray:
        r0, r1, step = rows.indices(self.shape[0])
        if step != 1:
            raise IndexError("a spilled plane is read by row ranges only")
        return self.spill.rows(self.index, r0, max(r0, r1))

    def __array__(self, dtype=None, copy=None):
        a = self.spill.plane(self.index)
        return a if dtype is None else a.astype(dtype, copy=False)


def load(array) -> np.ndarray:
    """A row store's whole array in memory (:meth:`FileRows.load`, :meth:`MemoryRows.load`); an array as it is."""
    return array.load() if isinstance(array, (FileRows, MemoryRows)) else array
