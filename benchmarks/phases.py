"""Where a ``ptp`` command's time goes: wall and CPU time of each of its progress phases.

    python -m benchmarks.phases [--min-s 0.5] -- calibrate DIR --out F [...]

Runs :func:`ptpcore.cli.main` in this process with its progress bar replaced by a
recorder: every change of the progress message starts a new phase; at the end
each phase's wall time, process CPU time (all threads) and the resident memory's
maximum so far (``ru_maxrss``) and at its end are printed, largest first, then in order. A
breakdown for choosing what to make faster: the headline numbers come from
:mod:`benchmarks.commands` (a fresh process beside the read floor).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import time


def _rss_mb() -> float:
    """This process's resident memory now (MB; Linux ``/proc``, NaN elsewhere)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except OSError:
        return float("nan")


class _Recorder:
    """A ``progress(fraction, message)`` callback that times the phases between message changes."""

    def __init__(self, *_args, **_kwargs):
        self.phases: list[list] = []  # [message, wall start, cpu start, wall s, cpu s, maxrss MB, rss MB]
        self._last = None

    def _close_last(self) -> None:
        if self.phases:
            p = self.phases[-1]
            p[3] = time.perf_counter() - p[1]
            p[4] = time.process_time() - p[2]
            p[5] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
            p[6] = _rss_mb()

    def __call__(self, fraction: float, message: str) -> None:
        key = message.split(" (")[0]
        # Per-position messages ("decoding position 3 of 21") count as one phase per position.
        if key != self._last:
            self._close_last()
            self.phases.append([key, time.perf_counter(), time.process_time(), 0.0, 0.0, 0.0, 0.0])
            self._last = key

    def close(self) -> None:
        self._close_last()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--min-s", type=float, default=0.5, help="print phases at least this long (wall or CPU)")
    ap.add_argument("ptp", nargs=argparse.REMAINDER, help="the ptp command's arguments (after --)")
    args = ap.parse_args(argv)
    ptp_args = args.ptp[1:] if args.ptp[:1] == ["--"] else args.ptp

    import ptpcore.cli.progress as progress_mod

    recorder = _Recorder()
    progress_mod.ProgressBar = lambda *a, **k: recorder  # every command's bar is this one recorder
    from ptpcore.cli import main as ptp_main

    t0, c0 = time.perf_counter(), time.process_time()
    code = ptp_main(ptp_args)
    recorder.close()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    rows = [p for p in recorder.phases if max(p[3], p[4]) >= args.min_s]
    print(f"exit {code}: {wall:.1f} s wall, {cpu:.1f} s CPU; phases of at least {args.min_s} s:", file=sys.stderr)
    for title, order in (("largest first", sorted(rows, key=lambda p: -p[3])[:15]), ("in order", rows)):
        print(f"-- {title}", file=sys.stderr)
        for p in order:
            print(f"{p[3]:8.1f} s wall {p[4]:8.1f} s CPU  max RSS {p[5]:6.0f} MB, at its end {p[6]:6.0f} MB  {p[0]}",
                  file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
