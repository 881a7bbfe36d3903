"""GUI tests: headless (offscreen), Qt warnings fail, leaked top-level widgets fail."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import pytest  # noqa: E402

pytest.importorskip("PySide6")
pytest.importorskip("pyqtgraph")
pytest.importorskip("pytestqt")

from pathlib import Path  # noqa: E402

_HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config, items):
    for item in items:
        if _HERE in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.qt_log_level_fail("WARNING"))
            # The offscreen platform says this about every window; it is not ours.
            item.add_marker(pytest.mark.qt_log_ignore("propagateSizeHints"))


@pytest.fixture(scope="session")
def qapp_cls():
    from PySide6.QtWidgets import QApplication

    import ptp_studio  # noqa: F401 - applies the binding work-arounds first

    return QApplication


@pytest.fixture(scope="session", autouse=True)
def _configured(qapp):
    from ptp_studio.wizard import configure_app

    configure_app(qapp)
    yield


@pytest.fixture(autouse=True)
def no_leaks(qtbot, qapp):
    """Fail a test that leaves a top-level widget or a running job behind."""
    from PySide6.QtCore import QEvent
    from PySide6.QtWidgets import QApplication

    from ptp_studio.worker import ACTIVE_JOBS, wait_for_jobs

    before = set(QApplication.topLevelWidgets())
    yield
    running = [j.name for j in ACTIVE_JOBS]
    assert wait_for_jobs(30000)
    for _ in range(3):
        qapp.processEvents()
        QApplication.sendPostedEvents(None, QEvent.DeferredDelete)
    leaked = [w for w in QApplication.topLevelWidgets()
              if w not in before and w.parentWidget() is None and w.isVisible()]
    assert not running, f"jobs still running after the test: {running}"
    assert not leaked, f"leaked top-level widgets: {[type(w).__name__ for w in leaked]}"


class Questions:
    """Stands in for QMessageBox.question: records every question and gives ``answer`` (True: Yes)."""

    def __init__(self):
        self.asked: list[str] = []
        self.answer = True

    def __call__(self, parent, title, text, *args, **kwargs):
        from PySide6.QtWidgets import QMessageBox

        self.asked.append(f"{title}: {text}")
        return QMessageBox.Yes if self.answer else QMessageBox.No


@pytest.fixture(autouse=True)
def questions(monkeypatch):
    """No modal question ever blocks a test: answered Yes unless a test sets ``questions.answer``.

    Autouse, so the window closed at the end of a test (by pytest-qt) is answered too.
    """
    from PySide6.QtWidgets import QMessageBox

    q = Questions()
    monkeypatch.setattr(QMessageBox, "question", q)
    return q


@pytest.fixture(scope="session")
def small_session_args():
    """A 160x120 simulated camera, 9 positions, looking at the LCD's corner."""
    return dict(width=160, height=120, positions=9, view_offset_mm=(85.0, 45.0))


@pytest.fixture
def wizard(qtbot, small_session_args):
    from ptp_studio.session import tour_session
    from ptp_studio.wizard import StudioWizard

    wiz = StudioWizard(tour_session(**small_session_args))
    qtbot.addWidget(wiz)
    wiz.resize(1300, 850)
    wiz.show()
    qtbot.waitExposed(wiz)
    return wiz
