"""Ask the engineer before something they made is dropped (one place, so tests can answer it)."""

from __future__ import annotations

from PySide6.QtWidgets import QMessageBox, QWidget

__all__ = ["confirm"]


def confirm(parent: QWidget | None, title: str, text: str, detail: str = "") -> bool:
    """A Yes/No question whose default is No; True for Yes.

    Goes through :meth:`QMessageBox.question`, which the GUI tests replace to answer.
    """
    body = f"{text}\n\n{detail}" if detail else text
    answer = QMessageBox.question(parent, title, body, QMessageBox.Yes | QMessageBox.No, QMessageBox.No)
    return answer == QMessageBox.Yes
