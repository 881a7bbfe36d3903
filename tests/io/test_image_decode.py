"""The product's image decoding (tifffile and imagecodecs, ``ptpcore.io.images``) against OpenCV.

- every encoding a dataset may hold (TIFF uncompressed, LZW, deflate, with and without
  predictor, big-endian, tiled; PNG; 8 and 16 bits) decodes to OpenCV's pixels, through
  ``read_into``, ``read_image`` and the dataset reader (``ptpcore.io.readahead``; mapped or read);
- ``[camera] bit_shift`` is applied on every one of those paths;
- a damaged file is declined by the fast path and named in one message, with nothing printed.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import tifffile

from ptpcore.errors import DatasetError
from ptpcore.io import DatasetSource, read_image, read_into, validate_dataset
from ptpcore.rig import Camera, load_rig, save_rig
from ptpcore.io.readahead import DatasetReader
from ptpcore.simulate import preset, simulate_dataset


def _write(path, img: np.ndarray, encoding: str) -> None:
    """``img`` saved as ``encoding`` (OpenCV for what it writes, tifffile for the rest)."""
    cv_params = {"tif-none": [cv2.IMWRITE_TIFF_COMPRESSION, 1], "tif-lzw": [cv2.IMWRITE_TIFF_COMPRESSION, 5],
                 "tif-deflate": [cv2.IMWRITE_TIFF_COMPRESSION, 8],
                 "tif-deflate-old": [cv2.IMWRITE_TIFF_COMPRESSION, 32946], "png": []}
    if encoding in cv_params:
        assert cv2.imwrite(str(path), img, cv_params[encoding])
    elif encoding == "tif-big-endian":
        tifffile.imwrite(path, img, byteorder=">", photometric="minisblack")
    elif encoding == "tif-tiled-zlib-predictor":
        tifffile.imwrite(path, img, tile=(16, 16), compression="zlib", predictor=True, photometric="minisblack")
    elif encoding == "tif-strips-lzw-no-predictor":
        tifffile.imwrite(path, img, rowsperstrip=5, compression="lzw", photometric="minisblack")
    else:  # pragma: no cover
        raise ValueError(encoding)


ENCODINGS = ["tif-none", "tif-lzw", "tif-deflate", "tif-deflate-old", "png", "tif-big-endian",
             "tif-tiled-zlib-predictor", "tif-strips-lzw-no-predictor"]


@pytest.mark.parametrize("depth", [8, 16])
@pytest.mark.parametrize("encoding", ENCODINGS)
def test_read_into_gives_opencvs_pixels(tmp_path, encoding, depth):
    dtype = np.uint8 if depth == 8 else np.uint16
    img = np.random.default_rng(depth).integers(0, 1 << depth, (45, 67), dtype=dtype)
    path = tmp_path / ("img.png" if encoding == "png" else "img.tif")
    _write(path, img, encoding)
    ref = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(ref, img)
    out = np.zeros_like(img)
    assert read_into(path, out)
    np.testing.assert_array_equal(out, ref)


def _dataset(tmp_path, encoding: str, bit_depth: int, bit_shift: int = 0):
    """A small simulated dataset with every image re-encoded as ``encoding``."""
    rig, settings = preset("mild")
    rig = dataclasses.replace(rig, camera=Camera(64, 48, bit_depth)).with_z([0.0, 20.0])
    ext = ".png" if encoding == "png" else ".tif"
    ds = simulate_dataset(tmp_path / "ds", rig, settings, seed=4, image_ext=ext)
    for p in sorted(ds.rglob(f"*{ext}")):
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        _write(p, img << bit_shift if bit_shift else img, encoding)
    if bit_shift:  # MSB-aligned samples, declared in rig.toml (ptp-dataset/2)
        written = load_rig(ds / "rig.toml")
        save_rig(dataclasses.replace(written, camera=Camera(64, 48, bit_depth, bit_shift)), ds / "rig.toml")
    return ds


@pytest.mark.parametrize("encoding", ["tif-none", "tif-lzw", "tif-deflate", "png", "tif-big-endian"])
@pytest.mark.parametrize("bit_depth, bit_shift", [(8, 0), (12, 0), (12, 4)])
def test_dataset_reader_and_read_image_give_opencvs_pixels(tmp_path, encoding, bit_depth, bit_shift):
    ds = _dataset(tmp_path, encoding, bit_depth, bit_shift)
    src = DatasetSource(ds)
    assert src.rig.camera.bit_shift == bit_shift
    validate_dataset(ds, full=True)
    for map_files in (False, True):
        reader = DatasetReader(src, [0], map_files=map_files)
        try:
            for (d, j), frames in reader.sets_of(0):
                t, big_n = src.rig.fringes.periods(d)[j], src.rig.fringes.steps_of(d)[j]
                for n in range(big_n):
                    path = src.path(0, d, t, n, big_n, j)
                    ref = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) >> bit_shift
                    np.testing.assert_array_equal(np.asarray(frames[n]), ref, err_msg=f"{path} map={map_files}")
                    np.testing.assert_array_equal(read_image(path, src.rig), ref)
        finally:
            reader.close()


@pytest.mark.parametrize("encoding", ["tif-none", "tif-lzw", "png"])
def test_damaged_files_are_named_once_with_nothing_printed(tmp_path, capfd, encoding):
    ds = _dataset(tmp_path, encoding, 8)
    ext = ".png" if encoding == "png" else ".tif"
    first, second = sorted(p.relative_to(ds).as_posix() for p in ds.rglob(f"*{ext}"))[:2]
    data = (ds / first).read_bytes()
    (ds / first).write_bytes(data[:len(data) * 2 // 3])  # cut
    corrupt = bytearray((ds / second).read_bytes())
    if encoding == "png":  # pixels whose chunk checksum no longer fits
        start = corrupt.index(b"IDAT") + 4
        corrupt[start + 2:start + 40] = bytes(38)
    else:  # the first directory's offset points nowhere
        corrupt[4:8] = b"\xf0\xff\xff\x7f" if corrupt[:2] == b"II" else b"\x7f\xff\xff\xf0"
    (ds / second).write_bytes(bytes(corrupt))
    capfd.readouterr()
    out = np.empty((48, 64), np.uint8)
    assert not read_into(ds / first, out)
    with pytest.raises(DatasetError) as err:
        validate_dataset(ds, full=True)
    msg = str(err.value)
    assert f"{first}: truncated" in msg, msg
    assert second in msg and "2 of " in msg, msg
    with pytest.raises(DatasetError, match=first):
        read_image(ds / first, DatasetSource(ds).rig)
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == "", captured


def test_tiff_header_from_tifffile_reports_what_the_rig_checks(tmp_path):
    ds = _dataset(tmp_path, "tif-lzw", 8)
    rig = DatasetSource(ds).rig
    first = sorted(ds.rglob("*.tif"))[0]
    tifffile.imwrite(first, np.zeros((48, 64), np.float32), photometric="minisblack")
    with pytest.raises(DatasetError) as err:
        validate_dataset(ds, rig)
    assert "32-bit float image" in str(err.value) and "1 wrong bit depth" in str(err.value), err.value
