"""``ptp-studio --tour OUTDIR``: walk the whole wizard on the simulated rig and screenshot every page.

The tour drives the wizard exactly as a user would (the same buttons, the
same jobs on the same worker pattern) on a small simulated camera so that it
takes seconds, and writes one PNG per page with its real data showing, plus
the exported files under ``OUTDIR/export``.
"""

from __future__ import annotations

import time
from pathlib import Path

from PySide6.QtCore import QEventLoop
from PySide6.QtWidgets import QApplication

from .session import tour_session
from .wizard import StudioWizard
from .worker import Job

__all__ = ["run_tour", "wait_job", "settle"]


def settle(ms: int = 50) -> None:
    """Let queued signals and repaints run."""
    app = QApplication.instance()
    end = time.monotonic() + ms / 1000
    while True:
        app.processEvents(QEventLoop.AllEvents, 20)
        if time.monotonic() >= end:
            break
        time.sleep(0.005)


def wait_job(job: Job | None, timeout: float = 300.0) -> str:
    """Process events until ``job`` has ended; its outcome."""
    if job is None:
        raise RuntimeError("the job did not start (see the page's message)")
    app = QApplication.instance()
    end = time.monotonic() + timeout
    while job.running or job.outcome is None:
        app.processEvents(QEventLoop.AllEvents, 50)
        time.sleep(0.005)
        if time.monotonic() > end:
            job.cancel()
            raise TimeoutError(f"job '{job.name}' took longer than {timeout:g} s")
    settle(100)
    if job.outcome == "errored":
        raise RuntimeError(f"job '{job.name}' failed: {job.error}")
    return job.outcome


def run_tour(outdir, width: int = 320, height: int = 240, positions: int = 11, log=print) -> list[Path]:
    """Walk every page; returns the PNGs written.

    Raises
    ------
    RuntimeError
        If a page cannot go on (its reason is in the message) or a job fails.
    """
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    wiz = StudioWizard(tour_session(width, height, positions))
    wiz.resize(1366, 768)  # a laptop screen, whatever screen the tour runs on (offscreen: 800x800)
    wiz.show()
    settle(200)
    shots: list[Path] = []

    def shot(name: str) -> None:
        settle(150)
        path = out / f"{len(shots) + 1:02d}-{name}.png"
        if not wiz.grab().save(str(path), "PNG"):
            raise OSError(f"{path}: could not write the screenshot")
        shots.append(path)
        log(f"  {path}")

    def next_page() -> None:
        reason = wiz.next_blocker()
        if reason:
            raise RuntimeError(f"page '{wiz.currentPage().heading}' cannot go on: {reason}")
        wiz.next()
        settle(100)

    t0 = time.monotonic()
    log(f"PTP Studio tour: simulated '{wiz.model.session.preset_name}' rig, camera {width}x{height},"
        f" {positions} positions -> {out}")
    p = wiz.page_by_key
    shot("rig")
    next_page()

    p["fringes"].scrub("x", 1, 1, positions // 2)
    shot("fringes")
    next_page()

    shot("acquire-before")  # Next disabled, with its reason
    wait_job(p["acquire"].start())
    shot("acquire")
    next_page()

    ph = p["phase"]
    ph.select(position=0, direction="x", kind="validity")
    if ph.jobs.busy:
        wait_job(ph.jobs.job)
    h, w = wiz.model.session.rig.camera.shape
    ph.set_line((0.05 * w, 0.15 * h), (0.95 * w, 0.85 * h))
    shot("phase-validity")
    ph.select(kind="coord")
    shot("phase-coordinate")
    ph.select(kind="wrapped", level=len(wiz.model.session.rig.fringes.periods_px) - 1)
    shot("phase-wrapped")
    next_page()

    cal = p["calibrate"]
    cal.configure("poly", 3, "all")
    wait_job(cal.fit())
    rows, cols = (wiz.model.session.lut.valid).nonzero()
    if rows.size:
        i = rows.size // 3
        cal.select_pixel(int(rows[i]), int(cols[i]))
    cal.show_map("rms_x")
    shot("calibrate")
    cal.show_map("loo_y")
    shot("calibrate-loo")
    cal.configure("smooth", 2, "all")  # the smooth LUT, with its predicted uncertainty map
    wait_job(cal.fit())
    if rows.size:
        cal.select_pixel(int(rows[i]), int(cols[i]))
    cal.show_map("sigma_x")
    shot("calibrate-smooth-sigma")
    next_page()

    wait_job(p["compare"].run())
    shot("compare")
    next_page()

    ex = p["export"]
    ex.set_folder(out / "export")
    wait_job(ex.export())
    shot("export")
    if wiz.next_blocker():
        raise RuntimeError(f"Finish is disabled: {wiz.next_blocker()}")
    log(f"done in {time.monotonic() - t0:.1f} s: {len(shots)} screenshots, exported files in {out / 'export'}")
    wiz.closing = True  # a scripted walk: nothing to ask before closing
    wiz.close()
    wiz.deleteLater()
    settle(50)
    return shots
