"""The wizard keeps the engineer's work and its own state honest (issue 20).

A laptop screen, closing with a job running or results unsaved, the step list, pages that follow a new
dataset, a second import over a finished session, export names, Calibrate's settings in Compare,
the last page's wording and plain axis units.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import replace

import numpy as np
import pyqtgraph as pg
import pytest
from gui_helpers import run_job
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QWizard

from ptpcore.errors import Cancelled
from ptpcore.decode import design_check
from ptpcore.rig import Camera
from ptpcore.run import load_session
from ptpcore.simulate import preset, simulate_dataset
from ptp_studio.session import tour_session
from ptp_studio.worker import Job
from ptp_studio.wizard import StudioWizard

SCREEN = (1366, 768)


def _dataset(folder, width, height, positions, seed):
    rig, settings = preset("mild")
    rig = replace(rig, camera=Camera(width, height, rig.camera.bit_depth)).with_z(np.linspace(0, 40, positions))
    return simulate_dataset(folder, rig, settings, seed=seed), rig


def _fit(wiz, qtbot, model="poly", degree=2):
    wiz.go_to("calibrate")
    cal = wiz.page_by_key["calibrate"]
    assert wiz.currentPage() is cal, wiz.next_blocker()
    cal.configure(model, degree, "all")
    assert run_job(qtbot, cal.fit()) == "finished"
    return cal


def _acquire(wiz, qtbot):
    wiz.go_to("acquire")
    assert run_job(qtbot, wiz.page_by_key["acquire"].start()) == "finished"


def _endless(ctx):
    """A job that runs until it is cancelled (reports progress, as every engine call does)."""
    while True:
        ctx.progress(0.5, "working")
        time.sleep(0.005)


# ---- a laptop screen ---------------------------------------------------------------------------------
def _fits(wiz):
    frame, geo = wiz.frameGeometry(), wiz.geometry()
    assert frame.width() <= SCREEN[0] and frame.height() <= SCREEN[1], (frame, wiz.currentPage().key)
    # The window's minimum (what makes it grow) fits the screen with its frame.
    extra_w, extra_h = frame.width() - geo.width(), frame.height() - geo.height()
    hint = wiz.minimumSizeHint()
    assert hint.width() + extra_w <= SCREEN[0] and hint.height() + extra_h <= SCREEN[1]
    # The page fits across: only tall pages scroll, and only vertically.
    page = wiz.currentPage()
    assert page.body.minimumSizeHint().width() <= page.scroll.viewport().width(), page.key
    assert not page.scroll.horizontalScrollBar().isVisible(), page.key


def test_the_window_fits_a_1366x768_screen_on_every_page(qtbot, small_session_args):
    wiz = StudioWizard(tour_session(**small_session_args))
    qtbot.addWidget(wiz)
    wiz.show()
    qtbot.waitExposed(wiz)
    dw = wiz.frameGeometry().width() - wiz.geometry().width()
    dh = wiz.frameGeometry().height() - wiz.geometry().height()
    wiz.resize(SCREEN[0] - dw, SCREEN[1] - dh)
    qtbot.wait(20)
    _fits(wiz)
    _acquire(wiz, qtbot)
    _fit(wiz, qtbot)
    wiz.go_to("rig")
    for i in range(len(wiz.pages)):
        assert wiz.page_index() == i
        qtbot.wait(20)
        _fits(wiz)
        page = wiz.currentPage()
        if page.jobs is not None and page.jobs.busy:
            run_job(qtbot, page.jobs.job)
            _fits(wiz)
        if i < len(wiz.pages) - 1:
            wiz.next()


def test_the_first_size_stays_on_a_small_screen(qtbot, small_session_args):
    wiz = StudioWizard(tour_session(**small_session_args))
    qtbot.addWidget(wiz)
    avail = wiz.screen().availableGeometry()  # offscreen: 800x800
    assert wiz.width() <= avail.width() and wiz.height() <= avail.height()


# ---- closing ------------------------------------------------------------------------------------------
def test_close_with_a_running_job_asks_and_stops_the_job(wizard, qtbot, questions):
    page = wizard.page_by_key["rig"]
    job = page.run_job(Job(_endless, "a long job"))
    qtbot.waitUntil(lambda: job.running)
    questions.answer = False
    wizard.close()
    assert wizard.isVisible() and job.running  # "No": nothing happens
    assert len(questions.asked) == 1 and "a long job" in questions.asked[0]
    wizard.button(QWizard.CancelButton).click()  # the Cancel button asks too
    assert wizard.isVisible() and job.running and len(questions.asked) == 2
    questions.answer = True
    wizard.close()
    assert not wizard.isVisible()
    assert not job.running and job.outcome == "cancelled"  # stopped, and waited for
    assert page.jobs.message.text().endswith("cancelled")  # its end reached the page


def test_close_asks_only_while_results_are_unsaved(wizard, qtbot, questions, tmp_path):
    wizard.close()  # nothing computed yet
    assert not wizard.isVisible() and questions.asked == []
    wizard.show()
    wizard.closing = False
    _acquire(wizard, qtbot)
    questions.answer = False
    wizard.close()
    assert wizard.isVisible() and "not saved" in questions.asked[-1]
    _fit(wizard, qtbot)
    wizard.go_to("export")
    ex = wizard.page_by_key["export"]
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export()) == "finished"  # with the session file
    n = len(questions.asked)
    wizard.close()
    assert not wizard.isVisible() and len(questions.asked) == n


# ---- the step list ------------------------------------------------------------------------------------
def _click_step(wiz, qtbot, index):
    steps = wiz.steps
    rect = steps.visualItemRect(steps.item(index))
    qtbot.mouseClick(steps.viewport(), Qt.LeftButton, pos=rect.center())


def test_sidebar_steps_go_back_and_forward_to_completed_steps(wizard, qtbot):
    _click_step(wizard, qtbot, 4)  # Calibrate: not reached
    assert wizard.page_index() == 0
    _acquire(wizard, qtbot)
    _fit(wizard, qtbot)
    assert wizard.page_index() == 4
    _click_step(wizard, qtbot, 6)  # Export: never shown, so not clickable
    assert wizard.page_index() == 4
    _click_step(wizard, qtbot, 1)  # back to Fringes
    assert wizard.currentPage() is wizard.page_by_key["fringes"]
    assert set(wizard.steps.reachable) == {0, 2, 3, 4}
    _click_step(wizard, qtbot, 4)  # forward again: every page on the way is complete
    assert wizard.currentPage() is wizard.page_by_key["calibrate"]
    ph = wizard.page_by_key["phase"]
    assert not ph.jobs.busy  # passed on the way, not shown: it decoded nothing
    # A new rig drops the samples: the steps after Acquire are out of reach until it runs again.
    _click_step(wizard, qtbot, 0)
    rig_page = wizard.page_by_key["rig"]
    rig_page.z_count.setValue(rig_page.z_count.value() + 1)
    assert wizard.model.session.samples is None
    assert set(wizard.steps.reachable) == {1, 2}
    _click_step(wizard, qtbot, 4)
    assert wizard.page_index() == 0
    assert not wizard.jump_to(4)


# ---- a new dataset ------------------------------------------------------------------------------------
def test_pages_follow_a_new_import(wizard, qtbot, tmp_path):
    folder_a, rig_a = _dataset(tmp_path / "a", 64, 48, 7, 1)
    folder_b, rig_b = _dataset(tmp_path / "b", 80, 60, 6, 2)
    model = wizard.model
    assert wizard.page_by_key["rig"].import_folder(folder_a)
    _acquire(wizard, qtbot)
    cal = _fit(wizard, qtbot)
    assert cal.heatmap.view.data.shape == (48, 64)
    wizard.next()
    cmp_page = wizard.page_by_key["compare"]
    assert run_job(qtbot, cmp_page.run()) == "finished"
    assert cmp_page.stats.rowCount() > 0
    fr = wizard.page_by_key["fringes"]
    seen = {p.key: p.shown_version for p in wizard.pages}
    version = model.version

    wizard.jump_to(0)
    assert wizard.page_by_key["rig"].import_folder(folder_b)  # asked (and answered Yes)
    assert model.version > version
    wizard.next()
    assert fr.shown_version == model.version != seen["fringes"]
    want = design_check(rig_b)
    assert [i.message for i in fr.report.items] == [i.message for i in want.items]
    np.testing.assert_array_equal(fr.floor_bars.opts["x"], rig_b.stage.z_mm)
    # Whatever showed dataset A is cleared: heatmaps, statistics, pixel curves, comparison.
    assert cal.maps == {} and cal.heatmap.view.data is None and cal.stats.text() == ""
    assert cal.heatmap.hist_counts.size == 0
    assert cmp_page.stats.rowCount() == 0 and cmp_page.heat["ptp"].data is None
    # and once B is acquired and fitted, its own maps show
    wizard.next()
    assert run_job(qtbot, wizard.page_by_key["acquire"].start()) == "finished"
    _fit(wizard, qtbot)
    assert cal.heatmap.view.data.shape == (60, 80)
    ph = wizard.page_by_key["phase"]
    wizard.back()
    assert wizard.currentPage() is ph
    if ph.jobs.busy:
        run_job(qtbot, ph.jobs.job)
    assert ph.decoded.reasons.shape == (60, 80) and ph.view.data.shape == (60, 80)


@pytest.mark.parametrize("answer", [False, True])
def test_a_second_import_over_a_finished_session_asks(wizard, qtbot, tmp_path, questions, answer):
    folder_a, rig_a = _dataset(tmp_path / "a", 64, 48, 5, 1)
    folder_b, rig_b = _dataset(tmp_path / "b", 64, 48, 5, 2)
    rig_page = wizard.page_by_key["rig"]
    assert rig_page.import_folder(folder_a)
    assert questions.asked == []  # nothing to lose yet
    _acquire(wizard, qtbot)
    _fit(wizard, qtbot)
    wizard.go_to("export")
    ex = wizard.page_by_key["export"]
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export()) == "finished"
    session_file = tmp_path / "out" / "session.ptps.h5"
    assert run_job(qtbot, ex.export()) == "finished"  # the same session again: its own files, no question
    assert questions.asked == []
    before = session_file.read_bytes()
    s = wizard.model.session
    samples, lut = s.samples, s.lut
    wizard.jump_to(0)

    questions.answer = answer
    assert rig_page.import_folder(folder_b) is answer
    assert len(questions.asked) == 1
    assert "replaces the decoded samples and the LUT" in questions.asked[0]
    assert str(session_file) in questions.asked[0]  # where the finished session is, and that it stays
    if not answer:
        assert s.dataset_folder == folder_a and s.samples is samples and s.lut is lut
        assert rig_page.folder_edit.text() == str(folder_a)
        assert wizard.autosave.path == session_file
        questions.answer = True
        return
    assert s.dataset_folder == folder_b and s.samples is None and s.lut is None
    assert wizard.autosave.path is None and "left as it was" in wizard.session_status.text()
    # Dataset B's results never go into A's finished session file.
    _acquire(wizard, qtbot)
    _fit(wizard, qtbot)
    qtbot.wait(100)
    assert wizard.autosave.job is None
    assert session_file.read_bytes() == before
    assert load_session(session_file).dataset == str(folder_a)
    # Exporting into the same folder asks before replacing the finished session there.
    wizard.go_to("export")
    questions.answer = False
    assert ex.export() is None
    assert "finished session" in questions.asked[-1] and session_file.read_bytes() == before
    assert "Nothing written" in ex.jobs.error.text()
    questions.answer = True


def test_reimporting_the_same_folder_drops_stale_samples(wizard, qtbot, tmp_path):
    folder, _ = _dataset(tmp_path / "a", 64, 48, 5, 1)
    rig_page = wizard.page_by_key["rig"]
    assert rig_page.import_folder(folder)
    _acquire(wizard, qtbot)
    wizard.jump_to(0)
    _dataset(tmp_path / "a2", 64, 48, 5, 7)  # the same rig; new images written over the old ones
    shutil.rmtree(folder)
    (tmp_path / "a2").rename(folder)
    assert rig_page.import_folder(folder)
    assert wizard.model.session.samples is None
    # Leaving the folder field without typing anything imports nothing
    _acquire(wizard, qtbot)
    wizard.jump_to(0)
    rig_page.folder_edit.editingFinished.emit()
    assert wizard.model.session.samples is not None


# ---- an opened session ----------------------------------------------------------------------------------
def test_a_restored_comparison_is_shown_not_an_empty_page(wizard, qtbot, tmp_path, small_session_args):
    _acquire(wizard, qtbot)
    _fit(wizard, qtbot)
    wizard.next()
    cmp_page = wizard.page_by_key["compare"]
    cmp_page.seed.setValue(5)
    assert run_job(qtbot, cmp_page.run()) == "finished"
    rows = [cmp_page.stats.item(i, 1).text() for i in range(cmp_page.stats.rowCount())]
    wizard.next()
    ex = wizard.page_by_key["export"]
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export()) == "finished"

    wiz = StudioWizard(tour_session(**small_session_args))
    qtbot.addWidget(wiz)
    wiz.show()
    assert run_job(qtbot, wiz.open_session(tmp_path / "out" / "session.ptps.h5")) == "finished"
    assert wiz.currentPage() is wiz.page_by_key["export"]
    wiz.back()
    page = wiz.page_by_key["compare"]
    assert wiz.currentPage() is page
    assert "Saved comparison" in page.verdict.text()
    assert [page.stats.item(i, 1).text() for i in range(page.stats.rowCount())] == rows
    assert page.params.rowCount() > 0 and "Reprojection RMS" in page.reproj.text()
    assert page.seed.value() == 5 and "Run comparison" in page.coverage.text()
    wiz.closing = True


# ---- export names, Compare settings, wording, units -------------------------------------------------
def test_quality_pngs_are_named_after_their_map(wizard, qtbot, tmp_path):
    _acquire(wizard, qtbot)
    cal = _fit(wizard, qtbot)
    cal.show_map("loo_y")  # the tab open last does not matter
    wizard.go_to("export")
    ex = wizard.page_by_key["export"]
    assert ex.why.text().startswith("Finish is disabled:")  # the last page's button is Finish
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export()) == "finished"
    names = {p.name for p in (tmp_path / "out").iterdir()}
    assert {f"lut_quality_{k}.png" for k in cal.maps} <= names
    assert "lut_quality.png" not in names and "rms_x" in cal.maps and "loo_y" in cal.maps


def test_compare_uses_the_calibrate_settings(wizard, qtbot, monkeypatch):
    import ptp_studio.pages.compare as compare_module

    calls = []

    def fake_compare(samples, rig, **kwargs):
        calls.append(kwargs)
        raise Cancelled("test")

    monkeypatch.setattr(compare_module, "compare", fake_compare)
    _acquire(wizard, qtbot)
    cal = _fit(wizard, qtbot, "smooth", 2)
    cal.level_bias.setChecked(False)
    cal.degree.setValue(4)  # changed after the fit: the LUT's own settings count
    wizard.next()
    page = wizard.page_by_key["compare"]
    run_job(qtbot, page.run())
    kw = calls[-1]
    assert (kw["model"], kw["degree"], kw["smooth_degree"]) == ("poly", 2, 2)
    assert kw["level_bias"] is True and kw["footprint"] is True
    # degree 3 needs 5 calibration positions per fold; 9 positions held out alternately leave 5
    wizard.back()
    cal.configure("poly", 3, "all")
    cal.footprint.setChecked(False)
    assert run_job(qtbot, cal.fit()) == "finished"
    wizard.next()
    run_job(qtbot, page.run())
    assert (calls[-1]["model"], calls[-1]["degree"], calls[-1]["smooth_degree"]) == ("poly", 3, 3)
    assert calls[-1]["footprint"] is False and page.settings_note == ""


def test_compare_lowers_the_degree_only_when_a_fold_cannot_fit_it(qtbot, monkeypatch, small_session_args):
    import ptp_studio.pages.compare as compare_module

    calls = []

    def fake_compare(samples, rig, **kwargs):
        calls.append(kwargs)
        raise Cancelled("test")

    monkeypatch.setattr(compare_module, "compare", fake_compare)
    wiz = StudioWizard(tour_session(**{**small_session_args, "positions": 7}))
    qtbot.addWidget(wiz)
    wiz.show()
    _acquire(wiz, qtbot)
    _fit(wiz, qtbot, "smooth", 3)
    wiz.next()
    page = wiz.page_by_key["compare"]
    run_job(qtbot, page.run())
    # 7 positions, alternate: 4 calibration positions per fold, degree 3 needs 5
    assert calls[-1]["smooth_degree"] == 1 and "needs 5 calibration positions" in page.settings_note


def test_axes_show_plain_units(wizard):
    axes = []
    for view in wizard.findChildren(pg.GraphicsView):
        axes += [item for item in view.scene().items() if isinstance(item, pg.AxisItem)]
    assert len(axes) > 30
    assert not [a for a in axes if a.autoSIPrefix], "an axis rescales its unit with an SI prefix"
    labelled = [a.labelString() for a in axes if a.labelUnits]
    assert any("(µm)" in t for t in labelled) and not any("(x" in t for t in labelled)


# ---- the data's sanity checks on the page, not only on the console -------------------------------------

def test_stuck_positions_are_shown_on_the_acquire_page(wizard, qtbot, tmp_path):
    folder, _rig = _dataset(tmp_path / "a", 64, 48, 5, 1)
    shutil.rmtree(folder / "z002")
    shutil.copytree(folder / "z001", folder / "z002")  # the stage did not move: position 2 repeats 1
    assert wizard.page_by_key["rig"].import_folder(folder)
    _acquire(wizard, qtbot)
    warning = wizard.page_by_key["acquire"].jobs.warning
    assert warning.isVisibleTo(wizard) and "positions 1" in warning.text() and "stuck" in warning.text()
    _acquire(wizard, qtbot)  # the same data again: the warning is shown again, not stacked
    assert warning.text().count("stuck") == 1


def test_clean_data_shows_no_warning_on_the_acquire_page(wizard, qtbot, tmp_path):
    folder, _rig = _dataset(tmp_path / "a", 64, 48, 5, 1)
    assert wizard.page_by_key["rig"].import_folder(folder)
    _acquire(wizard, qtbot)
    assert not wizard.page_by_key["acquire"].jobs.warning.isVisibleTo(wizard)
