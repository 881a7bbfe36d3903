"""The smooth LUT fit (:func:`ptpcore.fit.smooth.fit_smooth_lut`) at benchmark sizes, beside its floors.

    python -m benchmarks.smooth_fit --sizes 0.3,5 --positions 21            # every task, a fresh process each
    python -m benchmarks.smooth_fit --task smooth --mp 5 --positions 21     # one measurement (one JSON line)

The samples are built straight from the true rays
(:func:`ptpcore.simulate.synthetic.synthetic_photometric_samples`, no images): X, Y with Gaussian
noise of each sample's own predicted sigma (from its modulation, background and a
:class:`ptpcore.decode.noise.NoiseModel`), a few % of invalid samples in regions that move with z.
Above 256 MiB they are spilled to a temporary file exactly as :func:`ptpcore.run.pipeline.collect_samples`
does (``numpy.memmap`` arrays), so the peak RSS is the fit's own, not the
samples' (``--in-memory`` keeps them in the process instead).

Tasks (each in its own process; ``base_mb`` is the RSS after building the samples,
``peak_mb`` the peak RSS of the task alone (``VmHWM`` after resetting it through
``/proc/self/clear_refs`` once the samples are built; building them peaks
higher than holding them), ``maxrss_mb`` the whole process's ``ru_maxrss``):

smooth  ``fit_smooth_lut`` (degree 2, all positions), without the level-bias and footprint corrections
        (the synthetic samples have neither effect)
smooth-corrected  the same with them, as the product runs it: time and memory
poly    the floor: ``fit_lut(samples, "poly", 2)`` (the plain per-pixel fit, same samples)
copy    the floor: one copy of the sample arrays (read block by block from the file when spilled)
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def rss_mb() -> float:
    """Current resident memory (MB, Linux), else the peak."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:  # pragma: no cover - not Linux
        return maxrss_mb()


def reset_peak() -> bool:
    """Start a new peak-RSS measurement (Linux: ``/proc/self/clear_refs``); False where unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:  # pragma: no cover - not Linux, or not allowed
        return False


def peak_mb() -> float | None:
    """Peak RSS since :func:`reset_peak` (``VmHWM``, MB), None where unknown."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:  # pragma: no cover
        pass
    return None


def maxrss_mb() -> float:
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 2**20


def _copy_floor(samples) -> None:
    """Every sample array once, block by block (file reads when spilled), into one buffer."""
    from ptpcore.io import read_block

    k = samples.z.size
    p = samples.shape[0] * samples.shape[1]
    step = 1 << 16
    for name in ("x", "y", "reasons", "modulation", "background"):
        arr = getattr(samples, name)
        buf = np.empty((k, step), arr.dtype)
        for start in range(0, p, step):
            blk = read_block(arr, start, min(start + step, p))
            buf[:, : blk.shape[1]] = blk


