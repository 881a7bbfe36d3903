"""One benchmark measurement in a fresh process; prints one JSON line.

    python -m benchmarks.measure TASK DATASET_DIR [--repeat R] [--positions K]

Every task times its own floor in the same process, interleaved with the
task itself (best of ``repeat`` each), so machine load hits both alike.
``maxrss_mb`` is this process's peak resident memory (``ru_maxrss``: numpy,
OpenCV and libc allocations alike), so run one task per process.

Tasks
-----
decode     one position's frames (in memory) -> DecodedPosition; floor: copy of the frames
unwrap     wrapped phases -> coordinates + validity; floor: copy of the phase maps
fit        SampleStack (K positions) -> poly LUT; floor: copy of the sample arrays
evaluate   LUT at a z map; floor: copy of the LUT's coefficient arrays
read       floors only: every image decoded on all cores as the product does (ptpcore.io.read_into:
           tifffile/imagecodecs), with cv2.imread, and the file bytes alone
frames     per-frame decode time of position 0's files: cv2.imdecode against ptpcore.io.read_into,
           on one thread and on the reader's pool
calibrate  the whole calibration from the folder (images -> LUT), nothing else in the process
calibrate-vs-read  the calibration interleaved with the read floors (time and CPU time)
spatial    the spatial-consistency check of one decoded position (both directions) against
           the decode with it and without it (``DecodeOptions(spatial_k=None)``)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np


def maxrss_mb() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 2**20


CPU: dict = {}
"""Least process CPU time (all threads, s) of each call of the last :func:`best_of`, by index."""


def best_of(repeat: int, *fns):
    """Interleave the calls; best wall time of each (least CPU time in :data:`CPU`)."""
    best = [float("inf")] * len(fns)
    out = [None] * len(fns)
    CPU.clear()
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            out[i] = None
            c0 = time.process_time()
            t0 = time.perf_counter()
            out[i] = fn()
            best[i] = min(best[i], time.perf_counter() - t0)
            CPU[i] = min(CPU.get(i, float("inf")), time.process_time() - c0)
    return best, out


def image_paths(folder: Path, rig, positions=None):
    ks = range(rig.stage.n_positions) if positions is None else positions
    return [[folder / rig.image_name(k, d, t, n, big_n) for d, _j, t, n, big_n in rig.fringes.frames()] for k in ks]


def read_cv2(paths, out: np.ndarray, pool: ThreadPoolExecutor) -> None:
    """The floor: cv2.imread on all cores into a preallocated stack."""
    def one(i):
        out[i] = cv2.imread(str(paths[i]), cv2.IMREAD_UNCHANGED)
    for _ in pool.map(one, range(len(paths))):
        pass


def read_product(paths, out: np.ndarray, pool: ThreadPoolExecutor) -> None:
    """The floor: the product's own decode on all cores into a reused stack.

    :func:`ptpcore.io.read_into` (tifffile and imagecodecs: the same decompression
    the dataset reader does), ``cv2.imread`` for a file it declines (BMP, JPEG, colour).
    """
    from ptpcore.io import read_into

    def one(i):
        if not read_into(paths[i], out[i]):
            out[i] = cv2.imread(str(paths[i]), cv2.IMREAD_UNCHANGED)
    for _ in pool.map(one, range(len(paths))):
        pass


_RAW = threading.local()


def read_raw(paths, out: np.ndarray, pool: ThreadPoolExecutor) -> None:
    """The lower floor: the file bytes only, no decoding (into a buffer each thread reuses)."""
    def one(i):
        size = os.path.getsize(paths[i])
        if getattr(_RAW, "buf", np.empty(0)).size < size:
            _RAW.buf = np.empty(size, np.uint8)
        with open(paths[i], "rb", buffering=0) as fh:
            fh.readinto(memoryview(_RAW.buf)[:size])
    for _ in pool.map(one, range(len(paths))):
        pass


def task_read(folder, rig, repeat, positions):
    """Every image of the folder: the product's decode (the floor), ``cv2.imread`` and the raw bytes.

    Returns
    -------
    dict
        ``read_s`` / ``read_cpu_s``: :func:`read_product` (least wall / CPU time, all threads);
        ``read_cv2_s`` / ``read_cv2_cpu_s``: ``cv2.imread``; ``read_raw_s`` / ``read_raw_cpu_s``:
        the bytes only; ``images``.
    """
    pos_paths = image_paths(folder, rig, positions)
    buf = np.empty((len(pos_paths[0]), *rig.camera.shape), np.uint8 if rig.camera.bit_depth <= 8 else np.uint16)
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        (t_new, t_cv, t_raw), _ = best_of(repeat, lambda: [read_product(p, buf, pool) for p in pos_paths],
                                          lambda: [read_cv2(p, buf, pool) for p in pos_paths],
                                          lambda: [read_raw(p, buf, pool) for p in pos_paths])
    return {"read_s": t_new, "read_cpu_s": CPU[0], "read_cv2_s": t_cv, "read_cv2_cpu_s": CPU[1],
            "read_raw_s": t_raw, "read_raw_cpu_s": CPU[2], "images": sum(map(len, pos_paths))}


def _per_frame(paths, out, fn, workers: int, repeat: int) -> tuple[float, float]:
    """Least wall and CPU time per frame (ms) of ``fn(path, out_slice)`` over ``paths``."""
    def run():
        if workers == 1:
            for i, p in enumerate(paths):
                fn(p, out[i])
        else:
            with ThreadPoolExecutor(workers) as pool:
                for _ in pool.map(lambda i: fn(paths[i], out[i]), range(len(paths))):
                    pass
    (t,), _ = best_of(repeat, run)
    return 1e3 * t / len(paths), 1e3 * CPU[0] / len(paths)


def task_frames(folder, rig, repeat, positions):
    """Per-frame decode time of position 0's files: OpenCV against the product's path.

    ``cv2.imdecode`` of the file's bytes (what ``read_image`` did) and
    :func:`ptpcore.io.read_into` (tifffile/imagecodecs into the caller's buffer),
    each on one thread and on the reader's pool (``tile_workers()`` threads, one
    file per thread); the pixels of both are compared. For TIFF also tifffile's own
    decoder (``TiffPage.asarray(out=...)``): one file per pool thread
    (``maxworkers=1``), and files in turn with ``maxworkers`` = the pool's size;
    and the CPU time of reading a TIFF's structure by hand and with tifffile.
    """
    from ptpcore.io import read_into
    from ptpcore.parallel import tile_workers

    paths = image_paths(folder, rig, [0])[0]
    dtype = np.uint8 if rig.camera.bit_depth <= 8 else np.uint16
    ref = np.empty((len(paths), *rig.camera.shape), dtype)
    out = np.zeros_like(ref)

    def cv(p, o):
        o[...] = cv2.imdecode(np.fromfile(p, np.uint8), cv2.IMREAD_UNCHANGED)

    def new(p, o):
        if not read_into(p, o):
            raise RuntimeError(f"{p}: declined by read_into")
    res = {"frames": len(paths), "file_mb": float(np.mean([os.path.getsize(p) for p in paths]) / 2**20),
           "pool_threads": tile_workers()}
    for workers in (1, tile_workers()):
        tag = "1thread" if workers == 1 else "pool"
        res[f"cv2_ms_{tag}"], res[f"cv2_cpu_ms_{tag}"] = _per_frame(paths, ref, cv, workers, repeat)
        res[f"new_ms_{tag}"], res[f"new_cpu_ms_{tag}"] = _per_frame(paths, out, new, workers, repeat)
    res["identical"] = bool(np.array_equal(ref, out))
    if str(paths[0]).endswith((".tif", ".tiff")):  # tifffile's own decoder, rejected for compressed files
        import tifffile

        def tiff(workers):
            def one(p, o):
                with tifffile.TiffFile(p) as tf:
                    tf.pages.first.asarray(out=o, maxworkers=workers)
            return one
        n = tile_workers()
        res["tifffile_ms_pool"], res["tifffile_cpu_ms_pool"] = _per_frame(paths, out, tiff(1), n, repeat)
        res["tifffile_ms_maxworkers"], res["tifffile_cpu_ms_maxworkers"] = _per_frame(paths, out, tiff(n), 1, repeat)
        res["tifffile_identical"] = bool(np.array_equal(ref, out))
        res.update(_header_costs(paths, repeat))
    return res


def _header_costs(paths, repeat: int) -> dict:
    """CPU time (ms per file, one thread) of a TIFF's structure: the hand parsers against tifffile's page."""
    import tifffile
    from ptpcore.io.dataset import read_header
    from ptpcore.io.images import tiff_layout

    def layout(p, o):
        with open(p, "rb", buffering=0) as fh:
            tiff_layout(lambda offset, n: os.pread(fh.fileno(), n, offset), os.fstat(fh.fileno()).st_size)

    def page(p, o):
        with tifffile.TiffFile(p) as tf:
            tf.pages.first.dataoffsets
    out = [None] * len(paths)
    return {"hand_layout_cpu_ms": _per_frame(paths, out, layout, 1, repeat)[1],
            "hand_header_cpu_ms": _per_frame(paths, out, lambda p, o: read_header(p), 1, repeat)[1],
            "tifffile_page_cpu_ms": _per_frame(paths, out, page, 1, repeat)[1]}


class MemorySource:
    """A frame source over frames already in memory."""

    def __init__(self, rig, stack, specs):
        self.rig, self.stack, self.specs = rig, stack, specs

    def frames(self, k):
        for spec, img in zip(self.specs, self.stack):
            yield spec, img


def task_decode(folder, rig, repeat, positions):
    from ptpcore.run import decode_position

    paths = image_paths(folder, rig, [0])[0]
    stack = np.empty((len(paths), *rig.camera.shape), np.uint8 if rig.camera.bit_depth <= 8 else np.uint16)
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        read_cv2(paths, stack, pool)
        dst = np.empty_like(stack)
        src = MemorySource(rig, stack, list(rig.fringes.frames()))
        (t_dec, t_copy, t_read), (pos, _, _) = best_of(repeat, lambda: decode_position(src, 0),
                                                       lambda: np.copyto(dst, stack),
                                                       lambda: read_cv2(paths, dst, pool))
    return {"decode_s": t_dec, "copy_s": t_copy, "read_cv2_s": t_read, "frames": len(paths),
            "decode_cpu_s": CPU[0], "read_cv2_cpu_s": CPU[2],
            "valid_fraction": float(pos.valid.mean()),
            "u_virtual_sub8": None}, pos


def task_unwrap(folder, rig, repeat, positions):
    from ptpcore.decode import decode_direction, finish_position

    _, pos = task_decode(folder, rig, 1, positions)
    f = rig.fringes
    z = rig.stage.z_mm[0]
    wrapped = {d: pos.directions[d].wrapped for d in f.directions}
    phases = [w.phase for d in f.directions for w in wrapped[d]]
    dst = [np.empty_like(p) for p in phases]

    def run():
        dec = {d: decode_direction(wrapped[d], f.periods_px, f.carrier(d) * z) for d in f.directions}
        return finish_position(rig, 0, dec)

    (t_un, t_copy), _ = best_of(repeat, run, lambda: [np.copyto(a, b) for a, b in zip(dst, phases)])
    return {"unwrap_s": t_un, "copy_s": t_copy}


def synthetic_samples(rig, k, seed=0):
    """A SampleStack straight from the true rays (noise 0.3 um, a few % invalid samples in regions)."""
    from benchmarks.synth import SyntheticStack
    from ptpcore.io import SampleStack

    truth = SyntheticStack(rig, seed).truth
    rng = np.random.default_rng(seed)
    h, w = rig.camera.shape
    z = 3.0 * np.arange(k)
    s = SampleStack(z, np.empty((k, h, w), np.float32), np.empty((k, h, w), np.float32),
                    truth.x0.copy(), truth.y0.copy(), np.zeros((k, h, w), np.uint8))
    for i in range(k):
        s.x[i] = truth.sx * z[i] + rng.normal(0, 3e-4, (h, w)).astype(np.float32)
        s.y[i] = truth.sy * z[i] + rng.normal(0, 3e-4, (h, w)).astype(np.float32)
        # Invalid samples come in regions (bezel, border, saturation) that move with z.
        s.reasons[i, : int(h * (0.02 + 0.002 * i))] = 1
        s.reasons[i, :, w - int(w * (0.03 - 0.001 * (i % 7))):] = 8
    return s, truth


def task_fit(folder, rig, repeat, positions):
    from ptpcore.fit import fit_lut

    k = len(positions) if positions else rig.stage.n_positions
    s, truth = synthetic_samples(rig, k)
    arrays = [s.x, s.y, s.reasons]
    dst = [np.empty_like(a) for a in arrays]
    (t_fit, t_copy), (lut, _) = best_of(repeat, lambda: fit_lut(s, "poly", 3),
                                        lambda: [np.copyto(a, b) for a, b in zip(dst, arrays)])
    ev = lut.evaluate(float(s.z[k // 2]))
    tx, ty = truth.xy(float(s.z[k // 2]))
    err = np.hypot(ev.x - tx, ev.y - ty)[ev.in_range]
    return {"fit_s": t_fit, "copy_s": t_copy, "positions": k, "lut_rms_error_um": float(np.sqrt(np.mean(err ** 2)) * 1e3)}


def task_evaluate(folder, rig, repeat, positions):
    from ptpcore.fit import fit_lut

    s, _ = synthetic_samples(rig, 6)
    lut = fit_lut(s, "poly", 3)
    del s
    rng = np.random.default_rng(1)
    zmap = rng.uniform(lut.z_min, lut.z_max, lut.shape)
    coefs = [lut.x, lut.y]
    dst = [np.empty_like(a) for a in coefs]
    (t_ev, t_copy), _ = best_of(max(repeat, 5), lambda: lut.evaluate(zmap),
                                lambda: [np.copyto(a, b) for a, b in zip(dst, coefs)])
    return {"evaluate_s": t_ev, "copy_s": t_copy}


def task_calibrate(folder, rig, repeat, positions):
    """Only the calibration in this process (its peak memory is the calibration's)."""
    from ptpcore.io import DatasetSource
    from ptpcore.run import calibrate

    src = DatasetSource(folder)
    c0 = time.process_time()
    t0 = time.perf_counter()
    lut, samples = calibrate(src, model="poly", degree=3, positions=positions)
    t = time.perf_counter() - t0
    return {"calibrate_s": t, "calibrate_cpu_s": time.process_time() - c0, "valid_pixels": float(lut.valid.mean()),
            "spilled": bool(isinstance(samples.x, np.memmap))}


def task_calibrate_vs_read(folder, rig, repeat, positions):
    """The whole calibration and its floors, interleaved in one process (best of ``repeat``)."""
    from ptpcore.io import DatasetSource
    from ptpcore.run import calibrate

    pos_paths = image_paths(folder, rig, positions)
    buf = np.empty((len(pos_paths[0]), *rig.camera.shape), np.uint8 if rig.camera.bit_depth <= 8 else np.uint16)

    spill = {"auto": None, "file": True, "memory": False}[os.environ.get("PTP_BENCH_SPILL", "auto")]

    def cal():
        lut, samples = calibrate(DatasetSource(folder), model="poly", degree=3, positions=positions, spill=spill)
        return float(lut.valid.mean())

    with ThreadPoolExecutor(os.cpu_count()) as pool:
        (t_new, t_cv, t_raw, t_cal), (_, _, _, valid) = best_of(
            repeat, lambda: [read_product(p, buf, pool) for p in pos_paths],
            lambda: [read_cv2(p, buf, pool) for p in pos_paths],
            lambda: [read_raw(p, buf, pool) for p in pos_paths], cal)
    return {"read_s": t_new, "read_cv2_s": t_cv, "read_raw_s": t_raw, "calibrate_s": t_cal, "read_cpu_s": CPU[0],
            "read_cv2_cpu_s": CPU[1], "read_raw_cpu_s": CPU[2], "calibrate_cpu_s": CPU[3],
            "images": sum(map(len, pos_paths)),
            "valid_pixels": valid, "spill": os.environ.get("PTP_BENCH_SPILL", "auto")}


def task_spatial(folder, rig, repeat, positions):
    from ptpcore.decode import DecodeOptions
    from ptpcore.decode.spatial import spatial_outliers
    from ptpcore.run import decode_position

    paths = image_paths(folder, rig, [0])[0]
    stack = np.empty((len(paths), *rig.camera.shape), np.uint8 if rig.camera.bit_depth <= 8 else np.uint16)
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        read_cv2(paths, stack, pool)
    src = MemorySource(rig, stack, list(rig.fringes.frames()))
    pos = decode_position(src, 0)  # loads the kernels; the maps the check is timed on
    base = decode_position(src, 0, DecodeOptions(spatial_k=None)).reasons == 0
    sigma = pos.info["sigma"]

    def check():
        return [spatial_outliers(pos.directions[d].coord, base, sigma.get(d), 5.0)[0] for d in rig.fringes.directions]

    (t_dec, t_plain, t_sp), _ = best_of(repeat, lambda: decode_position(src, 0),
                                        lambda: decode_position(src, 0, DecodeOptions(spatial_k=None)), check)
    return {"decode_s": t_dec, "decode_without_spatial_s": t_plain, "spatial_s": t_sp,
            "spatial_cpu_s": CPU[2], "spatial_share": t_sp / t_dec, "frames": len(paths)}


TASKS = {"spatial": task_spatial, "read": task_read, "frames": task_frames, "decode": task_decode,
         "unwrap": task_unwrap, "fit": task_fit,
         "evaluate": task_evaluate, "calibrate": task_calibrate, "calibrate-vs-read": task_calibrate_vs_read}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("task", choices=sorted(TASKS))
    ap.add_argument("dataset")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--positions", type=int, default=None, help="use the first K positions")
    ap.add_argument("--save-coords", default=None, help="decode: save x coords (every 8th pixel) here")
    args = ap.parse_args(argv)
    from ptpcore.rig import load_rig

    folder = Path(args.dataset)
    rig = load_rig(folder / "rig.toml")
    positions = list(range(args.positions)) if args.positions else None
    t0 = time.perf_counter()
    out = TASKS[args.task](folder, rig, args.repeat, positions)
    if args.task == "decode":
        out, pos = out
        if args.save_coords:
            f = rig.fringes
            z = rig.stage.z_mm[0]
            c = np.stack([pos.u + f.carrier("x") * z, pos.v + f.carrier("y") * z])[:, ::8, ::8]
            np.savez_compressed(args.save_coords, x=c.astype(np.float32), valid=pos.valid[::8, ::8])
        del out["u_virtual_sub8"]
    out.update(task=args.task, maxrss_mb=maxrss_mb(), total_s=time.perf_counter() - t0,
               size=f"{rig.camera.width}x{rig.camera.height}")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
