"""Positions counted from 0 as the dataset's folders count them, always with their height (issue 31):
the Acquire table, the Phase maps position list and title, the residual panel of the Calibrate page."""

from __future__ import annotations

from gui_helpers import run_job
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QWizard


def test_positions_are_named_from_0_with_their_height(wizard, qtbot):
    z = wizard.model.session.rig.stage.z_mm  # 9 positions, 0 … 40 mm
    wizard.go_to("acquire")
    acq = wizard.page_by_key["acquire"]
    assert run_job(qtbot, acq.start()) == "finished"
    assert [acq.table.item(i, 0).text() for i in (0, 8)] == ["0", "8"]

    qtbot.mouseClick(wizard.button(QWizard.NextButton), Qt.LeftButton)
    ph = wizard.page_by_key["phase"]
    assert wizard.currentPage() is ph
    qtbot.waitUntil(lambda: not ph.jobs.busy, timeout=60000)
    combo = ph.pos_combo
    assert [combo.itemText(i) for i in (0, 8)] == [f"position 0, z = {z[0]:g} mm", f"position 8, z = {z[8]:g} mm"]
    combo.setFocus(Qt.TabFocusReason)  # as Tab would (a click opens the list: a popup offscreen Qt warns about)
    qtbot.keyClick(combo, Qt.Key_Home)
    qtbot.keyClick(combo, Qt.Key_Down)
    assert combo.currentData() == 1 and wizard.isVisible()
    qtbot.waitUntil(lambda: not ph.jobs.busy and f"position 1, z = {z[1]:g} mm" in ph.title.text(), timeout=60000)

    wizard.go_to("calibrate")
    cal = wizard.page_by_key["calibrate"]
    cal.configure("poly", 2, "half")
    assert run_job(qtbot, cal.fit()) == "finished"
    panel, field = cal.residuals, cal.residual_field
    k = int(field.worst_positions[0])
    assert panel.position.itemText(0).startswith(f"position {k}, z = {field.z[k]:g} mm")
    assert "RMS (X and Y)" in panel.position.itemText(0)
    assert f"position {k}, z = {field.z[k]:g} mm" in panel.worst.text()
