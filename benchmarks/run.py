"""Run the benchmarks and write ``benchmarks/results/<time>.json`` plus a markdown table.

    python -m benchmarks.run --sizes 0.3,5,12 --positions 21 --calibrate-sizes 0.3,5 \\
        --memory-positions 5,11,21,31 --fringes-python /tmp/fringes-venv/bin/python

Each measurement runs in a fresh process (``benchmarks.measure``) that also
times its floor, interleaved with it (best of ``--repeat``), so every number
below is a ratio to a floor measured in the same run on the same machine.
Datasets are synthetic (:mod:`benchmarks.synth`), written once under
``--data`` as uncompressed TIFF (or ``--format png`` / ``lzw``) and reused.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.synth import GENERATION, make_rig, sensor, write_dataset

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def dataset(data: Path, mp: float, positions: int, steps, fmt: str) -> Path:
    """The dataset folder for a size (written on first use; positions beyond K symlinked views)."""
    ext = ".png" if fmt == "png" else ".tif"
    tag = "-".join(map(str, steps))
    base = data / f"{mp:g}mp-k{positions}-s{tag}-{fmt}-g{GENERATION}"
    if not (base / "rig.toml").is_file():
        print(f"writing {base} ...", flush=True)
        write_dataset(base, make_rig(mp, positions, steps, ext=ext), tiff_compression=5 if fmt == "lzw" else 1)
    return base


def subset(base: Path, k: int) -> Path:
    """A view of ``base`` with its first ``k`` positions (own rig.toml, symlinked image folders)."""
    from ptpcore.rig import load_rig, save_rig

    rig = load_rig(base / "rig.toml")
    if k >= rig.stage.n_positions:
        return base
    out = base.parent / f"{base.name}-first{k}"
    if not (out / "rig.toml").is_file():
        out.mkdir(exist_ok=True)
        for i in range(k):
            sub = Path(rig.image_name(i, "x", 1, 0, 1)).parent
            link = out / sub
            if not link.exists():
                link.symlink_to(base / sub, target_is_directory=True)
        save_rig(rig.with_z(rig.stage.z_mm[:k]), out / "rig.toml")
    return out


def measure(task: str, folder: Path, repeat: int, *extra) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "benchmarks.measure", task, str(folder), "--repeat", str(repeat), *extra]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr[-3000:]}")
    out = json.loads(res.stdout.strip().splitlines()[-1])
    print(f"  {task:10s} {json.dumps(out)}", flush=True)
    return out


def fringes(python: str, folder: Path, repeat: int, out_npz: Path) -> dict | None:
    if not python or not Path(python).exists():
        print("  fringes: no venv (see docs/performance.md), skipped", flush=True)
        return None
    cmd = [python, str(HERE / "fringes_decode.py"), str(folder), "--repeat", str(repeat), "--out", str(out_npz)]
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH",)}
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise RuntimeError(f"fringes failed:\n{res.stderr[-3000:]}")
    out = json.loads(res.stdout.strip().splitlines()[-1])
    print(f"  fringes    {json.dumps(out)}", flush=True)
    return out


def agreement(ours: Path, theirs: Path) -> float:
    """Median |ours - fringes| (LCD px) over pixels valid for us, both directions."""
    a, b = np.load(ours), np.load(theirs)
    m = a["valid"]
    d = np.abs(a["x"][:, m] - b["x"][:, m])
    return float(np.median(d))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="0.3,5,12", help="megapixels: decode, unwrap, fit, evaluate, fringes")
    ap.add_argument("--calibrate-sizes", default="0.3,5", help="megapixels: whole calibration from the folder")
    ap.add_argument("--positions", type=int, default=21, help="positions of the whole calibration")
    ap.add_argument("--memory-positions", default="5,11,21,31", help="peak memory of the calibration vs positions"
                    " (at the largest calibrate size)")
    ap.add_argument("--steps", default="8,8,8")
    ap.add_argument("--format", default="tif", choices=["tif", "lzw", "png"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cal-repeat", type=int, default=2, help="repeats of the whole calibration and its floor")
    ap.add_argument("--rounds", type=int, default=3, help="alternating rounds of our decode and fringes'")
    ap.add_argument("--data", default=os.environ.get("PTP_BENCH_DATA", "/tmp/ptp-bench"))
    ap.add_argument("--fringes-python", default="/tmp/fringes-venv/bin/python")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    data = Path(args.data)
    data.mkdir(parents=True, exist_ok=True)
    steps = tuple(int(s) for s in args.steps.split(","))
    sizes = [float(s) for s in args.sizes.split(",") if s]
    cal_sizes = [float(s) for s in args.calibrate_sizes.split(",") if s]
    mem_k = [int(s) for s in args.memory_positions.split(",") if s]
    results = {"started": time.strftime("%Y-%m-%d %H:%M:%S"), "cpus": os.cpu_count(), "argv": sys.argv[1:],
               "steps": steps, "format": args.format, "sizes": {}}
    for mp in sorted(set(sizes) | set(cal_sizes)):
        w, h = sensor(mp)
        print(f"{mp:g} MP ({w}x{h})", flush=True)
        need_k = max([args.positions] + (mem_k if mp == max(cal_sizes, default=-1) else [])) if mp in cal_sizes else 2
        base = dataset(data, mp, need_k, steps, args.format)
        r = results["sizes"][f"{mp:g}"] = {"width": w, "height": h}
        if mp in sizes:
            one = subset(base, 2)  # a rig needs two positions; the tasks use the first
            ours = data / f"coords-{mp:g}.npz"
            theirs = data / f"fringes-{mp:g}.npz"
            # Ours and fringes alternate (rounds of best-of-2 each), so load changes hit both.
            dec, fr = None, None
            for _ in range(args.rounds):
                d = measure("decode", one, 2, "--save-coords", str(ours))
                dec = d if dec is None or d["decode_s"] < dec["decode_s"] else dec
                f = fringes(args.fringes_python, one, 2, theirs)
                if f and (fr is None or f["seconds"] < fr["seconds"]):
                    fr = f
            r["decode"] = dec
            if fr:
                fr["median_abs_diff_px"] = agreement(ours, theirs)
                r["fringes"] = fr
            r["unwrap"] = measure("unwrap", one, args.repeat)
            r["fit"] = measure("fit", one, args.repeat, "--positions", str(args.positions))
            r["evaluate"] = measure("evaluate", one, args.repeat)
        if mp in cal_sizes:
            folder = subset(base, args.positions)
            r["calibrate"] = measure("calibrate-vs-read", folder, args.cal_repeat)
            if mp == max(cal_sizes):
                r["memory"] = {str(k): measure("calibrate", subset(base, k), 1) for k in mem_k}
    out = Path(args.out) if args.out else HERE / "results" / f"{time.strftime('%Y%m%d-%H%M%S')}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}")
    print(table(results))
    return 0


def table(results: dict) -> str:
    """The markdown table of docs/performance.md."""
    lines = ["| size | stage | time | floor | ratio to floor | throughput | peak RSS |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for mp, r in results["sizes"].items():
        size = f"{mp} MP"
        mpx = r["width"] * r["height"] / 1e6
        if "decode" in r:
            d = r["decode"]
            lines.append(f"| {size} | decode {d['frames']} frames (in memory) | {d['decode_s']:.3f} s |"
                         f" copy {d['copy_s'] * 1e3:.1f} ms; cv2 read {d['read_cv2_s']:.3f} s |"
                         f" {d['decode_s'] / d['copy_s']:.0f}x copy, {d['decode_s'] / d['read_cv2_s']:.2f}x read |"
                         f" {d['frames'] * mpx / d['decode_s']:.0f} MP frames/s | {d['maxrss_mb']:.0f} MB |")
            if "fringes" in r:
                f = r["fringes"]
                lines.append(f"| {size} | `fringes` {f['fringes']} decode, same frames (numba, {f['threads']} threads,"
                             f" after JIT) | {f['seconds']:.3f} s | ours {d['decode_s']:.3f} s |"
                             f" **ours {f['seconds'] / d['decode_s']:.1f}x faster** |"
                             f" {d['frames'] * mpx / f['seconds']:.0f} MP frames/s | agree to"
                             f" {f['median_abs_diff_px']:.4f} px (median) |")
            u = r["unwrap"]
            lines.append(f"| {size} | unwrap + classify (2 directions) | {u['unwrap_s']:.3f} s |"
                         f" copy of the phase maps {u['copy_s'] * 1e3:.1f} ms | {u['unwrap_s'] / u['copy_s']:.0f}x |"
                         f" {mpx / u['unwrap_s']:.0f} MP/s | |")
            f = r["fit"]
            lines.append(f"| {size} | fit poly-3 LUT, {f['positions']} positions | {f['fit_s']:.3f} s |"
                         f" copy of the samples {f['copy_s'] * 1e3:.0f} ms | {f['fit_s'] / f['copy_s']:.0f}x |"
                         f" {mpx / f['fit_s']:.1f} MP/s | {f['maxrss_mb']:.0f} MB |")
            e = r["evaluate"]
            lines.append(f"| {size} | evaluate poly-3 LUT at a z map | {e['evaluate_s'] * 1e3:.1f} ms |"
                         f" copy of the coefficients {e['copy_s'] * 1e3:.1f} ms | **{e['evaluate_s'] / e['copy_s']:.2f}x** |"
                         f" {mpx / e['evaluate_s']:.0f} MP/s | |")
        if "calibrate" in r:
            c = r["calibrate"]
            lines.append(f"| {size} | whole calibration, {c['images']} images from the folder (wall) |"
                         f" {c['calibrate_s']:.2f} s | read (cv2, all cores) {c['read_cv2_s']:.2f} s;"
                         f" raw bytes {c['read_raw_s']:.2f} s | **{c['calibrate_s'] / c['read_cv2_s']:.2f}x read**,"
                         f" {c['calibrate_s'] / c['read_raw_s']:.1f}x raw | {c['images'] * mpx / c['calibrate_s']:.0f}"
                         f" MP frames/s | |")
            lines.append(f"| {size} | same, CPU time (all threads) | {c['calibrate_cpu_s']:.2f} s |"
                         f" read (cv2) {c['read_cv2_cpu_s']:.2f} s; raw {c['read_raw_cpu_s']:.2f} s |"
                         f" **{c['calibrate_cpu_s'] / c['read_cv2_cpu_s']:.2f}x read**,"
                         f" {c['calibrate_cpu_s'] / c['read_raw_cpu_s']:.1f}x raw | | |")
        for k, m in r.get("memory", {}).items():
            lines.append(f"| {size} | peak memory, calibration of {k} positions | {m['calibrate_s']:.2f} s | | | |"
                         f" **{m['maxrss_mb']:.0f} MB** |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
