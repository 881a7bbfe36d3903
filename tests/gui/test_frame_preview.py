"""Live frame previews at 5 MP reach the GUI reduced, drawn over the whole camera, saturation kept."""

from __future__ import annotations

import numpy as np

from ptpcore.evaluate import DISPLAY_PIXELS, display_step
from ptp_studio.session import SATURATION_RGBA, FramePreview
from ptp_studio.widgets.maps import MapView

H, W = 2048, 2448  # 5 MP


class _Ctx:
    def __init__(self):
        self.sent = []

    def emit(self, payload):
        self.sent.append(payload)


def test_preview_is_reduced_on_the_worker_and_placed_over_the_camera(qtbot):
    frame = np.full((H, W), 100, np.uint8)
    frame[H - 1, W - 1] = 255  # one saturated pixel, in the padded corner block
    ctx = _Ctx()
    FramePreview(ctx, max_level=255, interval=0.0)(3, ("x", 0, 24, 0, 8), frame)
    (kind, k, _spec, image, overlay, sat_frac, step, shape), = ctx.sent
    assert (kind, k, shape, step) == ("frame", 3, (H, W), display_step((H, W)))
    assert image.size <= DISPLAY_PIXELS and image.dtype == np.uint8
    assert sat_frac == 1.0 / (H * W)  # from the whole frame
    red = (overlay == SATURATION_RGBA).all(axis=-1)
    assert red.sum() == 1 and red[-1, -1]

    view = MapView()
    qtbot.addWidget(view)
    view.resize(700, 600)
    view.show()
    qtbot.waitExposed(view)
    view.set_map(image, levels=(0, 255), cmap="CET-L1", step=step, extent=shape)
    view.set_overlay(overlay)
    rect = view.image.mapRectToParent(view.image.boundingRect())
    assert (rect.left(), rect.top()) == (-0.5, -0.5)
    assert (rect.width(), rect.height()) == (image.shape[1] * step, image.shape[0] * step)
    orect = view.overlay.mapRectToParent(view.overlay.boundingRect())
    assert (orect.width(), orect.height()) == (rect.width(), rect.height())
    assert view.pixel_at(view.scene_pos_of(H - 3, W - 5)) == (H - 3, W - 5)  # camera pixels, not the preview's


def test_preview_takes_the_views_size_and_sends_no_overlay_without_saturation(qtbot):
    """A 12 MP frame previewed in a 500 x 400 view: reduced on the worker to at most twice the
    view's device pixels (the GUI thread draws no more than the screen shows); resizing the view
    during the job changes the next frame's size; a frame with nothing saturated has no overlay."""
    view = MapView()
    qtbot.addWidget(view)
    view.resize(500, 400)
    view.show()
    qtbot.waitExposed(view)
    rect, dpr = view.plot.vb.rect(), view.devicePixelRatioF()
    shown = rect.width() * rect.height() * dpr * dpr
    assert 0 < shown < 500 * 400 * dpr * dpr
    assert view.preview_pixels() == 2 * int(shown)

    frame = np.full((3000, 4000), 100, np.uint8)
    ctx = _Ctx()
    preview = FramePreview(ctx, max_level=255, interval=0.0, max_pixels=view.preview_pixels)
    preview(0, ("x", 0, 24, 0, 8), frame)
    (_, _, _, image, overlay, sat_frac, step, shape), = ctx.sent
    assert step == display_step(shape, view.preview_pixels()) and image.size <= view.preview_pixels()
    assert image.size < DISPLAY_PIXELS / 2
    assert overlay is None and sat_frac == 0.0

    view.resize(1000, 800)
    qtbot.waitUntil(lambda: view.preview_pixels() > 3 * shown)
    preview(1, ("x", 0, 24, 0, 8), frame)
    assert ctx.sent[-1][6] < step  # a bigger view: a finer preview


def test_a_view_never_shown_asks_for_its_widgets_size_not_a_megapixel(qtbot):
    """The Acquire page may start its job before its frame view was ever laid out: the preview
    size then comes from the widget's own size (a megapixel preview cost the GUI 130 ms a frame)."""
    view = MapView()
    qtbot.addWidget(view)
    view.resize(400, 300)  # a hidden widget gets no resize event: the page measures before its job
    view.note_size()
    dpr = view.devicePixelRatioF()
    assert 0 < view.preview_pixels() <= 2 * 400 * 300 * dpr * dpr < DISPLAY_PIXELS
