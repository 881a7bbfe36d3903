"""Trust what you export (issue 16) in the wizard: auto by default with its table; the Export page's diff."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from gui_helpers import run_job

from ptpcore.evaluate.diff import diff_luts
from ptpcore.fit.choice import AUTO_CANDIDATES, ModelChoice
from ptpcore.fit.sigma import sigma_parts
from ptpcore.io import save_lut


def _acquire(wizard, qtbot):
    wizard.go_to("acquire")
    assert run_job(qtbot, wizard.page_by_key["acquire"].start()) == "finished"
    wizard.go_to("calibrate")
    return wizard.page_by_key["calibrate"]


def test_calibrate_defaults_to_auto_and_shows_the_choice(wizard, qtbot):
    cal = _acquire(wizard, qtbot)
    assert cal.model_combo.currentData() == "auto" and cal.fit_settings().model == "auto"
    assert not cal.degree.isEnabled() and cal.level_bias.isEnabled()  # the smooth candidate applies them
    assert not cal.choice_table.isVisibleTo(cal)
    # A hang guard, not a time bound: 54 s on the quiet machine, 135 s at load 8.
    assert run_job(qtbot, cal.fit(), timeout=400000) == "finished"
    lut = wizard.model.session.lut
    choice = ModelChoice.from_json(lut.provenance["model_choice"])
    assert cal.choice_table.isVisibleTo(cal) and cal.choice_table.rowCount() == len(AUTO_CANDIDATES)
    chosen = cal.choice_table.item(choice.chosen, 0)
    assert "chosen" in chosen.text() and chosen.font().bold()
    for i, c in enumerate(choice.candidates):
        if not c.note:
            assert float(cal.choice_table.item(i, 1).text()) == round(c.held_out_rms_um, 3)
    assert "chosen by held-out positions" in cal.stats.text()
    # Issue 30: the predicted sigma's two parts, noise and model, beside the total.
    v = lut.valid
    for a in "xy":
        total, noise, model = sigma_parts(lut, a)
        assert model is not None  # every model auto can pick estimates its own error
        parts = (f"{a.upper()} {1e3 * np.nanmedian(total[v]):.2f} µm (noise {1e3 * np.nanmedian(noise[v]):.2f},"
                 f" model {1e3 * np.nanmedian(model[v]):.2f})")
        assert parts in cal.stats.text()
    assert "Robust fit: " in cal.stats.text() and "SUSPECT" not in cal.stats.text()  # the default is robust
    # A fixed model hides the table again.
    cal.configure("poly", 2, "all")
    assert run_job(qtbot, cal.fit()) == "finished"
    assert not cal.choice_table.isVisibleTo(cal)


def test_export_page_diffs_against_a_reference_lut(wizard, qtbot, tmp_path):
    cal = _acquire(wizard, qtbot)
    cal.configure("poly", 2, "half")
    assert run_job(qtbot, cal.fit()) == "finished"
    lut = wizard.model.session.lut
    wizard.go_to("export")
    panel = wizard.page_by_key["export"].diff_panel
    assert panel.result is None
    # no comparison yet: the views' place says what will be drawn there (empty axes before)
    assert panel.stack.currentWidget() is panel.placeholder and "No comparison yet" in panel.placeholder.text()
    assert panel.compare(tmp_path / "missing.lut.h5") is None and "no such LUT file" in panel.jobs.error.text()

    # Itself: no difference, consistent.
    same = tmp_path / "same.lut.h5"
    save_lut(lut, same)
    assert run_job(qtbot, panel.compare(same)) == "finished"
    assert panel.result.consistent and panel.result.max_um < 1e-6
    assert panel.stack.currentWidget() is panel.views
    assert "consistent" in panel.verdict.text()

    # Moved by 10 predicted sigmas in X (5 of the difference RMS): it differs; the heatmap shows the shift,
    # the histogram counts every pixel.
    shift = 10 * float(np.sqrt(np.nanmean(lut.sigma_x[lut.valid] ** 2)))
    moved = replace(lut, x=lut.x.copy())
    moved.x[0] += shift
    save_lut(moved, tmp_path / "moved.lut.h5")
    assert run_job(qtbot, panel.compare(tmp_path / "moved.lut.h5")) == "finished"
    r = panel.result
    want = diff_luts(lut, moved)
    assert not r.consistent and "DIFFER" in panel.verdict.text()
    # The common mode's line: the shift in X (the same LUT moved: measured exactly, standard error 0).
    assert "Common mode" in panel.verdict.text() and f"X {r.common_x.shift_um:+.3f}" in panel.verdict.text()
    assert r.common_x.flagged and abs(-r.common_x.shift_um - shift * 1e3) <= 3 * r.common_x.se_um + 1e-9
    shown = panel.heatmap.view.image.image
    np.testing.assert_allclose(shown[r.common], want.diff[r.common] * 1e3, rtol=1e-5)
    # |dX| = shift everywhere, so |d| = shift / sqrt(2) (RMS over X and Y)
    assert abs(np.median(shown[r.common]) - shift * 1e3 / np.sqrt(2)) < 0.01 * shift * 1e3
    assert int(np.sum(panel.bars.opts["height"])) == r.n_pixels
    assert panel.tol_line.isVisible() and panel.tol_line.value() > 0

    # A new LUT forgets the comparison.
    wizard.model.set_lut(lut, wizard.model.session.lut_positions)
    assert panel.result is None and panel.stack.currentWidget() is panel.placeholder


def test_calibrate_shows_residual_arrows_and_export_writes_them(wizard, qtbot, tmp_path):
    from ptpcore.evaluate.residuals import residual_field
    from ptp_studio.pages.export import N_RESIDUAL_PNGS
    from ptp_studio.widgets.residuals import arrow_segments

    cal = _acquire(wizard, qtbot)
    cal.configure("poly", 2, "half")
    assert run_job(qtbot, cal.fit()) == "finished"
    s = wizard.model.session
    want = residual_field(s.lut, s.samples, s.lut_positions)
    panel = cal.residuals
    k_all = s.samples.z.size
    assert panel.position.count() == k_all
    # worst first, and the held-out positions (odd ones) marked
    assert [panel.position.itemData(i) for i in range(k_all)] == want.worst_positions.tolist()
    assert any("held out" in panel.position.itemText(i) for i in range(k_all))
    x, y, _scale = arrow_segments(want, int(want.worst_positions[0]))
    shown_x, shown_y = panel.arrows.getData()
    np.testing.assert_allclose(shown_x, x)
    np.testing.assert_allclose(shown_y, y)
    assert "worst positions" in panel.worst.text() and "worst pixels" in panel.worst.text()
    panel.position.setCurrentIndex(k_all - 1)
    x, _y, _scale = arrow_segments(want, int(want.worst_positions[-1]))
    np.testing.assert_allclose(panel.arrows.getData()[0], x)

    wizard.go_to("export")
    ex = wizard.page_by_key["export"]
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export()) == "finished"
    names = {f.name for f in ex.files}
    for k in want.worst_positions[:N_RESIDUAL_PNGS]:
        assert f"residuals_position_{k}.png" in names
        assert (tmp_path / "out" / f"residuals_position_{k}.png").read_bytes()[:4] == b"\x89PNG"


def test_calibrate_page_shows_the_drift_of_a_repeated_position(wizard, qtbot):
    """A sweep that ends at its first position again ([stage] repeat_z_mm), the camera moved 2 um in X
    before the repeat: the Calibrate page names the drift warning, gives the figures and maps |d|."""
    import json

    s = wizard.model.session
    s.rig = replace(s.rig, stage=replace(s.rig.stage, repeat_z_mm=(s.rig.stage.z_mm[0],)))
    s.sim_settings = replace(s.sim_settings, drift_um=(2.0, 0.0))
    cal = _acquire(wizard, qtbot)
    cal.configure("poly", 2, "all")
    assert run_job(qtbot, cal.fit()) == "finished"
    lut = wizard.model.session.lut
    d = json.loads(lut.provenance["drift"])
    r = d["repeats"][0]
    assert r["position"] == 0 and d["warnings"] and abs(abs(r["mean_um"][0]) - 2.0) < 5 * r["mean_se_um"][0]
    text = cal.stats.text()
    assert "DRIFT WARNING" in text and "Drift at z = " in text and "position 0 again" in text
    button = cal.map_buttons.button(cal._map_keys.index("drift"))
    assert button.isVisibleTo(cal)
    cal.show_map("drift")
    shown = cal.heatmap.view.image.image
    assert np.nanmedian(shown) > 0 and np.isfinite(shown).sum() > 0.5 * lut.valid.sum()
    # Another fit without repeats hides the map again.
    s.rig = replace(s.rig, stage=replace(s.rig.stage, repeat_z_mm=()))
    assert run_job(qtbot, cal.fit()) == "finished"
    assert "drift" not in wizard.model.session.lut.provenance and not button.isVisibleTo(cal)
