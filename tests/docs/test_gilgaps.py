"""benchmarks.gilgaps: a stretch that holds the GIL shows as a gap, with the stack that held it."""

from __future__ import annotations

import sys
import time

from benchmarks.gilgaps import GapRecorder


def _hold_the_gil(seconds: float) -> None:
    """Pure-Python work: the GIL is passed on only every switch interval (5 ms), never for long."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def test_a_sleep_leaves_no_gap_and_a_thread_holding_the_gil_does():
    with GapRecorder(tick_s=0.001, min_s=0.050) as rec:
        time.sleep(0.3)  # releases the GIL: the ticker runs freely
    assert rec.ticks > 20
    quiet = len(rec.gaps)
    old = sys.getswitchinterval()
    sys.setswitchinterval(0.5)  # the running thread keeps the GIL for up to 0.5 s
    try:
        with GapRecorder(tick_s=0.001, min_s=0.050) as rec:
            time.sleep(0.01)
            _hold_the_gil(0.3)
            time.sleep(0.01)
    finally:
        sys.setswitchinterval(old)
    assert quiet <= 1  # a loaded machine may deschedule the ticker once
    longest = max(rec.gaps, key=lambda g: g["gap_ms"])
    assert longest["gap_ms"] >= 150
    # The stacks are taken when the ticker runs again: the holder just gave up the GIL (here at the
    # sleep after the loop), so they name the thread that held it.
    assert any("test_a_sleep_leaves_no_gap" in stack for stack in longest["stacks"]), longest
