"""The worker pattern: progress on the GUI thread, errors reach a message, cancel leaves no partial file."""

from __future__ import annotations

import time

import pytest
from gui_helpers import run_job
from PySide6.QtCore import QThread
from PySide6.QtWidgets import QApplication, QWizard

from ptpcore.errors import DatasetError
from ptp_studio.widgets.jobpanel import JobPanel
from ptp_studio.worker import Job


def test_signals_arrive_on_the_gui_thread(qtbot):
    seen = []

    def work(ctx):
        seen.append(("worker", QThread.currentThread() is QApplication.instance().thread()))
        for i in range(5):
            ctx.progress(i / 5, f"step {i}")
            ctx.emit(i)
            time.sleep(0.04)
        return 42

    job = Job(work, "test")
    on_gui = []
    job.progress.connect(lambda f, m: on_gui.append(QThread.currentThread() is QApplication.instance().thread()))
    job.partial.connect(lambda x: on_gui.append(QThread.currentThread() is QApplication.instance().thread()))
    with qtbot.waitSignal(job.finished, timeout=10000) as blocker:
        job.start()
    assert blocker.args == [42]
    assert seen == [("worker", False)]
    assert on_gui and all(on_gui)


@pytest.mark.parametrize("exc, expect", [
    (DatasetError("z000/x_T16_n00.png: image file is empty (0 bytes)"), "z000/x_T16_n00.png: image file is empty"),
    (ZeroDivisionError("division by zero"), "ZeroDivisionError: division by zero"),
])
def test_worker_errors_reach_a_message(qtbot, exc, expect, caplog):
    panel = JobPanel()
    qtbot.addWidget(panel)
    panel.show()

    def work(ctx):
        ctx.progress(0.5, "half way")
        raise exc

    job = Job(work, "failing job")
    with qtbot.waitSignal(job.errored, timeout=10000) as blocker:
        panel.run(job)
    assert expect in blocker.args[0]
    qtbot.waitUntil(lambda: panel.error.isVisible())
    assert expect in panel.error.text()
    assert "failed" in panel.message.text()
    assert not panel.busy


def test_cancel_stops_at_the_next_progress_report(qtbot):
    steps = []

    def work(ctx):
        for i in range(10_000):
            ctx.progress(i / 10_000, "")
            steps.append(i)
            time.sleep(0.001)
        return "should not finish"

    panel = JobPanel()
    qtbot.addWidget(panel)
    job = Job(work, "long job")
    panel.run(job)
    qtbot.waitUntil(lambda: len(steps) > 5, timeout=5000)
    with qtbot.waitSignal(job.cancelled, timeout=10000):
        panel.cancel_button.click()
    assert job.outcome == "cancelled" and len(steps) < 10_000
    assert "cancelled" in panel.message.text()


def test_cancelled_acquisition_leaves_no_partial_file(wizard, qtbot, tmp_path):
    """Cancel while the simulated images are being written: no half-written file, no rig.toml."""
    wiz = wizard
    wiz.next()
    wiz.next()
    acq = wiz.page_by_key["acquire"]
    out = tmp_path / "dataset"
    acq.write_edit.setText(str(out))
    acq.write_check.setChecked(True)
    job = acq.start()
    qtbot.waitUntil(lambda: out.exists() and any(out.rglob("*.png")), timeout=30000)
    acq.jobs.cancel_button.click()
    assert run_job(qtbot, job) == "cancelled"
    assert not list(out.rglob("*.part")), "a cancelled run left a partial file"
    assert not (out / "rig.toml").exists(), "a cancelled dataset must stay visibly incomplete"
    assert wiz.model.session.samples is None
    assert "cancelled" in wiz.next_blocker()
    assert any(st.state == "cancelled" for st in wiz.model.session.positions)


def test_import_of_a_broken_folder_says_why(wizard, qtbot, tmp_path):
    rig_page = wizard.page_by_key["rig"]
    rig_page.import_folder(tmp_path / "nowhere")
    assert "folder not found" in wizard.next_blocker()
    (tmp_path / "empty").mkdir()
    rig_page.import_folder(tmp_path / "empty")
    reason = wizard.next_blocker()
    assert reason and "rig.toml" in reason and "not found" in reason
    assert not wizard.button(QWizard.NextButton).isEnabled()
    assert reason in wizard.button(QWizard.NextButton).toolTip()
