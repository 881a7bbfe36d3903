"""Image sources: a ``ptp-dataset/1`` folder on disk, or the virtual rig directly.

A source answers one question: "give me frame (k, dir, period, step)". The
pipeline asks for one position's frames at a time, so nothing ever holds a
whole stack in memory.

Before a long run, :func:`validate_dataset` checks the whole folder in one
pass (file headers and structure, not pixels) and reports every unusable
image together, so a bad capture costs seconds, not a failed run per file.
"""

from __future__ import annotations

import contextlib
import os
import struct
import threading
import warnings
import weakref
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Protocol

import cv2
import numpy as np

from ptpcore.errors import ConfigError, DatasetError
from ptpcore.io.images import PNG_SIGNATURE, TIFF_SIGNATURES, BadImage, png_check_bytes, read_into
from ptpcore.rig.rigfile import Rig, load_rig

__all__ = [
    "FrameSource",
    "DatasetSource",
    "SimulatedSource",
    "ImageHeader",
    "DatasetReport",
    "read_image",
    "read_header",
    "validate_dataset",
    "check_calibration_design",
    "open_source",
]

# Our own messages name the file and say what is wrong; OpenCV's and libtiff's
# console chatter about the same file would only add lines to the CLI's one.
try:  # pragma: no cover - depends on the OpenCV build
    import cv2.utils.logging as _cv_logging

    _cv_logging.setLogLevel(_cv_logging.LOG_LEVEL_SILENT)
except (ImportError, AttributeError):  # pragma: no cover
    pass

MAX_LISTED = 10  # unusable images named in one DatasetError; the rest are counted


class FrameSource(Protocol):
    """Anything that yields camera frames of a rig."""

    rig: Rig

    def frames(self, k: int) -> Iterator[tuple[tuple[str, int, int, int, int], np.ndarray]]:
        """Yield ``((dir, level, period, step, N), image (H, W))`` for position ``k``."""
        ...


# --------------------------------------------------------------------------- headers

_Unusable = BadImage  # one image's problem: ``kind`` (a short category) and ``detail``


@dataclass(frozen=True)
class ImageHeader:
    """What a PNG or TIFF header says about an image.

    Attributes
    ----------
    fmt : {"png", "tiff"}
    width, height : int
        Pixels.
    bits : int
        Bits per sample (PNG palette images: 8).
    channels : int
        Samples per pixel (1 grey; 2 grey + alpha; 3 colour; 4 colour + alpha).
    sample_format : {"uint", "int", "float"}
    """

    fmt: str
    width: int
    height: int
    bits: int
    channels: int
    sample_format: str = "uint"


_PNG_SIGNATURE = PNG_SIGNATURE
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # colour type -> channels after decoding


def _png_header(fh, size: int) -> ImageHeader:
    """IHDR, then a walk over every chunk's length field to the IEND chunk.

    The walk reads 8 bytes per chunk and seeks over the data, so it is cheap
    and still finds a file cut anywhere (inside a chunk or between chunks).
    Hand-written because no library reads a PNG's structure without decoding
    its pixels (imagecodecs.png_decode: 45 ms for a 5 MP frame; this: well
    under a millisecond, docs/performance.md).
    """
    head = fh.read(33)
    if len(head) < 33:
        raise _Unusable("truncated", f"truncated PNG ({size} bytes, header incomplete)")
    length, ctype = struct.unpack(">I4s", head[8:16])
    if ctype != b"IHDR" or length != 13:
        raise _Unusable("unreadable", "corrupt PNG (first chunk is not IHDR)")
    w, h, depth, colour = struct.unpack(">IIBB", head[16:26])
    if colour not in _PNG_CHANNELS:
        raise _Unusable("unreadable", f"corrupt PNG (colour type {colour})")
    pos, saw_idat = 8, False
    while True:
        if pos + 12 > size:
            raise _Unusable("truncated", f"truncated PNG (ends at byte {size} before the IEND chunk)")
        fh.seek(pos)
        length, ctype = struct.unpack(">I4s", fh.read(8))
        end = pos + 12 + length
        if end > size:
            name = ctype.decode("latin-1") if ctype.isalpha() else "?"
            raise _Unusable("truncated",
                            f"truncated PNG (chunk {name} needs {end} bytes, file has {size})")
        if ctype == b"IDAT":
            saw_idat = True
        if ctype == b"IEND":
            break
        pos = end
    if not saw_idat:
        raise _Unusable("unreadable", "corrupt PNG (no image data)")
    bits = 8 if colour == 3 else depth
    return ImageHeader("png", w, h, bits, _PNG_CHANNELS[colour])


