"""The banner over every page while the session's results are set aside as stale (issue 31).

An edit of the rig, the simulator or the source never discards results
(:class:`ptp_studio.session.SessionModel`): they are set aside with the reason; the banner says so
on every page, and its button sets the values back, which brings the results back as they were.
"""

from __future__ import annotations

from PySide6.QtWidgets import QFrame, QHBoxLayout, QLabel, QPushButton

__all__ = ["StaleBanner"]

_STYLE = ("QFrame#staleBanner { background: #fff1e0; border: 1px solid #d4832c; border-radius: 5px; }"
          " QLabel { color: #7d3f00; }")


class StaleBanner(QFrame):
    """Shown while ``model.stale`` holds results; says why and offers to set the values back.

    Parameters
    ----------
    model : SessionModel
    """

    def __init__(self, model, parent=None):
        super().__init__(parent)
        self.model = model
        self.setObjectName("staleBanner")
        self.setStyleSheet(_STYLE)
        row = QHBoxLayout(self)
        row.setContentsMargins(8, 4, 8, 4)
        self.text = QLabel(self)
        self.text.setWordWrap(True)
        self.restore_button = QPushButton("Set the values back", self)
        self.restore_button.setToolTip("The rig, simulator and source as the stale results were computed with:"
                                       " the results come back as they were")
        self.restore_button.clicked.connect(lambda: self.model.restore_stale_inputs())
        row.addWidget(self.text, 1)
        row.addWidget(self.restore_button)
        for signal in (model.staleChanged, model.rigChanged, model.sourceChanged):
            signal.connect(self.update_text)
        self.update_text()

    def update_text(self) -> None:
        reason = self.model.stale_reason()
        self.text.setText(reason or "")
        self.setVisible(reason is not None)
