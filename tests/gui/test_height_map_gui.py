"""The scanner's height map in the wizard (issue 34): a dataset with a height sweep gets its /height from the
Calibrate page's job (the engine call ``ptp calibrate`` makes), the page shows it and Export keeps it.

Fast tier: a LUT with a rational height map of known coefficients, shown and exported. Slow tier: the whole
chain on a 64 x 48 scanner-mild dataset (5 LCD positions, 5 plate heights, no object scans).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from gui_helpers import run_job

from ptp_studio.layoutcheck import check_page
from ptp_studio.pages.export import LUT_NAME, SESSION_NAME, quality_png
from ptpcore.io.heightmap import HeightMap
from ptpcore.io.lutfile import Lut, load_lut
from ptpcore.rig.rigfile import Projector
from ptpcore.run.scanner import calibrate_height, reconstruct
from ptpcore.run.session import load_session
from ptpcore.simulate.scanner import ScannerRig, default_objects, scanner_preset, simulate_scan, simulate_scanner_dataset

HEIGHT_ARRAYS = ("u_center", "u_scale", "p", "q", "valid", "u_min", "u_max", "rms_z", "loo_z", "sigma_z", "n_positions")


def _lut_with_height(h: int, w: int, seed: int = 34) -> Lut:
    """Straight rays over z 0..40 mm and a rational height map over u_p 200..1100 px, 10 % of pixels without."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    x = np.stack([0.1 * cols + 0.0, 0.002 * (cols - w / 2)]).astype(float)
    y = np.stack([0.1 * rows + 0.0, 0.002 * (rows - h / 2)]).astype(float)
    zero = np.zeros((h, w), f32)
    valid = rng.random((h, w)) > 0.1
    centre, scale = 200.0 + 900.0 * cols / w, np.full((h, w), 30.0)
    p = np.stack([np.full((h, w), 20.0), np.full((h, w), -20.0)])
    q = rng.uniform(-0.05, 0.05, (1, h, w))
    p[:, ~valid], q[:, ~valid] = np.nan, np.nan
    sigma_z = np.where(valid, 0.02 + 0.01 * rows / h, np.nan).astype(f32)
    hm = HeightMap(1, "x", centre, scale, p, q, valid, np.where(valid, centre - scale, np.nan).astype(f32),
                   np.where(valid, centre + scale, np.nan).astype(f32), zero + f32(0.01), zero + f32(0.012), sigma_z,
                   np.where(valid, 21, 0).astype(np.uint16), design=Projector().design_attrs,
                   chosen_by="held-out positions")
    return Lut("poly", 1, 20.0, 20.0, 0.0, 40.0, x, y, None, np.ones((h, w), bool), np.full((h, w), 9, np.uint16),
               zero, zero + f32(40.0), zero, zero, zero, zero, height=hm)


def test_the_height_map_is_shown_and_exported(wizard, qtbot, tmp_path):
    """Summary (degree, coverage, median σ_z), the σ Z heatmap among the maps, Export keeps /height. (The pages
    are not walked to: without samples the wizard stops at Acquire; the slow test checks the layout.)"""
    h, w = wizard.model.session.rig.camera.shape
    lut = _lut_with_height(h, w)
    hm = lut.height
    cal = wizard.page_by_key["calibrate"]
    wizard.model.set_lut(lut)
    text = cal.stats.text()
    assert "rational of degree 1, chosen by held-out positions" in text
    assert f"{int(hm.valid.sum())} of {h * w} pixels covered ({100 * hm.valid.mean():.1f} %)" in text
    assert f"median predicted 1σ of Z {1e3 * float(np.nanmedian(hm.sigma_z[hm.valid])):.1f} µm" in text
    assert cal.map_buttons.button(cal._map_keys.index("sigma_z")).isVisibleTo(cal)
    cal.show_map("sigma_z")
    qtbot.wait(100)
    assert "1σ of Z" in cal.heatmap.title.text()
    np.testing.assert_allclose(cal.maps["sigma_z"][1][hm.valid], 1e3 * hm.sigma_z[hm.valid], rtol=1e-6)  # µm
    row, col = np.argwhere(~hm.valid)[0]
    assert cal.heatmap.value_text(row, col) == "no height map at this pixel"
    ex = wizard.page_by_key["export"]
    assert ex.cloud_panel.use_scan.isVisibleTo(ex)  # a scan folder can be reconstructed with this LUT
    ex.on_enter()
    assert f"height map /height (degree 1, {100 * hm.valid.mean():.1f} % of pixels)" in ex.summary.text()
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export()) == "finished"
    _same_height_map(load_lut(tmp_path / "out" / LUT_NAME).height, hm)
    assert (tmp_path / "out" / quality_png("sigma_z")).is_file()
    wizard.model.set_lut(replace(lut, height=None))  # a LUT without /height: no scan source
    assert not ex.cloud_panel.use_scan.isVisibleTo(ex) and "Height map" not in cal.stats.text()
    assert not cal.map_buttons.button(cal._map_keys.index("sigma_z")).isVisibleTo(cal)