def run_task(task: str, mp: float, k: int, spill: bool | None, degree: int = 2) -> dict:
    from ptpcore.simulate.synthetic import synthetic_photometric_samples

    samples, rig, truth = synthetic_photometric_samples(mp, k, spill=spill)
    gc.collect()
    base = rss_mb()
    # Building the samples peaks higher than holding them: the task's peak is measured from here.
    fresh_peak = reset_peak()
    out = {"task": task, "mp": mp, "positions": k, "size": f"{samples.shape[1]}x{samples.shape[0]}",
           "spilled": bool(isinstance(samples.x, np.memmap)), "base_mb": base}
    t0 = time.perf_counter()
    c0 = time.process_time()
    if task in ("smooth", "smooth-corrected"):
        from ptpcore.fit import fit_smooth_lut

        # The samples are exact rays plus noise: no displayed levels were rounded and no pixel
        # footprint was integrated, so the level-bias and footprint corrections (the product's
        # default) would only add a bias. "smooth" leaves them out and checks the LUT against the
        # rays; "smooth-corrected" runs them for their time and memory only.
        corrected = task == "smooth-corrected"
        lut, info = fit_smooth_lut(samples, rig, degree, level_bias=corrected, footprint=corrected)
        out["scale_px"] = info.scale_px
        out["cv_score"] = [None if not np.isfinite(v) else float(v) for v in info.cv_rms_mm]
    elif task == "poly":
        from ptpcore.fit import fit_lut

        lut = fit_lut(samples, "poly", degree)
    elif task == "copy":
        _copy_floor(samples)
        lut = None
    else:
        raise ValueError(task)
    out["seconds"] = time.perf_counter() - t0
    out["cpu_s"] = time.process_time() - c0
    if lut is not None and task != "smooth-corrected":
        zm = float(samples.z[k // 2])
        ev = lut.evaluate(zm)
        tx, ty = truth.xy(zm)
        err = np.hypot(ev.x - tx, ev.y - ty)[ev.in_range]
        out["rms_error_um"] = float(np.sqrt(np.mean(err ** 2)) * 1e3)
    out["maxrss_mb"] = maxrss_mb()
    out["peak_mb"] = (peak_mb() if fresh_peak else None) or out["maxrss_mb"]
    return out


def _subprocess(task: str, mp: float, k: int, extra=()) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "benchmarks.smooth_fit", "--task", task, "--mp", f"{mp:g}", "--positions",
           str(k), *extra]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr[-3000:]}")
    out = json.loads(res.stdout.strip().splitlines()[-1])
    print(f"  {json.dumps(out)}", flush=True)
    return out


def table(rows: list[dict]) -> str:
    """Markdown rows for docs/performance.md: each task with its time, CPU time, ratios and memory."""
    lines = ["| size | task | time | CPU time | ratio | peak RSS | above the samples |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    by: dict = {}
    for r in rows:
        by.setdefault((r["mp"], r["positions"]), {})[r["task"]] = r
    for (mp, k), t in by.items():
        for task, label in (("copy", "copy of the samples (floor)"), ("poly", "plain poly-2 fit (floor)"),
                            ("smooth", "smooth fit, degree 2"),
                            ("smooth-corrected", "smooth fit, degree 2, with the level-bias and footprint corrections")):
            if task not in t:
                continue
            r = t[task]
            floors = {"copy": (), "poly": ("copy",), "smooth": ("poly", "copy"),
                      "smooth-corrected": ("smooth", "poly")}[task]
            ratios = [f"{r['seconds'] / t[f]['seconds']:.1f}x {f}" for f in floors if f in t]
            extra = f" (chose {r['scale_px']:g} px)" if "scale_px" in r else ""
            err = f", {r['rms_error_um']:.3f} um RMS vs truth" if "rms_error_um" in r else ""
            lines.append(f"| {mp:g} MP x {k} | {label}{extra}{err} | {r['seconds']:.2f} s | {r['cpu_s']:.2f} s |"
                         f" {', '.join(ratios)} | {r['peak_mb']:.0f} MB | {r['peak_mb'] - r['base_mb']:.0f} MB |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", choices=["smooth", "smooth-corrected", "poly", "copy"], default=None,
                    help="one measurement")
    ap.add_argument("--mp", type=float, default=5)
    ap.add_argument("--sizes", default="0.3,5")
    ap.add_argument("--positions", type=int, default=21)
    ap.add_argument("--in-memory", action="store_true", help="never spill the samples to a file")
    ap.add_argument("--out", default=None, help="write the rows here (JSON)")
    args = ap.parse_args(argv)
    spill = False if args.in_memory else None
    if args.task:
        print(json.dumps(run_task(args.task, args.mp, args.positions, spill)))
        return 0
    rows = []
    extra = ["--in-memory"] if args.in_memory else []
    for mp in [float(s) for s in args.sizes.split(",") if s]:
        print(f"{mp:g} MP x {args.positions}", flush=True)
        for task in ("copy", "poly", "smooth", "smooth-corrected"):
            rows.append(_subprocess(task, mp, args.positions, extra))
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1))
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
