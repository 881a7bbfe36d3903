"""Helpers shared by the GUI tests."""

from __future__ import annotations


def run_job(qtbot, job, timeout=60000):
    """Wait for a job started by a page; return its outcome."""
    assert job is not None, "the page did not start its job"
    if job.running:
        with qtbot.waitSignal(job.done, timeout=timeout):
            pass
    return job.outcome