_TIFF_TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 16: 8}
_TIFF_TYPE_CODE = {1: "B", 3: "H", 4: "I", 6: "b", 8: "h", 9: "i", 16: "Q"}
_TIFF_SAMPLE_FORMAT = {1: "uint", 2: "int", 3: "float"}


def _tiff_header(fh, size: int) -> ImageHeader:
    """The first IFD, then the extents of its strips or tiles against the file size.

    Hand-written because it is measured 2.5-5x cheaper than tifffile's page object
    (0.06-0.19 s against 0.30-0.47 s of CPU for 1008 files, docs/performance.md,
    "Reading the images"), on a pass over every file of the dataset.
    """
    head = fh.read(8)
    if len(head) < 8:
        raise _Unusable("truncated", f"truncated TIFF ({size} bytes, header incomplete)")
    bo = "<" if head[:2] == b"II" else ">"
    magic = struct.unpack(bo + "H", head[2:4])[0]
    if magic != 42:
        raise _Unusable("unsupported", "BigTIFF or unknown TIFF variant")  # decoded fully instead
    ifd = struct.unpack(bo + "I", head[4:8])[0]
    if ifd + 2 > size:
        raise _Unusable("truncated", f"truncated TIFF (directory at byte {ifd}, file has {size})")
    fh.seek(ifd)
    (n,) = struct.unpack(bo + "H", fh.read(2))
    raw = fh.read(12 * n)
    if len(raw) < 12 * n:
        raise _Unusable("truncated", f"truncated TIFF (directory cut at byte {size})")
    tags: dict[int, list[int]] = {}
    for i in range(n):
        tag, typ, count, value = struct.unpack(bo + "HHI4s", raw[12 * i:12 * i + 12])
        if typ not in _TIFF_TYPE_CODE or count == 0:
            continue  # rationals, ASCII, ...: nothing we need
        nbytes = _TIFF_TYPE_SIZE[typ] * count
        if nbytes <= 4:
            data = value[:nbytes]
        else:
            (off,) = struct.unpack(bo + "I", value)
            if off + nbytes > size:
                raise _Unusable("truncated", f"truncated TIFF (tag {tag} data beyond byte {size})")
            if count > 1_000_000:
                raise _Unusable("unreadable", f"corrupt TIFF (tag {tag} has {count} values)")
            fh.seek(off)
            data = fh.read(nbytes)
        tags[tag] = list(struct.unpack(f"{bo}{count}{_TIFF_TYPE_CODE[typ]}", data))
    try:
        w, h = tags[256][0], tags[257][0]
    except KeyError:
        raise _Unusable("unreadable", "corrupt TIFF (no image size)") from None
    channels = tags.get(277, [1])[0]
    bits_list = tags.get(258, [1])
    sample_format = _TIFF_SAMPLE_FORMAT.get(tags.get(339, [1])[0], "unknown")
    if 273 in tags and 279 in tags:
        offsets, counts = tags[273], tags[279]
    elif 324 in tags and 325 in tags:
        offsets, counts = tags[324], tags[325]
    else:
        raise _Unusable("unsupported", "TIFF without strip or tile byte counts")
    if len(offsets) != len(counts):
        raise _Unusable("unreadable", "corrupt TIFF (strip offsets and byte counts differ in number)")
    end = max(o + c for o, c in zip(offsets, counts))
    if end > size:
        raise _Unusable("truncated", f"truncated TIFF (image data needs {end} bytes, file has {size})")
    return ImageHeader("tiff", w, h, bits_list[0], channels, sample_format)


