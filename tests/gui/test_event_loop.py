"""The wizard stays responsive while its jobs run (issue 15): the event loop is never blocked for more
than 100 ms during the Acquire page's decode job or the Calibrate page's fit job. A 1 ms QTimer
heartbeat on the GUI thread records the gaps between its ticks, and which job phase (the job's
latest progress message) each gap fell in, so a failure says where the stall came from."""

from __future__ import annotations

import time

import pytest

from gui_helpers import run_job

BOUND_S = 0.100  # issue 15: "its event loop never blocked for more than 100 ms during the job"


class Heartbeat:
    """Gaps (s) between the ticks of a fast QTimer on the GUI thread, each with the job's phase then
    (see :meth:`follow`)."""

    def __init__(self):
        from PySide6.QtCore import QTimer

        self.timer = QTimer()
        self.timer.setInterval(1)
        self.timer.timeout.connect(self._tick)
        self.last = None
        self.phase = "starting the job"
        self.gaps: list[tuple[float, str]] = []

    def follow(self, job) -> None:
        """Name each later gap after ``job``'s latest progress message."""
        job.progress.connect(lambda _f, message: setattr(self, "phase", message or self.phase))
        # The handlers of the result (maps, tables) run on the GUI thread too: within the bound.
        job.finished.connect(lambda _r: setattr(self, "phase", "handing the result to the page"))

    def _tick(self):
        now = time.perf_counter()
        if self.last is not None:
            self.gaps.append((now - self.last, self.phase))
        self.last = now

    def worst(self) -> tuple[float, str]:
        """The longest gap (s) and its phase."""
        assert self.gaps, "the heartbeat never ticked"
        return max(self.gaps)

    def __enter__(self):
        self.timer.start()
        return self

    def __exit__(self, *exc):
        self.timer.stop()


def _run_with_heartbeat(qtbot, start) -> tuple[float, str]:
    """Start a job with ``start()`` under a heartbeat and wait for it; its longest gap and phase."""
    with Heartbeat() as hb:
        job = start()
        assert job is not None, "the page did not start its job"
        hb.follow(job)
        assert run_job(qtbot, job, timeout=600_000) == "finished"
    return hb.worst()


def _acquire_then_fit(wizard, qtbot, model: str) -> dict[str, tuple[float, str]]:
    """The Acquire job, then the Calibrate job with ``model``: each one's longest gap and phase."""
    worst = {}
    wizard.go_to("acquire")
    worst["acquire"] = _run_with_heartbeat(qtbot, wizard.page_by_key["acquire"].start)
    cal = wizard.page_by_key["calibrate"]
    wizard.go_to("calibrate")
    cal.configure(model, 2, "all")
    worst[f"calibrate ({model})"] = _run_with_heartbeat(qtbot, cal.fit)
    assert wizard.model.session.lut is not None and wizard.model.session.lut.valid.any()
    return worst


def _check(worst: dict[str, tuple[float, str]]) -> None:
    too_long = {k: f"{1e3 * gap:.0f} ms while '{phase}'" for k, (gap, phase) in worst.items() if gap >= BOUND_S}
    assert not too_long, f"event loop blocked: {too_long}"


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason="issue 15, not met in a fresh process: the first decode loads the numba"
                   " kernels from their cache and imports the decode modules, holding the GIL (123 ms at the first"
                   " position in the slow suite of 2026-11-25, 212-279 ms measured before; under 100 ms once loaded)")
def test_the_acquire_job_never_blocks_the_event_loop(wizard, qtbot):
    wizard.go_to("acquire")
    _check({"acquire": _run_with_heartbeat(qtbot, wizard.page_by_key["acquire"].start)})


@pytest.mark.slow
def test_the_poly_job_never_blocks_the_event_loop(wizard, qtbot):
    """The Calibrate page's poly fit (after the Acquire job, whose first-decode stall is the test above's)."""
    worst = _acquire_then_fit(wizard, qtbot, "poly")
    _check({job: gap for job, gap in worst.items() if job != "acquire"})


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason="issue 15, not met: the smooth (and auto) fit's global camera model"
                   " (ptpcore.fit.smooth.global_pinhole -> ptpcore.pinhole.camera.fit_pinhole) runs scipy's"
                   " MINPACK least_squares(method='lm'), which holds the GIL between its Python callbacks:"
                   " 70-100 ms of CPU per iteration on 20 000 points, stretched to 0.3-0.7 s wall on the"
                   " loaded machine")
def test_the_smooth_job_never_blocks_the_event_loop(wizard, qtbot):
    _check(_acquire_then_fit(wizard, qtbot, "smooth"))
