"""Fringes page: per-direction conventions and Gray bits, [[images.frames]] listed and kept, and the
design check with the display's measured harmonics (issue 13)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ptpcore.decode.harmonics import measured_harmonics
from ptpcore.rig import FrameEntry, load_rig, position_label, rig_to_toml, save_rig
from ptpcore.run import decode_position
from ptpcore.simulate import scaled_preset, simulate_dataset


def test_per_direction_origin_sign_and_gray_bits(wizard):
    p = wizard.page_by_key["fringes"]
    s = wizard.model.session
    for w in (p.origin_y, p.sign_y, p.gray_bits_y):
        assert "[fringes.y]" in w.toolTip()
    p.origin.setValue(3.14159)
    p.sign_y.setCurrentIndex(2)  # -1
    p.origin_y.setText("0.5")
    p.origin_y.editingFinished.emit()
    f = s.rig.fringes
    assert (f.origin("x"), f.sign("x"), f.origin("y"), f.sign("y")) == (3.14159, 1, 0.5, -1)
    text = rig_to_toml(s.rig)
    assert "[fringes.y]" in text and "shift_sign = -1" in text
    # Gray code, y with a bit fewer than x
    p.unwrap.setCurrentText("gray")
    p.gray_bits.setValue(3)
    p.gray_bits_y.setValue(2)
    f = s.rig.fringes
    assert f.unwrap == "gray" and (f.bits("x"), f.bits("y")) == (3, 2)
    # y back to "as x": no [fringes.y] left
    p.gray_bits_y.setValue(-1)
    p.sign_y.setCurrentIndex(0)
    p.origin_y.setText("")
    p.origin_y.editingFinished.emit()
    assert s.rig.fringes.per_direction == () and s.rig.fringes.bits("y") == 3
    p.origin_y.setText("pi")
    p.origin_y.editingFinished.emit()
    assert "phase origin y" in p.blocker()


def _frames_dataset(tmp_path):
    """A small simulated dataset whose rig.toml names every image in [[images.frames]]."""
    rig, settings = scaled_preset("mild", 48, positions=3)
    folder = simulate_dataset(tmp_path / "ds", rig, settings, seed=3)
    rig = load_rig(folder)
    frames = tuple(FrameEntry(rig.image_name(k, d, t, n, big_n, j), k, d, j, n)
                   for k in range(rig.stage.n_positions) for d, j, t, n, big_n in rig.fringes.frames())
    listed = replace(rig, frame_list=frames)
    save_rig(listed, folder / "rig.toml")
    assert load_rig(folder).frame_list == frames
    return folder, listed


def test_frames_named_one_by_one_are_listed_and_kept(wizard, tmp_path, monkeypatch):
    folder, listed = _frames_dataset(tmp_path)
    assert wizard.page_by_key["rig"].import_folder(folder)
    p = wizard.page_by_key["fringes"]
    assert not p.frames_box.isHidden()
    n = len(listed.frame_list)
    assert p.frames_table.rowCount() == n and str(n) in p.frames_box.title()
    e = listed.frame_list[5]
    assert p.frames_table.item(5, 3).text() == e.file and p.frames_table.item(5, 1).text() == e.dir
    assert f"step {e.step}" in p.frames_table.item(5, 2).text()
    # Saved from the Rig page: the frames as they were.
    from PySide6.QtWidgets import QFileDialog
    monkeypatch.setattr(QFileDialog, "getSaveFileName", lambda *a, **k: (str(tmp_path / "saved.toml"), ""))
    wizard.page_by_key["rig"]._save_dialog()
    assert load_rig(tmp_path / "saved.toml").frame_list == listed.frame_list
    # A design without them hides the list.
    wizard.page_by_key["rig"].src_sim.setChecked(True)
    assert p.frames_box.isHidden()


def test_design_check_takes_the_measured_harmonics(wizard):
    p = wizard.page_by_key["fringes"]
    model = wizard.model
    s = model.session
    assert "predicted for the simulated rig" in p.verdict.text() or "Design OK" in p.verdict.text()
    pos = decode_position(s.make_source(), 2)
    measured = measured_harmonics(pos.info["noise_samples"])
    assert measured is not None and measured.noise_dn > 0 and measured.n_pixels > 100
    before = p._basis
    model.set_decoded(pos)
    # A hidden page only notes the new position (no work on the GUI thread during an acquisition, issue 15)...
    assert not p.isVisible() and p._basis == before
    # ...and catches up when shown.
    wizard.go_to("fringes")
    assert p.measured_harmonics()[0] == 2
    assert p._basis.startswith(f"measured at {position_label(2, s.rig.stage.z_mm[2])}") and f"{measured.harmonic_dn:.2g}" in p._basis
    has_item = any(i.name == "display harmonics" for i in p.report.items)
    assert has_item == (measured.harmonic_dn > measured.noise_dn)


def test_a_heterodyne_design_is_chosen_and_checked_with_keys(wizard, qtbot):
    """Issue 32: the page designs heterodyne sets (periods typed, the unwrapping picked with the keyboard),
    the rig gets ``unwrap = "heterodyne"`` and the design check shows the beats."""
    from PySide6.QtCore import Qt

    wizard.go_to("fringes")
    p = wizard.page_by_key["fringes"]
    s = wizard.model.session
    width = max(s.rig.lcd.width, s.rig.lcd.height)
    # Three close periods whose absolute beat covers the LCD (and the carrier) with room to spare.
    base = max(40.0, round(width / 60.0))
    periods = (base, base + 2, base + 5)
    qtbot.mouseClick(p.periods, Qt.LeftButton)
    p.periods.selectAll()
    qtbot.keyClicks(p.periods, ", ".join(f"{t:g}" for t in periods))
    qtbot.keyClick(p.periods, Qt.Key_Tab)
    qtbot.mouseClick(p.steps, Qt.LeftButton)
    p.steps.selectAll()
    qtbot.keyClicks(p.steps, "8, 8, 8")
    qtbot.keyClick(p.steps, Qt.Key_Tab)
    p.unwrap.setFocus()
    qtbot.keyClick(p.unwrap, Qt.Key_End)  # the last item: heterodyne
    qtbot.waitUntil(lambda: s.rig.fringes.unwrap == "heterodyne", timeout=5000)
    assert sorted(s.rig.fringes.periods_px) == sorted(periods)
    assert "heterodyne" in rig_to_toml(s.rig)
    qtbot.waitUntil(lambda: p.report is not None and any("T123" in str(i) or "beat" in str(i).lower()
                                                         for i in p.report.items), timeout=10000)
