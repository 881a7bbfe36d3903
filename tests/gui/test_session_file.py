"""Session files in the wizard: save at Export, open in a fresh window, land on the right page, autosave."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gui_helpers import run_job

from ptpcore.fit.settings import FitSettings
from ptpcore.errors import FileFormatError
from ptpcore.run import load_session, save_session
from ptp_studio.__main__ import build_parser
from ptp_studio.session import Session, tour_session
from ptp_studio.sessionfile import to_engine
from ptp_studio.wizard import StudioWizard


def _fresh_wizard(qtbot):
    wiz = StudioWizard(Session.from_preset("mild"))
    qtbot.addWidget(wiz)
    wiz.resize(1300, 850)
    wiz.show()
    qtbot.waitExposed(wiz)
    return wiz


def _acquire(wiz, qtbot):
    wiz.go_to("acquire")
    assert run_job(qtbot, wiz.page_by_key["acquire"].start()) == "finished"


def _wait_autosave(wiz, qtbot):
    job = wiz.autosave.job
    assert job is not None, "nothing was autosaved"
    run_job(qtbot, job)
    qtbot.waitUntil(lambda: not (wiz.autosave.job.running or wiz.autosave._again))


def test_save_at_export_then_open_in_a_fresh_window(wizard, qtbot, tmp_path):
    _acquire(wizard, qtbot)
    cal = wizard.page_by_key["calibrate"]
    wizard.go_to("calibrate")
    assert wizard.currentPage() is cal
    cal.configure("poly", 2, "half")
    assert run_job(qtbot, cal.fit()) == "finished"
    wizard.go_to("export")
    ex = wizard.page_by_key["export"]
    assert wizard.currentPage() is ex and ex.do_session.isChecked()
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export()) == "finished"
    path = tmp_path / "out" / "session.ptps.h5"
    saved = load_session(path)
    assert saved.stage == "lut" and saved.positions == tuple(range(0, 9, 2))
    assert wizard.autosave.path == path and "session saved" in wizard.session_status.text()
    old = wizard.model.session

    wiz = _fresh_wizard(qtbot)
    assert wiz.model.session.rig != old.rig
    assert run_job(qtbot, wiz.open_session(path)) == "finished"
    s = wiz.model.session
    # everything is back: rig and fringes, the simulator, samples, LUT; the truth is rebuilt
    assert s.rig == old.rig and s.source_kind == "simulated"
    assert (s.sim_settings, s.seed) == (old.sim_settings, old.seed)
    np.testing.assert_array_equal(s.samples.x, old.samples.x)
    np.testing.assert_array_equal(s.samples.reasons, old.samples.reasons)
    assert s.lut_positions == list(range(0, 9, 2)) and s.truth is not None
    assert all(st.state == "done" for st in s.positions)
    # the LUT is fitted and there is no comparison yet: the wizard goes on at Compare
    assert wiz.currentPage() is wiz.page_by_key["compare"]
    assert wiz.next_blocker() is None
    cal2 = wiz.page_by_key["calibrate"]
    assert (cal2.model_combo.currentData(), cal2.degree.value(), cal2.positions_combo.currentData()) == \
           ("poly", 2, "half")
    cal2.show_map("rms_x")
    np.testing.assert_allclose(cal2.heatmap.view.image.image, saved.lut.rms_x * 1000, rtol=1e-6, equal_nan=True)
    assert wiz.autosave.path == path and "autosaved" in wiz.session_status.text()
    assert wiz.autosave.job is None  # opening is not a stage: nothing written
    # Back from Compare shows the pages the wizard passed, filled in when first shown
    wiz.back()
    assert wiz.currentPage() is cal2 and wiz.next_blocker() is None
    ph = wiz.page_by_key["phase"]
    assert ph.decoded is None and not ph.jobs.busy  # passed, not entered: no decoding on the way
    wiz.back()
    assert wiz.currentPage() is ph
    assert run_job(qtbot, ph.jobs.job) == "finished"
    np.testing.assert_array_equal(ph.decoded.reasons, s.samples.reasons[ph.decoded.index])


def test_landing_page_follows_the_stage_and_autosave_writes_after_a_fit(qtbot, tmp_path, small_session_args):
    # A session decoded but not fitted yet (as `ptp calibrate --session` leaves it after decoding).
    src = StudioWizard(tour_session(**small_session_args))
    qtbot.addWidget(src)
    _acquire(src, qtbot)
    es = to_engine(src.model.session, settings=FitSettings(model="poly", degree=1))
    save_session(es, tmp_path / "samples.ptps.h5")
    es_cmp = dataclasses.replace(es, comparison={"references": {"measured": {"verdict": {"text": "PTP is ahead."}}}},
                                 lut=None)

    wiz = _fresh_wizard(qtbot)
    assert run_job(qtbot, wiz.open_session(tmp_path / "samples.ptps.h5")) == "finished"
    cal = wiz.page_by_key["calibrate"]
    assert wiz.currentPage() is cal
    assert "Fit the LUT first" in wiz.next_blocker()
    assert cal.model_combo.currentData() == "poly" and cal.degree.value() == 1
    # fitting is a completed stage: the file is saved again, with the LUT
    assert run_job(qtbot, cal.fit()) == "finished"
    _wait_autosave(wiz, qtbot)
    back = load_session(tmp_path / "samples.ptps.h5")
    assert back.stage == "lut" and back.degree == 1
    np.testing.assert_array_equal(back.lut.rms_x, wiz.model.session.lut.rms_x)
    assert "session saved" in wiz.session_status.text()

    # with a LUT and a saved comparison there is nothing left but Export; the verdict is shown
    es_cmp.lut = wiz.model.session.lut
    save_session(es_cmp, tmp_path / "done.ptps.h5")
    assert run_job(qtbot, wiz.open_session(tmp_path / "done.ptps.h5")) == "finished"
    assert wiz.currentPage() is wiz.page_by_key["export"]
    assert "PTP is ahead." in wiz.page_by_key["compare"].verdict.text()
    assert wiz.page_by_key["export"].do_report.isEnabled()
    assert wiz.autosave.path == tmp_path / "done.ptps.h5"
    src.close()


@pytest.mark.slow  # ~65 s (a smooth fit with stage refinement in the GUI's worker)
def test_the_fit_settings_of_the_calibrate_page_are_saved_and_restored(qtbot, tmp_path, small_session_args):
    src = StudioWizard(tour_session(**small_session_args))
    qtbot.addWidget(src)
    _acquire(src, qtbot)
    save_session(to_engine(src.model.session), tmp_path / "s.ptps.h5")
    wiz = _fresh_wizard(qtbot)
    assert run_job(qtbot, wiz.open_session(tmp_path / "s.ptps.h5")) == "finished"
    cal = wiz.page_by_key["calibrate"]
    cal.configure("smooth", 1, "all", stage_sigma_um=0.4, level_bias=False, footprint=False, refine_stage=True)
    assert run_job(qtbot, cal.fit()) == "finished"
    # The refined stage pose: a row per position (value ± sigma) and the plots (issue 14).
    k = wiz.model.session.rig.stage.n_positions
    assert not cal.stage_pose.isHidden() and cal.stage_pose.table.rowCount() == k
    assert "±" in cal.stage_pose.table.item(0, 1).text()
    curve, bars = cal.stage_pose.plots["angle"].series[0]
    assert len(curve.getData()[0]) == k and np.allclose(bars.opts["height"], 2 * wiz.model.session.lut.stage_pose_sigma[:, 3])
    _wait_autosave(wiz, qtbot)
    back = load_session(tmp_path / "s.ptps.h5")
    want = FitSettings(model="smooth", degree=1, stage_sigma_um=0.4, level_bias=False, footprint=False,
                       refine_stage=True)
    assert back.settings == want
    assert FitSettings.from_json(back.lut.provenance["fit_settings"]) == want  # the LUT records them too
    assert np.array_equal(back.lut.stage_pose, wiz.model.session.lut.stage_pose)
    other = _fresh_wizard(qtbot)
    assert run_job(qtbot, other.open_session(tmp_path / "s.ptps.h5")) == "finished"
    assert other.page_by_key["calibrate"].fit_settings() == want
    assert other.page_by_key["calibrate"].stage_pose.table.rowCount() == k
    # Fitted again without the refinement: the panel goes.
    other.page_by_key["calibrate"].configure("poly", 1, "all")
    assert run_job(qtbot, other.page_by_key["calibrate"].fit()) == "finished"
    assert other.page_by_key["calibrate"].stage_pose.isHidden()
    src.close()


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_a_bad_file_says_why_and_keeps_everything(wizard, qtbot, tmp_path, damage):
    _acquire(wizard, qtbot)
    s = wizard.model.session
    samples, rig = s.samples, s.rig
    path = tmp_path / "bad.ptps.h5"
    if damage == "garbage":
        path.write_bytes(b"this is not an HDF5 file\n" * 40)
    else:
        save_session(to_engine(s), path)
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    with pytest.raises(FileFormatError) as exc:
        load_session(path)
    wizard.go_to("rig")
    rig_page = wizard.page_by_key["rig"]
    assert run_job(qtbot, wizard.open_session(path)) == "errored"
    assert rig_page.jobs.error.isVisible() and rig_page.jobs.error.text() == str(exc.value)
    assert "\n" not in rig_page.jobs.error.text() and str(path) in rig_page.jobs.error.text()
    # nothing is lost: same samples, same rig, same page, no session file adopted
    assert wizard.model.session.samples is samples and wizard.model.session.rig == rig
    assert wizard.currentPage() is rig_page and wizard.next_blocker() is None
    assert wizard.autosave.path is None and wizard.session_status.text() == ""


def test_command_line_option():
    assert build_parser().parse_args(["--session", "a.ptps.h5"]).session == "a.ptps.h5"