def read_header(path: Path) -> ImageHeader:
    """Read a PNG or TIFF header and check the file is complete (not truncated).

    Reads a few bytes per PNG chunk or TIFF directory entry, never the pixels.

    Raises
    ------
    DatasetError
        Missing, empty, unreadable, truncated or not PNG/TIFF, naming the file.
    """
    try:
        return _header(Path(path))
    except _Unusable as exc:
        raise DatasetError(f"{path}: {exc.detail}") from None


@contextlib.contextmanager
def _file_errors():
    """Map the OS's errors on opening or reading an image to :class:`_Unusable` reasons."""
    try:
        yield
    except FileNotFoundError:
        raise _Unusable("missing", "image missing") from None
    except IsADirectoryError:
        raise _Unusable("unreadable", "is a folder, not an image") from None
    except OSError as exc:
        raise _Unusable("unreadable", f"cannot read ({exc.strerror or exc})") from None


def _header(path: Path) -> ImageHeader:
    try:
        with _file_errors(), open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size == 0:
                raise _Unusable("empty", "image file is empty (0 bytes)")
            sig = fh.read(8)
            fh.seek(0)
            if sig == _PNG_SIGNATURE:
                return _png_header(fh, size)
            if sig[:4] in TIFF_SIGNATURES:
                return _tiff_header(fh, size)
            raise _Unusable("unsupported", "not a PNG or TIFF file")  # BMP, JPEG: decoded instead
    except struct.error:
        raise _Unusable("truncated", "truncated image (header cut short)") from None


def _expected_bits(rig: Rig) -> int:
    return 8 if rig.camera.bit_depth == 8 else 16


def _check_header(hdr: ImageHeader, rig: Rig) -> None:
    """Size and bit depth against ``rig.toml``; raises :class:`_Unusable`."""
    h, w = rig.camera.shape
    if (hdr.height, hdr.width) != (h, w):
        raise _Unusable("wrong size", f"image is {hdr.width}x{hdr.height} px, rig.toml says camera {w}x{h}")
    _check_depth(hdr.bits, hdr.sample_format, rig)


def _check_depth(bits: int, sample_format: str, rig: Rig) -> None:
    want = _expected_bits(rig)
    if sample_format != "uint" or bits != want:
        kind = "unsigned" if sample_format == "uint" else sample_format
        raise _Unusable("wrong bit depth",
                        f"{bits}-bit {kind} image, but rig.toml says camera.bit_depth ="
                        f" {rig.camera.bit_depth} (expected {want}-bit unsigned)")


# --------------------------------------------------------------------------- full reads

BT601 = (0.299, 0.587, 0.114)
"""ITU-R BT.601 luminance weights of R, G, B (as OpenCV's conversion to grey)."""

_JPEG_SIGNATURE = b"\xff\xd8\xff"


def luminance(img: np.ndarray, max_level: int) -> np.ndarray:
    """Floating-point BT.601 luminance of a colour image (OpenCV's BGR or BGRA order).

    A pixel with any channel saturated (at ``max_level``) gets ``max_level``, one with
    any channel clipped at black (0) gets 0, so the decoder flags both per channel.
    """
    b, g, r = (img[:, :, i].astype(np.float32) for i in range(3))
    lum = np.float32(BT601[0]) * r + np.float32(BT601[1]) * g + np.float32(BT601[2]) * b
    chans = img[:, :, :3]
    lum[(chans <= 0).any(axis=2)] = 0.0
    lum[(chans >= max_level).any(axis=2)] = float(max_level)
    return lum


