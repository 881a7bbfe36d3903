"""The wizard window: seven pages over one session model, with a step list at the side."""

from __future__ import annotations

import pyqtgraph as pg
from PySide6.QtCore import QSize, Qt, Signal
from PySide6.QtGui import QFont, QIcon
from PySide6.QtWidgets import QApplication, QLabel, QListWidget, QListWidgetItem, QVBoxLayout, QWidget, QWizard

from . import __version__
from .assets import icon_path, stylesheet
from .pages.acquire import AcquirePage
from .pages.calibrate import CalibratePage
from .pages.compare import ComparePage
from .pages.export import ExportPage
from .pages.fringes import FringesPage
from .pages.phasemaps import PhaseMapsPage
from .pages.rig import RigPage
from .session import Session, SessionModel
from .sessionfile import Autosave, OpenedSession
from .wheel import install as install_wheel_guard
from .widgets.confirm import confirm
from .worker import ACTIVE_JOBS, wait_for_jobs

__all__ = ["StudioWizard", "configure_app", "freeze_startup_objects", "PAGE_CLASSES"]

PAGE_CLASSES = (RigPage, FringesPage, AcquirePage, PhaseMapsPage, CalibratePage, ComparePage, ExportPage)


def freeze_startup_objects() -> int:
    """Keep the objects alive at start-up (modules, classes, Qt wrappers: about 120 000) out of the
    cyclic garbage collector's full passes; how many were frozen.

    A full pass holds the GIL over every tracked object: 100-150 ms with PySide6, pyqtgraph, scipy and
    numba loaded, twice during a 5 MP Acquire job (the event loop's worst stall, issue 15); with them
    frozen, 60 ms on a loaded machine. They live as long as the process anyway; the garbage already
    there is collected first. For the application's start (``ptp-studio``), not for tests that build
    many wizards in one process.
    """
    import gc

    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def configure_app(app: QApplication) -> None:
    """Application-wide look: stylesheet, icon, pyqtgraph defaults."""
    pg.setConfigOptions(imageAxisOrder="row-major", background="w", foreground="#30363d", antialias=True)
    app.setApplicationName("PTP Studio")
    app.setApplicationVersion(__version__)
    app.setWindowIcon(QIcon(str(icon_path("app"))))
    install_wheel_guard(app, "Fusion")  # the style: Fusion; the wheel turns only a focused field
    app.setStyleSheet(stylesheet())


class StepList(QListWidget):
    """The steps at the wizard's side: the current one highlighted, the reachable ones clickable.

    Signals
    -------
    stepClicked(int)
        A reachable step (not the current one) was clicked.
    """

    stepClicked = Signal(int)

    def __init__(self, pages, parent=None):
        super().__init__(parent)
        self.setObjectName("stepList")
        self.setIconSize(QSize(22, 22))
        self.setFocusPolicy(Qt.NoFocus)
        self.setSelectionMode(QListWidget.NoSelection)
        self.setMouseTracking(True)
        for i, page in enumerate(pages):
            item = QListWidgetItem(page.icon, f"{i + 1}  {page.heading}")
            item.setSizeHint(QSize(140, 34))
            self.addItem(item)
        self.setFixedWidth(164)  # narrow: the pages' views take the width (a 1366x768 screen)
        self.reachable: set[int] = set()
        self.itemClicked.connect(self._clicked)

    def set_current(self, index: int, reachable=()) -> None:
        """Highlight step ``index``; ``reachable``: the other steps a click may go to."""
        self.reachable = set(reachable) - {index}
        for i in range(self.count()):
            item = self.item(i)
            font = item.font()
            font.setBold(i == index)
            item.setFont(font)
            item.setForeground(Qt.black if i == index or i in self.reachable else Qt.gray)
            item.setBackground(Qt.transparent if i != index else pg.mkColor("#dbe8f6"))
            name = item.text().split(maxsplit=1)[-1]
            item.setToolTip("" if i == index else f"Go to {name}" if i in self.reachable else
                            f"{name}: not reached yet (complete the steps before it)")

    def _clicked(self, item: QListWidgetItem) -> None:
        i = self.row(item)
        if i in self.reachable:
            self.stepClicked.emit(i)

    def mouseMoveEvent(self, event) -> None:  # noqa: N802 - Qt API
        item = self.itemAt(event.position().toPoint())
        self.viewport().setCursor(Qt.PointingHandCursor if item is not None and self.row(item) in self.reachable
                                  else Qt.ArrowCursor)
        super().mouseMoveEvent(event)


