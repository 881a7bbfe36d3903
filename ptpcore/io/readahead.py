"""The read-ahead: the sets of a position's frames, from any frame source or read ahead from a folder.

A *set* is the N phase-step frames of one period and direction, ``(N, H, W)``; the decoding
(:func:`ptpcore.decode.position.decode_sets`) takes the sets of one position as an iterator of
``((direction, level), stack)``. This module makes those iterators:

- :func:`source_sets` from any :class:`~ptpcore.io.dataset.FrameSource` (frames copied into
  reused buffers as they arrive);
- :class:`DatasetReader` from a dataset folder, on threads of its own, reading the next sets
  while the current one is decoded: plain TIFFs are mapped (:func:`ptpcore.io.fastio.map_frame`,
  with the numba kernels); compressed TIFFs (LZW, deflate) and PNGs are decoded straight into
  the buffers on every core (:func:`ptpcore.io.images.read_into`: imagecodecs, the GIL released);
- :func:`tapped_sets`, the same sets with every frame shown to a listener first (a live preview).
"""

from __future__ import annotations

import queue
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ptpcore.decode.phase import fused_kernels
from ptpcore.parallel import tile_workers
from ptpcore.rig import Rig

__all__ = ["READ_AHEAD_BYTES", "DatasetReader", "source_sets", "tapped_sets", "is_dataset", "check_alignment"]


def _set_order(rig: Rig) -> list[tuple[str, int, int, int]]:
    """``(direction, level, period, N)`` of every set, in capture order."""
    f = rig.fringes
    return [(d, j, t, n) for d in f.directions for j, (t, n) in enumerate(zip(f.periods(d), f.steps_of(d)))]


def _frame_dtype(rig: Rig):
    """The frames' integer type: uint8 up to 8 bits, else uint16."""
    return np.uint8 if rig.camera.bit_depth <= 8 else np.uint16


def source_sets(source, k: int):
    """Yield ``((d, j), stack (N, H, W))`` for every set of position ``k`` of any source.

    Frames are copied into reusable buffers as they arrive (in any order); a
    set is yielded as soon as its N frames are in. A yielded buffer is reused
    once the caller asks for the next set.
    """
    rig: Rig = source.rig
    shape = rig.camera.shape
    free: dict = {}
    pending: dict = {}
    count: dict = {}
    for (d, j, _t, n, big_n), img in source.frames(k):
        img = np.asarray(img)
        key = (d, j)
        buf = pending.get(key)
        if buf is None:
            if img.shape != shape:
                raise ValueError(f"frame ({d}, period level {j}, step {n}) of position {k} has shape"
                                 f" {img.shape}, expected {shape}")
            spare = free.get((big_n, img.dtype))
            buf = spare.pop() if spare else np.empty((big_n, *shape), img.dtype)
            pending[key] = buf
            count[key] = set()
        if n in count[key] or not 0 <= n < big_n:
            raise ValueError(f"step {n} repeated or outside 0..{big_n - 1}")
        buf[n] = img
        count[key].add(n)
        if len(count[key]) == big_n:
            del pending[key]
            yield key, buf
            free.setdefault((big_n, buf.dtype), []).append(buf)
    if pending:
        (d, j), buf = next(iter(pending.items()))
        raise ValueError(f"only {len(count[(d, j)])} of {len(buf)} steps were added")


READ_AHEAD_BYTES = 200 * 2 ** 20
"""The reader's buffers of sets read ahead, at most (but two sets): 3 sets of 8 frames at 5 MP (8 bit),
2 at 12 MP (96 MB each). Two keep a set ready while one is decoded; reading is several times faster
than decoding."""


