"""Per-position arrays ``(K, H, W)`` on disk: the decoder's sample stack, the comparison's blocks,
the model choice's held-out predictions and the leave-one-out's noise estimates.

:class:`SpillStore` writes one temporary file (in ``PTP_SPILL_DIR``; on POSIX unlinked at creation,
so that nothing is left even by SIGKILL; its blocks reserved up front with ``posix_fallocate`` so a
full disk is one clear error),
a position's rows at a time from several threads; :func:`read_block` reads pixel ranges back with
file reads, and :meth:`SpillStore.arrays` exposes the fields as ``numpy.memmap`` for everything
else. :class:`MemoryPositions` is the same interface in memory (:func:`position_store` picks).
"""

from __future__ import annotations

import contextlib
import errno
import mmap
import os
import tempfile
import threading
import weakref
from pathlib import Path

import numpy as np

from ptpcore.atomic import (disk_full_error, forget_temporary, is_disk_full, owner_tag, register_temporary,
                            sweep_orphans)
from ptpcore.store.release import on_release

__all__ = ["SpillStore", "MemoryPositions", "position_store", "read_block", "release_mapped_pages",
           "remove_orphaned_spill_files"]

_PREADV = hasattr(os, "preadv")
_PWRITE = hasattr(os, "pwrite")


def _reserve(fh, nbytes: int) -> None:
    """Give the file ``nbytes`` of real disk blocks now (not a sparse file).

    A sparse file on a disk that fills is written through a memory map, and the
    first page that finds no block kills the process (SIGBUS); reserved up
    front, a full disk is an ``OSError(ENOSPC)`` before any work.
    """
    if nbytes <= 0:
        return
    if hasattr(os, "posix_fallocate"):
        try:
            os.posix_fallocate(fh.fileno(), 0, nbytes)
            return
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
                raise
    fh.truncate(nbytes)  # pragma: no cover - no fallocate (Windows allocates on truncate)


_UNLINK_OPEN_FILES = os.name == "posix"


def _spill_file(directory) -> tuple:
    """``(file, path, named)``: a new temporary file of the spill folder, opened unbuffered.

    On POSIX its name is removed at once (``named`` False): the open file is all the store needs,
    so a process killed with SIGKILL leaves nothing behind. Elsewhere (Windows cannot remove an
    open file) the name carries the owner's process id and start time, and files of owners that
    are gone are removed first (:func:`ptpcore.atomic.sweep_orphans`).
    """
    folder = directory or tempfile.gettempdir()
    if not _UNLINK_OPEN_FILES:  # pragma: no cover - Windows
        sweep_orphans(folder, "ptp-samples-", ".tmp")
    fd, name = tempfile.mkstemp(prefix=f"ptp-samples-{owner_tag()}-", suffix=".tmp", dir=directory)
    if _UNLINK_OPEN_FILES:
        os.unlink(name)
    return os.fdopen(fd, "r+b", buffering=0), Path(name), not _UNLINK_OPEN_FILES


def remove_orphaned_spill_files(directory=None) -> list[Path]:
    """Remove the spill files that killed runs of this user left in the spill folder (``directory``,
    else ``PTP_SPILL_DIR``, else the system's temporary folder); return them. Only where spill files
    have names (not POSIX, where they are unlinked at creation); called when a program starts."""
    if _UNLINK_OPEN_FILES and directory is None:  # POSIX: no spill file ever has a name to leave
        return []
    folder = directory or os.environ.get("PTP_SPILL_DIR") or tempfile.gettempdir()
    return sweep_orphans(folder, "ptp-samples-", ".tmp")


