"""Grey PNG and TIFF frames decoded straight into a caller's buffer, on any thread.

The dataset reader keeps a few ``(N, H, W)`` stacks and fills them frame by
frame from a thread pool; this module decodes one file into one ``(H, W)``
slice of such a stack with the libraries' own C code, which releases the GIL,
so the pool decodes on every core:

- TIFF: the header and the pixels' place in the file come from ``tifffile``;
  an uncompressed image is read with one ``readinto`` (tifffile's
  ``asarray(out=...)``) or mapped (:func:`tiff_pixels_run`), a compressed one
  (LZW, deflate, with or without predictor) is decoded by libtiff through
  ``imagecodecs.tiff_decode(..., out=...)`` from the file's bytes, read into a
  buffer each thread reuses;
- PNG: ``imagecodecs.png_decode(..., out=...)`` after the chunk structure and
  checksum check of :func:`png_check_bytes` (the same test as before: a file
  libpng would complain about is declined and named by the full reader).

Anything else (colour, another depth or size, odd TIFF layouts, JPEG, BMP, a
damaged file) is declined, and the caller reads it with
:func:`ptpcore.io.dataset.read_image`, which also gives the proper message.
``docs/performance.md`` ("Reading the images: tifffile and imagecodecs") has
the measurements behind each choice.
"""

from __future__ import annotations

import logging
import os
import struct
import threading
import zlib

import imagecodecs
import numpy as np
import tifffile

__all__ = ["read_into", "tiff_pixels_run", "png_check_bytes", "PNG_SIGNATURE", "TIFF_SIGNATURES", "BadImage"]

# tifffile reports what it finds odd in a damaged file through `logging`; our own
# message names the file and says what is wrong (as for OpenCV's console chatter).
_TIFF_LOG = logging.getLogger("tifffile")
_TIFF_LOG.addHandler(logging.NullHandler())
_TIFF_LOG.propagate = False

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_TIFF_CODECS = {1, 5, 8, 32946}  # none, LZW, deflate (Adobe), deflate (old code): what libtiff decodes here
_scratch = threading.local()


class BadImage(Exception):
    """One image's problem: ``kind`` (a short category) and ``detail`` (for the message)."""

    def __init__(self, kind: str, detail: str):
        super().__init__(detail)
        self.kind = kind
        self.detail = detail


def _chunk_name(ctype: bytes) -> str:
    return ctype.decode("latin-1") if ctype.isalpha() else "?"


def png_check_bytes(buf) -> None:
    """Structure and CRC of every chunk of a PNG already in memory (about 1 ms per 10 MB).

    Hand-written because no library checks a PNG without decoding it: libpng
    (through OpenCV or imagecodecs) stops at the first bad chunk with its own
    wording, and skips the checksums of ancillary chunks.

    Parameters
    ----------
    buf : bytes-like
        The whole file, signature included.

    Raises
    ------
    BadImage
        ``truncated`` (cut before its IEND chunk) or ``unreadable`` (a wrong checksum).
    """
    buf = memoryview(buf).cast("B")
    size = len(buf)
    pos = 8
    while True:
        if pos + 12 > size:
            raise BadImage("truncated", f"truncated PNG (ends at byte {size} before the IEND chunk)")
        length, ctype = struct.unpack(">I4s", buf[pos:pos + 8])
        end = pos + 12 + length
        if end > size:
            raise BadImage("truncated", f"truncated PNG (chunk {_chunk_name(ctype)} needs {end} bytes,"
                                        f" file has {size})")
        (crc,) = struct.unpack(">I", buf[end - 4:end])
        if zlib.crc32(buf[pos + 4:end - 4]) != crc:
            raise BadImage("unreadable", f"corrupt PNG (checksum of chunk {_chunk_name(ctype)} at byte {pos}"
                                         " is wrong)")
        if ctype == b"IEND":
            return
        pos = end


def _file_bytes(fh, size: int) -> np.ndarray:
    """The whole file as a ``(size,)`` uint8 view of this thread's reused buffer.

    Valid until the same thread reads the next file; reusing it spares a fresh
    multi-megabyte allocation (and its page faults) per frame.
    """
    buf = getattr(_scratch, "buf", None)
    if buf is None or buf.size < size:
        buf = _scratch.buf = np.empty(max(size, 1 << 20), np.uint8)
    view = buf[:size]
    mv = memoryview(view)
    got = 0
    fh.seek(0)
    while got < size:
        n = fh.readinto(mv[got:])
        if not n:
            raise OSError("file cut short while read")
        got += n
    return view


