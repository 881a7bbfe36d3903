"""What every page shares: the session model, "why can't I go on?", and a job panel."""

from __future__ import annotations

from PySide6.QtCore import QSize, Qt
from PySide6.QtGui import QIcon
from PySide6.QtWidgets import (QFrame, QHBoxLayout, QLabel, QScrollArea, QSizePolicy, QSplitter, QVBoxLayout,
                               QWidget, QWizardPage)

from ..assets import icon_path
from ..session import SessionModel
from ..widgets.jobpanel import JobPanel
from ..widgets.stale import StaleBanner
from ..worker import Job

__all__ = ["SidePanel", "StudioPage", "side_panel"]


class SidePanel(QScrollArea):
    """Controls in a panel that scrolls vertically on its own, never across.

    The page around it keeps its height whatever the controls need (a 1366x768 screen): the
    main view beside it stays whole and in view. Its least width is its content's least width
    (as the content is now: hidden parts do not count) plus the scroll bar, so no control is cut
    at the side; a splitter beside it never makes it narrower.
    """

    def __init__(self, content: QWidget, name: str = "controlsPanel"):
        super().__init__()
        self.setObjectName(name)
        self.setFrameShape(QFrame.NoFrame)
        self.setWidgetResizable(True)
        self.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        self.setWidget(content)
        self.setSizePolicy(QSizePolicy.Preferred, QSizePolicy.Ignored)  # any height: it scrolls

    def minimumSizeHint(self) -> QSize:  # noqa: N802 - Qt API
        bar = self.verticalScrollBar().sizeHint().width()
        return QSize(self.widget().minimumSizeHint().width() + bar + 2, 80)


def side_panel(content: QWidget, name: str = "controlsPanel") -> SidePanel:
    """``content`` in a :class:`SidePanel`."""
    return SidePanel(content, name)


