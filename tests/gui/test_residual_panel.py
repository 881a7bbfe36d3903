"""The Calibrate page's residual arrows on a big sensor: a screenful of arrows, every block once zoomed in."""

from __future__ import annotations

import numpy as np

from ptpcore.evaluate.residuals import ResidualField
from ptp_studio.widgets.residuals import MAX_ARROWS, ResidualPanel, arrow_segments


def _field_12mp(block: int = 16, k: int = 3) -> ResidualField:
    """A 4000 x 3000 px field of 16 px blocks (250 x 188 of them), a 1 um shift in +X everywhere."""
    gy, gx = -(-3000 // block), -(-4000 // block)
    dx = np.full((k, gy, gx), 1e-3)
    dx[:, :10, :10] = np.nan  # a corner without samples
    return ResidualField(np.arange(k, dtype=float), np.ones(k, bool), np.ones(k), np.full(k, 10),
                         np.arange(gy) * block + (block - 1) / 2, np.arange(gx) * block + (block - 1) / 2,
                         dx, np.zeros_like(dx), np.zeros((3000, 4000)), np.arange(k), np.zeros((1, 2), int), block)


def test_a_big_field_is_drawn_merged_and_every_block_when_zoomed_in(qtbot):
    panel = ResidualPanel()
    qtbot.addWidget(panel)
    panel.resize(600, 500)
    panel.show()
    qtbot.waitExposed(panel)
    field = _field_12mp()
    panel.set_field(field)
    x, y = panel.arrows.getData()
    assert 0 < x.size // 2 <= MAX_ARROWS < np.isfinite(field.dx[0]).sum()
    assert "blocks of" in panel.plot.getPlotItem().titleLabel.text
    # the merged arrows point the field's way (+X), bases spread over the whole image
    assert np.all(x[1::2] > x[::2]) and np.allclose(y[1::2], y[::2])
    assert x[::2].min() < 400 and x[::2].max() > 3600 and y[::2].max() > 2600

    panel.plot.getViewBox().setRange(xRange=(1000, 1400), yRange=(1000, 1300), padding=0)
    qtbot.waitUntil(lambda: "blocks of" not in panel.plot.getPlotItem().titleLabel.text)
    x, _y = panel.arrows.getData()
    bases = set(np.round(x[::2], 3))
    want = field.cols[(field.cols >= 1000) & (field.cols <= 1400)]
    assert set(np.round(want, 3)) <= bases  # every block in view has its own arrow
    full_x, _fy, scale = arrow_segments(field, 0)
    assert f"{scale:.3g} px per µm" in panel.plot.getPlotItem().titleLabel.text  # the whole position's scale


def test_the_first_pixel_shown_is_the_valid_one_nearest_the_centre_searched_by_bands(monkeypatch):
    """The Calibrate page selects the valid pixel nearest the sensor's centre (the first in row order
    among equally near ones); searched in bands of 3 rows it is the whole image's argmin."""
    from ptp_studio.pages import calibrate

    rng = np.random.default_rng(4)
    for density in (0.002, 0.05, 0.8):
        valid = rng.random((37, 53)) < density
        rows, cols = np.nonzero(valid)
        i = int(np.argmin((rows - 37 / 2) ** 2 + (cols - 53 / 2) ** 2))
        monkeypatch.setattr(calibrate, "_CENTRE_ROWS", 3)
        assert calibrate._central_pixel(valid) == (rows[i], cols[i])
    tie = np.zeros((4, 4), bool)
    tie[1, 1] = tie[3, 3] = True  # both sqrt(2) px from the centre (2, 2): the first in row order
    assert calibrate._central_pixel(tie) == (1, 1)
    assert calibrate._central_pixel(np.zeros((5, 5), bool)) is None