def _decode(path: Path, rig: Rig) -> tuple[np.ndarray, bool, bool]:
    """Read, decode and check one image; returns ``(image (H, W), was_colour, was_jpeg)``.

    Grey images come back as they are stored (uint8/uint16); colour images as
    float32 luminance (:func:`luminance`). A grey PNG or TIFF of the rig's size
    and depth is decoded by imagecodecs (:func:`ptpcore.io.images.read_into`);
    anything else, or a file it declines, by OpenCV, with the checks below.
    """
    img = np.empty(rig.camera.shape, np.uint8 if _expected_bits(rig) == 8 else np.uint16)
    if read_into(path, img):
        return img, False, False
    with _file_errors():
        data = np.fromfile(path, dtype=np.uint8)
    if data.size == 0:
        raise _Unusable("empty", "image file is empty (0 bytes)")
    if data[:8].tobytes() == _PNG_SIGNATURE:
        png_check_bytes(data)  # before libpng, which would print its own complaint
    jpeg = data[:3].tobytes() == _JPEG_SIGNATURE
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise _Unusable("unreadable", "not a readable PNG, TIFF, BMP or JPEG image (truncated or corrupt?)")
    colour = img.ndim == 3 and img.shape[2] > 2
    if img.ndim == 3 and img.shape[2] <= 2:  # grey (+ alpha)
        img = np.ascontiguousarray(img[:, :, 0])
    expected = rig.camera.shape
    if img.shape[:2] != expected:
        raise _Unusable("wrong size", f"image is {img.shape[1]}x{img.shape[0]} px, rig.toml says camera"
                                      f" {expected[1]}x{expected[0]}")
    if img.dtype not in (np.uint8, np.uint16):
        kind = "float" if img.dtype.kind == "f" else ("int" if img.dtype.kind == "i" else "uint")
        _check_depth(8 * img.dtype.itemsize, kind, rig)
    _check_depth(8 * img.dtype.itemsize, "uint", rig)
    if colour:
        img = luminance(img, rig.camera.max_level)
    return img, colour, jpeg


def read_image(path: Path, rig: Rig) -> np.ndarray:
    """Read one image and check it against the rig.

    Colour images are decoded from their BT.601 luminance as floating point
    (saturation and black clipping per channel), with a warning; JPEG is read
    with a warning that its compression biases phases. 16-bit samples are
    shifted right by ``[camera] bit_shift`` (MSB-aligned samples, FORMATS.md).

    Returns
    -------
    (H, W) uint8 or uint16 (grey levels: counts, otherwise not scaled), or float32 (colour)

    Raises
    ------
    DatasetError
        Missing, unreadable, wrongly sized or wrong bit depth, naming the file.
    """
    try:
        img, colour, jpeg = _decode(Path(path), rig)
    except _Unusable as exc:
        raise DatasetError(f"{path}: {exc.detail}") from None
    if colour:
        _warn_colour(f"{path}: colour image decoded from its BT.601 luminance (and any others of this dataset)",
                     rig)
    if jpeg:
        _warn_once(_jpeg_warned, f"{path}: JPEG image: its lossy compression biases the phases (and any other"
                                 " JPEG of this dataset)", rig)
    shift = bit_shift(rig)
    if shift and img.dtype == np.uint16:
        np.right_shift(img, shift, out=img)
    elif shift and img.dtype == np.float32:  # colour luminance of MSB-aligned samples
        img *= np.float32(1.0 / (1 << shift))
    return img


def bit_shift(rig: Rig) -> int:
    """``[camera] bit_shift`` of the rig: how far 16-bit samples are MSB-aligned (0: not)."""
    return int(getattr(rig.camera, "bit_shift", 0) or 0)


def check_bit_alignment(path, rig: Rig, low_bits: int = 4) -> str | None:
    """Warn when a 16-bit image's low bits are all zero and the rig declares no ``bit_shift``.

    Machine-vision cameras commonly store 12-bit samples MSB-aligned in 16-bit
    files (value = counts << 4); read as counts they are 16 times too bright and
    saturate the decoder's checks. Called with one image of the dataset.

    Parameters
    ----------
    path : path
        One image of the dataset (with signal: e.g. the first fringe of position 0).
    rig : Rig
    low_bits : int
        Bits that must all be zero to suspect MSB alignment (4: 12-bit samples).

    Returns
    -------
    str or None
        The warning issued (``DataWarning``), or None.
    """
    from ptpcore.errors import DataWarning

    if rig.camera.bit_depth <= 8 or bit_shift(rig):
        return None
    try:
        img = _decode(Path(path), rig)[0]
    except _Unusable:
        return None  # reported by the validation with its reason
    if img.dtype != np.uint16 or not img.any():
        return None
    if np.bitwise_or.reduce(img, axis=None) & ((1 << low_bits) - 1):
        return None
    msg = (f"{path}: every sample's low {low_bits} bits are zero: samples stored MSB-aligned in 16 bits?"
           f" If so, add `bit_shift = {16 - rig.camera.bit_depth if rig.camera.bit_depth < 16 else low_bits}`"
           " under [camera] in rig.toml")
    warnings.warn(msg, DataWarning, stacklevel=2)
    return msg