@pytest.fixture(scope="module")
def scanner_dataset(tmp_path_factory):
    rig, sim, sc = scanner_preset("scanner-mild", 64, heights=5)
    rig = rig.with_z(np.linspace(min(rig.stage.z_mm), max(rig.stage.z_mm), 5))
    folder = simulate_scanner_dataset(tmp_path_factory.mktemp("scanner") / "ds", rig, sim, sc, seed=1, objects={})
    simulate_scan(folder / "plane", ScannerRig(rig, sim, sc, seed=1), default_objects(rig)["plane"])
    return folder


def _same_height_map(a, b) -> None:
    assert (a.degree, a.direction, a.design) == (b.degree, b.direction, b.design)
    for name in HEIGHT_ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.slow
def test_calibrate_fits_shows_and_exports_the_height_map(wizard, qtbot, scanner_dataset, tmp_path):
    wizard.resize(1366, 768)
    wizard.page_by_key["rig"].import_folder(scanner_dataset)
    wizard.go_to("acquire")
    assert run_job(qtbot, wizard.page_by_key["acquire"].start()) == "finished"
    wizard.go_to("calibrate")
    cal = wizard.page_by_key["calibrate"]
    cal.configure("poly", 1, "all")
    job = cal.fit()
    assert job.name.endswith("and the height map")
    assert run_job(qtbot, job) == "finished"
    lut = wizard.model.session.lut
    assert lut.height is not None
    want = calibrate_height(scanner_dataset)  # what `ptp calibrate` puts into /height
    _same_height_map(lut.height, want)
    hm = lut.height
    assert hm.valid.mean() > 0.9
    # the summary: degree, coverage, median sigma_z, as numbers of this map
    text = cal.stats.text()
    assert f"rational of degree {hm.degree}" in text
    assert f"{int(hm.valid.sum())} of {hm.valid.size} pixels covered" in text
    assert f"median predicted 1σ of Z {1e3 * float(np.nanmedian(hm.sigma_z[hm.valid])):.1f} µm" in text
    # its sigma_z heatmap among the page's maps, the page still laid out at 1366x768
    button = cal.map_buttons.button(cal._map_keys.index("sigma_z"))
    assert button.isVisibleTo(cal)
    cal.show_map("sigma_z")
    qtbot.wait(100)
    assert cal.current_map == "sigma_z" and "1σ of Z" in cal.heatmap.title.text()
    assert not check_page(cal, wizard).problems
    # Export keeps /height (and writes its map as PNG)
    wizard.go_to("export")
    ex = wizard.page_by_key["export"]
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export()) == "finished"
    _same_height_map(load_lut(tmp_path / "out" / LUT_NAME).height, hm)
    _same_height_map(load_session(tmp_path / "out" / SESSION_NAME).lut.height, hm)  # the session file too
    assert (tmp_path / "out" / quality_png("sigma_z")).is_file()
    assert not check_page(ex, wizard).problems
    # reconstruct a scan folder into a cloud file: the engine's points, with their sigma_z
    panel = ex.cloud_panel
    panel.set_scan_folder(scanner_dataset / "plane")
    assert run_job(qtbot, panel.apply()) == "finished"
    want = reconstruct(scanner_dataset / "plane", lut)[0].cloud
    assert panel.cloud.n_points == want.n_points > 100
    np.testing.assert_array_equal(panel.cloud.z, want.z)
    assert run_job(qtbot, panel.save(tmp_path / "plane.npy")) == "finished"
    back = np.load(tmp_path / "plane.npy")  # structured: x, y, z, row, col, sigma_x, sigma_y, sigma_z
    np.testing.assert_array_equal(back["z"], want.z)
    np.testing.assert_allclose(back["sigma_z"], want.sigma_z, rtol=1e-6)


@pytest.mark.slow
def test_a_broken_height_sweep_keeps_the_lut_and_says_why(wizard, qtbot, scanner_dataset, tmp_path):
    """A height frame missing: the XY LUT is fitted and kept, the page warns, naming the file."""
    import shutil

    folder = tmp_path / "ds"
    shutil.copytree(scanner_dataset, folder, ignore=shutil.ignore_patterns("scans"))
    frame = sorted((folder / "h002").glob("*.png"))[3]
    frame.unlink()
    wizard.page_by_key["rig"].import_folder(folder)
    wizard.go_to("acquire")
    assert run_job(qtbot, wizard.page_by_key["acquire"].start()) == "finished"
    wizard.go_to("calibrate")
    cal = wizard.page_by_key["calibrate"]
    cal.configure("poly", 1, "all")
    assert run_job(qtbot, cal.fit()) == "finished"
    lut = wizard.model.session.lut
    assert lut is not None and lut.height is None and lut.valid.any()
    warning = cal.jobs.warning.text()
    assert warning.startswith("The LUT is fitted (XY only): the scanner's height map was not made") and frame.name in warning
    assert "Height map" not in cal.stats.text()


def test_a_simulated_session_has_no_height_sweep(wizard):
    """The tour's simulated rig has no height sweep: the job fits no height map, no σ Z button."""
    from ptp_studio.pages.calibrate import height_sweep_folder

    cal = wizard.page_by_key["calibrate"]
    assert height_sweep_folder(wizard.model.session) is None
    assert not cal.map_buttons.button(cal._map_keys.index("sigma_z")).isVisibleTo(cal)
