"""Giving memory back to the operating system between the stages of a run.

:func:`release_free_memory` first calls every function registered with :func:`on_release`
(:mod:`ptpcore.store.positions` drops the spilled stacks' mapped pages), then trims the C heap.
"""

from __future__ import annotations

__all__ = ["release_free_memory", "on_release"]

_LIBC = None
_RELEASERS: list = []


def on_release(fn) -> None:
    """Have :func:`release_free_memory` call ``fn()`` too (e.g. to drop mapped file pages)."""
    if fn not in _RELEASERS:
        _RELEASERS.append(fn)


def release_free_memory() -> None:
    """Give the C allocator's free pages back to the operating system (glibc's ``malloc_trim``).

    Between the positions of a decode, numpy's and OpenCV's transient arrays of a few
    to tens of MB (from several threads) leave free but resident holes in glibc's heaps:
    at 2 MP x 6 positions the resident size grew by about 70 MB a position with nothing
    held (``tracemalloc`` saw 4 MB). ``malloc_trim(0)`` hands those pages back (a few
    milliseconds). Elsewhere than glibc (macOS, Windows, musl) it does nothing; no
    library offers this, hence ctypes. Functions registered with :func:`on_release` run first
    (:mod:`ptpcore.store.positions` drops the spilled samples' mapped pages).
    """
    global _LIBC
    for release in _RELEASERS:
        release()
    if _LIBC is None:
        try:
            import ctypes

            lib = ctypes.CDLL("libc.so.6")
            _LIBC = lib.malloc_trim if hasattr(lib, "malloc_trim") else False
        except (OSError, AttributeError):
            _LIBC = False
    if _LIBC:
        _LIBC(0)
