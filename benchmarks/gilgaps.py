"""How long a ``ptp`` command holds the GIL at a stretch: the gaps of a ticking thread beside it.

    python -m benchmarks.gilgaps [--tick-ms 1] [--min-ms 20] [--top 10] -- calibrate DIR --out F [...]

Runs :func:`ptpcore.cli.main` in this process beside a thread that sleeps ``--tick-ms`` and notes
the time. Python lets a waiting thread run only when the thread holding the GIL gives it up, so a
gap much longer than the tick is a stretch in which the other threads held the GIL (or the process
was descheduled: run on a quiet machine). After each gap over ``--min-ms`` the ticker records the
innermost frames of the other threads (``sys._current_frames``), i.e. what ran when the GIL came
back (where the holder gave it up: the stretch ends there). It prints the longest gaps, largest first, with the
command's progress phase and those frames, as JSON lines. The GUI's own measure of the same thing
while the wizard runs its jobs is :mod:`benchmarks.wizard_job`.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
import traceback

__all__ = ["GapRecorder", "main"]

_IDLE = {"wait", "_worker", "get", "sleep", "select", "_wait_for_tstate_lock"}


class GapRecorder:
    """A thread that ticks every ``tick_s`` and keeps the gaps over ``min_s`` with the other threads' stacks."""

    def __init__(self, tick_s: float = 0.001, min_s: float = 0.020, depth: int = 4):
        self.tick_s, self.min_s, self.depth = tick_s, min_s, depth
        self.gaps: list[dict] = []
        self.phase = ""
        self.ticks = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gilgaps", daemon=True)

    def _stacks(self) -> list[str]:
        own = threading.get_ident()
        out = []
        for ident, frame in sys._current_frames().items():
            if ident == own:
                continue
            summary = traceback.extract_stack(frame)[-self.depth:]
            if summary and summary[-1].name in _IDLE:  # a thread waiting for work held nothing
                continue
            out.append(" <- ".join(f"{fs.name} ({fs.filename.rsplit('/', 1)[-1]}:{fs.lineno})"
                                   for fs in reversed(summary)))
        return out

    def _run(self) -> None:
        last = time.perf_counter()
        while not self._stop.is_set():
            time.sleep(self.tick_s)
            now = time.perf_counter()
            self.ticks += 1
            if now - last > self.min_s:
                self.gaps.append({"gap_ms": round(1e3 * (now - last), 1), "phase": self.phase,
                                  "stacks": self._stacks()})
            last = now

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 usage="python -m benchmarks.gilgaps [options] -- PTP_COMMAND [ARG ...]")
    ap.add_argument("--tick-ms", type=float, default=1.0, help="the ticker's sleep (default 1 ms)")
    ap.add_argument("--min-ms", type=float, default=20.0, help="gaps kept: longer than this (default 20 ms)")
    ap.add_argument("--top", type=int, default=10, help="gaps printed, longest first (default 10)")
    ap.add_argument("command", nargs=argparse.REMAINDER)
    args = ap.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        ap.error("give the ptp command after --, e.g. -- calibrate DIR --out F.lut.h5")
    import importlib

    cli = importlib.import_module("ptpcore.cli.main")  # the module (ptpcore.cli.main is also its function)
    progress = importlib.import_module("ptpcore.cli.progress")

    recorder = GapRecorder(args.tick_ms / 1e3, args.min_ms / 1e3)
    plain_bar = progress.progress_bar

    def following_bar(cli_args):
        """The command's own progress bar, its messages also naming the recorder's phase."""
        bar = plain_bar(cli_args)

        def update(fraction, message=""):
            if message:
                recorder.phase = message
            return bar(fraction, message)

        update.close = bar.close
        return update

    cli.progress_bar = following_bar
    t0 = time.perf_counter()
    with recorder:
        code = cli.main(command)
    wall = time.perf_counter() - t0
    print(json.dumps({"command": command, "exit_code": code, "wall_s": round(wall, 2), "ticks": recorder.ticks,
                      "gaps_over_min": len(recorder.gaps), "tick_ms": args.tick_ms, "min_ms": args.min_ms}))
    for gap in sorted(recorder.gaps, key=lambda g: -g["gap_ms"])[:args.top]:
        print(json.dumps(gap))
    return code


if __name__ == "__main__":
    sys.exit(main())