# Rigs whose colour (JPEG) images were already reported: one warning per dataset, not one per file.
_colour_warned: "weakref.WeakSet[Rig]" = weakref.WeakSet()
_jpeg_warned: "weakref.WeakSet[Rig]" = weakref.WeakSet()
_colour_lock = threading.Lock()


def _warn_colour(message: str | None, rig: Rig) -> None:
    _warn_once(_colour_warned, message, rig)


def _warn_once(seen, message: str | None, rig: Rig) -> None:
    with _colour_lock:
        if rig in seen:
            return
        seen.add(rig)
    if message:
        warnings.warn(message, stacklevel=4)


# --------------------------------------------------------------------------- validation

@dataclass
class DatasetReport:
    """Result of :func:`validate_dataset` on a usable dataset.

    Attributes
    ----------
    folder : Path
    rig : Rig
    n_images : int
        Images the rig names (all present and usable).
    formats : dict of str -> int
        Count per file format (``"png"``, ``"tiff"``).
    colour : list of str
        Relative names of colour images (converted to grey when read).
    decoded : bool
        Whether every image was fully decoded (``full=True``) or only its header
        and structure were checked.
    """

    folder: Path
    rig: Rig
    n_images: int
    formats: dict = field(default_factory=dict)
    colour: list = field(default_factory=list)
    decoded: bool = False


def check_calibration_design(rig: Rig, source: str = "rig.toml") -> None:
    """Refuse a fringe design that cannot be calibrated, before any decoding.

    Both directions must be shown, and the coarsest period must cover the LCD
    plus the carrier span (:func:`ptpcore.decode.patterns.design_check`'s
    "unambiguous range" verdict): otherwise the absolute phase is ambiguous
    and every sample would be wrong by whole periods.

    Raises
    ------
    ConfigError
        Naming ``rig.toml`` and the key.
    """
    from ptpcore.decode.patterns import design_check

    if set(rig.fringes.directions) != {"x", "y"}:
        raise ConfigError(f"{source}: key 'fringes.directions' must be [\"x\", \"y\"] to calibrate,"
                          f" got {list(rig.fringes.directions)}")
    for item in design_check(rig).items:
        if item.name.startswith("unambiguous range") and not item.ok:
            key = "fringes.periods_px" if "does not cover" in item.message else "fringes.carrier_px_per_mm"
            raise ConfigError(f"{source}: key '{key}' gives an ambiguous period list"
                              f" (direction {item.name[-1]}): {item.message}")


