"""Keys and clicks as a person makes them (issue 31): Compare keeps the reference LUT's path; Return
never closes the wizard, on any page, in any field."""

from __future__ import annotations

from gui_helpers import lut_on_export, run_job
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QAbstractSpinBox, QComboBox, QFileDialog, QLineEdit, QPushButton, QWidget, QWizard

from ptpcore.io import save_lut


def _finished(wizard, qtbot):
    """Acquire and fit a LUT (poly 2 on half the positions: quick); the wizard on the Export page."""
    export = lut_on_export(wizard, qtbot)
    assert wizard.currentPage() is export
    return export


def _click(qtbot, button):
    assert button.isVisible() and button.isEnabled(), button.text()
    qtbot.mouseClick(button, Qt.LeftButton)


def test_compare_keeps_the_reference_path_typed_or_browsed(wizard, qtbot, tmp_path, monkeypatch):
    export = _finished(wizard, qtbot)
    panel = export.diff_panel
    # The panel is the second tab of the Export page's view: click its tab as a person would.
    tabs = export.view_tabs
    bar = tabs.tabBar()
    qtbot.mouseClick(bar, Qt.LeftButton, pos=bar.tabRect(tabs.indexOf(panel)).center())
    assert tabs.currentWidget() is panel
    reference = tmp_path / "reference.lut.h5"
    save_lut(wizard.model.session.lut, reference)

    # Typed: click into the field, type the path, click Compare.
    _click(qtbot, panel.reference)  # a line edit takes the click as focus
    qtbot.keyClicks(panel.reference, str(reference))
    _click(qtbot, panel.compare_button)
    assert panel.reference.text() == str(reference)
    assert panel.jobs.error.text() == "", panel.jobs.error.text()
    assert run_job(qtbot, panel.jobs.job) == "finished"
    assert panel.result is not None and panel.result.consistent and "reference.lut.h5" in panel.verdict.text()

    # Picked with Browse…: the file dialog answers with the path.
    panel.reset()
    panel.reference.clear()
    monkeypatch.setattr(QFileDialog, "getOpenFileName", lambda *a, **k: (str(reference), ""))
    browse = next(b for b in panel.findChildren(QPushButton) if b.text() == "Browse…")
    _click(qtbot, browse)
    assert panel.reference.text() == str(reference)
    _click(qtbot, panel.compare_button)
    assert panel.reference.text() == str(reference) and panel.jobs.error.text() == ""
    assert run_job(qtbot, panel.jobs.job) == "finished" and panel.result is not None


def _fields(page):
    """The page's value fields a person can type Return in (shown and enabled)."""
    kinds = (QLineEdit, QAbstractSpinBox, QComboBox)
    out = [w for w in page.findChildren(QWidget)
           if isinstance(w, kinds) and w.isVisible() and w.isEnabled() and not isinstance(w.parentWidget(), kinds)]
    return out


def test_return_never_closes_the_wizard(wizard, qtbot, tmp_path):
    export = _finished(wizard, qtbot)
    # Return in the reference-LUT field with nothing typed: the field says what is missing, the wizard stays.
    export.diff_panel.reference.setFocus()
    qtbot.keyClick(export.diff_panel.reference, Qt.Key_Return)
    assert wizard.isVisible() and wizard.result() == 0
    assert "no such LUT file" in export.diff_panel.jobs.error.text()
    # Export written: Finish is enabled (the default button): Return in a field still does not press it.
    export.set_folder(tmp_path / "out")
    assert run_job(qtbot, export.export()) == "finished"
    assert wizard.button(QWizard.FinishButton).isEnabled()
    pressed = 0
    for index in reversed(range(len(wizard.pages))):  # Export back to Rig, every page shown
        assert wizard.jump_to(index) or wizard.page_index() == index
        page = wizard.currentPage()
        fields = _fields(page)
        assert fields, f"{page.key}: no field found"
        for field in fields:
            field.setFocus()
            for key in (Qt.Key_Return, Qt.Key_Enter):
                qtbot.keyClick(field, key)
                pressed += 1
                assert wizard.isVisible() and wizard.result() == 0, f"{page.key}: {type(field).__name__} closed it"
                assert wizard.currentPage() is page, f"{page.key}: Return in a {type(field).__name__} left the page"
    assert pressed > 40
