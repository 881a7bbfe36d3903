"""A command's peak resident memory, read from outside, and its wall time.

    python -m benchmarks.rsswatch [--interval 0.25] [--json OUT.json] [--trace OUT.tsv] -- ptp calibrate DIR --out F

Starts the command as a fresh process (``ptp`` and ``ptp-studio`` resolve as the shell would
resolve them; ``python -m benchmarks.wizard_job DIR`` measures the wizard's jobs) and, every
``--interval`` seconds, reads its ``VmHWM`` (the kernel's high-water mark of resident memory, the
number ``ru_maxrss`` reports at exit) and ``VmRSS`` from ``/proc/PID/status``. Nothing runs inside
the measured process, so its heap's history is the plain command's (a sampler thread inside it,
as in :mod:`benchmarks.peak_stacks`, changes that history). At the end it prints the peak in MiB
(the larger of the last ``VmHWM`` read and the child's own ``ru_maxrss`` from ``os.wait4``, which
also catches a peak in the last interval), the time the peak was first seen, the wall time and the
command's exit code, which is also this tool's. ``--trace`` writes every sample (seconds,
VmRSS MiB, VmHWM MiB) to see where in the run the memory went.

The peak counts the measured process only (the commands of ``ptp`` run in one process; their
threads are counted). Linux only (``/proc``). Run the watcher as a process of its own, as above:
the kernel carries the forking process's resident size into the child's ``ru_maxrss`` (fork and
vfork share or copy its pages until the exec), so a watcher called inside a big process (a test
runner holding 700 MB) would report that size for any small command.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
import time

__all__ = ["watch", "read_status_kib"]


def read_status_kib(pid: int, keys=("VmHWM", "VmRSS")) -> dict[str, int]:
    """Fields of ``/proc/PID/status`` in KiB ({} once the process is gone or a zombie)."""
    out = {}
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                name, _, rest = line.partition(":")
                if name in keys:
                    out[name] = int(rest.split()[0])
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return {}
    return out


def watch(command: list[str], interval: float = 0.25, trace=None) -> dict:
    """Run ``command``, sample its memory every ``interval`` s; peak MiB, wall time, exit code."""
    t0 = time.perf_counter()
    child = subprocess.Popen(command)
    try:  # readable when the child exits: the wait between reads ends at once then
        exited = os.pidfd_open(child.pid)
    except (AttributeError, OSError):
        exited = None
    peak_kib, peak_at, samples = 0, 0.0, 0
    while True:
        pid, status, usage = os.wait4(child.pid, os.WNOHANG)
        if pid:
            break
        fields = read_status_kib(child.pid)
        now = time.perf_counter() - t0
        if fields:
            samples += 1
            if fields.get("VmHWM", 0) > peak_kib:
                peak_kib, peak_at = fields["VmHWM"], now
            if trace is not None:
                trace.write(f"{now:.2f}\t{fields.get('VmRSS', 0) / 1024:.1f}\t{fields.get('VmHWM', 0) / 1024:.1f}\n")
        if exited is None:
            time.sleep(interval)
        else:
            select.select([exited], [], [], interval)
    if exited is not None:
        os.close(exited)
    wall = time.perf_counter() - t0
    child.returncode = os.waitstatus_to_exitcode(status)
    if usage.ru_maxrss > peak_kib:  # KiB on Linux; a peak in the last interval
        peak_kib, peak_at = usage.ru_maxrss, wall
    return {"command": command, "peak_mib": round(peak_kib / 1024, 1), "peak_at_s": round(peak_at, 2),
            "wall_s": round(wall, 2), "cpu_s": round(usage.ru_utime + usage.ru_stime, 2),
            "samples": samples, "interval_s": interval, "exit_code": child.returncode}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 usage="python -m benchmarks.rsswatch [options] -- COMMAND [ARG ...]")
    ap.add_argument("--interval", type=float, default=0.25, help="seconds between two reads (default 0.25)")
    ap.add_argument("--json", metavar="OUT.json", help="also write the result as JSON")
    ap.add_argument("--trace", metavar="OUT.tsv", help="write every sample: seconds, VmRSS MiB, VmHWM MiB")
    ap.add_argument("command", nargs=argparse.REMAINDER)
    args = ap.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        ap.error("give the command after --, e.g. -- ptp calibrate DIR --out F.lut.h5")
    if not os.path.isdir("/proc/self"):
        ap.error("needs Linux's /proc")
    trace = open(args.trace, "w") if args.trace else None
    try:
        result = watch(command, args.interval, trace)
    finally:
        if trace is not None:
            trace.close()
    print(f"rsswatch: peak {result['peak_mib']:.1f} MiB (VmHWM, first seen at {result['peak_at_s']:.2f} s),"
          f" wall {result['wall_s']:.2f} s, CPU {result['cpu_s']:.2f} s, exit {result['exit_code']}:"
          f" {' '.join(command)}", file=sys.stderr)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=1)
    return result["exit_code"] if result["exit_code"] >= 0 else 128 - result["exit_code"]


if __name__ == "__main__":
    sys.exit(main())