class StudioWizard(QWizard):
    """PTP Studio.

    Parameters
    ----------
    session : Session, optional
        Default: the simulated ``realistic`` rig.
    """

    def __init__(self, session: Session | None = None, parent: QWidget | None = None):
        super().__init__(parent)
        self.setWindowTitle("PTP Studio — point-to-point camera calibration")
        self.setWindowIcon(QIcon(str(icon_path("app"))))
        self.setWizardStyle(QWizard.ModernStyle)
        self.setOption(QWizard.NoBackButtonOnStartPage, True)
        self.setOption(QWizard.NoCancelButton, False)
        self.model = SessionModel(session or Session.from_preset("realistic"), self)
        self.pages = [cls(self.model) for cls in PAGE_CLASSES]
        for page in self.pages:
            self.addPage(page)
            page.completeChanged.connect(self._update_buttons)
        self.page_by_key = {p.key: p for p in self.pages}
        export = self.page_by_key["export"]
        export.compare_page = self.page_by_key["compare"]
        export.calibrate_page = self.page_by_key["calibrate"]
        self.page_by_key["compare"].calibrate_page = self.page_by_key["calibrate"]
        self.jumping = False  # go_to() passing pages on its way: their on_enter waits until they are shown
        cal = self.page_by_key["calibrate"]
        self.autosave = Autosave(self.model, cal.fit_settings, self)
        self.page_by_key["rig"].sessionOpened.connect(self._session_opened)
        export.sessionWritten.connect(lambda path: self.autosave.set_path(path, just_saved=True))

        # Keep a reference: PySide does not take ownership in setSideWidget.
        self._side = side = QWidget(self)
        sl = QVBoxLayout(side)
        sl.setContentsMargins(6, 6, 6, 6)
        logo = QLabel("PTP Studio")
        f = QFont()
        f.setPointSize(13)
        f.setBold(True)
        logo.setFont(f)
        logo.setObjectName("logo")
        sl.addWidget(logo)
        self.steps = StepList(self.pages)
        sl.addWidget(self.steps, 1)
        self.session_status = QLabel("")
        self.session_status.setObjectName("hint")
        self.session_status.setWordWrap(True)
        self.autosave.status.connect(self._show_session_status)
        sl.addWidget(self.session_status)
        ver = QLabel(f"version {__version__}")
        ver.setObjectName("hint")
        sl.addWidget(ver)
        self.setSideWidget(side)
        self.steps.stepClicked.connect(self.jump_to)
        self.reached = 0  # the furthest step shown so far
        self.closing = False
        self.currentIdChanged.connect(self._page_changed)
        self.resize(self.initial_size())
        self._page_changed(self.currentId())

    def initial_size(self) -> QSize:
        """1500x950, or less on a smaller screen (the window's frame stays on the screen)."""
        screen = self.screen() or QApplication.primaryScreen()
        want = QSize(1500, 950)
        if screen is None:
            return want
        avail = screen.availableGeometry().size()
        # Leave room for the title bar and frame the window manager adds.
        return QSize(min(want.width(), avail.width() - 16), min(want.height(), avail.height() - 40))

    def page_index(self) -> int:
        page = self.currentPage()
        return self.pages.index(page) if page in self.pages else 0

    def _page_changed(self, _id: int) -> None:
        page = self.currentPage()
        if not self.jumping and page is not None:
            if page.enter_pending:
                page.enter()  # passed by go_to() and shown now: on_enter runs here
            else:
                page.refresh()  # e.g. reached with Back after the dataset changed
            page.update_complete()
        index = self.page_index()
        self.reached = max(self.reached, index)
        self.steps.set_current(index, self.reachable_steps())
        self._update_buttons()

    # ---- the step list --------------------------------------------------------------
    def reachable_steps(self) -> list[int]:
        """Steps a click in the side list may go to.

        Back to any earlier step; forward only to a step shown before, and only while every
        page on the way would let Next pass (their results are still there).
        """
        here = self.page_index()
        out = list(range(here + 1))
        if self.jumping or any(p.jobs is not None and p.jobs.busy for p in self.pages):
            return [here]  # no jumping while a job runs
        for i in range(here, self.reached):
            if not self.pages[i].isComplete():
                break
            out.append(i + 1)
        return out

    def jump_to(self, index: int) -> bool:
        """Go to step ``index`` (0-based) as Back or Next would; False if it is not reachable."""
        here = self.page_index()
        if index == here or index not in self.reachable_steps():
            return False
        if index < here:
            while self.page_index() > index:
                self.back()
            return True
        self.jumping = True  # pages passed on the way run on_enter only if shown
        try:
            while self.page_index() < index and self.currentPage().isComplete():
                self.next()
        finally:
            self.jumping = False
        self._page_changed(self.currentId())
        return self.page_index() == index

    # ---- session files -------------------------------------------------------------
    def open_session(self, path):
        """Open a session file (as the Rig page's Open session… does); the Job, or None if refused."""
        return self.page_by_key["rig"].open_session(path)

    def _session_opened(self, opened: OpenedSession) -> None:
        self.autosave.set_path(None)  # restoring is not a completed stage: nothing to save
        self.model.restore(opened.session)
        s = opened.session
        half = list(range(0, s.rig.stage.n_positions, 2))
        self.page_by_key["calibrate"].configure(opened.settings, positions="half" if s.lut_positions == half else "all",
                                                fitted=True)
        self.autosave.set_path(opened.path)
        self.go_to(opened.page)

    def _show_session_status(self, text: str) -> None:
        self.session_status.setText(text)
        self.session_status.setToolTip(str(self.autosave.path or ""))

    def go_to(self, key: str) -> None:
        """Land on page ``key``, passing every page before it as Next would (stops at one that blocks)."""
        target = self.pages.index(self.page_by_key[key])
        self.jumping = True
        try:
            self.restart()
            while self.page_index() < target and self.currentPage().isComplete():
                self.next()
        finally:
            self.jumping = False
        self._page_changed(self.currentId())

    def _update_buttons(self) -> None:
        self.steps.set_current(self.page_index(), self.reachable_steps())  # a page's state changed
        page = self.currentPage()
        reason = page.reason() if page is not None else None
        for which in (QWizard.NextButton, QWizard.FinishButton):
            self.button(which).setToolTip(f"Disabled: {reason}" if reason else "")

    def next_blocker(self) -> str | None:
        """Why Next (or Finish) is disabled on the current page, or None."""
        page = self.currentPage()
        return page.reason() if page is not None else None

    # ---- leaving ---------------------------------------------------------------------
    def running_jobs(self) -> list[str]:
        """Names of the jobs running now (pages' and the autosave's)."""
        return [j.name for j in list(ACTIVE_JOBS) if j.running]

    def confirm_quit(self) -> bool:
        """Ask before closing when a job runs or results are not saved; True: close."""
        jobs = self.running_jobs()
        unsaved = self.model.unsaved_work
        if not jobs and not unsaved:
            return True
        lines = []
        if jobs:
            lines.append(f"Running: {', '.join(dict.fromkeys(jobs))}. Quitting cancels it and waits until it has"
                         " stopped (files are written whole or not at all).")
        if unsaved:
            lines.append(f"{self.model.describe_results().capitalize()} of this session are not saved in a"
                         " session file (Export writes one).")
        return confirm(self, "Quit PTP Studio?", " ".join(lines), "Quit anyway?")

    def stop_jobs(self) -> bool:
        """Cancel every running job and wait until they have ended (their handlers ran)."""
        ok = wait_for_jobs()
        QApplication.processEvents()  # deliver the jobs' end signals while the pages still exist
        return ok

    def reject(self) -> None:  # noqa: D401 - Qt API (Cancel, Escape, and the window's close button)
        if not self.closing and not self.confirm_quit():
            return
        self.closing = True
        self.stop_jobs()
        super().reject()

    def done(self, result: int) -> None:  # noqa: D401 - Qt API
        self.stop_jobs()
        super().done(result)

    def keyPressEvent(self, event) -> None:  # noqa: N802 - Qt API
        # QDialog presses its default button (Next, or Finish on the last page) on a Return or Enter
        # that the focused widget leaves unused: a line edit's, a spin box's, a combo box's. Return in
        # the Export page's reference-LUT field finished the wizard. A focused button still takes its
        # own Return (QPushButton handles it before this).
        if event.key() in (Qt.Key_Return, Qt.Key_Enter):
            event.accept()
            return
        super().keyPressEvent(event)

    def closeEvent(self, event) -> None:  # noqa: N802 - Qt API
        if self.closing or not self.isVisible():
            self.stop_jobs()
            event.accept()
            return
        if not self.confirm_quit():
            event.ignore()
            return
        self.closing = True
        self.stop_jobs()
        super().closeEvent(event)
