"""The scanner's VDI/VDE 2634-2 acceptance in the wizard (issue 35): the Export page's tab, shown for a
LUT with a height map, runs what ``ptp acceptance`` runs and shows each figure's largest magnitude per
method, the verdicts and the engine's page of plots; Save report… writes the JSON and the page.

A 128 x 96 mild scanner: a height map fitted to its decoded sweep, an exact XY LUT, three poses. The
conventional calibration is replaced by a stand-in (tests/cli/test_acceptance.py's exact one is not
importable here; this one is the PTP point itself, so both columns must agree number for number).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from gui_helpers import run_job

from ptp_studio.widgets import acceptance as gui_acceptance
from ptp_studio.widgets.acceptance import AcceptancePanel
from ptpcore.evaluate.vdi2634 import FIGURES
from ptpcore.fit.height import fit_height_map
from ptpcore.run.scanner import decode_projector
from ptpcore.simulate.scanner import (HeightSweepSource, ScannerRig, acceptance_objects, exact_lut, scanner_preset,
                                      simulate_acceptance_scans)

POSES = ("sphere-09", "ballbar-05", "plane-01")


@pytest.fixture(scope="module")
def scanner(tmp_path_factory):
    folder = tmp_path_factory.mktemp("accept-gui")
    rig, sim, sc = scanner_preset("scanner-mild", 128, heights=11)
    sr = ScannerRig(rig, sim, sc, seed=6)
    dec = decode_projector(HeightSweepSource(sr, ("x",)))
    hm = fit_height_map(dec.u, dec.sigma_u, dec.z_mm, design=rig.projector.design_attrs)
    hm.camera_noise = (dec.noise.read_var, dec.noise.gain)
    objects = acceptance_objects(sr)
    simulate_acceptance_scans(folder / "acceptance", sr, {k: objects[k] for k in POSES})
    return folder, exact_lut(sr, hm)


class SameAsPtp:
    """A conventional stand-in giving, for each pixel and u_p, the PTP point of the same LUT."""

    def __init__(self, lut):
        self.lut = lut

    def points_from_up(self, cols, rows, u_p):
        rows, cols = np.asarray(rows).astype(int), np.asarray(cols).astype(int)
        u = np.full(self.lut.shape, np.nan)
        u[rows, cols] = u_p
        ev = self.lut.height.evaluate(u)
        z = np.where(np.isfinite(ev.z), ev.z, self.lut.z_min)
        xy = self.lut.evaluate(z)
        pts = np.stack([xy.x, xy.y, ev.z], axis=-1)[rows, cols]
        ok = np.isfinite(ev.z[rows, cols]) & xy.in_range[rows, cols]
        return np.where(ok[:, None], pts, np.nan)


def test_the_panel_runs_shows_and_saves(scanner, qtbot, tmp_path, monkeypatch):
    folder, lut = scanner
    monkeypatch.setattr(gui_acceptance, "conventional_calibration", lambda dataset, progress=None: SameAsPtp(lut))
    panel = AcceptancePanel(lambda: lut, lambda: folder, lambda: tmp_path)
    qtbot.addWidget(panel)
    panel.set_scans(folder / "acceptance")
    panel.mpe.setText("PF=1,PS=1,SD=1,F=1um")
    assert run_job(qtbot, panel.run()) == "finished"
    rep = panel.report
    assert rep.methods == ("ptp", "conventional") and len(rep.poses) == 2 * len(POSES)
    titles = [panel.table.horizontalHeaderItem(j).text() for j in range(2)]
    assert titles == ["PTP (per pixel)", "Conventional (two pinholes)"]
    for i, key in enumerate(FIGURES):
        cells = [panel.table.item(i, j).text() for j in range(2)]
        assert cells[0] == cells[1]  # the stand-in is PTP itself: the same figures
        big = rep.largest("ptp")[key]
        assert cells[0].startswith(f"{1e3 * big['value_mm']:+.1f} µm ({big['pose']})")
        assert cells[0].endswith("fail" if key == "F" else "pass")  # F's 1 µm is below the noise
    assert panel.image.pixmap() is not None and panel.image.pixmap().width() == panel.page.shape[1]
    out = tmp_path / "acc.json"
    assert run_job(qtbot, panel.save(out)) == "finished"
    js = json.loads(out.read_text())
    assert js["format"] == "ptp-acceptance/1" and set(js["points"]) == set(POSES)
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"


def test_missing_inputs_say_what_to_do(scanner, qtbot, tmp_path):
    folder, lut = scanner
    panel = AcceptancePanel(lambda: lut, lambda: None, lambda: tmp_path)
    qtbot.addWidget(panel)
    assert panel.run() is None and "Choose the scans" in panel.jobs.error.text()
    panel.set_scans(folder / "acceptance")
    panel.mpe.setText("PX=2")
    assert panel.run() is None and "unknown key 'PX'" in panel.jobs.error.text()
    panel.mpe.setText("")
    assert panel.run() is None and "needs the dataset folder" in panel.jobs.error.text()
    panel.conventional.setChecked(False)
    assert run_job(qtbot, panel.run()) == "finished" and panel.report.methods == ("ptp",)
    no_height = AcceptancePanel(lambda: replace(lut, height=None), lambda: None, lambda: tmp_path)
    qtbot.addWidget(no_height)
    assert no_height.run() is None and "no height map" in no_height.jobs.error.text()


def test_the_export_page_shows_the_tab_for_a_scanner_lut(wizard):
    """The tab only for a LUT with /height (the wizard's camera; the height map's own values do not matter)."""
    from test_height_map_gui import _lut_with_height

    ex = wizard.page_by_key["export"]
    tabs = ex.view_tabs
    assert not tabs.isTabVisible(ex._acceptance_tab)
    h, w = wizard.model.session.rig.camera.shape
    lut = _lut_with_height(h, w)
    wizard.model.set_lut(lut)
    assert tabs.isTabVisible(ex._acceptance_tab)
    assert tabs.tabText(ex._acceptance_tab) == "Accept the scanner: VDI/VDE 2634-2"
    wizard.model.set_lut(replace(lut, height=None))
    assert not tabs.isTabVisible(ex._acceptance_tab)
