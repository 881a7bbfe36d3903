"""``ptp-studio --tour OUTDIR``: walk the whole wizard on the simulated rig and screenshot every page.

The tour drives the wizard exactly as a user would (the same buttons, the
same jobs on the same worker pattern) on a small simulated camera so that it
takes seconds, and writes one PNG per page with its real data showing, plus
the exported files under ``OUTDIR/export``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from PySide6.QtCore import QEventLoop, QPoint, QPointF, QSize, Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import QApplication, QWizard

from .session import tour_session
from .wizard import StudioWizard
from .worker import Job

__all__ = ["QtDriver", "run_tour", "settle", "tour_size", "view_point", "wait_job"]


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
        """Replace a line edit's (or spin box's) text: a click into it, select all, type, Tab."""
        self.click(line_edit)
        QTest.keyClick(line_edit, Qt.Key_A, Qt.ControlModifier)
        QTest.keyClicks(line_edit, text)
        QTest.keyClick(line_edit, Qt.Key_Tab)  # leave the field: editingFinished, never Return (the default button)
        settle(50)

    def set_slider(self, slider, value: int) -> None:
        """A click on the slider (it takes the focus), then Home and Right ``value`` times."""
        self.click(slider)
        QTest.keyClick(slider, Qt.Key_Home)
        for _ in range(value):
            QTest.keyClick(slider, Qt.Key_Right)
        settle(50)

    def click_at(self, widget, point: QPoint) -> None:
        """A left click at ``point`` (widget coordinates; a graphics view's viewport for a plot)."""
        QTest.mouseClick(widget, Qt.LeftButton, pos=point)
        settle(50)

    def drag(self, widget, start: QPoint, end: QPoint, steps: int = 8) -> None:
        """Press at ``start``, move to ``end`` in ``steps`` moves, release (widget coordinates)."""
        QTest.mousePress(widget, Qt.LeftButton, pos=start)
        for i in range(1, steps + 1):
            QTest.mouseMove(widget, start + (end - start) * (i / steps))
            settle(10)
        QTest.mouseRelease(widget, Qt.LeftButton, pos=end)
        settle(50)


def view_point(view, x: float, y: float) -> QPoint:
    """Where the data point (x, y) of a pyqtgraph plot ``view`` (a GraphicsView with a ``plot`` or a PlotWidget)
    is drawn, in its viewport's coordinates: where to click or drag."""
    plot = view.plot if hasattr(view, "plot") else view.getPlotItem()
    return view.mapFromScene(plot.vb.mapViewToScene(QPointF(x, y)))


def tour_size() -> QSize:
    """The window's size on this screen (its available geometry); 1366x768 with no screen to measure
    (the offscreen platform's is 800x800)."""
    app = QApplication.instance()
    screen = app.primaryScreen() if app is not None else None
    if screen is None or app.platformName() in ("offscreen", "minimal"):
        return QSize(1366, 768)
    return screen.availableGeometry().size()


def _choose(drv, combo, data=None, index: int | None = None) -> None:
    """Pick a combo box's item (by its data or index) with the driver's clicks and keys; check it took."""
    index = combo.findData(data) if index is None else index
    if combo.currentIndex() != index:
        drv.choose(combo, index)
    if combo.currentIndex() != index:
        raise RuntimeError(f"choosing item {index} of a combo box left it at {combo.currentIndex()} (a missed key?)")


def _tour_phase_maps(wiz, drv, shot) -> None:
    """The Phase maps page: validity with a profile line dragged across, the coordinate and the finest
    wrapped phase; every choice made with the driver's clicks and keys."""
    ph = wiz.page_by_key["phase"]
    if ph.jobs.busy:
        wait_job(ph.jobs.job)
    for combo, data in ((ph.pos_combo, 0), (ph.dir_combo, "x"), (ph.kind_combo, "validity")):
        _choose(drv, combo, data)
        if ph.jobs.busy:
            wait_job(ph.jobs.job)
    h, w = wiz.model.session.rig.camera.shape
    view = ph.view
    port = view.viewport()
    for handle, target in zip(ph.roi.getHandles(), ((0.05 * w, 0.15 * h), (0.95 * w, 0.85 * h))):
        start = view.mapFromScene(handle.mapToScene(handle.boundingRect().center()))
        drv.drag(port, start, view_point(view, *target))
    shot("phase-validity")
    _choose(drv, ph.kind_combo, "coord")
    shot("phase-coordinate")
    _choose(drv, ph.kind_combo, "wrapped")
    _choose(drv, ph.level_combo, index=len(wiz.model.session.rig.fringes.periods_px) - 1)
    shot("phase-wrapped")


def _click_tab(drv, tabs, index: int) -> None:
    """A click on a tab widget's tab ``index``."""
    bar = tabs.tabBar()
    drv.click_at(bar, bar.tabRect(index).center())
    if tabs.currentIndex() != index:
        raise RuntimeError(f"a click on tab '{bar.tabText(index)}' left '{bar.tabText(tabs.currentIndex())}' shown")


def _click_pixel(drv, cal, row: int, col: int) -> None:
    """Select a pixel as a person does: a click on it in the heatmap."""
    view = cal.heatmap.view
    drv.click_at(view.viewport(), view_point(view, col, row))
    if cal.selected is None:
        raise RuntimeError(f"a click on pixel (row {row}, column {col}) selected none")


def _tour_calibrate(wiz, drv, press, shot, smooth: bool) -> None:
    """The Calibrate page: a poly fit (RMS and LOO maps, a pixel selected), then the smooth one."""
    cal = wiz.page_by_key["calibrate"]
    drv.choose(cal.model_combo, cal.model_combo.findData("poly"))
    wait_job(press(cal.fit_button))
    rows, cols = (wiz.model.session.lut.valid).nonzero()
    h, w = wiz.model.session.lut.valid.shape  # a valid pixel inside the map (an edge one was half drawn)
    i = int(np.argmin((rows - 0.4 * h) ** 2 + (cols - 0.4 * w) ** 2)) if rows.size else 0
    drv.click(cal.map_buttons.button(cal._map_keys.index("rms_x")))
    if rows.size:
        _click_pixel(drv, cal, int(rows[i]), int(cols[i]))
    shot("calibrate")
    drv.click(cal.map_buttons.button(cal._map_keys.index("loo_y")))
    shot("calibrate-loo")
    if smooth:  # the smooth LUT, with its predicted uncertainty map
        _choose(drv, cal.model_combo, "smooth")
        drv.type_text(cal.degree, "2")
        if cal.degree.value() != 2:
            raise RuntimeError(f"typing 2 into the degree left it at {cal.degree.value()}")
        wait_job(press(cal.fit_button))
        drv.click(cal.map_buttons.button(cal._map_keys.index("sigma_x")))
        if rows.size:
            _click_pixel(drv, cal, int(rows[i]), int(cols[i]))
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

    fr = p["fringes"]  # the preview at period 1, step 1, the middle position, with clicks and keys
    _choose(drv, fr.s_dir, index=fr.s_dir.findText("x"))
    for slider, value in ((fr.s_level, 1), (fr.s_step, 1), (fr.s_pos, positions // 2)):
        drv.set_slider(slider, value)
        if slider.value() != value:
            raise RuntimeError(f"the slider went to {slider.value()}, not {value} (a missed key?)")
    shot("fringes")
    next_page()

    shot("acquire-before")  # Next disabled, with its reason
    wait_job(press(p["acquire"].start_button))
    shot("acquire")
    next_page()

    _tour_phase_maps(wiz, drv, shot)
    next_page()
    _tour_calibrate(wiz, drv, press, shot, smooth)
    next_page()

    cmp_page = p["compare"]
    wait_job(press(cmp_page.run_button))
    shot("compare")
    _click_tab(drv, cmp_page.result_tabs, 1)
    shot("compare-table")
    _click_tab(drv, cmp_page.result_tabs, 0)
    next_page()

    ex = p["export"]
    drv.type_text(ex.folder, str(out / "export"))
    wait_job(press(ex.export_button))
    shot("export")
    panel = ex.cloud_panel  # the LUT applied at its default height (the middle of its range)
    drv.click(panel.apply_button)
    wait_job(panel.jobs.job)
    shot("export-cloud")
    _click_tab(drv, ex.view_tabs, 1)
    shot("export-trust")
    if wiz.next_blocker():
        raise RuntimeError(f"Finish is disabled: {wiz.next_blocker()}")
    log(f"done in {time.monotonic() - t0:.1f} s: {len(shots)} screenshots, exported files in {out / 'export'}")
    wiz.closing = True  # a scripted walk: nothing to ask before closing
    wiz.close()
    wiz.deleteLater()
    settle(50)
    return shots
