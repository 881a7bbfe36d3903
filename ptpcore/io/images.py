"""Grey PNG and TIFF frames decoded straight into a caller's buffer, on any thread.

The dataset reader keeps a few ``(N, H, W)`` stacks and fills them frame by
frame from a thread pool; this module decodes one file into one ``(H, W)``
slice of such a stack with the libraries' own C code, which releases the GIL,
so the pool decodes on every core:

- TIFF, uncompressed: the strips found by a small hand-written parser
  (:func:`tiff_layout`, measured faster than tifffile here) and read with
  positional reads straight into the buffer (or mapped,
  :func:`ptpcore.io.fastio.map_frame`); any other layout through tifffile;
- TIFF, compressed (LZW, deflate, with or without predictor): the header from
  ``tifffile``, the pixels decoded by libtiff through
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

import numpy as np

# tifffile and imagecodecs are imported where first used: together about 0.5 s, which a
# command that reads no image (`ptp inspect`, `ptp apply`) should not pay at start.

__all__ = ["read_into", "tiff_layout", "read_plain_tiff", "png_check_bytes", "PNG_SIGNATURE", "TIFF_SIGNATURES",
           "BadImage"]

# tifffile reports what it finds odd in a damaged file through `logging`; our own
# message names the file and says what is wrong (as for OpenCV's console chatter).
_TIFF_LOG = logging.getLogger("tifffile")
_TIFF_LOG.addHandler(logging.NullHandler())
_TIFF_LOG.propagate = False

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_TIFF_CODECS = {1, 5, 8, 32946}  # none, LZW, deflate (Adobe), deflate (old code): what libtiff decodes here
_scratch = threading.local()
_PREADV = hasattr(os, "preadv")


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


def _plain_grey_page(tf, shape, dtype: np.dtype, size: int):
    """The first page of ``tf`` (a ``tifffile.TiffFile``) if it is one grey image of ``shape``
    and ``dtype`` we decode, else None.

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


# --------------------------------------------------------------------------- uncompressed TIFF by hand
# Kept by hand, where measured faster than tifffile (docs/performance.md, "Reading the images"):
# tifffile builds its page object in Python, ~0.36 ms of CPU per file. 1008 uncompressed files
# of 0.3 MP: mapped 0.17-0.24 s by hand against 0.40-0.57 s, read 0.13-0.19 s against
# 0.45-0.67 s; of 5 MP: mapped a tie (1.36-1.59 s against 1.36-1.65 s), read 1.48-1.76 s
# against 1.87-2.02 s.

_TYPE_SIZE = {3: 2, 4: 4, 16: 8}
_TYPE_CODE = {3: "H", 4: "I", 16: "Q"}


