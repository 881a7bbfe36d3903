"""The wizard stays responsive while its calibrate job runs (issue 15): the event loop is never
blocked for more than 100 ms. A 1 ms QTimer heartbeat records the gaps between its ticks."""

from __future__ import annotations

import time

import pytest

from gui_helpers import run_job


class Heartbeat:
    """Largest gap (s) between the ticks of a fast QTimer on the GUI thread."""

    def __init__(self):
        from PySide6.QtCore import QTimer

        self.timer = QTimer()
        self.timer.setInterval(1)
        self.timer.timeout.connect(self._tick)
        self.last = None
        self.gaps = []

    def _tick(self):
        now = time.perf_counter()
        if self.last is not None:
            self.gaps.append(now - self.last)
        self.last = now

    def __enter__(self):
        self.timer.start()
        return self

    def __exit__(self, *exc):
        self.timer.stop()


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason="issue 15, not met yet: on the shared 2-core machine (load 11-15) the 160x120"
                   " smooth fit left gaps of 0.3-1.8 s (poly 0.43 s): the job's threads hold the GIL")
@pytest.mark.parametrize("model", ["poly", "smooth"])
def test_the_calibrate_job_never_blocks_the_event_loop(wizard, qtbot, model):
    wizard.go_to("acquire")
    assert run_job(qtbot, wizard.page_by_key["acquire"].start(), timeout=600_000) == "finished"
    cal = wizard.page_by_key["calibrate"]
    wizard.go_to("calibrate")
    cal.configure(model, 2, "all")
    with Heartbeat() as hb:
        job = cal.fit()
        assert run_job(qtbot, job, timeout=600_000) == "finished"
    # The heartbeat ran all along and never stalled.
    assert hb.gaps, "the heartbeat never ticked"
    assert max(hb.gaps) < 0.100, f"event loop blocked {max(hb.gaps) * 1e3:.0f} ms"
