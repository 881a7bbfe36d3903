"""Rig page: the cover glass fields (issue 14) and what they say."""

from __future__ import annotations


def test_cover_glass_fields_reach_the_rig_and_say_bare_panel(wizard, qtbot):
    p = wizard.page_by_key["rig"]
    s = wizard.model.session
    assert p.src_sim.isChecked()
    assert "datasheet" in p.glass_t.toolTip() and "polarizer" in p.glass_t.toolTip()
    p.glass_t.setValue(p.glass_t.minimum())
    assert p.glass_t.text() == "not declared"
    assert s.rig.lcd.cover_glass_mm is None
    assert "bare panel is assumed" in p.glass_hint.text()
    p.glass_t.setValue(0.0)  # declared: no glass, not a bare panel assumed
    assert s.rig.lcd.cover_glass_mm == 0.0
    assert "No cover glass (declared)" in p.glass_hint.text() and "assumed" not in p.glass_hint.text()
    p.glass_t.setValue(1.1)
    p.glass_n.setValue(1.5)
    assert (s.rig.lcd.cover_glass_mm, s.rig.lcd.cover_glass_index) == (1.1, 1.5)
    assert "1.1 mm" in p.glass_hint.text() and "removed" in p.glass_hint.text()
