"""Where ``ptp decode``'s CPU time goes, stage by stage, on a few positions of a dataset.

    python -m benchmarks.decode_stages DIR [--positions 0,1,2] [--compression none|gzip]

The positions' frames are read into memory first (the reading's CPU time is reported apart:
``read_into`` on two threads); then the first position is decoded once to load the numba kernels
(not counted), and the others are decoded by :func:`ptpcore.run.decoding.decode_dataset` into a
``ptp-decoded/1`` file with its writes made synchronous, so that each stage's process CPU time
(all threads) is its own: the N-step sums, the harmonic-free noise samples, unwrapping and
classification, the spatial check, the per-direction reasons, the file. Stages nest (the spatial
check is inside the per-direction reasons): read them as inclusive times. A breakdown on a loaded
machine is still a breakdown; the headline figures come from :mod:`benchmarks.commands`.
"""

from __future__ import annotations

import argparse
import collections
import functools
import os
import sys
import tempfile
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

RECIPE_MODULES = ("ptpcore.decode.position", "ptpcore.run.pipeline")
"""Where the per-position decode recipe calls the decoder's steps (the first that exists: it moved from
``run/`` to ``decode/``); ``RECIPE`` in :data:`STAGES` stands for it."""

STAGES = {  # (module, attribute): label
    ("RECIPE", "wrapped_phase"): "N-step sums (wrapped_phase)",
    ("RECIPE", "harmonic_noise_samples"): "noise samples (harmonic_noise_samples)",
    ("RECIPE", "black_clipped"): "black clipping (before it joined the N-step sums)",
    ("RECIPE", "decode_and_finish"): "unwrapping + classification (decode_and_finish)",
    ("ptpcore.decode.spatial", "spatial_outliers"): "spatial check (spatial_outliers)",
    ("ptpcore.run.decoding", "direction_reasons"): "per-direction reasons (spatial check included)",
    ("ptpcore.run.decoding", "_position_maps"): "the file's maps (_position_maps)",
    ("ptpcore.run.decoding", "convention_check"): "convention check (first position)",
}


def recipe_module():
    """The module of :data:`RECIPE_MODULES` whose functions the decode calls (its steps are patched there)."""
    import importlib
    import importlib.util

    for name in RECIPE_MODULES:
        if importlib.util.find_spec(name) is not None:
            module = importlib.import_module(name)
            if hasattr(module, "wrapped_phase"):
                return module
    raise ImportError(f"none of {RECIPE_MODULES} holds the per-position decode recipe")


class _Timer:
    def __init__(self):
        self.cpu = collections.defaultdict(float)
        self.calls = collections.Counter()

    def wrap(self, label, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            c0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.cpu[label] += time.process_time() - c0
                self.calls[label] += 1
        return timed


class _MemorySource:
    """The dataset's rig over frames already in memory (``frames(k)`` in capture order)."""

    def __init__(self, rig, stacks):
        self.rig, self.stacks = rig, stacks

    def frames(self, k):
        yield from zip(self.rig.fringes.frames(), self.stacks[k])


class _Synchronous:
    """A writer in the decoding thread (instead of :class:`ptpcore.io.decodedfile.BackgroundWriter`)."""

    def __init__(self, sink):
        self.sink = sink

    def write(self, *args):
        self.sink.write(*args)

    def close(self, quiet=False):
        pass


def measure(folder, positions, compression: str = "none", out_dir=None) -> dict:
    """Per-stage CPU seconds of decoding ``positions[1:]`` (``positions[0]`` warms up); see the module."""
    import importlib

    import ptpcore.io.decodedfile as decodedfile
    from ptpcore.io.dataset import DatasetSource
    from ptpcore.io.images import read_into
    from ptpcore.run import decoding

    if len(positions) < 2:
        raise ValueError("need at least two positions: the first one only warms up")
    source = DatasetSource(folder)
    rig = source.rig
    specs = list(rig.fringes.frames())
    stacks, c0 = {}, time.process_time()
    with ThreadPoolExecutor(2) as pool:
        for k in positions:
            paths = [source.path(k, d, t, s, n) for d, _j, t, s, n in specs]
            stacks[k] = np.empty((len(specs), *rig.camera.shape), np.uint8 if rig.camera.bit_depth <= 8 else np.uint16)
            list(pool.map(lambda i: read_into(paths[i], stacks[k][i]), range(len(specs))))
    read_cpu = time.process_time() - c0
    timer = _Timer()
    saved = []
    for (mod, name), label in STAGES.items():
        m = recipe_module() if mod == "RECIPE" else importlib.import_module(mod)
        if not hasattr(m, name):  # a stage that no longer runs apart (e.g. fused into another)
            continue
        saved.append((m, name, getattr(m, name)))
        setattr(m, name, timer.wrap(label, getattr(m, name)))
    write = decodedfile.DecodedWriter.write
    decodedfile.DecodedWriter.write = timer.wrap(f"the file ({compression})", write)
    background = decodedfile.BackgroundWriter
    decodedfile.BackgroundWriter = _Synchronous
    mem = _MemorySource(rig, stacks)
    try:
        with tempfile.TemporaryDirectory(dir=out_dir) as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore")  # what the data says (conventions, positions) is not measured here
            decoding.decode_dataset(mem, positions[:1], out=Path(tmp) / "warm.decoded.h5", compression=compression)
            timer.cpu.clear()
            timer.calls.clear()
            c0 = time.process_time()
            out = Path(tmp) / "stages.decoded.h5"
            decoding.decode_dataset(mem, positions[1:], out=out, compression=compression)
            total = time.process_time() - c0
            size = out.stat().st_size
    finally:
        for m, name, fn in saved:
            setattr(m, name, fn)
        decodedfile.DecodedWriter.write = write
        decodedfile.BackgroundWriter = background
    n = len(positions) - 1
    return {"positions": n, "frames": len(specs), "size": f"{rig.camera.width}x{rig.camera.height}",
            "read_cpu_s_per_position": read_cpu / len(positions), "decode_cpu_s_per_position": total / n,
            "file_mb_per_position": size / 2 ** 20 / n,
            "stages": {label: (timer.cpu[label] / n, timer.calls[label]) for label in timer.cpu}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--positions", default="0,1,2", help="indices; the first only warms up (default 0,1,2)")
    ap.add_argument("--compression", choices=("none", "gzip"), default="none")
    args = ap.parse_args(argv)
    res = measure(args.dataset, [int(p) for p in args.positions.split(",")], args.compression)
    print(f"{res['size']}, {res['frames']} frames a position, {res['positions']} position(s) measured, load"
          f" {os.getloadavg()[0]:.1f}")
    print(f"  {res['read_cpu_s_per_position']:7.3f} CPU-s  reading the frames (read_into, 2 threads; not in the decode)")
    print(f"  {res['decode_cpu_s_per_position']:7.3f} CPU-s  decode_dataset, all stages"
          f" ({res['file_mb_per_position']:.1f} MB of file)")
    for label, (cpu, calls) in sorted(res["stages"].items(), key=lambda kv: -kv[1][0]):
        print(f"  {cpu:7.3f} CPU-s  {label} ({calls} calls)")
    print("(CPU-s per measured position, process CPU of all threads; stages nest)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