def tiff_layout(read, size: int):
    """Strip layout of a plain TIFF, or None.

    Parameters
    ----------
    read : callable
        ``read(offset, n) -> bytes`` of the file (the IFD may be anywhere,
        libtiff writes it after the pixels).
    size : int
        The file's size in bytes.

    Returns
    -------
    (width, height, bits, byteorder, [(file offset, nbytes), ...]) or None
        None unless: classic TIFF, uncompressed, one sample per pixel, 8 or 16
        bits unsigned, black-is-zero, top-left orientation, strips (not
        tiles) that hold exactly the image rows, all inside the file.
    """
    head = read(0, 8)
    if len(head) < 8 or head[:4] not in (b"II*\x00", b"MM\x00*"):
        return None
    bo = "<" if head[:2] == b"II" else ">"
    (ifd,) = struct.unpack(bo + "I", head[4:8])
    if ifd + 2 > size:
        return None
    (n,) = struct.unpack(bo + "H", read(ifd, 2))
    entries = read(ifd + 2, 12 * n)
    if len(entries) < 12 * n:
        return None
    tags: dict[int, tuple[int, ...]] = {}
    for i in range(n):
        tag, typ, count, value = struct.unpack(bo + "HHI4s", entries[12 * i:12 * i + 12])
        if typ not in _TYPE_SIZE or count == 0 or count > 1_000_000:
            continue
        nbytes = _TYPE_SIZE[typ] * count
        if nbytes <= 4:
            data = value[:nbytes]
        else:
            (off,) = struct.unpack(bo + "I", value)
            if off + nbytes > size:
                return None
            data = read(off, nbytes)
            if len(data) < nbytes:
                return None
        tags[tag] = struct.unpack(f"{bo}{count}{_TYPE_CODE[typ]}", data)
    try:
        w, h = tags[256][0], tags[257][0]
        offsets, counts = tags[273], tags[279]
    except KeyError:
        return None
    bits = tags.get(258, (1,))
    if (tags.get(259, (1,))[0] != 1 or tags.get(277, (1,))[0] != 1 or len(bits) != 1
            or bits[0] not in (8, 16) or tags.get(339, (1,))[0] != 1 or tags.get(262, (1,))[0] != 1
            or tags.get(274, (1,))[0] != 1 or 322 in tags or len(offsets) != len(counts)):
        return None
    row_bytes = w * bits[0] // 8
    rps = min(tags.get(278, (h,))[0], h)
    if rps < 1 or len(offsets) != -(-h // rps):
        return None
    runs = []
    for i, (off, cnt) in enumerate(zip(offsets, counts)):
        need = min(rps, h - i * rps) * row_bytes
        if cnt < need or off + need > size:
            return None
        if runs and runs[-1][0] + runs[-1][1] == off:
            runs[-1] = (runs[-1][0], runs[-1][1] + need)  # contiguous strips: one read
        else:
            runs.append((off, need))
    return w, h, bits[0], bo, runs


def read_plain_tiff(fh, out: np.ndarray) -> bool:
    """Read an uncompressed grey TIFF (:func:`tiff_layout`) straight into ``out``; False if declined.

    Parameters
    ----------
    fh : binary file opened for reading, unbuffered
    out : (H, W) uint8 or uint16, C-contiguous
        Filled only if True is returned (partially on a short read, then declined).

    Returns
    -------
    bool
        True when the file is in the layout :func:`tiff_layout` accepts, of
        exactly ``out``'s size and depth, and was read completely.
    """
    size = os.fstat(fh.fileno()).st_size
    layout = tiff_layout(lambda offset, n: os.pread(fh.fileno(), n, offset), size)
    if layout is None:
        return False
    w, h, bits, bo, runs = layout
    if (h, w) != out.shape or bits != 8 * out.itemsize:
        return False
    buf = memoryview(out.reshape(-1).view(np.uint8))
    pos = 0
    for off, nbytes in runs:
        got = 0
        while got < nbytes:
            n = os.preadv(fh.fileno(), [buf[pos + got:pos + nbytes]], off + got) if _PREADV else \
                _read_at(fh, buf[pos + got:pos + nbytes], off + got)
            if not n:
                return False
            got += n
        pos += nbytes
    if bits == 16 and (bo == "<") != np.little_endian:
        out.byteswap(inplace=True)
    return True


def _read_at(fh, view, offset: int) -> int:  # pragma: no cover - no preadv (Windows, macOS < 11)
    fh.seek(offset)
    return fh.readinto(view)


# --------------------------------------------------------------------------- the libraries


def _read_tiff(fh, out: np.ndarray) -> bool:
    if read_plain_tiff(fh, out):  # uncompressed, by hand (see above)
        return True
    import imagecodecs
    import tifffile

    size = os.fstat(fh.fileno()).st_size
    fh.seek(0)  # tifffile reads from the handle's position
    with tifffile.TiffFile(fh) as tf:
        page = _plain_grey_page(tf, out.shape, out.dtype, size)
        if page is None:
            return False
        if page.is_final:  # uncompressed in a layout the hand parser declines: one readinto
            page.asarray(out=out, maxworkers=1)
            return True
    imagecodecs.tiff_decode(_file_bytes(fh, size), out=out)  # libtiff, GIL released
    return True


def _read_png(fh, out: np.ndarray) -> bool:
    import imagecodecs

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
            if sig == PNG_SIGNATURE:
                return _read_png(fh, out)
            if sig[:4] in TIFF_SIGNATURES:
                return _read_tiff(fh, out)
    except Exception:  # noqa: BLE001 - missing, cut, corrupt or unexpected: the full reader names it
        return False
    return False
