"""Image and heatmap views over per-pixel maps (pyqtgraph).

Every map is an ``(H, W)`` array indexed ``[row, col]`` (pyqtgraph runs in
row-major mode) drawn so that view coordinates are camera pixel coordinates
with pixel centres at integers (docs/method.md section 2). Large maps stay fluid:
drawn reduced to about a megapixel (:func:`ptpcore.evaluate.views.prepare_display`, on
the job's thread where a job made the map) and at camera resolution only for the part
in view once zoomed in; ``ImageItem(autoDownsample=True)``; colour levels computed once
with numpy on a subsample (:func:`ptpcore.evaluate.views.robust_levels`), histograms
likewise; no per-pixel Python anywhere.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QPointF, QRectF, Qt, Signal
from PySide6.QtWidgets import QHBoxLayout, QLabel, QSizePolicy, QVBoxLayout, QWidget
from scipy import ndimage

from ptpcore.evaluate import DISPLAY_PIXELS, DisplayMap, prepare_display, robust_levels

__all__ = ["MapView", "HeatmapPanel", "axis_label", "colormap", "legend_below", "line_profile", "plain_axes"]

PEN = "#3a3f44"

# Every map in PTP Studio is indexed [row, col] (docs/method.md section 2).
pg.setConfigOptions(imageAxisOrder="row-major")


def plain_axes(item) -> None:
    """Numbers as they are on every axis of ``item`` (a PlotWidget, PlotItem or ColorBarItem).

    pyqtgraph otherwise rescales the ticks and renames the unit ("um (x0.001)", "kpx").
    """
    if isinstance(item, pg.PlotWidget):
        item = item.getPlotItem()
    if isinstance(item, pg.ColorBarItem):
        # its axis is 45 px wide: "4000" and a label ("grey level") overlapped; as wide as its ticks and label
        item.axis.setWidth(None)
    axes = [a["item"] for a in item.axes.values()] if isinstance(item, pg.PlotItem) else [item.axis]
    for axis in axes:
        # pyqtgraph 0.14 still picks a prefix from the current range when disabling: no range allows one.
        axis.setSIPrefixEnableRanges(())
        axis.enableAutoSIPrefix(False)


def axis_label(plot, side: str, text: str, unit: str = "") -> None:
    """Label one axis ``text (unit)``, ticks in that unit (no SI prefix scaling)."""
    item = plot.getPlotItem() if isinstance(plot, pg.PlotWidget) else plot
    item.setLabel(side, text, units=unit or None)
    plain_axes(item)


def legend_below(plot, columns: int = 3) -> pg.LegendItem:
    """A legend under the plot's axes, in ``columns`` columns: never over the data, and in the plot's PNG.

    The items named when plotted (``name=``) are added to it as pyqtgraph's own legend would be.
    """
    item = plot.getPlotItem() if isinstance(plot, pg.PlotWidget) else plot
    legend = pg.LegendItem(colCount=columns, labelTextSize="8pt")
    item.layout.addItem(legend, 4, 1)
    item.legend = legend  # PlotItem.plot(name=...) and addItem(name=...) add their entries to it
    return legend


def colormap(name: str) -> pg.ColorMap:
    """A named pyqtgraph colour map (bundled; no network)."""
    return pg.colormap.get(name)


def line_profile(data: np.ndarray, p0, p1) -> tuple[np.ndarray, np.ndarray]:
    """Values along a segment, one sample per pixel of length (nearest pixel).

    Parameters
    ----------
    data : (H, W) array
    p0, p1 : (x, y) = (col, row) camera pixel coordinates

    Returns
    -------
    distance : (n,) float64, camera px from ``p0``
    values : (n,) float64 (NaN outside the map)
    """
    (x0, y0), (x1, y1) = p0, p1
    length = math.hypot(x1 - x0, y1 - y0)
    n = max(2, int(math.ceil(length)) + 1)
    t = np.linspace(0.0, 1.0, n)
    cols = x0 + t * (x1 - x0)
    rows = y0 + t * (y1 - y0)
    vals = ndimage.map_coordinates(np.asarray(data, dtype=np.float64), [rows, cols], order=0,
                                   mode="constant", cval=np.nan)
    return t * length, vals


class MapView(pg.GraphicsLayoutWidget):
    """One ``(H, W)`` map with an optional colour bar, overlay, cursor readout and pixel picking.

    Signals
    -------
    hovered(int, int)
        Camera pixel (row, col) under the cursor, (-1, -1) when outside.
    pixelClicked(int, int)
        Camera pixel (row, col) clicked.
    """

    hovered = Signal(int, int)
    pixelClicked = Signal(int, int)

    def __init__(self, parent: QWidget | None = None, colour_bar: bool = True, title: str = ""):
        super().__init__(parent)
        self.setMinimumSize(200, 160)
        self.plot = self.addPlot(row=0, col=0, title=title or None)
        self.plot.setAspectLocked(True)
        self.plot.invertY(True)
        axis_label(self.plot, "bottom", "column", "px")
        axis_label(self.plot, "left", "row", "px")
        self.plot.showGrid(False, False)
        self.image = pg.ImageItem(autoDownsample=True)
        self.plot.addItem(self.image)
        self.overlay = pg.ImageItem(autoDownsample=True)
        self.overlay.setZValue(5)
        self.plot.addItem(self.overlay)
        self.marker = pg.ScatterPlotItem(size=14, symbol="+", pen=pg.mkPen("#e8333a", width=2), brush=None)
        self.marker.setZValue(10)
        self.plot.addItem(self.marker)
        self.bar: pg.ColorBarItem | None = None
        if colour_bar:
            self.bar = pg.ColorBarItem(values=(0.0, 1.0), colorMap=colormap("viridis"), width=16,
                                       interactive=True, pen=PEN, colorMapMenu=False)
            self.bar.setImageItem(self.image, insert_in=self.plot)
            plain_axes(self.bar)
        self.data: np.ndarray | None = None
        self._shape: tuple[int, int] | None = None
        self._step = 1  # camera pixels per map pixel along each side (a reduced preview)
        self._full: np.ndarray | None = None  # the camera-resolution map behind a reduced one (set_map(full=))
        self._detail: tuple[int, int, int, int] | None = None  # rows r0:r1, cols c0:c1 shown at full resolution
        self._cmap_name: str | None = None  # the colour map last set by name
        self.plot.vb.sigRangeChanged.connect(self._update_detail)
        self._screen_pixels = DISPLAY_PIXELS  # the view box's device pixels (GUI thread writes, any reads)
        self.plot.vb.sigResized.connect(self.note_size)
        self._pad = (0, 0)  # margins (px) left and right, top and bottom, that give the view box the map's aspect
        self._base_margins = tuple(self.ci.layout.getContentsMargins())  # left, top, right, bottom
        self.plot.vb.sigResized.connect(self._frame_to_map)
        self.note_size()
        self.scene().sigMouseMoved.connect(self._on_moved)
        self.scene().sigMouseClicked.connect(self._on_clicked)

    def note_size(self, *_) -> None:
        """Take the view's current size for :meth:`preview_pixels` (GUI thread; on every resize)."""
        rect, dpr = self.plot.vb.rect(), self.devicePixelRatioF()
        shown = self.width() * self.height()  # the view box is inside: at most this
        if rect.width() * rect.height() >= 64 * 64:  # laid out (not a page never shown)
            shown = min(shown, rect.width() * rect.height())
        self._screen_pixels = max(1, int(shown * dpr * dpr))

    def _frame_to_map(self, *_) -> None:
        """Give the view box the map's aspect (pad the layout's sides), so that with the aspect locked the
        view range is the map's extent: the map fills the box instead of floating in empty rows or columns.

        The space the box may take (its size plus the current pads) is invariant, so one pass settles it.
        """
        if self._shape is None:
            return
        rect = self.plot.vb.rect()
        h, w = self._shape
        px, py = self._pad
        avail_w, avail_h = rect.width() + 2 * px, rect.height() + 2 * py
        if avail_w < 16 or avail_h < 16:
            return  # not laid out yet
        if avail_h * w > avail_w * h:  # too tall for the map: pad top and bottom
            pad = (0, int(round((avail_h - avail_w * h / w) / 2)))
        else:
            pad = (int(round((avail_w - avail_h * w / h) / 2)), 0)
        if pad == self._pad:
            return
        self._pad = pad
        m = self._base_margins
        self.ci.layout.setContentsMargins(m[0] + pad[0], m[1] + pad[1], m[2] + pad[0], m[3] + pad[1])

    def resizeEvent(self, event) -> None:  # noqa: N802 - Qt API
        super().resizeEvent(event)
        if hasattr(self, "_screen_pixels"):  # not while the base class is being built
            self.note_size()

    def preview_pixels(self) -> int:
        """How many pixels a live preview needs to look sharp here: twice the view's device pixels.

        Read from a worker thread (:class:`ptp_studio.session.FramePreview`): a plain number
        the GUI thread updates when the view is resized. Up to twice the screen's pixels, the
        preview is drawn as it is (pyqtgraph reduces an image only when a screen pixel holds
        two or more of its pixels along a side).
        """
        return 2 * self._screen_pixels

    # ---- content ----------------------------------------------------------
    def set_map(self, data: np.ndarray, levels: tuple[float, float] | None = None,
                cmap: pg.ColorMap | str | None = None, label: str | None = None,
                keep_view: bool = True, step: int = 1, extent: tuple[int, int] | None = None,
                full: np.ndarray | None = None) -> tuple[float, float]:
        """Show a scalar map; returns the colour levels used.

        ``levels`` default to the 1st-99th percentiles of a subsample. A reduced map
        (:func:`ptpcore.evaluate.views.reduce_for_display`) gives its ``step`` (each of its
        pixels a ``step x step`` block of camera pixels) and ``extent``, the camera shape (H, W)
        it covers; an overlay set afterwards is taken at the same step. ``full``, the map at
        camera resolution behind a reduced one, is shown instead (the part in view) once the
        view is zoomed in to at most :data:`ptpcore.evaluate.views.DISPLAY_PIXELS` camera pixels:
        every pixel stays inspectable, and the GUI thread never draws a whole 5-12 MP map.
        """
        data = np.asarray(data)
        if data.ndim != 2:
            raise ValueError(f"a map must be (H, W), got shape {data.shape}")
        if levels is None:
            levels = robust_levels(data)
        self.data = data
        if isinstance(cmap, str):
            # The colour bar rebuilds its lookup table on every setColorMap: not for each live frame.
            name, cmap = cmap, (None if cmap == self._cmap_name else colormap(cmap))
            self._cmap_name = name
        else:
            self._cmap_name = None
        if self.bar is not None:
            if cmap is not None:
                self.bar.setColorMap(cmap)
            lo, hi = levels
            self.bar.rounding = max((hi - lo) / 1000.0, 1e-12)
            self.bar.setLevels(levels)
            if label is not None:
                self.bar.axis.setLabel(label)
        elif cmap is not None:
            self.image.setColorMap(cmap)
        self.image.setImage(data, levels=levels, autoLevels=False)
        self._step = step
        self._full = full if step > 1 else None
        self._detail = None
        self._place(data.shape, keep_view, extent)
        self._update_detail()
        return levels

    def set_rgba(self, rgba: np.ndarray, keep_view: bool = True) -> None:
        """Show an (H, W, 4) uint8 image as it is (no colour bar)."""
        self.data = None
        self._step = 1
        self._full = self._detail = None
        self.image.setImage(rgba, autoLevels=False, levels=(0, 255))
        self._place(rgba.shape[:2], keep_view)

    def set_overlay(self, rgba: np.ndarray | None) -> None:
        """An (H, W, 4) uint8 overlay on top of the map (None clears it)."""
        if rgba is None:
            self.overlay.clear()
            return
        self.overlay.setImage(rgba, autoLevels=False, levels=(0, 255))
        self.overlay.setRect(self._covered(rgba.shape))

    def _covered(self, shape) -> QRectF:
        """The view rectangle of a map of ``shape`` at the current step (whole blocks of a reduced map)."""
        h, w = shape[:2]
        return QRectF(-0.5, -0.5, w * self._step, h * self._step)

    def _place(self, shape, keep_view: bool, extent=None) -> None:
        h, w = extent if extent is not None else shape[:2]
        if self._shape != (h, w) or not keep_view:
            self._shape = (h, w)
            self._frame_to_map()
            self.plot.setRange(xRange=(-0.5, w - 0.5), yRange=(-0.5, h - 0.5), padding=0)
        self.image.setRect(self._covered(shape))

    def _update_detail(self, *_) -> None:
        """Show the part of the full map in view at camera resolution when zoomed in far enough,
        the reduced map otherwise (see :meth:`set_map`)."""
        if self._full is None or self._shape is None:
            return
        h, w = self._shape
        (x0, x1), (y0, y1) = self.plot.vb.viewRange()
        c0, c1 = max(0, int(math.floor(x0 + 0.5))), min(w, int(math.ceil(x1 + 0.5)))
        r0, r1 = max(0, int(math.floor(y0 + 0.5))), min(h, int(math.ceil(y1 + 0.5)))
        if c1 <= c0 or r1 <= r0 or (r1 - r0) * (c1 - c0) > DISPLAY_PIXELS:
            if self._detail is not None:  # zoomed out again: the reduced map (self.data, self._step)
                self._detail = None
                self._show_part(self.data, self._covered(self.data.shape))
            return
        d = self._detail
        if d is not None and d[0] <= r0 and r1 <= d[1] and d[2] <= c0 and c1 <= d[3]:
            return  # the part shown still covers the view
        # A quarter view's margin on each side (at most 2.25 megapixels): panning a little does not cut a new part.
        mr, mc = (r1 - r0) // 4, (c1 - c0) // 4
        self._detail = (max(0, r0 - mr), min(h, r1 + mr), max(0, c0 - mc), min(w, c1 + mc))
        r0, r1, c0, c1 = self._detail
        self._show_part(self._full[r0:r1, c0:c1], QRectF(c0 - 0.5, r0 - 0.5, c1 - c0, r1 - r0))

    def _show_part(self, image: np.ndarray, rect: QRectF) -> None:
        self.image.setImage(image, levels=self.image.getLevels(), autoLevels=False)
        self.image.setRect(rect)

    def clear_map(self) -> None:
        """Show nothing (the data it showed are gone)."""
        self._full = self._detail = None
        self.data = None
        self.image.clear()
        self.overlay.clear()
        self.marker.setData([], [])

    def set_marker(self, row: int | None, col: int | None) -> None:
        if row is None:
            self.marker.setData([], [])
        else:
            self.marker.setData([col], [row])

    @property
    def levels(self) -> tuple[float, float]:
        lv = self.image.getLevels()
        return (float(lv[0]), float(lv[1])) if lv is not None else (0.0, 1.0)

    # ---- mouse ------------------------------------------------------------
    def pixel_at(self, scene_pos) -> tuple[int, int] | None:
        if self._shape is None or not self.plot.sceneBoundingRect().contains(scene_pos):
            return None
        p = self.plot.vb.mapSceneToView(scene_pos)
        col, row = int(math.floor(p.x() + 0.5)), int(math.floor(p.y() + 0.5))
        h, w = self._shape
        if 0 <= row < h and 0 <= col < w:
            return row, col
        return None

    def _on_moved(self, pos) -> None:
        px = self.pixel_at(pos)
        self.hovered.emit(*(px if px else (-1, -1)))

    def _on_clicked(self, ev) -> None:
        if ev.button() != Qt.LeftButton:
            return
        px = self.pixel_at(ev.scenePos())
        if px is not None:
            self.pixelClicked.emit(*px)

    def scene_pos_of(self, row: float, col: float) -> QPointF:
        """Scene position of a pixel centre (for tests and the tour)."""
        return self.plot.vb.mapViewToScene(QPointF(col, row))