def validate_dataset(folder, rig: Rig | None = None, *, full: bool = False, workers: int | None = None,
                     max_listed: int = MAX_LISTED, check_design: bool = True) -> DatasetReport:
    """Check a whole dataset folder in one pass, before a long run.

    Every image the rig names is checked (in parallel): present, not empty,
    PNG or TIFF, complete (a truncated file is found from its structure: PNG
    chunk lengths up to IEND, TIFF strip/tile extents), the camera's size and
    the bit depth ``rig.toml`` implies (8-bit files for ``bit_depth = 8``,
    16-bit files above). Colour images pass with one warning. Files the rig
    does not name are ignored.

    Parameters
    ----------
    folder : path
        The dataset folder (holding ``rig.toml``).
    rig : Rig, optional
        Default: loaded (and validated) from ``folder/rig.toml``.
    full : bool
        Also decode every image's pixels (slower; finds corrupt compressed data
        that leaves the file structure intact).
    workers : int, optional
        Reader threads.
    max_listed : int
        Name at most this many unusable images in the error; the rest are counted.
    check_design : bool
        Also refuse a design that cannot be calibrated
        (:func:`check_calibration_design`).

    Returns
    -------
    DatasetReport

    Raises
    ------
    ConfigError
        ``rig.toml`` is invalid, or its design cannot be calibrated.
    DatasetError
        One error listing every unusable image (names, grouped counts).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: dataset folder not found")
    toml_path = folder / "rig.toml"
    if rig is None:
        rig = load_rig(toml_path)
    if check_design:
        check_calibration_design(rig, str(toml_path))
    names = [rig.image_name(k, d, t, n, big_n, j)
             for k in range(rig.stage.n_positions)
             for d, j, t, n, big_n in rig.fringes.frames()]
    names += [rig.gray_name(k, d, b, inv) for k in range(rig.stage.n_positions)
              for d, b, inv in rig.fringes.gray_frames()]
    names += [n for k in range(rig.stage.n_positions) for n in (rig.reference_name(k, "white"),
                                                              rig.reference_name(k, "black")) if n]
    dupes = [n for n, c in Counter(names).items() if c > 1]
    if dupes:
        raise ConfigError(f"{toml_path}: key 'images.template' gives several images the same name"
                          f" ({dupes[0]!r}); use {{pos}}, {{dir}}, {{period}} and {{step}}")

    def check(name: str):
        path = folder / name
        try:
            unparsed = None
            try:
                hdr = _header(path)
                _check_header(hdr, rig)
                fmt, colour = hdr.fmt, hdr.channels > 1
            except _Unusable as exc:
                if exc.kind != "unsupported":
                    raise
                # Not a variant the header reader parses (BigTIFF, another format): decode it.
                unparsed, fmt = exc, {"tif": "tiff"}.get(path.suffix.lower()[1:], path.suffix.lower()[1:])
            if full or unparsed is not None:
                try:
                    _img, colour, _jpeg = _decode(path, rig)
                except _Unusable as exc:
                    if unparsed is not None and exc.kind == "unreadable":
                        raise _Unusable("unreadable", unparsed.detail) from None
                    raise
            return name, fmt, colour, None
        except _Unusable as exc:
            return name, None, False, exc

    with ThreadPoolExecutor(workers or min(32, 4 * (os.cpu_count() or 1))) as pool:
        results = list(pool.map(check, names))
    problems = [(name, exc) for name, _f, _c, exc in results if exc is not None]
    if problems:
        raise DatasetError(_problem_message(folder, problems, len(names), max_listed))
    colour = [name for name, _f, c, _e in results if c]
    if colour:
        warnings.warn(f"{folder}: {len(colour)} colour image{'s' if len(colour) > 1 else ''} will be"
                      f" decoded from their BT.601 luminance (e.g. {colour[0]})", stacklevel=2)
        _warn_colour(None, rig)  # said once here; reading them later stays quiet
    jpeg = [name for name, f, _c, _e in results if f in ("jpg", "jpeg")]
    if jpeg:
        warnings.warn(f"{folder}: {len(jpeg)} JPEG image{'s' if len(jpeg) > 1 else ''} (e.g. {jpeg[0]}):"
                      " lossy compression biases the phases; capture PNG, TIFF or BMP", stacklevel=2)
        _warn_once(_jpeg_warned, None, rig)
    formats = dict(Counter(f for _n, f, _c, _e in results))
    return DatasetReport(folder, rig, len(names), formats, colour, full)


def _problem_message(folder: Path, problems, total: int, max_listed: int) -> str:
    """One line: counts per kind, then the first ``max_listed`` files and their problems."""
    kinds = Counter(exc.kind for _n, exc in problems)
    summary = ", ".join(f"{c} {k}" for k, c in kinds.most_common())
    listed = "; ".join(f"{name}: {exc.detail}" for name, exc in problems[:max(max_listed, 1)])
    more = len(problems) - max(max_listed, 1)
    tail = f"; ... and {more} more" if more > 0 else ""
    n = len(problems)
    return (f"{folder}: {n} of {total} image{'s' if total > 1 else ''} unusable ({summary}):"
            f" {listed}{tail}")


# --------------------------------------------------------------------------- sources

class DatasetSource:
    """Frames read from a ``ptp-dataset/1`` folder, several files in parallel.

    Parameters
    ----------
    folder : path
        The dataset folder (holding ``rig.toml``).
    workers : int, optional
        Reader threads (OpenCV decoding releases the GIL).
    rig : Rig, optional
        Read the folder's frames as this rig describes them instead of its ``rig.toml``'s: a height
        sweep (:meth:`ptpcore.rig.Rig.height_rig`) or a scan (:meth:`ptpcore.rig.ScanSpec.rig`).
    """

    def __init__(self, folder, workers: int | None = None, rig: Rig | None = None):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise DatasetError(f"{self.folder}: dataset folder not found")
        self.rig = load_rig(self.folder / "rig.toml") if rig is None else rig
        self.workers = workers
        self._colour = None

    @property
    def colour(self) -> bool:
        """Whether the dataset's images are colour (decoded as float32 luminance): any image of its
        first position (headers only, where the format has one we parse)."""
        if self._colour is None:
            self._colour = False
            for d, j, t, n, big_n in self.rig.fringes.frames():
                path = self.path(0, d, t, n, big_n, j)
                try:
                    colour = _header(path).channels > 2
                except _Unusable:
                    try:
                        colour = _decode(path, self.rig)[1]
                    except _Unusable:
                        colour = False  # the read itself will name the problem
                if colour:
                    self._colour = True
                    break
        return self._colour

    def path(self, k: int, direction: str, period, step: int, n_steps: int, level: int | None = None) -> Path:
        return self.folder / self.rig.image_name(k, direction, period, step, n_steps, level)

    def gray_frames(self, k: int) -> dict:
        """``{(dir, bit, inverse): image}``: the Gray-code frames of position ``k``."""
        specs = list(self.rig.fringes.gray_frames())
        paths = [self.folder / self.rig.gray_name(k, d, b, inv) for d, b, inv in specs]
        with ThreadPoolExecutor(self.workers) as pool:
            return dict(zip(specs, pool.map(lambda p: read_image(p, self.rig), paths)))

    def reference_frames(self, k: int) -> dict:
        """``{"white": image, "black": image}`` of position ``k`` (empty without them)."""
        out = {}
        for which in ("white", "black"):
            name = self.rig.reference_name(k, which)
            if name is not None:
                out[which] = read_image(self.folder / name, self.rig)
        return out

    def validate(self, **kwargs) -> DatasetReport:
        """:func:`validate_dataset` of this folder with this source's rig."""
        return validate_dataset(self.folder, self.rig, **kwargs)

    def frames(self, k: int):
        specs = list(self.rig.fringes.frames())
        paths = [self.path(k, d, t, n, big_n, j) for d, j, t, n, big_n in specs]
        with ThreadPoolExecutor(self.workers) as pool:
            for spec, img in zip(specs, pool.map(lambda p: read_image(p, self.rig), paths)):
                yield spec, img


class SimulatedSource:
    """Frames rendered on demand by a :class:`ptpcore.simulate.VirtualRig`."""

    def __init__(self, virtual_rig):
        self.virtual_rig = virtual_rig
        self.rig = virtual_rig.rig

    def frames(self, k: int):
        return self.virtual_rig.frames(k)

    def gray_frames(self, k: int) -> dict:
        """``{(dir, bit, inverse): image}`` rendered for position ``k``."""
        return self.virtual_rig.gray_frames(k)

    def reference_frames(self, k: int) -> dict:
        """``{"white": image, "black": image}`` rendered for position ``k`` (empty without them)."""
        return self.virtual_rig.reference_frames(k)


def open_source(folder) -> DatasetSource:
    """Open a dataset folder as a frame source."""
    return DatasetSource(folder)
