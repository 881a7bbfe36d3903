"""Synthetic fringe datasets at realistic sensor sizes, fast enough to write for benchmarks.

The analytic stack itself (a rig like the real one, its frames and true rays) is the engine's
:mod:`ptpcore.simulate.synthetic` (tests use it too); this module keeps the benchmarks' names for
it and writes its images into a dataset folder (:func:`write_dataset`).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2

from ptpcore.rig import Rig, save_rig
from ptpcore.simulate.synthetic import SENSOR_SIZES as SIZES
from ptpcore.simulate.synthetic import AnalyticRays as Truth
from ptpcore.simulate.synthetic import SyntheticStack
from ptpcore.simulate.synthetic import sensor_size as sensor
from ptpcore.simulate.synthetic import synthetic_rig as make_rig

__all__ = ["GENERATION", "SIZES", "Truth", "SyntheticStack", "sensor", "make_rig", "write_dataset"]

GENERATION = 2
"""Bumped whenever the rendered images change (benchmark folders are named with it, so a
folder written by an older generator is not reused). 2: rays no longer a mirror image."""


def write_dataset(folder, rig: Rig, seed: int = 0, tiff_compression: int = 1, png_level: int = 1,
                  workers: int | None = None, progress=None) -> Path:
    """Render every image of ``rig`` into ``folder`` (a ``ptp-dataset/1`` with ``rig.toml``).

    ``tiff_compression``: 1 none (what machine-vision software saves), 5 LZW (OpenCV's default).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_rig(rig, folder / "rig.toml")
    synth = SyntheticStack(rig, seed)
    f = rig.fringes
    params = [cv2.IMWRITE_TIFF_COMPRESSION, tiff_compression] if rig.template.endswith(".tif") else \
        [cv2.IMWRITE_PNG_COMPRESSION, png_level]
    jobs = [(k, d, j) for k in range(rig.stage.n_positions) for d in f.directions for j in range(len(f.periods_px))]

    def one(job):
        k, d, j = job
        stack = synth.set_frames(k, d, j)
        for n in range(len(stack)):
            path = folder / rig.image_name(k, d, f.periods_px[j], n, f.steps[j])
            path.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(path), stack[n], params):
                raise OSError(f"could not write {path}")

    with ThreadPoolExecutor(workers or os.cpu_count()) as pool:
        for i, _ in enumerate(pool.map(one, jobs)):
            if progress:
                progress((i + 1) / len(jobs))
    return folder