class HeatmapPanel(QWidget):
    """A heatmap with its colour bar, its histogram and a value-under-cursor line.

    The histogram is drawn from the same numbers as the image (a subsample
    of at most two million pixels), with the colour levels marked on it.
    """

    pixelClicked = Signal(int, int)

    def __init__(self, parent: QWidget | None = None, histogram: bool = True):
        super().__init__(parent)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.setSpacing(4)
        self.title = QLabel()
        self.title.setObjectName("panelTitle")
        lay.addWidget(self.title)
        self.view = MapView(self)
        lay.addWidget(self.view, 4)
        self.hist: pg.PlotWidget | None = None
        if histogram:
            self.hist = pg.PlotWidget(self)
            self.hist.setMinimumHeight(110)
            self.hist.setMaximumHeight(170)
            self.hist.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Preferred)
            self.hist.setMouseEnabled(x=False, y=False)
            self.hist.hideButtons()
            self.hist.setLabel("left", "pixels")
            plain_axes(self.hist)
            self.hist_curve = pg.PlotDataItem(stepMode="center", fillLevel=0, pen=pg.mkPen("#2b6cb0"),
                                              brush=pg.mkBrush(43, 108, 176, 90))
            self.hist.addItem(self.hist_curve)
            self.lo_line = pg.InfiniteLine(angle=90, pen=pg.mkPen("#e8333a", style=Qt.DashLine))
            self.hi_line = pg.InfiniteLine(angle=90, pen=pg.mkPen("#e8333a", style=Qt.DashLine))
            self.hist.addItem(self.lo_line)
            self.hist.addItem(self.hi_line)
            lay.addWidget(self.hist, 1)
            if self.view.bar is not None:
                self.view.bar.sigLevelsChanged.connect(self._levels_moved)
        self.readout = QLabel("move the cursor over the map")
        self.readout.setObjectName("readout")
        self.readout.setTextInteractionFlags(Qt.TextSelectableByMouse)
        lay.addWidget(self.readout)
        self.unit = ""
        self.scale = 1.0
        self.value_text: Callable[[int, int], str] | None = None
        self.data: np.ndarray | None = None  # the full map (the view may show it reduced)
        self.view.hovered.connect(self._hovered)
        self.view.pixelClicked.connect(self.pixelClicked)
        self.hist_edges = np.zeros(0)
        self.hist_counts = np.zeros(0)

    def set_map(self, data: np.ndarray, *, title: str, unit: str = "", cmap: str = "viridis",
                levels: tuple[float, float] | None = None, integer: bool = False,
                value_text: Callable[[int, int], str] | None = None,
                prepared: DisplayMap | None = None) -> None:
        """Show ``data`` (already in display units: µm, px, counts).

        Parameters
        ----------
        data : (H, W) array
            The full map: the readout shows its values.
        title : str
        unit : str
            Shown on the colour bar, histogram axis and readout.
        cmap : str
        levels : (lo, hi), optional
            Default: 1st-99th percentile of a subsample; integer maps use min-max.
        integer : bool
            Integer-valued map (counts): one histogram bin per value.
        value_text : callable (row, col) -> str, optional
            Custom readout text.
        prepared : ptpcore.evaluate.views.DisplayMap, optional
            ``data`` already reduced, with its levels and histogram
            (:func:`ptpcore.evaluate.views.prepare_display`, on a worker thread); computed here otherwise.
        """
        if prepared is None:
            prepared = prepare_display(data, integer=integer, levels=levels)
        self.unit = unit
        self.value_text = value_text
        self.title.setText(title)
        self.data = data
        self.view.set_map(prepared.image, levels=prepared.levels, cmap=cmap, label=unit, step=prepared.step,
                          extent=prepared.extent, full=data)
        if self.hist is not None:
            self.hist_edges, self.hist_counts = prepared.hist_edges, prepared.hist_counts
            self.hist_curve.setData(self.hist_edges, self.hist_counts)
            self.hist.setLabel("bottom", unit or "value")
            self._levels_moved()

    def clear(self, title: str = "") -> None:
        """Empty the heatmap, its histogram and readout; ``title`` says why."""
        self.title.setText(title)
        self.value_text = None
        self.data = None
        self.view.clear_map()
        if self.hist is not None:
            self.hist_edges, self.hist_counts = np.zeros(0), np.zeros(0)
            self.hist_curve.clear()
        self.readout.setText("")

    def _levels_moved(self, *_):
        if self.hist is None:
            return
        lo, hi = self.view.levels
        self.lo_line.setValue(lo)
        self.hi_line.setValue(hi)

    def _hovered(self, row: int, col: int) -> None:
        if row < 0:
            return
        if self.value_text is not None:
            text = self.value_text(row, col)
        else:
            v = self.data[row, col] if self.data is not None else np.nan
            text = f"{v:.4g} {self.unit}".strip() if np.isfinite(v) else "no value (invalid pixel)"
        self.readout.setText(f"row {row}, col {col}: {text}")


