"""``ptp-studio --tour OUTDIR``: walk the whole wizard on the simulated rig and screenshot every page.

The tour drives the wizard exactly as a user would (the same buttons, the
same jobs on the same worker pattern) on a small simulated camera so that it
takes seconds, and writes one PNG per page with its real data showing, plus
the exported files under ``OUTDIR/export``.
"""

from __future__ import annotations

import time
from pathlib import Path

from PySide6.QtCore import QEventLoop, QSize, Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QApplication, QWizard

from .session import tour_session
from .wizard import StudioWizard
from .worker import Job

__all__ = ["QtDriver", "run_tour", "tour_size", "wait_job", "settle"]


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


class QtDriver:
    """Presses the wizard's buttons as a person does: mouse clicks and keys as Qt events to the widget
    under them (:mod:`QTest`). ``benchmarks.gui_walk`` sends real X events instead (xdotool)."""

    def click(self, widget) -> None:
        """A left click at the middle of ``widget``."""
        QTest.mouseClick(widget, Qt.LeftButton, pos=widget.rect().center())
        settle(50)

    def choose(self, combo, index: int) -> None:
        """Pick item ``index`` of a combo box with the keyboard (focus, Home, Down ``index`` times)."""
        combo.setFocus(Qt.OtherFocusReason)
        QTest.keyClick(combo, Qt.Key_Home)
        for _ in range(index):
            QTest.keyClick(combo, Qt.Key_Down)
        settle(50)

    def type_text(self, line_edit, text: str) -> None:
        """Replace a line edit's text by typing (select all, type, Return)."""
        line_edit.setFocus(Qt.OtherFocusReason)
        QTest.keyClick(line_edit, Qt.Key_A, Qt.ControlModifier)
        QTest.keyClicks(line_edit, text)
        QTest.keyClick(line_edit, Qt.Key_Tab)  # leave the field: editingFinished, never Return (the default button)
        settle(50)


def tour_size() -> QSize:
    """The window's size on this screen (its available geometry); 1366x768 with no screen to measure
    (the offscreen platform's is 800x800)."""
    app = QApplication.instance()
    screen = app.primaryScreen() if app is not None else None
    if screen is None or app.platformName() in ("offscreen", "minimal"):
        return QSize(1366, 768)
    return screen.availableGeometry().size()


def _tour_phase_maps(wiz, shot) -> None:
    """The Phase maps page: validity with a profile line, the coordinate and the finest wrapped phase."""
    ph = wiz.page_by_key["phase"]
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


def _tour_calibrate(wiz, drv, press, shot, smooth: bool) -> None:
    """The Calibrate page: a poly fit (RMS and LOO maps, a pixel selected), then the smooth one."""
    cal = wiz.page_by_key["calibrate"]
    drv.choose(cal.model_combo, cal.model_combo.findData("poly"))
    wait_job(press(cal.fit_button))
    rows, cols = (wiz.model.session.lut.valid).nonzero()
    i = rows.size // 3
    if rows.size:
        cal.select_pixel(int(rows[i]), int(cols[i]))
    drv.click(cal.map_buttons.button(cal._map_keys.index("rms_x")))
    shot("calibrate")
    drv.click(cal.map_buttons.button(cal._map_keys.index("loo_y")))
    shot("calibrate-loo")
    if smooth:  # the smooth LUT, with its predicted uncertainty map
        drv.choose(cal.model_combo, cal.model_combo.findData("smooth"))
        cal.degree.setValue(2)
        wait_job(press(cal.fit_button))
        if rows.size:
            cal.select_pixel(int(rows[i]), int(cols[i]))
        drv.click(cal.map_buttons.button(cal._map_keys.index("sigma_x")))
        shot("calibrate-smooth-sigma")


def run_tour(outdir, width: int = 320, height: int = 240, positions: int = 11, log=print, driver=None,
             size: QSize | None = None, on_page=None, smooth: bool = True) -> list[Path]:
    """Walk every page with clicks and keys; returns the PNGs written.

    Parameters
    ----------
    outdir : folder of the screenshots (and ``export/``)
    width, height, positions : the simulated camera and the stage positions
    driver : QtDriver, optional
        How buttons are pressed (default: Qt events, :class:`QtDriver`).
    size : QSize, optional
        The window's size; default :func:`tour_size` (the screen's).
    on_page : callable (name, wizard) -> None, optional
        Called at each screenshot (``benchmarks.gui_walk`` checks the layout there).
    smooth : bool
        Also fit the smooth LUT on the Calibrate page (a slower fit).

    Raises
    ------
    RuntimeError
        If a page cannot go on (its reason is in the message) or a job fails.
    """
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    drv = driver or QtDriver()
    wiz = StudioWizard(tour_session(width, height, positions))
    size = size or tour_size()
    wiz.resize(size)
    wiz.show()
    settle(300)
    shots: list[Path] = []

    def shot(name: str) -> None:
        settle(300)
        path = out / f"{len(shots) + 1:02d}-{name}.png"
        if not wiz.grab().save(str(path), "PNG"):
            raise OSError(f"{path}: could not write the screenshot")
        shots.append(path)
        log(f"  {path}")
        if on_page is not None:
            on_page(name, wiz)

    def next_page() -> None:
        reason = wiz.next_blocker()
        if reason:
            raise RuntimeError(f"page '{wiz.currentPage().heading}' cannot go on: {reason}")
        drv.click(wiz.button(QWizard.NextButton))
        settle(150)

    def press(button):
        """Click a page's button that starts a job; the job."""
        page = wiz.currentPage()
        before = page.jobs.job
        drv.click(button)
        if page.jobs.job is before:
            raise RuntimeError(f"'{button.text()}' on page '{page.heading}' started no job (the click missed?)")
        return page.jobs.job

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
    wait_job(press(p["acquire"].start_button))
    shot("acquire")
    next_page()

    _tour_phase_maps(wiz, shot)
    next_page()
    _tour_calibrate(wiz, drv, press, shot, smooth)
    next_page()

    wait_job(press(p["compare"].run_button))
    shot("compare")
    next_page()

    ex = p["export"]
    drv.type_text(ex.folder, str(out / "export"))
    wait_job(press(ex.export_button))
    shot("export")
    if wiz.next_blocker():
        raise RuntimeError(f"Finish is disabled: {wiz.next_blocker()}")
    log(f"done in {time.monotonic() - t0:.1f} s: {len(shots)} screenshots, exported files in {out / 'export'}")
    wiz.closing = True  # a scripted walk: nothing to ask before closing
    wiz.close()
    wiz.deleteLater()
    settle(50)
    return shots
