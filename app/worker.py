"""The one worker pattern for every long job.

A :class:`Job` runs a plain function on Qt's thread pool. The function gets a
:class:`JobContext` whose :meth:`~JobContext.progress` is the engine's
``progress(fraction, message)`` callback: it raises
:class:`ptpcore.errors.Cancelled` once :meth:`Job.cancel` was called, so every
engine call stops at its next progress report (engine writes are atomic: a
cancelled run leaves no partial file). :meth:`JobContext.emit` sends an
intermediate result (a frame, a decoded position) to the GUI.

Everything the worker thread reports travels through queued signals to the
``Job`` (which lives on the GUI thread) and is re-emitted there, so handlers
always run on the GUI thread and may touch widgets.
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from typing import Any, Callable

from PySide6.QtCore import QObject, QRunnable, QThreadPool, Qt, Signal, Slot

from ptpcore.errors import Cancelled, PtpError

__all__ = ["Job", "JobContext", "error_message", "wait_for_jobs"]

log = logging.getLogger(__name__)


def error_message(exc: BaseException) -> str:
    """One readable line (or a few) for a failed job."""
    if isinstance(exc, PtpError):
        return str(exc)
    if isinstance(exc, (ValueError, OSError)):
        return f"{exc}"
    return f"{type(exc).__name__}: {exc} (this is a bug; details on the console)"


class JobContext:
    """What the job's function receives.

    Attributes
    ----------
    cancel_event : threading.Event
    """

    def __init__(self, job: "Job"):
        self._job = job
        self.cancel_event = threading.Event()
        self._last_progress = 0.0

    @property
    def cancelled(self) -> bool:
        return self.cancel_event.is_set()

    def check(self) -> None:
        """Raise :class:`Cancelled` if the job was cancelled."""
        if self.cancel_event.is_set():
            raise Cancelled("cancelled")

    def progress(self, fraction: float, message: str = "") -> None:
        """The engine's progress callback: reports, and raises Cancelled when asked to stop."""
        self.check()
        now = time.monotonic()
        # At most ~30 reports a second reach the GUI; the last one (1.0) always does.
        if fraction >= 1.0 or now - self._last_progress > 0.03:
            self._last_progress = now
            self._job._sig_progress.emit(float(fraction), str(message))

    def emit(self, payload: Any) -> None:
        """Send an intermediate result to the GUI thread (``Job.partial``)."""
        self.check()
        self._job._sig_partial.emit(payload)


class _Runnable(QRunnable):
    def __init__(self, job: "Job"):
        super().__init__()
        self.job = job
        self.setAutoDelete(True)

    def run(self) -> None:  # worker thread
        self.job._execute()


class Job(QObject):
    """A long job on the thread pool.

    Parameters
    ----------
    fn : callable
        ``fn(ctx: JobContext) -> result``, run on a worker thread; must not touch widgets.
    name : str
        Shown in messages ("simulating", "fitting the LUT").

    Signals
    -------
    progress(float, str)
    partial(object)
        Each :meth:`JobContext.emit` payload.
    finished(object)
        The function's result.
    errored(str)
        A readable message.
    cancelled()
    done()
        After any of the three above.
    """

    progress = Signal(float, str)
    partial = Signal(object)
    finished = Signal(object)
    errored = Signal(str)
    cancelled = Signal()
    done = Signal()

    # Emitted on the worker thread, delivered to this object's (GUI) thread.
    _sig_progress = Signal(float, str)
    _sig_partial = Signal(object)
    _sig_end = Signal(str, object)

    def __init__(self, fn: Callable[[JobContext], Any], name: str = "job", parent: QObject | None = None):
        super().__init__(parent)
        self.fn = fn
        self.name = name
        self.ctx = JobContext(self)
        self.running = False
        self.outcome: str | None = None  # "finished", "errored", "cancelled"
        self.error: str | None = None
        self._sig_progress.connect(self._on_progress, Qt.QueuedConnection)
        self._sig_partial.connect(self._on_partial, Qt.QueuedConnection)
        self._sig_end.connect(self._on_end, Qt.QueuedConnection)

    def start(self) -> "Job":
        if self.running:
            raise RuntimeError(f"job '{self.name}' is already running")
        self.running = True
        ACTIVE_JOBS.add(self)
        QThreadPool.globalInstance().start(_Runnable(self))
        return self

    def cancel(self) -> None:
        """Ask the job to stop at its next progress report."""
        self.ctx.cancel_event.set()

    # ---- worker thread --------------------------------------------------
    def _execute(self) -> None:
        try:
            result = self.fn(self.ctx)
            if self.ctx.cancelled:
                raise Cancelled("cancelled")
        except Cancelled:
            self._sig_end.emit("cancelled", None)
        except Exception as exc:  # noqa: BLE001 - every failure must reach the user
            if not isinstance(exc, PtpError):
                log.error("job '%s' failed:\n%s", self.name, traceback.format_exc())
            self._sig_end.emit("errored", error_message(exc))
        else:
            self._sig_end.emit("finished", result)

    # ---- GUI thread -----------------------------------------------------
    @Slot(float, str)
    def _on_progress(self, fraction: float, message: str) -> None:
        if self.running:
            self.progress.emit(fraction, message)

    @Slot(object)
    def _on_partial(self, payload) -> None:
        if self.running:
            self.partial.emit(payload)

    @Slot(str, object)
    def _on_end(self, outcome: str, payload) -> None:
        self.running = False
        self.outcome = outcome
        ACTIVE_JOBS.discard(self)
        if outcome == "finished":
            self.finished.emit(payload)
        elif outcome == "errored":
            self.error = str(payload)
            self.errored.emit(self.error)
        else:
            self.cancelled.emit()
        self.done.emit()


ACTIVE_JOBS: set[Job] = set()


def wait_for_jobs(timeout_ms: int = 30000) -> bool:
    """Cancel every running job and wait for the pool to drain (at exit and in tests)."""
    for job in list(ACTIVE_JOBS):
        job.cancel()
    return QThreadPool.globalInstance().waitForDone(timeout_ms)
