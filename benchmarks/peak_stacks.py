"""Where a ``ptp`` command's memory peaks: its stacks at each new resident-memory maximum.

    python -m benchmarks.peak_stacks [--step-mb 50] [--top 8] -- calibrate DIR --out F [...]
    python -m benchmarks.peak_stacks [--step-mb 50] [--top 8] -- wizard DIR [--model auto]

Runs :func:`ptpcore.cli.main` in this process with a sampler thread that reads
``/proc/self/statm`` every few milliseconds; whenever the resident size passes the
previous maximum by ``--step-mb``, it records every thread's stack (innermost frames
of our code); ``wizard`` runs :mod:`benchmarks.wizard_job` (offscreen) instead. At the end it prints the largest maxima with their stacks, the last
one being the command's peak. A breakdown for finding what to put in row blocks:
the headline numbers come from :mod:`benchmarks.commands` (a fresh process, the
child's own ``ru_maxrss``). Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
import traceback

_PAGE = os.sysconf("SC_PAGE_SIZE")


def _rss_mb() -> float:
    return _rss_split_mb()[0]


def _rss_split_mb() -> tuple[float, float]:
    """Resident size and its file-backed part (mapped files, e.g. the spilled samples), MB."""
    with open("/proc/self/statm") as fh:
        fields = fh.read().split()
    return int(fields[1]) * _PAGE / 2 ** 20, int(fields[2]) * _PAGE / 2 ** 20


def _our_stack(frame, depth: int = 7) -> list[str]:
    """The innermost ``depth`` frames that belong to ptpcore, ptp_studio or app."""
    lines = []
    # No source lines (lookup_lines=False): reading them from this thread can stall the GUI's.
    for fs in traceback.StackSummary.extract(traceback.walk_stack(frame), lookup_lines=False):
        if any(p in fs.filename for p in ("ptpcore", "ptp_studio", "/app/")):
            lines.append(f"{fs.filename.split('/')[-2]}/{fs.filename.split('/')[-1]}:{fs.lineno} {fs.name}")
            if len(lines) == depth:
                break
    return lines


class PeakSampler(threading.Thread):
    """Records ``(rss_mb, seconds, {thread name: stack})`` at every new maximum."""

    def __init__(self, step_mb: float, interval_s: float = 0.004):
        super().__init__(daemon=True, name="peak-sampler")
        self.step_mb, self.interval_s = step_mb, interval_s
        self.records: list[tuple[float, float, dict]] = []
        self.peak = 0.0
        self.stop_event = threading.Event()
        self.t0 = time.perf_counter()

    def run(self) -> None:
        names = {}
        recorded = -self.step_mb
        while not self.stop_event.wait(self.interval_s):
            rss, file_mb = _rss_split_mb()
            if rss > self.peak:
                if rss > recorded + self.step_mb:
                    recorded = rss
                    names.update({t.ident: t.name for t in threading.enumerate()})
                    frames = sys._current_frames()
                    stacks = {names.get(i, str(i)): _our_stack(f) for i, f in frames.items()
                              if i != threading.get_ident()}
                    self.records.append((rss, time.perf_counter() - self.t0, {k: v for k, v in stacks.items() if v},
                                         file_mb))
                self.peak = rss


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step-mb", type=float, default=50.0, help="record a new maximum this far above the last")
    ap.add_argument("--top", type=int, default=8, help="how many maxima to print (the largest)")
    ap.add_argument("ptp", nargs=argparse.REMAINDER, help="the ptp command's arguments (after --)")
    args = ap.parse_args(argv)
    ptp_args = args.ptp[1:] if args.ptp[:1] == ["--"] else args.ptp
    if ptp_args[:1] == ["wizard"]:
        from benchmarks.wizard_job import main as ptp_main

        ptp_args = ptp_args[1:]
    else:
        from ptpcore.cli import main as ptp_main

    sampler = PeakSampler(args.step_mb)
    sampler.start()
    try:
        code = ptp_main(ptp_args)
    finally:
        sampler.stop_event.set()
        sampler.join()
    print(f"\nexit {code}; peak RSS {sampler.peak:.0f} MB (sampled), ru_maxrss "
          f"{__import__('resource').getrusage(0).ru_maxrss / 1024:.0f} MB", file=sys.stderr)
    for rss, t, stacks, file_mb in sorted(sampler.records, key=lambda r: r[0])[-args.top:]:
        print(f"--- {rss:.0f} MB at {t:.1f} s ({file_mb:.0f} MB of it file-backed)", file=sys.stderr)
        for name, stack in stacks.items():
            print(f"  [{name}] " + " <- ".join(stack[:4]), file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
