"""Rig page: the ptp-dataset/2 keys (bit shift, flatness, display, repeats, [decode]) round-trip (issue 13)."""

from __future__ import annotations

from ptpcore.rig import load_rig, rig_to_toml


def _type(edit, text):
    """Type into a line edit as the user would: text, then Enter (editingFinished)."""
    edit.setText(text)
    edit.setModified(True)
    edit.editingFinished.emit()


def test_every_v2_field_has_a_tooltip(wizard):
    p = wizard.page_by_key["rig"].v2
    for w in p.widgets():
        assert len(w.toolTip()) > 40, w
    assert "MSB" in p.bit_shift.toolTip() and "default 0.03" in p.min_mod.toolTip()


def test_v2_fields_reach_the_rig_and_round_trip(wizard, tmp_path, monkeypatch):
    page = wizard.page_by_key["rig"]
    p = page.v2
    s = wizard.model.session
    assert 'format = "ptp-dataset/1"' in rig_to_toml(s.rig)  # nothing /2 yet
    page.cam_bits.setValue(12)
    p.bit_shift.setValue(4)
    _type(p.flat_u, "0, 1920, 3840")
    _type(p.flat_v, "0 2160")
    _type(p.flat_um, "0 5 0; 5 12 5")
    _type(p.disp_levels, "0, 128, 255")
    _type(p.disp_lum, "0, 0.22, 1")
    _type(p.repeat_z, "0, 16")
    _type(p.min_mod, "0.05")
    _type(p.border, "4")
    _type(p.unwrap_tol, "0.3")
    assert page.blocker() is None, page.blocker()
    rig = s.rig
    assert rig.camera.bit_shift == 4
    assert rig.lcd.flatness_um == ((0, 5, 0), (5, 12, 5)) and rig.lcd.flatness_v_px == (0, 2160)
    assert rig.display.levels == (0, 128, 255) and rig.display.luminance == (0, 0.22, 1)
    assert rig.stage.repeat_z_mm == (0, 16)
    assert (rig.decode.min_modulation, rig.decode.border_margin_px, rig.decode.unwrap_tolerance) == (0.05, 4, 0.3)
    text = rig_to_toml(rig)
    assert 'format = "ptp-dataset/2"' in text and "[decode]" in text and "[display]" in text
    # Saved by the page, read back: the same rig; shown again: the same text in the fields.
    from PySide6.QtWidgets import QFileDialog
    monkeypatch.setattr(QFileDialog, "getSaveFileName", lambda *a, **k: (str(tmp_path / "rig.toml"), ""))
    page._save_dialog()
    back = load_rig(tmp_path / "rig.toml")
    assert back == rig
    monkeypatch.setattr(QFileDialog, "getOpenFileName", lambda *a, **k: (str(tmp_path / "rig.toml"), ""))
    _type(p.min_mod, "")  # changed, then the saved file loaded again
    assert s.rig.decode.min_modulation is None
    page._load_dialog()
    assert s.rig == back and p.min_mod.text() == "0.05" and p.flat_um.text() == "0 5 0; 5 12 5"
    # Emptied again: back to ptp-dataset/1
    p.bit_shift.setValue(0)
    for w in p.line_edits():
        _type(w, "")
    assert page.blocker() is None
    assert 'format = "ptp-dataset/1"' in rig_to_toml(s.rig)


def test_bad_v2_values_name_the_field(wizard):
    page = wizard.page_by_key["rig"]
    p = page.v2
    rig_before = wizard.model.session.rig
    _type(p.unwrap_tol, "0.9")
    assert "unwrap_tolerance" in page.blocker() and wizard.model.session.rig == rig_before
    _type(p.unwrap_tol, "")
    _type(p.border, "two")
    assert "border margin" in page.blocker() and "'two'" in page.blocker()
    _type(p.border, "")
    _type(p.disp_levels, "0, 255")
    assert "display levels and luminance go together" in page.blocker()
    _type(p.disp_lum, "1, 0")
    assert "display.luminance" in page.blocker()
    _type(p.disp_levels, "")
    _type(p.disp_lum, "")
    assert page.blocker() is None
