"""The row blocks every step of the smooth fit works in, on the engine's tile pool.

Each step computes on ``[r0, r1)`` row ranges: their temporaries keep one size whatever the image
(12 MP or 0.3 MP), and the blocks run side by side (numpy and OpenCV release the GIL). Every
pixel's numbers come from its own samples (and, for the footprint bias, the global rays of the rows
next to it), whatever the block.
"""

from __future__ import annotations

import numpy as np

from ptpcore.parallel import map_in_order, row_tiles

__all__ = ["BLOCK_PIXELS", "BLOCK_SAMPLES", "row_blocks", "sample_blocks", "run_blocks", "nanmean0"]

BLOCK_PIXELS = 1 << 15
"""Pixels per block of the per-pixel passes (fits, residuals, final evaluation)."""

BLOCK_SAMPLES = 5 * BLOCK_PIXELS
"""Samples (positions x pixels) per block of the passes over the samples: their ``(K, n)``
float64 temporaries keep one size whatever the number of positions K (up to 5 positions,
blocks of :data:`BLOCK_PIXELS` pixels; fewer pixels above)."""


def row_blocks(h: int, w: int) -> list[tuple[int, int]]:
    """Row ranges of about :data:`BLOCK_PIXELS` pixels (one row at least)."""
    return row_tiles(h, w, BLOCK_PIXELS)


def sample_blocks(h: int, w: int, k: int) -> list[tuple[int, int]]:
    """Row ranges of about ``BLOCK_SAMPLES / max(k, 5)`` pixels for ``(K, n)`` sample blocks (one row at least)."""
    return row_tiles(h, w, BLOCK_SAMPLES // max(k, 5))


def run_blocks(fn, blocks) -> None:
    """``fn(r0, r1)`` for every block, on the engine's tile pool (results go to disjoint rows)."""
    for _ in map_in_order(lambda b: fn(*b), blocks):
        pass


def nanmean0(a: np.ndarray) -> np.ndarray:
    """``np.nanmean(a, axis=0)`` (same arithmetic), NaN where all NaN, without warnings (thread-safe)."""
    nan = np.isnan(a)
    cnt = a.shape[0] - nan.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(nan, 0.0, a).sum(axis=0) / cnt
