"""Export page: the LUT applied to a constant height and to a height-map file, shown as a top view, saved."""

from __future__ import annotations

import numpy as np
from gui_helpers import lut_on_export, run_job
from PySide6.QtCore import Qt
from PySide6.QtTest import QTest

from ptp_studio.widgets.pointcloud import top_view


def _lut_on_export(wizard, qtbot):
    return lut_on_export(wizard, qtbot), wizard.model.session.lut


def test_apply_show_and_save_a_point_cloud(wizard, qtbot, tmp_path):
    ex, lut = _lut_on_export(wizard, qtbot)
    panel = ex.cloud_panel
    assert panel.cloud is None and not panel.save_button.isEnabled()
    # The height defaults to the middle of the calibrated range.
    assert abs(panel.height.value() - 0.5 * (lut.z_min + lut.z_max)) < 1e-3

    # Before Apply the view's place says what it will show, with the LUT's range (it was an empty plot).
    assert panel.view.currentWidget() is panel.placeholder and panel.placeholder.isVisible()
    assert not panel.plot.isVisible()
    assert "No point cloud yet" in panel.placeholder.text() and "Apply the LUT" in panel.placeholder.text()
    assert f"z = {lut.z_min:g} … {lut.z_max:g} mm" in panel.placeholder.text()

    z = round(0.5 * (lut.z_min + lut.z_max) + 0.37, 4)
    panel.set_constant(z)
    QTest.mouseClick(panel.apply_button, Qt.LeftButton, pos=panel.apply_button.rect().center())
    assert run_job(qtbot, panel.jobs.job) == "finished"
    assert panel.view.currentWidget() is panel.plot and panel.plot.isVisible()
    want = lut.points(z)
    assert panel.cloud.n_points == want.n_points > 0
    np.testing.assert_array_equal(panel.cloud.x, want.x)
    assert panel.summary.text() == want.summary()
    image, rect = top_view(want)
    shown = panel.image.image
    assert shown is not None and shown.shape == image.shape
    assert np.nanmin(shown) == z == np.nanmax(shown)  # a flat cloud: one colour
    assert rect.left() == want.x.min() and rect.top() == want.y.min()

    # A tilted height map from a file, with holes.
    h, w = lut.shape
    rows, cols = np.mgrid[0:h, 0:w]
    zmap = lut.z_min + (lut.z_max - lut.z_min) * (0.2 + 0.6 * cols / (w - 1))
    zmap[rows % 9 == 0] = np.nan
    np.save(tmp_path / "heights.npy", zmap)
    panel.set_height_file(tmp_path / "heights.npy")
    assert run_job(qtbot, panel.apply()) == "finished"
    assert panel.cloud.n_no_height == int(np.isnan(zmap).sum())
    assert panel.cloud.n_points == lut.points(zmap).n_points
    assert np.nanmax(panel.image.image) > np.nanmin(panel.image.image)
    assert panel.colorbar.levels()[0] < panel.colorbar.levels()[1]

    assert panel.save_button.isEnabled()
    out = tmp_path / "cloud.ply"
    assert run_job(qtbot, panel.save(out)) == "finished"
    data = out.read_bytes()
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert f"element vertex {panel.cloud.n_points}\n".encode() in data
    assert panel.saved == out and "saved" in panel.summary.text()
    assert ex.isComplete() is False  # the Export page still wants its own export: unchanged rules


def test_bad_height_map_is_one_readable_error(wizard, qtbot, tmp_path):
    ex, lut = _lut_on_export(wizard, qtbot)
    panel = ex.cloud_panel
    np.save(tmp_path / "small.npy", np.zeros((3, 4)))
    panel.set_height_file(tmp_path / "small.npy")
    assert run_job(qtbot, panel.apply()) == "errored"
    assert "small.npy" in panel.jobs.error.text() and panel.jobs.error.isVisible()
    assert panel.cloud is None and not panel.save_button.isEnabled()
    panel.set_constant(lut.z_max + 100.0)  # above every pixel's range: no point
    assert run_job(qtbot, panel.apply()) == "errored"
    assert "no point" in panel.jobs.error.text()
    panel.extrapolate.setChecked(True)  # poly LUTs extrapolate when asked
    assert run_job(qtbot, panel.apply()) == "finished"
    assert panel.cloud.n_extrapolated == panel.cloud.n_points > 0