class SpillStore:
    """``(K, H, W)`` arrays in one temporary file, written a position at a time.

    Parameters
    ----------
    k : int
        Positions.
    shape : (H, W)
    fields : dict of str -> dtype
        E.g. ``{"x": float32, "y": float32, "reasons": uint8}``.
    fill : dict of str -> scalar
        Value of positions never written (e.g. NaN, 0xFF).
    directory : path, optional
        Where the file goes (default: the system's temporary folder, or
        ``PTP_SPILL_DIR``). On POSIX the file has no name from the start (``path``
        is the name it was created under, for messages); elsewhere it is removed
        when the store and every array from :meth:`arrays` are gone (at the
        latest when Python exits).
    """

    def __init__(self, k: int, shape, fields: dict, fill: dict, directory=None):
        self.k = int(k)
        self.shape = tuple(int(s) for s in shape)
        self.pixels = int(np.prod(self.shape))
        directory = directory or os.environ.get("PTP_SPILL_DIR") or None
        self._fh, self.path, named = _spill_file(directory)
        self._lock = threading.Lock()
        self.layout: dict[str, tuple[np.dtype, int]] = {}
        offset = 0
        for name_, dt in fields.items():
            dt = np.dtype(dt)
            self.layout[name_] = (dt, offset)
            offset += self.k * self.pixels * dt.itemsize
        self.nbytes = offset
        self._written = set()
        self._fill = dict(fill)
        self._finalizer = weakref.finalize(self, SpillStore._remove, self._fh, self.path if named else None)
        if named:
            register_temporary(self.path)
        try:
            _reserve(self._fh, offset)
        except OSError as exc:
            self._finalizer()
            if is_disk_full(exc):
                raise disk_full_error(self.path, offset, hint="the decoded samples' spill file; set"
                                      " PTP_SPILL_DIR to a folder with more space") from None
            raise

    @staticmethod
    def _remove(fh, path: Path | None) -> None:
        try:
            fh.close()
        finally:
            if path is None:  # unlinked at creation: closing freed it
                return
            forget_temporary(path)
            try:
                path.unlink()
            except OSError:  # pragma: no cover - still mapped (Windows): the OS temp cleaner takes it
                pass

    def _offset(self, name: str, k: int, start: int = 0) -> int:
        dt, base = self.layout[name]
        return base + (k * self.pixels + start) * dt.itemsize

    def write(self, name: str, k: int, array: np.ndarray) -> None:
        """Store position ``k`` of field ``name`` (an ``(H, W)`` array of its dtype)."""
        if np.shape(array) != self.shape:
            raise ValueError(f"{name}[{k}] has shape {np.shape(array)}, expected {self.shape}")
        self.write_rows(name, k, 0, array)
        self.mark_written(name, k)

    def write_rows(self, name: str, k: int, row0: int, rows: np.ndarray) -> None:
        """Store rows ``[row0, row0 + len(rows))`` of position ``k`` of field ``name``.

        A positional write (no shared file position), so the row tiles of a
        position write their rows from several threads at once, each while its
        rows are still in the cache (a third less CPU than writing the whole
        maps afterwards). Call :meth:`mark_written` once every row is in.
        """
        dt, _ = self.layout[name]
        a = np.ascontiguousarray(rows, dtype=dt)
        h, w = self.shape
        if a.ndim != 2 or a.shape[1] != w or not 0 <= row0 <= h - a.shape[0]:
            raise ValueError(f"{name}[{k}]: rows {row0}..{row0 + len(a)} of shape {a.shape} do not fit {self.shape}")
        data = memoryview(a.reshape(-1).view(np.uint8))
        offset = self._offset(name, k, row0 * w)
        done = 0
        while done < len(data):
            if _PWRITE:
                n = os.pwrite(self._fh.fileno(), data[done:], offset + done)
            else:  # pragma: no cover - Windows
                with self._lock:
                    self._fh.seek(offset + done)
                    n = self._fh.write(data[done:])
            if not n:
                raise OSError(f"{self.path}: nothing written")
            done += n

    def mark_written(self, name: str, k: int) -> None:
        """Position ``k`` of field ``name`` is complete (:meth:`write_rows` of every row)."""
        self._written.add((name, k))

    def finish(self) -> None:
        """Fill every position never written with its field's fill value."""
        for name, (dt, _) in self.layout.items():
            blank = None
            for k in range(self.k):
                if (name, k) not in self._written:
                    if blank is None:
                        blank = np.full(self.shape, self._fill.get(name, 0), dt)
                    self.write(name, k, blank)

    def read(self, name: str, start: int, stop: int, positions=None) -> np.ndarray:
        """Pixels ``[start, stop)`` (flat index) of every position: ``(K', stop - start)``.

        Read with plain file reads (never through the memory map), so fitting
        a big stack block by block keeps the process small.
        """
        dt, _ = self.layout[name]
        ks = range(self.k) if positions is None else [int(p) for p in positions]
        out = np.empty((len(ks), stop - start), dt)
        raw = out.view(np.uint8)
        for i, k in enumerate(ks):
            view = memoryview(raw[i])
            offset = self._offset(name, k, start)
            got = 0
            while got < len(view):
                if _PREADV:  # positional: the fit's threads read side by side, no lock
                    n = os.preadv(self._fh.fileno(), [view[got:]], offset + got)
                else:  # pragma: no cover - no preadv (Windows, macOS < 11)
                    with self._lock:
                        self._fh.seek(offset + got)
                        n = self._fh.readinto(view[got:])
                if not n:
                    raise OSError(f"{self.path}: spill file cut short")
                got += n
        return out

    def arrays(self) -> dict[str, np.ndarray]:
        """Every field as a writable ``(K, H, W)`` ``numpy.memmap`` of the file."""
        out = {}
        for name, (dt, base) in self.layout.items():
            mm = np.memmap(self._fh, dtype=dt, mode="r+", offset=base, shape=(self.k, *self.shape))
            mm._ptp_store = self  # the store (and so its file) lives as long as any of its maps
            _SPILLED[id(mm)] = (weakref.ref(mm), self, name)
            weakref.finalize(mm, _SPILLED.pop, id(mm), None)
            out[name] = mm
        return out