def _plain_grey_page(tf: tifffile.TiffFile, shape, dtype: np.dtype, size: int):
    """The first page if it is one grey image of ``shape`` and ``dtype`` we decode, else None.

    One sample per pixel, unsigned 8 or 16 bits, black is zero, no orientation
    other than top-left, compression none/LZW/deflate, every strip or tile
    inside the file (a cut file is declined: mapping it would fault).
    """
    page = tf.pages.first
    orientation = page.tags.get(274)
    if (page.samplesperpixel != 1 or page.sampleformat != 1 or page.bitspersample != 8 * dtype.itemsize
            or page.photometric != 1 or page.compression not in _TIFF_CODECS or page.fillorder != 1
            or (orientation is not None and orientation.value != 1) or page.is_subsampled
            or tuple(page.shape) != tuple(shape) or len(page.dataoffsets) == 0):
        return None
    if max(o + c for o, c in zip(page.dataoffsets, page.databytecounts)) > size:
        return None
    return page


def tiff_pixels_run(fh, shape, dtype) -> tuple[int, str] | None:
    """Where an uncompressed grey TIFF's pixels lie in one run, for mapping; or None.

    Parameters
    ----------
    fh : binary file opened for reading
    shape : (H, W)
    dtype : uint8 or uint16

    Returns
    -------
    (offset, byteorder) or None
        File offset (bytes, a multiple of the pixel size) of the ``H * W``
        pixels stored row after row, and ``"<"`` or ``">"``. None unless the
        file is such a TIFF of exactly this size and depth.
    """
    dtype = np.dtype(dtype)
    size = os.fstat(fh.fileno()).st_size
    try:
        fh.seek(0)
        with tifffile.TiffFile(fh) as tf:
            page = _plain_grey_page(tf, shape, dtype, size)
            if page is None or not page.is_final or page.dataoffsets[0] % dtype.itemsize:
                return None
            offset = page.dataoffsets[0]
            if offset + page.nbytes > size:
                return None
            return offset, tf.byteorder
    except Exception:  # noqa: BLE001 - tifffile raises many kinds on a damaged file: declined, named later
        return None


def _read_tiff(fh, out: np.ndarray) -> bool:
    size = os.fstat(fh.fileno()).st_size
    with tifffile.TiffFile(fh) as tf:
        page = _plain_grey_page(tf, out.shape, out.dtype, size)
        if page is None:
            return False
        if page.is_final:  # uncompressed: one readinto straight into `out` (byte order handled)
            page.asarray(out=out, maxworkers=1)
            return True
    imagecodecs.tiff_decode(_file_bytes(fh, size), out=out)  # libtiff, GIL released
    return True


def _read_png(fh, out: np.ndarray) -> bool:
    data = _file_bytes(fh, os.fstat(fh.fileno()).st_size)
    try:
        png_check_bytes(data)
    except BadImage:
        return False
    imagecodecs.png_decode(data, out=out)  # a colour, paletted or other-sized PNG: ValueError
    return True


def read_into(path, out: np.ndarray) -> bool:
    """Decode a grey PNG or TIFF straight into ``out``; False if declined.

    Parameters
    ----------
    path : path
    out : (H, W) uint8 or uint16, C-contiguous
        Filled only if True is returned (possibly partly overwritten
        otherwise: then read the file with the full reader).

    Returns
    -------
    bool
        True when the file is a grey PNG or a TIFF (uncompressed, LZW or
        deflate) of exactly ``out``'s size and depth, and decoded completely.
        16-bit samples are returned as stored (``[camera] bit_shift`` is the
        caller's).
    """
    if out.ndim != 2 or out.dtype not in (np.uint8, np.uint16) or not out.flags.c_contiguous:
        return False
    try:
        with open(path, "rb") as fh:
            sig = fh.read(8)
            fh.seek(0)  # tifffile reads from the handle's position
            if sig == PNG_SIGNATURE:
                return _read_png(fh, out)
            if sig[:4] in TIFF_SIGNATURES:
                return _read_tiff(fh, out)
    except Exception:  # noqa: BLE001 - missing, cut, corrupt or unexpected: the full reader names it
        return False
    return False
