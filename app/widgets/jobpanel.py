"""Progress bar, message, Cancel button and error line for one :class:`~ptp_studio.worker.Job`."""

from __future__ import annotations

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QHBoxLayout, QLabel, QProgressBar, QPushButton, QVBoxLayout, QWidget

from ..worker import Job

__all__ = ["JobPanel"]


class JobPanel(QWidget):
    """Runs jobs one at a time and shows how they go.

    Signals
    -------
    started()
    ended(str)
        ``finished``, ``errored`` or ``cancelled``.
    """

    started = Signal()
    ended = Signal(str)

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        row = QHBoxLayout()
        self.bar = QProgressBar(self)
        self.bar.setRange(0, 1000)
        self.bar.setTextVisible(True)
        self.bar.setFormat("%p %")
        self.cancel_button = QPushButton("Cancel", self)
        self.cancel_button.setEnabled(False)
        self.cancel_button.clicked.connect(self.cancel)
        row.addWidget(self.bar, 1)
        row.addWidget(self.cancel_button)
        lay.addLayout(row)
        self.message = QLabel("", self)
        self.message.setObjectName("jobMessage")
        self.message.setWordWrap(True)  # a long message wraps; it never widens the page
        lay.addWidget(self.message)
        self.error = QLabel("", self)
        self.error.setObjectName("errorText")
        self.error.setWordWrap(True)
        self.error.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.error.hide()
        lay.addWidget(self.error)
        self.warning = QLabel("", self)
        self.warning.setObjectName("warningText")
        self.warning.setWordWrap(True)
        self.warning.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.warning.hide()
        lay.addWidget(self.warning)
        self.job: Job | None = None

    @property
    def busy(self) -> bool:
        return self.job is not None and self.job.running

    def show_error(self, text: str) -> None:
        """Show ``text`` in the panel's error line (cleared when the next job starts)."""
        self.error.setText(text)
        self.error.show()

    def show_warning(self, text: str) -> None:
        """Show ``text`` (a finding the job made, the result still usable) until the next job starts."""
        self.warning.setText(text)
        self.warning.show()

    def run(self, job: Job) -> Job:
        """Start ``job`` (after the previous one has ended)."""
        if self.busy:
            raise RuntimeError("a job is already running here")
        self.job = job
        job.setParent(self)
        job.progress.connect(self._progress)
        job.finished.connect(lambda _r: self._end("finished", f"{job.name}: done"))
        job.errored.connect(lambda msg: self._end("errored", f"{job.name}: failed", msg))
        job.cancelled.connect(lambda: self._end("cancelled", f"{job.name}: cancelled"))
        self._set_bar(0)
        self.message.setText(f"{job.name} …")
        self.error.hide()
        self.error.setText("")
        self.warning.hide()
        self.warning.setText("")
        self.cancel_button.setEnabled(True)
        job.start()
        self.started.emit()
        return job

    def cancel(self) -> None:
        if self.busy:
            self.job.cancel()
            self.message.setText(f"{self.job.name}: cancelling …")
            self.cancel_button.setEnabled(False)

    def _set_bar(self, value: int) -> None:
        """Move the bar without painting now.

        QProgressBar.setValue repaints synchronously whenever its text changes, which flushes every
        pending paint of the window (the pyqtgraph views too) at each progress report: with updates
        off it only schedules an ordinary paint, coalesced with the others (issue 15).
        """
        if value != self.bar.value():
            self.bar.setUpdatesEnabled(False)
            self.bar.setValue(value)
            self.bar.setUpdatesEnabled(True)

    def _progress(self, fraction: float, message: str) -> None:
        self._set_bar(int(round(1000 * min(max(fraction, 0.0), 1.0))))
        if message:
            self.message.setText(message)

    def _end(self, outcome: str, text: str, error: str = "") -> None:
        self.cancel_button.setEnabled(False)
        if outcome == "finished":
            self._set_bar(1000)
        self.message.setText(text)
        if error:
            self.error.setText(error)
            self.error.show()
        self.ended.emit(outcome)
