"""The user's own commands, each in a fresh process, beside the read floor measured in the same run.

    python -m benchmarks.commands DATASET_DIR [--commands calibrate,calibrate-poly,...] [--repeat R]
        [--floor-repeat F] [--cold] [--json OUT.json]

Every command runs as the user runs it (``ptp calibrate DIR --out F`` through
:func:`ptpcore.cli.main`, in a new Python process); its wall time, CPU time
(all threads) and peak resident memory come from the child's own rusage
(``os.wait4``: ``ru_maxrss``, numpy, OpenCV and libc allocations alike). The
read floor is reading the same images on all cores with the product's own decode
(tifffile and imagecodecs into reused buffers, :func:`benchmarks.measure.task_read`,
in this process; ``cv2.imread``'s time is reported beside it), timed before and after
the commands; the ratio divides by the smaller of the two. On a shared machine the
CPU-time ratio (command's CPU time over the read's, all threads) moves less than the wall ratio. ``--cold`` also runs
the first command once with an empty numba cache (``NUMBA_CACHE_DIR`` set to a
new folder): its extra time over the warm run is the first run's compile time.

Commands
--------
calibrate          ``ptp calibrate DIR --out F`` (the default model)
calibrate-poly     ``ptp calibrate DIR --out F --model poly``
calibrate-smooth   ``ptp calibrate DIR --out F --model smooth``
compare            ``ptp compare DIR`` (PTP against 3DSTC on held-out heights)
decode             ``ptp decode DIR --out F.decoded.h5`` (every position)
wizard             the wizard's Acquire (decode) and Calibrate (default model) jobs on the folder,
                   offscreen (:mod:`benchmarks.wizard_job`); its JSON line (each job's time and the
                   event loop's longest stall) is in ``tail``
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = "import sys; from ptpcore.cli import main; sys.exit(main())"

COMMANDS = {
    "calibrate": ["calibrate", "{dir}", "--out", "{out}"],
    "calibrate-poly": ["calibrate", "{dir}", "--out", "{out}", "--model", "poly"],
    "calibrate-smooth": ["calibrate", "{dir}", "--out", "{out}", "--model", "smooth"],
    "compare": ["compare", "{dir}", "--out", "{out}.json", "-q"],
    "decode": ["decode", "{dir}", "--out", "{out}.decoded.h5", "-q", "--force"],  # --force: the repeats write it again
}
MODULES = {"wizard": ["benchmarks.wizard_job", "{dir}"]}
"""Commands that run a module of ours (``python -m``) instead of the ``ptp`` command line."""
"""Command name -> ``ptp`` arguments (``{dir}`` the dataset, ``{out}`` a LUT file in a temporary folder)."""


def run_child(argv: list[str], env: dict | None = None) -> dict:
    """Run ``argv`` in a fresh process; its wall time (s), CPU time (s) and peak RSS (MB).

    Parameters
    ----------
    argv : list of str
    env : dict, optional
        Environment of the child (default this process's).

    Returns
    -------
    dict
        ``wall_s``, ``cpu_s`` (user + system, all threads), ``maxrss_mb`` (the child's
        ``ru_maxrss``), ``returncode`` and the last lines of its output in ``tail``.
    """
    with tempfile.TemporaryFile() as log:
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env)
        _pid, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        log.seek(0)
        tail = log.read().decode("utf-8", "replace").strip().splitlines()[-3:]
    scale = 1024.0 if sys.platform != "darwin" else 2.0 ** 20  # ru_maxrss: KB on Linux, bytes on macOS
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "maxrss_mb": usage.ru_maxrss / scale,
            "returncode": proc.returncode, "tail": tail}


def command_argv(name: str, dataset: Path, out: Path) -> list[str]:
    """The fresh process's arguments for command ``name`` on ``dataset``, writing ``out``."""
    if name in MODULES:
        return [sys.executable, "-m"] + [a.format(dir=dataset, out=out) for a in MODULES[name]]
    return [sys.executable, "-c", CLI] + [a.format(dir=dataset, out=out) for a in COMMANDS[name]]


def read_floor(dataset: Path, repeat: int) -> tuple[float, float, float, float]:
    """Reading every image of ``dataset`` on all cores as the product does (best of ``repeat``).

    :func:`benchmarks.measure.task_read`: the product's decode (tifffile and
    imagecodecs into reused buffers, the same decompression as the dataset
    reader), and ``cv2.imread`` for reference.

    Returns
    -------
    wall_s, cpu_s, cv2_wall_s, cv2_cpu_s : float
        Least wall time and least process CPU time (all threads), seconds, of
        the product's read, then of ``cv2.imread``.
    """
    from benchmarks.measure import task_read
    from ptpcore.rig import load_rig

    rig = load_rig(dataset / "rig.toml")
    r = task_read(dataset, rig, repeat, None)
    return r["read_s"], r["read_cpu_s"], r["read_cv2_s"], r["read_cv2_cpu_s"]


def measure(dataset, names, repeat: int = 1, floor_repeat: int = 2, cold: bool = False) -> dict:
    """Floor, every command (best of ``repeat`` fresh processes), floor again.

    Returns
    -------
    dict
        ``floor_s`` (the smaller floor), ``floor_cpu_s`` (its CPU time, all threads), ``floors_s``
        (before, after), ``floor_cv2_s`` and ``floor_cv2_cpu_s`` (the same read with ``cv2.imread``,
        for reference), ``commands``: name -> {``wall_s``, ``cpu_s``, ``maxrss_mb`` (largest),
        ``failed`` (True for a command that exited non-zero: its ``returncode`` and log ``tail``, no ratios),
        ``ratio`` (wall / floor), ``cpu_ratio`` (CPU time / the floor's)},
        ``cold`` (first run with an empty numba cache, if asked), ``load`` (load averages before, after).
    """
    dataset = Path(dataset)
    result: dict = {"dataset": str(dataset), "load": [os.getloadavg()]}
    floors = [read_floor(dataset, floor_repeat)]
    work = Path(tempfile.mkdtemp(prefix="ptp-cmd-"))
    try:
        runs = {}
        if cold and names:
            env = dict(os.environ, NUMBA_CACHE_DIR=str(work / "numba-cold"))
            result["cold"] = dict(run_child(command_argv(names[0], dataset, work / "cold.lut.h5"), env), command=names[0])
        for name in names:
            best = None
            for _ in range(repeat):
                r = run_child(command_argv(name, dataset, work / f"{name}.lut.h5"))
                if r["returncode"] != 0:  # kept with its log's tail; the other commands still run
                    best = dict(r, failed=True)
                    break
                if best is None or r["wall_s"] < best["wall_s"]:
                    best = dict(r, maxrss_mb=max(r["maxrss_mb"], best["maxrss_mb"] if best else 0.0))
            runs[name] = best
    finally:
        shutil.rmtree(work, ignore_errors=True)
    floors.append(read_floor(dataset, floor_repeat))
    floor, floor_cpu = min(f[0] for f in floors), min(f[1] for f in floors)
    result.update(floor_cv2_s=min(f[2] for f in floors), floor_cv2_cpu_s=min(f[3] for f in floors))
    for r in runs.values():
        if r.get("failed"):
            continue
        r["ratio"] = r["wall_s"] / floor
        r["cpu_ratio"] = r["cpu_s"] / floor_cpu
    if "cold" in result and not runs[result["cold"]["command"]].get("failed"):
        result["cold"]["compile_s"] = result["cold"]["wall_s"] - runs[result["cold"]["command"]]["wall_s"]
    result.update(floor_s=floor, floor_cpu_s=floor_cpu, floors_s=[f[0] for f in floors], commands=runs)
    result["load"].append(os.getloadavg())
    return result


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--commands", default="calibrate,calibrate-poly,calibrate-smooth,compare")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--floor-repeat", type=int, default=2)
    ap.add_argument("--cold", action="store_true", help="also a first run with an empty numba cache")
    ap.add_argument("--json", default=None, help="write the result here too")
    args = ap.parse_args(argv)
    names = [n for n in args.commands.split(",") if n]
    unknown = sorted(set(names) - set(COMMANDS) - set(MODULES))
    if unknown:
        ap.error(f"unknown commands {unknown}; choose from {sorted(COMMANDS) + sorted(MODULES)}")
    res = measure(args.dataset, names, args.repeat, args.floor_repeat, args.cold)
    text = json.dumps(res, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    print(f"read floor {res['floor_s']:.2f} s (before/after {res['floors_s'][0]:.2f}/{res['floors_s'][1]:.2f};"
          f" cv2.imread {res['floor_cv2_s']:.2f} s, {res['floor_cv2_cpu_s']:.2f} s CPU);"
          f" load {res['load'][0][0]:.1f} -> {res['load'][1][0]:.1f}", file=sys.stderr)
    for name, r in res["commands"].items():
        if r.get("failed"):
            print(f"{name:18s} FAILED ({r['returncode']}): {' / '.join(r['tail'])}", file=sys.stderr)
            continue
        print(f"{name:18s} {r['wall_s']:8.2f} s  {r['ratio']:6.2f}x read  cpu {r['cpu_s']:8.2f} s"
              f" ({r['cpu_ratio']:.2f}x the read's {res['floor_cpu_s']:.2f} s)"
              f"  peak {r['maxrss_mb']:7.0f} MB", file=sys.stderr)
    return 1 if any(r.get("failed") for r in res["commands"].values()) else 0


if __name__ == "__main__":
    sys.exit(main())
