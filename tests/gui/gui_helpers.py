"""Helpers shared by the GUI tests."""

from __future__ import annotations


def run_job(qtbot, job, timeout=60000):
    """Wait for a job started by a page; return its outcome."""
    assert job is not None, "the page did not start its job"
    if job.running:
        with qtbot.waitSignal(job.done, timeout=timeout):
            pass
    return job.outcome


def lut_on_export(wizard, qtbot):
    """Acquire and fit a LUT (poly 2 on half the positions: quick); the wizard on the Export page,
    which is returned."""
    wizard.go_to("acquire")
    assert run_job(qtbot, wizard.page_by_key["acquire"].start()) == "finished"
    wizard.go_to("calibrate")
    cal = wizard.page_by_key["calibrate"]
    cal.configure("poly", 2, "half")
    assert run_job(qtbot, cal.fit()) == "finished"
    wizard.go_to("export")
    return wizard.page_by_key["export"]