class StudioPage(QWizardPage):
    """A wizard page over the session model.

    Subclasses fill :attr:`body`, implement :meth:`blocker` and call
    :meth:`update_complete` whenever its answer may have changed.

    Class attributes
    ----------------
    key : str
        Short name (file names of the tour, icons).
    heading, subheading : str
    """

    key = "page"
    heading = ""
    subheading = ""

    def __init__(self, model: SessionModel, parent: QWidget | None = None):
        super().__init__(parent)
        self.model = model
        # No QWizard header (title and subtitle: 62 px of a 768 px screen); the step list names the page
        # and its introduction heads the controls (split_body) or the page.
        self.intro = QLabel(f"<b>{self.heading}</b>: {self.subheading}" if self.subheading else self.heading)
        self.intro.setObjectName("hint")
        self.intro.setWordWrap(True)
        outer = QVBoxLayout(self)
        outer.setContentsMargins(4, 4, 4, 4)
        outer.addWidget(StaleBanner(model, self))  # results set aside by an edit: why, and how to get them back
        outer.addWidget(self.intro)
        # The body scrolls when the window is smaller than the page needs (a 1366x768 laptop screen):
        # the page's minimum size never forces the window past the screen.
        self.scroll = QScrollArea(self)
        self.scroll.setObjectName("pageScroll")
        self.scroll.setFrameShape(QFrame.NoFrame)
        self.scroll.setWidgetResizable(True)
        self.body = QWidget()
        self.scroll.setWidget(self.body)
        outer.addWidget(self.scroll, 1)
        self.why = QLabel(self)
        self.why.setObjectName("whyBlocked")
        self.why.setWordWrap(True)
        self.why.setTextInteractionFlags(Qt.TextSelectableByMouse)
        outer.addWidget(self.why)
        self.jobs: JobPanel | None = None
        self.main_view: QWidget | None = None  # the map, plot or pattern the page is for (split_body)
        self.enter_pending = False  # the wizard passed this page without showing it (StudioWizard.go_to)
        self.shown_version: int | None = None  # SessionModel.version this page last showed

    def split_body(self, controls: QWidget, view: QWidget, controls_width: int = 330) -> QSplitter:
        """Lay the body out as controls in a side panel (:func:`side_panel`) and the main view beside it.

        The view takes the rest of the page (MATLAB's Camera Calibrator: one screen, the main view
        largest); the splitter's handle moves the border, and dragging it to the side collapses the
        controls. ``self.main_view`` is the view (the walk measures its share of the window).
        """
        lay = QHBoxLayout(self.body)
        lay.setContentsMargins(0, 0, 0, 0)
        self.layout().removeWidget(self.intro)  # at the top of the controls: the view keeps the page's height
        controls.layout().insertWidget(0, self.intro)
        self.splitter = QSplitter(Qt.Horizontal, self.body)
        self.splitter.setObjectName("pageSplitter")
        self.controls_panel = side_panel(controls)
        self.splitter.addWidget(self.controls_panel)
        self.splitter.addWidget(view)
        self.splitter.setCollapsible(0, True)
        self.splitter.setCollapsible(1, False)
        self.splitter.setStretchFactor(0, 0)
        self.splitter.setStretchFactor(1, 1)
        self._controls_width = controls_width  # the panel's width when the page is first shown
        lay.addWidget(self.splitter)
        self.main_view = view
        return self.splitter

    def showEvent(self, event) -> None:  # noqa: N802 - Qt API
        super().showEvent(event)
        width = getattr(self, "_controls_width", None)
        if width is not None and self.splitter.width() > 0:  # first shown: the panel at its width, the view the rest
            self._controls_width = None
            width = max(width, self.controls_panel.minimumSizeHint().width())
            self.splitter.setSizes([width, max(1, self.splitter.width() - width - self.splitter.handleWidth())])

    @property
    def icon(self) -> QIcon:
        return QIcon(str(icon_path(self.key)))

    def make_job_panel(self) -> JobPanel:
        """The page's job panel; a running job blocks Next."""
        self.jobs = JobPanel(self)
        self.jobs.started.connect(self.update_complete)
        self.jobs.ended.connect(lambda _o: self.update_complete())
        return self.jobs

    def run_job(self, job: Job) -> Job:
        assert self.jobs is not None
        return self.jobs.run(job)

    # ---- "why can't I go on?" ---------------------------------------------
    def blocker(self) -> str | None:
        """None if Next may be pressed, else the reason in words."""
        return None

    def reason(self) -> str | None:
        if self.jobs is not None and self.jobs.busy:
            return f"Wait for '{self.jobs.job.name}' to finish, or cancel it."
        return self.blocker()

    def isComplete(self) -> bool:  # noqa: N802 - Qt API
        return self.reason() is None

    def update_complete(self) -> None:
        r = self.reason()
        if r is None:
            self.why.setText("")
            self.why.hide()
        else:
            button = "Finish" if self._is_last() else "Next"
            self.why.setText(f"{button} is disabled: {r}")
            self.why.show()
        self.setToolTip(r or "")
        self.completeChanged.emit()

    def _is_last(self) -> bool:
        """The wizard's last page: its button is Finish, not Next."""
        wiz = self.wizard()
        ids = wiz.pageIds() if wiz is not None else []
        return bool(ids) and wiz.page(ids[-1]) is self

    def initializePage(self) -> None:  # noqa: N802 - Qt API
        if getattr(self.wizard(), "jumping", False):
            self.enter_pending = True  # run on_enter (and its jobs) only if the page is shown
        else:
            self.enter()
        self.update_complete()

    def enter(self) -> None:
        """The page is being shown: bring it up to date with the dataset, then :meth:`on_enter`."""
        self.enter_pending = False
        self.refresh()
        self.on_enter()

    def refresh(self) -> None:
        """Call :meth:`dataset_changed` if the dataset changed since this page last showed it."""
        if self.shown_version != self.model.version:
            self.shown_version = self.model.version
            self.dataset_changed()

    def dataset_changed(self) -> None:
        """The dataset (rig, source or samples) changed since this page was last shown.

        Recompute or clear everything that depends on it. Called on entering the page
        (and by pages that are visible while it changes).
        """

    def cleanupPage(self) -> None:  # noqa: N802 - Qt API
        # Going Back keeps what this page holds (QWizard would reset fields).
        pass

    def on_enter(self) -> None:
        """Called when the page is shown (going forward)."""