class Legend(QWidget):
    """Colour swatches with labels, one row each (rows are reused, never re-created)."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__(parent)
        self._lay = QVBoxLayout(self)
        self._lay.setContentsMargins(0, 0, 0, 0)
        self._lay.setSpacing(2)
        self.entries: list[tuple[str, tuple[int, int, int, int]]] = []
        self._rows: list[tuple[QWidget, QLabel, QLabel]] = []

    def set_entries(self, entries: list[tuple[str, tuple[int, int, int, int], str]]) -> None:
        """``entries``: (name, rgba, extra text) per row."""
        while len(self._rows) < len(entries):
            row = QWidget(self)
            h = QHBoxLayout(row)
            h.setContentsMargins(0, 0, 0, 0)
            sw = QLabel(row)
            sw.setFixedSize(14, 14)
            text = QLabel(row)
            text.setWordWrap(True)  # a long reason wraps in a narrow side panel
            h.addWidget(sw)
            h.addWidget(text, 1)
            self._lay.addWidget(row)
            self._rows.append((row, sw, text))
        self.entries = [(name, rgba) for name, rgba, _ in entries]
        for i, (row, sw, text) in enumerate(self._rows):
            row.setVisible(i < len(entries))
            if i >= len(entries):
                continue
            name, rgba, extra = entries[i]
            sw.setStyleSheet(f"background: rgba({rgba[0]},{rgba[1]},{rgba[2]},{rgba[3]});"
                             " border: 1px solid #555;")
            text.setText(f"{name}  <span style='color:#666'>{extra}</span>" if extra else name)

    def texts(self) -> list[str]:
        """The names shown, in order (tests)."""
        return [name for name, _ in self.entries]
