"""Fast paths for big sensors: direct image reads.

Two things that decide whether a 5-12 megapixel calibration is limited by
reading its images:

- :func:`read_into` (from :mod:`ptpcore.io.images`): a grey PNG or TIFF
  (uncompressed, LZW or deflate) decoded by tifffile/imagecodecs straight into
  a caller's preallocated array, on any thread. Any other file (colour, odd
  layouts, wrong size or depth, damaged) is declined, and the caller reads it
  with the full reader, which also gives the proper error message.
- :func:`map_frame`: an uncompressed grey TIFF mapped instead of read: the
  pixels are used where they lie in the operating system's page cache, with
  no copy at all (where they lie: :func:`ptpcore.io.images.tiff_layout`).

The per-position sample arrays on disk (``SpillStore``, ``read_block``) are in :mod:`ptpcore.store`.
"""

from __future__ import annotations

import mmap
import os
import struct

import numpy as np

from ptpcore.io.images import read_into, tiff_layout

__all__ = ["read_into", "map_frame", "tiff_layout"]


def map_frame(path, shape, dtype) -> np.ndarray | None:
    """A plain uncompressed TIFF's pixels, mapped read-only from the file; None if declined.

    Parameters
    ----------
    path : path
    shape : (H, W)
    dtype : uint8 or uint16

    Returns
    -------
    (H, W) array of ``dtype`` (read-only) or None
        The pixels where they lie in the file (the map is released with the
        last reference to the array). None unless the file is in the layout
        :func:`tiff_layout` accepts, of exactly this size and depth, with its
        pixels in one contiguous run at an offset aligned to the pixel size
        and, for 16 bits, in the machine's byte order: then read it with
        :func:`read_into` or the full reader.

    Notes
    -----
    The map is populated at once (``MAP_POPULATE`` where the system has it),
    so the cost of mapping falls on the calling thread (the pipeline's reader)
    rather than on the first pass over the pixels. A file cut short while
    mapped makes the process fail on access (``SIGBUS``): map only files that
    are complete and not rewritten in place (capture writes images atomically,
    by renaming).
    """
    dtype = np.dtype(dtype)
    if dtype not in (np.uint8, np.uint16) or len(shape) != 2:
        return None
    try:
        with open(path, "rb", buffering=0) as fh:
            fd = fh.fileno()
            size = os.fstat(fd).st_size
            layout = tiff_layout(lambda offset, n: os.pread(fd, n, offset), size)  # by hand: images.py says why
            if layout is None:
                return None
            w, h, bits, bo, runs = layout
            if ((h, w) != tuple(shape) or bits != 8 * dtype.itemsize or len(runs) != 1
                    or runs[0][0] % dtype.itemsize or (bits == 16 and (bo == "<") != np.little_endian)):
                return None
            if hasattr(mmap, "MAP_SHARED"):
                flags = mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0)
                mm = mmap.mmap(fd, size, flags=flags, prot=mmap.PROT_READ)
            else:  # pragma: no cover - Windows
                mm = mmap.mmap(fd, size, access=mmap.ACCESS_READ)
    except (OSError, ValueError, struct.error):
        return None
    return np.frombuffer(mm, dtype, count=h * w, offset=runs[0][0]).reshape(h, w)
