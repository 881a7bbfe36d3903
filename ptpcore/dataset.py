"""Image sources: a ``ptp-dataset/1`` folder on disk, or the virtual rig directly.

A source answers one question: "give me frame (k, dir, period, step)". The
pipeline asks for one position's frames at a time, so nothing ever holds a
whole stack in memory.
"""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator, Protocol

import cv2
import numpy as np

from .errors import DatasetError
from .rig import Rig, load_rig

__all__ = ["FrameSource", "DatasetSource", "SimulatedSource", "read_image", "open_source"]


class FrameSource(Protocol):
    """Anything that yields camera frames of a rig."""

    rig: Rig

    def frames(self, k: int) -> Iterator[tuple[tuple[str, int, int, int, int], np.ndarray]]:
        """Yield ``((dir, level, period, step, N), image (H, W))`` for position ``k``."""
        ...


def read_image(path: Path, rig: Rig) -> np.ndarray:
    """Read one single-channel image and check it against the rig.

    Colour images are converted to grey with a warning.

    Raises
    ------
    DatasetError
        Missing, unreadable, wrongly sized or wrong bit depth, naming the file.
    """
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise DatasetError(f"{path}: image missing") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    if data.size == 0:
        raise DatasetError(f"{path}: image file is empty (0 bytes)")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{path}: not a readable PNG or TIFF image (truncated or corrupt?)")
    if img.ndim == 3:
        warnings.warn(f"{path}: colour image converted to grey", stacklevel=2)
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    expected = rig.camera.shape
    if img.shape != expected:
        raise DatasetError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]} px, rig.toml says camera"
            f" {expected[1]}x{expected[0]}")
    if img.dtype not in (np.uint8, np.uint16):
        raise DatasetError(f"{path}: pixel type {img.dtype} is not 8- or 16-bit unsigned")
    if rig.camera.bit_depth > 8 and img.dtype == np.uint8:
        raise DatasetError(f"{path}: 8-bit image but rig.toml says camera.bit_depth = {rig.camera.bit_depth}")
    if rig.camera.bit_depth == 8 and img.dtype == np.uint16:
        raise DatasetError(f"{path}: 16-bit image but rig.toml says camera.bit_depth = 8")
    return img


class DatasetSource:
    """Frames read from a ``ptp-dataset/1`` folder, several files in parallel.

    Parameters
    ----------
    folder : path
        The dataset folder (holding ``rig.toml``).
    workers : int, optional
        Reader threads (OpenCV decoding releases the GIL).
    """

    def __init__(self, folder, workers: int | None = None):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise DatasetError(f"{self.folder}: dataset folder not found")
        self.rig = load_rig(self.folder / "rig.toml")
        self.workers = workers

    def path(self, k: int, direction: str, period: int, step: int, n_steps: int) -> Path:
        return self.folder / self.rig.image_name(k, direction, period, step, n_steps)

    def frames(self, k: int):
        specs = list(self.rig.fringes.frames())
        paths = [self.path(k, d, t, n, big_n) for d, _j, t, n, big_n in specs]
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


def open_source(folder) -> DatasetSource:
    """Open a dataset folder as a frame source."""
    return DatasetSource(folder)
