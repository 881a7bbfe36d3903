"""The mouse wheel over a value field scrolls the page unless the field has the focus.

Qt turns a spin box, a combo box or a slider under the pointer with the wheel, and gives it the
focus on the way (their focus policy is ``Qt.WheelFocus``): scrolling a long page changed whatever
field passed under the pointer (the Fringes amplitude 100 -> 87, the Rig position count 11 -> 9,
issue 31). Here a value field takes the wheel only once clicked or tabbed into; otherwise the wheel
goes on to the field's parents, as over a label, and the page's scroll area scrolls.

The mechanism is installed once for the application (:func:`install`, from
:func:`ptp_studio.wizard.configure_app`) and reaches every widget, also those created later: the
application's style is a :class:`QProxyStyle` whose :meth:`WheelGuardStyle.polish` (Qt calls it
once per widget, before it is first shown) gives each value field ``Qt.StrongFocus`` and the event
filter. An application-wide event filter would do the same but run Python for every event of every
widget (paints, timers), each waiting for the GIL while a job's thread holds it; this filter sees only
the value fields' events.
"""

from __future__ import annotations

from PySide6.QtCore import QEvent, QObject, Qt
from PySide6.QtWidgets import (QAbstractSlider, QAbstractSpinBox, QApplication, QComboBox, QProxyStyle,
                               QScrollBar, QWidget)

__all__ = ["WheelGuard", "WheelGuardStyle", "install", "is_value_field"]

_VALUE_FIELDS = (QAbstractSpinBox, QComboBox, QAbstractSlider)


def is_value_field(widget) -> bool:
    """A widget whose value the wheel turns: a spin box, a combo box or a slider (not a scroll bar)."""
    return isinstance(widget, _VALUE_FIELDS) and not isinstance(widget, QScrollBar)


class WheelGuard(QObject):
    """Event filter of the value fields: an unfocused field passes the wheel on to its parents."""

    def eventFilter(self, obj, event) -> bool:  # noqa: N802 - Qt API
        if event.type() == QEvent.Wheel:
            # The receiver is the field or its own line edit (a spin box's, an editable combo box's).
            field = obj if is_value_field(obj) else obj.parentWidget()
            if not field.hasFocus():
                # Ignored and filtered: Qt offers a (spontaneous) wheel event to the parent next,
                # up to the page's scroll area.
                event.ignore()
                return True
        return False


class WheelGuardStyle(QProxyStyle):
    """The application's style (``Fusion`` underneath) with the wheel guard added to every value field
    when Qt polishes it."""

    def __init__(self, base: str = "Fusion"):
        super().__init__(base)
        self.guard = WheelGuard(self)

    def polish(self, arg):  # one name for Qt's three overloads: widget, palette, application
        if isinstance(arg, QWidget):
            if is_value_field(arg):
                if arg.focusPolicy() & Qt.WheelFocus == Qt.WheelFocus:
                    arg.setFocusPolicy(Qt.StrongFocus)  # a click or Tab focuses it, the wheel does not
                arg.installEventFilter(self.guard)
            elif is_value_field(arg.parentWidget()):
                arg.installEventFilter(self.guard)  # a spin box's line edit, an editable combo box's
        return super().polish(arg)


def install(app: QApplication, base: str = "Fusion") -> WheelGuardStyle:
    """Make ``app``'s style ``base`` with the wheel guard (before the widgets are created)."""
    style = WheelGuardStyle(base)
    app.setStyle(style)
    return style
