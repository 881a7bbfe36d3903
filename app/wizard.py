"""The wizard window: seven pages over one session model, with a step list at the side."""

from __future__ import annotations

import pyqtgraph as pg
from PySide6.QtCore import QSize, Qt
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
from .worker import wait_for_jobs

__all__ = ["StudioWizard", "configure_app", "PAGE_CLASSES"]

PAGE_CLASSES = (RigPage, FringesPage, AcquirePage, PhaseMapsPage, CalibratePage, ComparePage, ExportPage)


def configure_app(app: QApplication) -> None:
    """Application-wide look: stylesheet, icon, pyqtgraph defaults."""
    pg.setConfigOptions(imageAxisOrder="row-major", background="w", foreground="#30363d", antialias=True)
    app.setApplicationName("PTP Studio")
    app.setApplicationVersion(__version__)
    app.setWindowIcon(QIcon(str(icon_path("app"))))
    app.setStyle("Fusion")
    app.setStyleSheet(stylesheet())


class StepList(QListWidget):
    """The steps at the wizard's side; the current one highlighted, later ones greyed."""

    def __init__(self, pages, parent=None):
        super().__init__(parent)
        self.setObjectName("stepList")
        self.setIconSize(QSize(22, 22))
        self.setFocusPolicy(Qt.NoFocus)
        self.setSelectionMode(QListWidget.NoSelection)
        for i, page in enumerate(pages):
            item = QListWidgetItem(page.icon, f"{i + 1}  {page.heading}")
            item.setSizeHint(QSize(170, 38))
            self.addItem(item)
        self.setFixedWidth(190)

    def set_current(self, index: int) -> None:
        for i in range(self.count()):
            item = self.item(i)
            font = item.font()
            font.setBold(i == index)
            item.setFont(font)
            item.setForeground(Qt.black if i <= index else Qt.gray)
            item.setBackground(Qt.transparent if i != index else pg.mkColor("#dbe8f6"))


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
        self.currentIdChanged.connect(self._page_changed)
        self.resize(1500, 950)
        self._page_changed(self.currentId())

    def page_index(self) -> int:
        page = self.currentPage()
        return self.pages.index(page) if page in self.pages else 0

    def _page_changed(self, _id: int) -> None:
        page = self.currentPage()
        if not self.jumping and getattr(page, "enter_pending", False):
            page.enter_pending = False
            page.on_enter()
            page.update_complete()
        self.steps.set_current(self.page_index())
        self._update_buttons()

    # ---- session files -------------------------------------------------------------
    def open_session(self, path):
        """Open a session file (as the Rig page's Open session… does); the Job, or None if refused."""
        return self.page_by_key["rig"].open_session(path)

    def _session_opened(self, opened: OpenedSession) -> None:
        self.autosave.set_path(None)  # restoring is not a completed stage: nothing to save
        self.model.restore(opened.session)
        s = opened.session
        half = list(range(0, s.rig.stage.n_positions, 2))
        self.page_by_key["calibrate"].configure(opened.model, opened.degree,
                                                "half" if s.lut_positions == half else "all",
                                                opened.stage_sigma_um, opened.level_bias, opened.footprint)
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
        page = self.currentPage()
        reason = page.reason() if page is not None else None
        for which in (QWizard.NextButton, QWizard.FinishButton):
            self.button(which).setToolTip(f"Disabled: {reason}" if reason else "")

    def next_blocker(self) -> str | None:
        """Why Next (or Finish) is disabled on the current page, or None."""
        page = self.currentPage()
        return page.reason() if page is not None else None

    def done(self, result: int) -> None:  # noqa: D401 - Qt API
        wait_for_jobs()
        super().done(result)

    def closeEvent(self, event) -> None:  # noqa: N802 - Qt API
        wait_for_jobs()
        super().closeEvent(event)
