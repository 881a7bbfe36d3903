"""Heatmaps stay fluid at 5 megapixels: downsampled image items, levels and histograms from numpy subsamples."""

from __future__ import annotations

import time

import numpy as np

from ptpcore.evaluate import display_step, reduce_for_display, robust_levels
from ptp_studio.widgets.maps import HeatmapPanel

H, W = 2048, 2448  # 5 MP


def test_five_megapixel_maps_switch_without_stalls(qtbot):
    rng = np.random.default_rng(0)
    maps = [rng.gamma(2.0, 1.5, size=(H, W)).astype(np.float32) for _ in range(3)]
    for m in maps:
        m[:100] = np.nan  # invalid pixels
    panel = HeatmapPanel()
    qtbot.addWidget(panel)
    panel.resize(900, 700)
    panel.show()
    qtbot.waitExposed(panel)
    assert panel.view.image.autoDownsample
    panel.set_map(maps[0], title="warm-up", unit="µm")
    panel.grab()
    t0 = time.perf_counter()
    for i in range(6):
        m = maps[i % 3]
        panel.set_map(m, title=f"map {i}", unit="µm")
        panel.grab()  # a full repaint, as on screen
    per_switch = (time.perf_counter() - t0) / 6
    # Generous bound for slow CI machines; a per-pixel Python path would take minutes.
    assert per_switch < 1.0, f"switching a 5 MP heatmap took {per_switch:.2f} s"
    shown = maps[5 % 3]
    assert panel.view.levels == robust_levels(shown)  # levels of the full map
    # drawn reduced to about a megapixel (3 x 3 camera pixels a block at 5 MP), over the whole camera
    step = display_step(shown.shape)
    assert step == 3
    np.testing.assert_array_equal(panel.view.image.image, reduce_for_display(shown, step))
    rect = panel.view.image.mapRectToParent(panel.view.image.boundingRect())
    assert (rect.left(), rect.top()) == (-0.5, -0.5)
    assert (rect.width(), rect.height()) == (816 * 3, 683 * 3)  # whole blocks: the last row of blocks is padded
    # the readout gives the full map's values
    panel._hovered(1001, 2002)
    assert f"{shown[1001, 2002]:.4g}" in panel.readout.text()
    # zoom and pan re-render only what is visible
    t0 = time.perf_counter()
    for k in range(1, 6):
        panel.view.plot.setRange(xRange=(0, W / (2 * k)), yRange=(0, H / (2 * k)), padding=0)
        panel.grab()
    assert (time.perf_counter() - t0) / 5 < 1.0


def test_zoomed_in_a_five_megapixel_map_shows_camera_pixels(qtbot):
    """Reduced when the whole map is in view; zoomed in to at most a megapixel, the part in view (and a
    margin) at camera resolution, so that every pixel can be inspected; zoomed out, reduced again."""
    rng = np.random.default_rng(1)
    data = rng.normal(5.0, 1.0, size=(H, W)).astype(np.float32)
    panel = HeatmapPanel()
    qtbot.addWidget(panel)
    panel.resize(900, 700)
    panel.show()
    qtbot.waitExposed(panel)
    panel.set_map(data, title="residuals", unit="µm")
    view = panel.view
    assert view.image.image.shape == (683, 816)  # reduced, 3 x 3 px a block
    levels = view.levels
    view.plot.setRange(xRange=(1000, 1400), yRange=(600, 900), padding=0)
    panel.grab()
    shown = view.image.image
    assert shown.size <= 2.25 * (1 << 20) and shown.shape[0] >= 300 and shown.shape[1] >= 400
    rect = view.image.mapRectToParent(view.image.boundingRect())
    r0, c0 = int(rect.top() + 0.5), int(rect.left() + 0.5)
    assert r0 <= 600 and c0 <= 1000 and r0 + shown.shape[0] >= 900 and c0 + shown.shape[1] >= 1400
    np.testing.assert_array_equal(shown, data[r0:r0 + shown.shape[0], c0:c0 + shown.shape[1]])
    assert view.levels == levels  # the same colours as the reduced map
    panel._hovered(700, 1100)
    assert f"{data[700, 1100]:.4g}" in panel.readout.text()
    view.plot.setRange(xRange=(0, W), yRange=(0, H), padding=0)
    assert view.image.image.shape == (683, 816)
