"""The mouse wheel over a value field (issue 31): it scrolls the page unless the field has the focus.

The wheel events go through the window as the platform delivers a real wheel (``QTest.wheelEvent``:
spontaneous, found under the pointer by Qt, propagated to the parents when ignored).
"""

from __future__ import annotations

from PySide6.QtCore import QPoint, QPointF, Qt
from PySide6.QtTest import QTest
from PySide6.QtWidgets import (QAbstractSlider, QAbstractSpinBox, QComboBox, QScrollArea, QScrollBar, QSpinBox,
                               QWidget)

NOTCH = 120  # one click of a mouse wheel (QWheelEvent.angleDelta, eighths of a degree)


def wheel(qtbot, widget, notches: int) -> None:
    """Turn the wheel ``notches`` clicks (negative: towards the user, the page scrolls down) with the
    pointer over the middle of ``widget``."""
    top = widget.window()
    pos = widget.mapTo(top, widget.rect().center())
    assert top.childAt(pos) is widget or widget.isAncestorOf(top.childAt(pos)), "the field is not under the pointer"
    for _ in range(abs(notches)):
        QTest.wheelEvent(top.windowHandle(), QPointF(pos), QPoint(0, NOTCH if notches > 0 else -NOTCH))
        qtbot.wait(1)


def _small(wizard, qtbot):
    """A window smaller than the pages: every page scrolls."""
    wizard.resize(1366, 560)  # a laptop's width, shorter than any page
    qtbot.wait(20)


def _scroller(page, field) -> QScrollArea:
    """The scroll area that holds ``field``: the page's own, or the side panel of a page with a view
    (its controls scroll on their own beside the view)."""
    w = field.parentWidget()
    while w is not None and not isinstance(w, QScrollArea):
        w = w.parentWidget()
    assert w is not None and (w is page.scroll or page.isAncestorOf(w)), f"{page.key}: no scroll area"
    return w


def _scroll_to(page, field):
    """Show ``field`` inside its scroll area's viewport with room to scroll down (or up, at the end):
    the direction to turn the wheel, -1 or +1."""
    area = _scroller(page, field)
    area.ensureWidgetVisible(field, 0, 40)  # well inside: nothing at the viewport's edge covers it
    bar = area.verticalScrollBar()
    assert bar.maximum() > 0, f"{page.key}: the page does not scroll at this size"
    return -1 if bar.value() < bar.maximum() else 1


def _check_wheel_scrolls_not_edits(qtbot, page, field, read):
    bar = _scroller(page, field).verticalScrollBar()
    direction = _scroll_to(page, field)
    before, scrolled = read(), bar.value()
    assert not field.hasFocus()
    wheel(qtbot, field, 2 * direction)
    assert read() == before, f"{page.key}: the wheel changed an unfocused field"
    assert bar.value() != scrolled, f"{page.key}: the page did not scroll"
    assert not field.hasFocus(), "the wheel gave the field the focus"


def test_wheel_over_fringes_amplitude_scrolls_the_page(wizard, qtbot):
    _small(wizard, qtbot)
    wizard.next()
    page = wizard.page_by_key["fringes"]
    assert wizard.currentPage() is page
    rig_fringes = wizard.model.session.rig.fringes
    _check_wheel_scrolls_not_edits(qtbot, page, page.amplitude, page.amplitude.value)
    assert wizard.model.session.rig.fringes == rig_fringes
    # Clicked into, the field takes the wheel: one notch up is one step.
    _scroll_to(page, page.amplitude)
    qtbot.mouseClick(page.amplitude.lineEdit(), Qt.LeftButton)
    assert page.amplitude.hasFocus()
    value = page.amplitude.value()
    bar = _scroller(page, page.amplitude).verticalScrollBar()
    bar_value = bar.value()
    wheel(qtbot, page.amplitude, 1)
    assert page.amplitude.value() == value + page.amplitude.singleStep()
    assert bar.value() == bar_value  # the page stays while the field turns
    assert wizard.model.session.rig.fringes.amplitude == page.amplitude.value()


def test_wheel_over_rig_position_count_scrolls_the_page(wizard, qtbot):
    _small(wizard, qtbot)
    page = wizard.page_by_key["rig"]
    rig = wizard.model.session.rig
    _check_wheel_scrolls_not_edits(qtbot, page, page.z_count, page.z_count.value)
    assert wizard.model.session.rig == rig
    for combo in (page.preset, page.template):  # combo boxes alike
        _check_wheel_scrolls_not_edits(qtbot, page, combo, combo.currentIndex)
    assert wizard.model.session.rig == rig


def test_fields_created_later_are_guarded_too(wizard, qtbot):
    _small(wizard, qtbot)
    page = wizard.page_by_key["rig"]
    late = QSpinBox()
    late.setRange(0, 100)
    late.setValue(50)
    page.body.layout().itemAt(0).layout().insertWidget(0, late)  # top of the left column, after start-up
    qtbot.wait(20)
    page.scroll.verticalScrollBar().setValue(0)
    _check_wheel_scrolls_not_edits(qtbot, page, late, late.value)


def test_no_value_field_takes_focus_from_the_wheel(wizard, qtbot):
    """Qt gives a WheelFocus widget the focus before the wheel reaches it: no value field may have it."""
    kinds = (QAbstractSpinBox, QComboBox, QAbstractSlider)
    fields = [w for p in wizard.pages for w in p.findChildren(QWidget)
              if isinstance(w, kinds) and not isinstance(w, QScrollBar)]
    for w in fields:  # as when shown (a page never shown has not been polished yet)
        w.ensurePolished()
    assert len(fields) > 30
    wheel_focus = [f"{type(w).__name__} {w.objectName() or ''}" for w in fields
                   if (w.focusPolicy() & Qt.WheelFocus) == Qt.WheelFocus]
    assert not wheel_focus, wheel_focus
