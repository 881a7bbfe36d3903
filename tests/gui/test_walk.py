"""The whole wizard, driven as a user would, asserting on what every page shows."""

from __future__ import annotations

import json

import numpy as np
import pytest
import pyqtgraph as pg
from gui_helpers import run_job
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QWizard

from ptpcore.evaluate import METHODS
from ptpcore.io import load_lut
from ptpcore.fit import fit_lut
from ptpcore.run.decoding import direction_reasons
from ptpcore.run import load_session
from ptpcore.decode import REASON_NAMES, Reason
from ptpcore.run import decode_position
from ptpcore.evaluate import REASON_ORDER, pixel_series, reason_rgba, reason_text


def _next_enabled(wiz) -> bool:
    return wiz.button(QWizard.NextButton).isEnabled()


# Slow tier: the default tier walks every page in test_tour and test_layout; this walk (~100 s) adds the
# state checks between pages, and runs in CI with the slow tests.
@pytest.mark.slow
def test_full_walk(wizard, qtbot, tmp_path):
    wiz = wizard
    s = wiz.model.session
    p = wiz.page_by_key

    # 1 Rig: the default simulated rig may go on; live capture is offered beside it.
    assert wiz.currentPage() is p["rig"]
    assert wiz.next_blocker() is None and _next_enabled(wiz)
    assert p["rig"].src_live.isEnabled()
    wiz.next()

    # 2 Fringes: the design check passes; every item has a verdict row.
    fr = p["fringes"]
    assert wiz.currentPage() is fr
    assert fr.report.ok and fr.table.rowCount() == len(fr.report.items)
    assert all(fr.table.item(i, 0).text().startswith("✔") for i in range(fr.table.rowCount()))
    # an ambiguous design blocks Next and says which check fails
    original = s.rig.fringes
    fr.steps.setText("4")
    fr.steps.editingFinished.emit()
    fr.periods.setText("512, 128, 32")
    fr.periods.editingFinished.emit()
    reason = wiz.next_blocker()
    assert reason and "design check fails" in reason and "unambiguous range x" in reason
    assert not _next_enabled(wiz)
    assert any(fr.table.item(i, 0).text().startswith("✘") for i in range(fr.table.rowCount()))
    fr.periods.setText(", ".join(map(str, original.periods_px)))
    fr.periods.editingFinished.emit()
    fr.steps.setText(", ".join(map(str, original.steps)))
    fr.steps.editingFinished.emit()
    assert s.rig.fringes == original and wiz.next_blocker() is None
    fr.scrub("y", 2, 1, 3)
    assert fr.preview.data.shape == (s.rig.lcd.height, s.rig.lcd.width)
    wiz.next()

    # 3 Acquire: Next is disabled with a reason, in words and as tooltip, until the run.
    acq = p["acquire"]
    assert wiz.currentPage() is acq
    reason = wiz.next_blocker()
    assert reason and "Acquire the images first" in reason
    assert not _next_enabled(wiz)
    assert reason in wiz.button(QWizard.NextButton).toolTip()
    assert acq.why.isVisible() and reason in acq.why.text()
    assert run_job(qtbot, acq.start()) == "finished"
    assert s.samples is not None and s.truth is not None
    assert all(st.state == "done" for st in s.positions)
    assert acq.table.rowCount() == s.rig.stage.n_positions
    assert acq.frame_view.data is not None
    assert wiz.next_blocker() is None and _next_enabled(wiz) and not acq.why.isVisible()
    wiz.next()

    # 4 Phase maps: the validity mask, its legend (every Reason flag), values under the cursor.
    ph = p["phase"]
    ph.select(position=0, direction="x", kind="validity")
    if ph.jobs.busy:
        run_job(qtbot, ph.jobs.job)
    pos = s.decoded[0]
    names = ph.legend.texts()
    assert names == ["valid"] + [REASON_NAMES[f] for f in REASON_ORDER]
    flags = {v for k, v in vars(Reason).items() if not k.startswith("_")}
    assert set(REASON_ORDER) == flags
    # the reasons of direction x alone (issue 13), as `ptp decode` writes them
    rx = direction_reasons(s.rig, pos)["x"]
    np.testing.assert_array_equal(ph.view.image.image, reason_rgba(rx))
    # the corner of the LCD is in view: several kinds of rejection show
    assert len(np.unique(rx)) >= 3
    r, c = map(int, np.argwhere(rx != 0)[0])
    ph._hovered(r, c)
    assert reason_text(rx[r, c]) in ph.readout.text()
    # the unwrapped coordinate is the engine's, invalid pixels (of x) blank
    ph.select(kind="coord")
    ref = decode_position(s.make_source(), 0)
    np.testing.assert_allclose(ph.view.image.image, np.where(direction_reasons(s.rig, ref)["x"] == 0, ref.u, np.nan),
                               equal_nan=True)
    h, w = s.rig.camera.shape
    ph.set_line((2, h / 2), (w - 3, h / 2))
    assert ph.profile_x.size >= w - 5 and np.isfinite(ph.profile_y).any()
    wiz.next()

    # 5 Calibrate: Next disabled until fitted; heatmaps are the engine's arrays in µm.
    cal = p["calibrate"]
    assert "Fit the LUT" in wiz.next_blocker()
    cal.configure("poly", 3, "all")
    assert run_job(qtbot, cal.fit()) == "finished"
    lut = s.lut
    engine = fit_lut(s.samples, "poly", 3)
    np.testing.assert_array_equal(engine.rms_x, lut.rms_x)
    for key, attr in (("rms_x", "rms_x"), ("rms_y", "rms_y"), ("loo_x", "loo_x"), ("loo_y", "loo_y")):
        cal.show_map(key)
        np.testing.assert_allclose(cal.heatmap.view.image.image, getattr(lut, attr) * 1e3, rtol=1e-6,
                                   equal_nan=True)
        assert cal.heatmap.unit == "µm" and cal.heatmap.view.bar.axis.labelText == "µm"
        assert cal.heatmap.hist_counts.sum() > 0
    cal.show_map("n_positions")
    np.testing.assert_array_equal(cal.heatmap.view.image.image, lut.n_positions)
    # click a pixel: its samples, curves and residuals are the engine's
    rr, cc = map(int, np.argwhere(lut.valid)[len(np.argwhere(lut.valid)) // 2])
    view = cal.heatmap.view
    qtbot.mouseClick(view.viewport(), Qt.LeftButton, pos=view.mapFromScene(view.scene_pos_of(rr, cc)))
    assert cal.selected == (rr, cc)
    ref = pixel_series(lut, s.samples, rr, cc)
    np.testing.assert_allclose(cal.plot_x.curve.getData()[1], ref.x_curve)
    np.testing.assert_allclose(cal.bars_x.opts["height"], ref.resid_x[np.isfinite(ref.resid_x)] * 1e3)
    assert f"row {rr}, col {cc}" in cal.pixel_label.text()
    # the plain LUT carries its predicted uncertainty, shown like every other heatmap
    assert lut.sigma_x is not None
    cal.show_map("sigma_x")
    np.testing.assert_allclose(cal.heatmap.view.image.image, lut.sigma_x * 1000, rtol=1e-6, equal_nan=True)
    assert cal.heatmap.unit == "µm" and cal.heatmap.hist_counts.sum() > 0
    # the smooth kind: offered in the model choice, with its degree; its sigma maps shown in µm
    assert cal.model_combo.findData("smooth") >= 0
    cal.configure("smooth", 1, "all")
    assert cal.degree.isEnabled() and cal.level_bias.isEnabled() and cal.level_bias.isChecked()
    assert run_job(qtbot, cal.fit()) == "finished"
    lut = s.lut
    assert lut.kind == "poly" and lut.degree == 1 and lut.extra_attrs["method"] == "smooth"
    for key in ("sigma_x", "sigma_y"):
        assert cal.map_buttons.button(cal._map_keys.index(key)).isVisibleTo(cal)
        cal.show_map(key)
        np.testing.assert_allclose(cal.heatmap.view.image.image, getattr(lut, key) * 1000, rtol=1e-6,
                                   equal_nan=True)
        assert cal.heatmap.unit == "µm" and cal.heatmap.view.bar.axis.labelText == "µm"
        assert cal.heatmap.hist_counts.sum() > 0
    assert "smooth, poly degree 1" in cal.stats.text() and "Predicted 1σ" in cal.stats.text()
    # the stage's reading error (its specification) adds to the predicted sigma, not to the LUT
    cal.configure("smooth", 1, "all", stage_sigma_um=0.5)
    assert run_job(qtbot, cal.fit()) == "finished"
    v = lut.valid
    np.testing.assert_array_equal(s.lut.x, lut.x)
    assert np.all(s.lut.sigma_x[v] >= lut.sigma_x[v]) and np.nanmean(s.lut.sigma_x[v]) > np.nanmean(lut.sigma_x[v])
    lut = s.lut
    cal.configure("pchip", 3, "all")  # the degree applies to poly and smooth only
    assert not cal.degree.isEnabled()
    assert not cal.level_bias.isEnabled() and not cal.footprint.isEnabled()  # smooth-only corrections
    cal.configure("smooth", 1, "all")
    assert wiz.next_blocker() is None
    wiz.next()

    # 6 Compare: three methods, one shared colour scale, heatmaps are the comparison's arrays.
    cmp_page = p["compare"]
    assert cmp_page.with_smooth.isChecked()
    assert run_job(qtbot, cmp_page.run()) == "finished"
    result = s.compare
    assert result.methods == METHODS == ("ptp", "smooth", "3dstc")
    ref_key = cmp_page.reference.currentData()
    assert ref_key == "truth"
    for m in METHODS:
        assert cmp_page.heat[m].isVisibleTo(cmp_page)
        np.testing.assert_allclose(cmp_page.heat[m].image.image,
                                   result.references[ref_key].methods[m].heatmap_mm * 1e3, rtol=1e-6,
                                   equal_nan=True)
    assert cmp_page.heat["ptp"].levels == cmp_page.heat["smooth"].levels == cmp_page.heat["3dstc"].levels
    assert cmp_page.stats.rowCount() == 3 * len(METHODS)
    assert [cmp_page.stats.item(3 * i, 0).text() for i in range(3)] == \
           ["PTP coord.", "PTP smooth coord.", "3DSTC coord."]
    bars = [i for i in cmp_page.per_pos.getPlotItem().items if isinstance(i, pg.BarGraphItem)]
    assert len(bars) == len(METHODS)
    names = {item.name() for item in cmp_page.hist.getPlotItem().listDataItems()}
    assert names == {"PTP", "PTP smooth", "3DSTC"}
    assert cmp_page.params.rowCount() == len(result.pinhole.param_names)
    assert result.references[ref_key].verdict.text in cmp_page.verdict.text()
    wiz.next()

    # 7 Export: Finish is disabled until the LUT is written; then the files are what the engine reads.
    ex = p["export"]
    assert "Export the LUT file" in wiz.next_blocker()
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export()) == "finished"
    assert wiz.next_blocker() is None and wiz.button(QWizard.FinishButton).isEnabled()
    back = load_lut(tmp_path / "out" / "calibration.lut.h5")
    np.testing.assert_array_equal(back.rms_x, lut.rms_x)
    np.testing.assert_array_equal(back.sigma_x, lut.sigma_x)
    assert back.extra_attrs["method"] == "smooth"
    report = json.loads((tmp_path / "out" / "comparison.json").read_text())
    assert report["format"] == "ptp-compare/1" and report["config"]["methods"] == list(METHODS)
    assert set(report["references"]["truth"]) == {"verdict", *METHODS}
    back_session = load_session(tmp_path / "out" / "session.ptps.h5")
    assert back_session.model == "smooth" and back_session.degree == 1
    pngs = sorted(f.name for f in (tmp_path / "out").glob("*.png"))
    assert "comparison_compare_heatmaps.png" in pngs and "lut_quality_rms_x.png" in pngs and "lut_quality_sigma_x.png" in pngs
    assert not list((tmp_path / "out").glob("*.part"))


def test_upstream_change_drops_results(wizard, qtbot):
    """A new rig after acquisition sets the samples aside as stale (issue 31), and Acquire blocks again."""
    wiz = wizard
    wiz.next()
    wiz.next()
    acq = wiz.page_by_key["acquire"]
    assert run_job(qtbot, acq.start()) == "finished"
    assert wiz.model.session.samples is not None
    wiz.back()
    wiz.back()
    rig_page = wiz.page_by_key["rig"]
    rig_page.z_count.setValue(7)
    assert wiz.model.session.samples is None and wiz.model.stale is not None
    assert wiz.model.session.rig.stage.n_positions == 7
    wiz.next()
    wiz.next()
    assert "Acquire the images first" in wiz.next_blocker()
    assert acq.table.rowCount() == 7