_SPILLED: dict[int, tuple] = {}


def read_block(array: np.ndarray, start: int, stop: int, positions=None) -> np.ndarray:
    """Pixels ``[start, stop)`` (flat) of every position of a ``(K, H, W)`` array: ``(K', n)``.

    An array from :meth:`SpillStore.arrays` is read with file reads (its pages
    are not mapped into the process); anything else is sliced (a view where
    possible).
    """
    entry = _SPILLED.get(id(array))
    if entry is not None and entry[0]() is array:
        return entry[1].read(entry[2], start, stop, positions)
    flat = array.reshape(array.shape[0], -1)
    return flat[:, start:stop] if positions is None else flat[np.asarray(positions), start:stop]


def release_mapped_pages() -> None:
    """Drop the pages of every spilled stack's memory maps from this process.

    Indexing a :meth:`SpillStore.arrays` map (``samples.x[k]``, a strided subsample) maps
    the pages it touches into the process, where they stay and count in its resident
    memory until the map is gone: at 5 MP x 21 positions the sanity checks alone left
    950 MB of them. ``MADV_DONTNEED`` on a shared file mapping only unmaps them: the data
    stays in the file and the page cache, and the next access maps it again.
    """
    if not hasattr(mmap, "MADV_DONTNEED"):  # pragma: no cover - not Linux/BSD
        return
    for ref, _store, _name in list(_SPILLED.values()):
        mm = ref()
        raw = getattr(mm, "_mmap", None) if mm is not None else None
        if raw is not None:
            with contextlib.suppress(ValueError, OSError):  # closed meanwhile
                # In ranges: madvise holds the GIL, about 25 ms per GB of resident pages (a thread
                # ticking every 0.5 ms waited 11.5 ms for 13 ms of it), so the GUI thread gets a
                # turn between them.
                for start in range(0, len(raw), _MADVISE_BYTES):
                    raw.madvise(mmap.MADV_DONTNEED, start, min(_MADVISE_BYTES, len(raw) - start))


_MADVISE_BYTES = 1 << 26
"""Bytes of a spilled map released per ``madvise`` call (64 MiB: a few ms each)."""


on_release(release_mapped_pages)


class MemoryPositions:
    """:class:`SpillStore`'s :meth:`~SpillStore.write_rows` and :meth:`~SpillStore.read` on arrays in
    memory: ``(K, H * W)`` per field, every position at its fill value until written."""

    def __init__(self, k: int, shape, fields: dict, fill: dict):
        self.k = int(k)
        self.shape = tuple(int(s) for s in shape)
        n = int(np.prod(self.shape))
        self._arrays = {name: np.full((self.k, n), fill.get(name, 0), np.dtype(dt)) for name, dt in fields.items()}

    def write_rows(self, name: str, k: int, row0: int, rows: np.ndarray) -> None:
        """Store rows ``[row0, row0 + len(rows))`` of position ``k`` of field ``name``."""
        w = self.shape[1]
        self._arrays[name][k, row0 * w:(row0 + len(rows)) * w] = rows.reshape(-1)

    def read(self, name: str, start: int, stop: int, positions=None) -> np.ndarray:
        """Pixels ``[start, stop)`` (flat index) of every position (or ``positions``): ``(K', stop - start)``."""
        a = self._arrays[name]
        return a[:, start:stop] if positions is None else a[[int(p) for p in positions], start:stop]


def position_store(k: int, shape, fields: dict, fill: dict, on_disk: bool) -> "SpillStore | MemoryPositions":
    """Per-position arrays written by rows and read by pixel ranges: a :class:`SpillStore` file
    ``on_disk``, else :class:`MemoryPositions`."""
    if on_disk:
        return SpillStore(k, shape, fields, fill)
    return MemoryPositions(k, shape, fields, fill)
