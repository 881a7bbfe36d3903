"""The row-tile thread pool every stage of the engine shares.

Images are processed in row tiles (``[r0, r1)`` ranges of about ``tile_pixels``
pixels) so that each tile's working set stays in cache; the tiles run on one
process-wide thread pool (numpy, OpenCV and the numba kernels release the GIL).
``PTP_THREADS`` caps the number of threads. This module imports nothing of
ptpcore, so every layer may use it. Giving memory back to the system is :mod:`ptpcore.store`'s.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

__all__ = ["TILE_PIXELS", "KERNEL_TILE_PIXELS", "tile_workers", "row_tiles", "run_tiles", "map_in_order", "worker_pool"]


TILE_PIXELS = 1 << 15
"""Pixels per row tile: N uint8 frames of a tile plus its float32 sums fit in L2."""

KERNEL_TILE_PIXELS = 1 << 18
"""Pixels per row tile of the numba kernels (:func:`fused_kernels`): they make one pass
over their pixels, so they need no cache-sized tiles, and bigger tiles mean fewer
dispatches, each of which holds the GIL (at 5 MP, 20 tiles instead of 157 per map)."""

_pool_lock = threading.Lock()
_pool_obj: ThreadPoolExecutor | None = None
_in_worker = threading.local()


def _worker_init() -> None:
    _in_worker.flag = True


def tile_workers() -> int:
    """Threads used for row tiles: every core (``PTP_THREADS`` overrides)."""
    env = os.environ.get("PTP_THREADS", "")
    return max(1, int(env)) if env.isdigit() else max(1, os.cpu_count() or 1)


def worker_pool() -> ThreadPoolExecutor:
    """The shared tile pool (created on first use, ``tile_workers()`` threads)."""
    global _pool_obj
    with _pool_lock:
        if _pool_obj is None:
            _pool_obj = ThreadPoolExecutor(tile_workers(), thread_name_prefix="ptp-tiles",
                                           initializer=_worker_init)
        return _pool_obj


def row_tiles(h: int, w: int, tile_pixels: int = TILE_PIXELS) -> list[tuple[int, int]]:
    """Row ranges ``[r0, r1)`` of about ``tile_pixels`` pixels each, covering ``h`` rows."""
    rows = max(1, tile_pixels // max(int(w), 1))
    return [(r, min(h, r + rows)) for r in range(0, h, rows)]


def run_tiles(fn, h: int, w: int, tile_pixels: int = TILE_PIXELS) -> None:
    """Call ``fn(r0, r1)`` for every row tile, in parallel on the tile pool.

    Exceptions propagate. Called from inside a tile (nested), it runs serially
    so the pool cannot deadlock on itself.
    """
    for _ in map_in_order(lambda t: fn(*t), row_tiles(h, w, tile_pixels)):
        pass


def map_in_order(fn, items):
    """``fn(item)`` for every item on the tile pool; an iterator of the results, in order.

    Serial when there is one item or one thread, and when called from inside a tile
    (nested), so the pool cannot deadlock on itself. Exceptions propagate.
    """
    items = list(items)
    if len(items) <= 1 or tile_workers() == 1 or getattr(_in_worker, "flag", False):
        return map(fn, items)
    return worker_pool().map(fn, items)
