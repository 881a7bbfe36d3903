"""An edit never discards results (issue 31): after reopening a finished session, changing the position
count sets the results aside as stale, with the reason on every page; setting it back brings them back
as they were, not stale."""

from __future__ import annotations

from gui_helpers import lut_on_export, run_job
from PySide6.QtCore import Qt

from ptp_studio.widgets.stale import StaleBanner


def _reopened_finished_session(wizard, qtbot, tmp_path):
    """Acquire, fit, export the session file, open it again (the wizard goes on at Compare)."""
    export = lut_on_export(wizard, qtbot)
    export.set_folder(tmp_path / "out")
    assert run_job(qtbot, export.export()) == "finished"
    assert run_job(qtbot, wizard.open_session(tmp_path / "out" / "session.ptps.h5")) == "finished"
    assert wizard.currentPage() is wizard.page_by_key["compare"]


def _click_step(qtbot, wizard, index):
    steps = wizard.steps
    qtbot.mouseClick(steps.viewport(), Qt.LeftButton, pos=steps.visualItemRect(steps.item(index)).center())
    assert wizard.page_index() == index
    # Going back passes pages the reopening skipped: the Phase maps page decodes its position on the way.
    qtbot.waitUntil(lambda: not any(p.jobs is not None and p.jobs.busy for p in wizard.pages), timeout=60000)


def _banner(page):
    return page.findChild(StaleBanner)


def test_an_edit_sets_results_aside_and_setting_back_restores_them(wizard, qtbot, tmp_path, questions):
    _reopened_finished_session(wizard, qtbot, tmp_path)
    model, s = wizard.model, wizard.model.session
    samples, lut, positions = s.samples, s.lut, [(p.index, p.state) for p in s.positions]
    reachable = wizard.reachable_steps()
    assert max(reachable) >= 5  # up to Compare at least

    _click_step(qtbot, wizard, 0)  # back to Rig by the step list
    rig = wizard.page_by_key["rig"]
    count = rig.z_count
    assert count.value() == 9
    qtbot.mouseClick(count.lineEdit(), Qt.LeftButton)
    # 9 -> 8 -> 9 positions with the arrow keys: the results come back as they were.
    qtbot.keyClick(count, Qt.Key_Down)
    assert count.value() == 8 and s.rig.stage.n_positions == 8 and s.samples is None
    qtbot.keyClick(count, Qt.Key_Up)
    assert count.value() == 9
    assert s.samples is samples and s.lut is lut
    assert [(p.index, p.state) for p in s.positions] == positions
    assert wizard.reachable_steps() == reachable and not model.unsaved_work

    # While they differ: set aside, not discarded; every page says why; no question was asked.
    qtbot.keyClick(count, Qt.Key_Down)
    assert s.samples is None and s.lut is None and model.stale is not None
    assert model.stale.values["samples"] is samples and model.stale.values["lut"] is lut
    assert questions.asked == []
    banner = _banner(rig)
    assert banner.isVisible()
    text = banner.text.text()
    assert "stale" in text and "9 positions, z = 0 … 40 mm then" in text and "8 positions" in text, text
    assert all(_banner(p).isVisibleTo(p) for p in wizard.pages)
    assert "stale" in wizard.page_by_key["acquire"].blocker()
    assert wizard.reachable_steps() == [0, 1, 2]  # nothing to show beyond Acquire: the rig is another
    assert model.unsaved_work is False  # the stale results are in the session file as they are

    session_file = tmp_path / "out" / "session.ptps.h5"
    assert wizard.autosave.path is None  # set aside: the file is left as it was (another rig now)
    qtbot.keyClick(count, Qt.Key_Up)  # back to 9: the same objects, not stale
    assert s.samples is samples and s.lut is lut and model.stale is None
    assert not banner.isVisible() and not model.unsaved_work
    assert wizard.autosave.path == session_file  # their file is autosaved again
    _click_step(qtbot, wizard, 4)  # Calibrate shows the LUT again
    cal = wizard.page_by_key["calibrate"]
    assert wizard.currentPage() is cal and cal.maps and wizard.next_blocker() is None
    # the next completed stage is written to it
    before = session_file.stat().st_mtime_ns
    with qtbot.waitSignal(wizard.autosave.saved, timeout=60000) as saved:
        assert run_job(qtbot, cal.fit()) == "finished"
    assert saved.args == [session_file] and session_file.stat().st_mtime_ns != before
    assert not model.unsaved_work


def test_the_banner_sets_the_values_back_and_a_new_run_drops_the_stale_results(wizard, qtbot, tmp_path):
    _reopened_finished_session(wizard, qtbot, tmp_path)
    model, s = wizard.model, wizard.model.session
    samples = s.samples
    _click_step(qtbot, wizard, 0)
    rig = wizard.page_by_key["rig"]
    qtbot.mouseClick(rig.z_count.lineEdit(), Qt.LeftButton)
    qtbot.keyClick(rig.z_count, Qt.Key_Down)
    qtbot.keyClick(rig.z_count, Qt.Key_Down)  # 7 positions
    rig.off_x.setFocus()
    qtbot.keyClick(rig.off_x, Qt.Key_Up)  # and the simulator's view offset
    banner = _banner(rig)
    assert "the simulator" in banner.text.text() and "7 positions" in banner.text.text()
    qtbot.mouseClick(banner.restore_button, Qt.LeftButton)
    assert s.samples is samples and model.stale is None and rig.z_count.value() == 9
    assert rig.off_x.value() == s.sim_settings.offset_mm[0]

    # An edit, then a new acquisition: the stale results go ("until the next run").
    qtbot.mouseClick(rig.z_count.lineEdit(), Qt.LeftButton)
    qtbot.keyClick(rig.z_count, Qt.Key_Down)
    assert model.stale is not None
    wizard.go_to("acquire")
    assert run_job(qtbot, wizard.page_by_key["acquire"].start()) == "finished"
    assert model.stale is None and s.samples is not samples and s.samples.x.shape[0] == 8
    assert wizard.autosave.path is None  # new results of another rig: never written over the old file
    assert not _banner(rig).isVisibleTo(rig)