class DatasetReader:
    """Reads the sets of some positions of a dataset folder ahead, on its own threads.

    Each set's N files are read in parallel: with the numba kernels, plain
    TIFFs are mapped (:func:`ptpcore.io.fastio.map_frame`: no copy, the kernels
    read the page cache); otherwise, or for a file that cannot be mapped, they
    are decoded into a preallocated buffer (grey PNG and TIFF, uncompressed,
    LZW or deflate, with :func:`ptpcore.io.fastio.read_into`: tifffile and
    imagecodecs, the GIL released; anything else with
    :func:`ptpcore.io.dataset.read_image`, which also names a bad file). At most
    ``depth`` sets are buffered or mapped: reading runs ahead of decoding by that much (default: 3
    sets, fewer where their buffers would pass :data:`READ_AHEAD_BYTES`, at least 2).

    Parameters
    ----------
    source : DatasetSource
    positions : sequence of int
        The positions to read, in this order; :meth:`sets_of` is asked for them in the same order.
    depth : int, optional
        Sets buffered or mapped ahead (default above).
    map_files : bool, optional
        Map plain TIFFs (default: when the numba kernels are there).
    """

    def __init__(self, source, positions, depth: int | None = None, map_files: bool | None = None):
        from ptpcore.io.dataset import bit_shift, read_image
        from ptpcore.io.fastio import map_frame, read_into

        self._read_image, self._read_into, self._map_frame = read_image, read_into, map_frame
        self.shift = bit_shift(source.rig)
        self.map_files = fused_kernels() is not None if map_files is None else bool(map_files)
        self.source = source
        self.rig: Rig = source.rig
        self.positions = list(positions)
        self.sets = _set_order(self.rig)
        n_max = max(n for *_, n in self.sets)
        self.free: queue.Queue = queue.Queue()
        self.dtype = np.dtype(np.float32) if getattr(source, "colour", False) else np.dtype(_frame_dtype(self.rig))
        if self.dtype == np.float32:
            self.map_files = False
        set_bytes = n_max * int(np.prod(self.rig.camera.shape)) * self.dtype.itemsize
        if depth is None:
            depth = min(3, max(2, READ_AHEAD_BYTES // set_bytes))
        for _ in range(depth):
            self.free.put(np.empty((n_max, *self.rig.camera.shape), self.dtype))
        self.out: queue.Queue = queue.Queue()
        self.stop = threading.Event()
        self.pool = ThreadPoolExecutor(tile_workers(), thread_name_prefix="ptp-read")
        self.thread = threading.Thread(target=self._run, name="ptp-reader", daemon=True)
        self.thread.start()

    def _read_one(self, args) -> np.ndarray:
        """One frame: mapped from its file, or read into ``out`` (returned)."""
        path, out = args
        if self.map_files and not self.shift:
            mapped = self._map_frame(path, out.shape, out.dtype)
            if mapped is not None:
                return mapped
        if out.dtype != np.float32 and self._read_into(path, out):
            if self.shift and out.dtype == np.uint16:  # [camera] bit_shift: MSB-aligned samples
                np.right_shift(out, self.shift, out=out)
        else:
            img = self._read_image(path, self.rig)  # shifted there
            if img.dtype.kind == "f" and out.dtype.kind != "f":
                img = np.rint(img)  # a colour image among grey ones (DatasetSource.colour looks at position 0)
            out[...] = img
        return out

    def _run(self) -> None:
        try:
            for k in self.positions:
                for d, j, t, n in self.sets:
                    buf = None
                    while buf is None:
                        if self.stop.is_set():
                            return
                        try:
                            buf = self.free.get(timeout=0.1)
                        except queue.Empty:
                            pass
                    paths = [self.source.path(k, d, t, s, n, j) for s in range(n)]
                    frames = list(self.pool.map(self._read_one, zip(paths, buf[:n])))
                    if all(f.base is buf for f in frames):
                        frames = buf[:n]  # all read into the buffer: the stack itself
                    self.out.put((k, (d, j), buf, frames))
                    del frames
        except BaseException as exc:  # handed to the consumer, raised there
            self.out.put(exc)

    def sets_of(self, k: int):
        """Yield ``((d, j), frames)`` for position ``k`` (the next one in order).

        ``frames``: an (N, H, W) stack, or a list of N (H, W) frames when some
        are mapped from their files (valid until the next set is asked for).
        """
        for _ in self.sets:
            item = self.out.get()
            if isinstance(item, BaseException):
                raise item
            kk, key, buf, frames = item
            del item
            assert kk == k, (kk, k)
            try:
                yield key, frames
            finally:
                del frames  # unmaps the mapped files (with the caller's last reference)
                self.free.put(buf)

    def close(self) -> None:
        """Stop the reading thread and its pool (sets read ahead but not asked for are dropped)."""
        self.stop.set()
        while self.thread.is_alive():
            try:  # unblock a reader waiting for a buffer
                item = self.out.get(timeout=0.05)
                if not isinstance(item, BaseException):
                    self.free.put(item[2])
            except queue.Empty:
                pass
        self.pool.shutdown(wait=True)


def check_alignment(source, positions) -> None:
    """Warn when a dataset's 16-bit samples look MSB-aligned (:func:`ptpcore.io.dataset.check_bit_alignment`)."""
    if not is_dataset(source) or not positions:
        return
    from ptpcore.io.dataset import check_bit_alignment

    d, _j, t, n, big_n = next(iter(source.rig.fringes.frames()))
    check_bit_alignment(source.path(positions[0], d, t, n, big_n), source.rig)


def is_dataset(source) -> bool:
    """True when ``source`` is a dataset folder (:class:`~ptpcore.io.dataset.DatasetSource`): its
    sets are then read ahead by a :class:`DatasetReader`."""
    from ptpcore.io.dataset import DatasetSource

    return type(source) is DatasetSource


def tapped_sets(sets, rig: Rig, k: int, on_frame):
    """The sets of position ``k`` unchanged, each frame shown to ``on_frame`` first."""
    f = rig.fringes
    for (d, j), stack in sets:
        period = f.periods(d)[j]
        for n in range(len(stack)):
            on_frame(k, (d, j, period, n, len(stack)), stack[n])
        yield (d, j), stack
