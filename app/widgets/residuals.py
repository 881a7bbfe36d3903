"""The Calibrate page's residual diagnostics: per position the field of (sample - LUT) as arrows.

The engine computes the field (:func:`ptpcore.evaluate.residuals.residual_field`);
this panel draws one position's arrows (a segment from each block's centre, a dot
at its base), lists the positions worst first and names the worst pixels. At most
:data:`MAX_ARROWS` arrows are drawn: where more blocks are in view, neighbouring blocks are
merged (:meth:`~ptpcore.evaluate.residuals.ResidualField.merged`); zoomed in, every block
has its arrow again.
"""

from __future__ import annotations

import math

import numpy as np
import pyqtgraph as pg
from PySide6.QtWidgets import QComboBox, QGroupBox, QHBoxLayout, QLabel, QVBoxLayout

from ptpcore.evaluate import ResidualField
from ptpcore.rig import position_label

from .maps import axis_label

__all__ = ["ResidualPanel", "arrow_segments", "arrow_group", "MAX_ARROWS"]

MAX_ARROWS = 4000
"""Arrows drawn at most: 21 000 of them (a 12 MP field) cost the GUI thread 0.1-0.2 s to set and to paint."""


def arrow_group(n_rows: int, n_cols: int, max_arrows: int = MAX_ARROWS) -> int:
    """Blocks per side merged into one arrow so that ``n_rows x n_cols`` blocks give at most ``max_arrows``."""
    return max(1, math.ceil(math.sqrt(max(n_rows, 0) * max(n_cols, 0) / max_arrows)))


def arrow_segments(field: ResidualField, k: int, window=None) -> tuple[np.ndarray, np.ndarray, float]:
    """Position ``k``'s arrows as segment end points in image coordinates (col, row; px).

    ``window``: ``(i0, i1, j0, j1)``, the block rows and columns drawn (default all); the scale is
    the whole position's either way, so that panning does not change it.

    Returns
    -------
    x, y : (2 A,) float64
        Base and tip of each of the A arrows, in turn (for ``connect="pairs"``).
    scale : float
        px of arrow per µm of residual (the longest arrow is 1.5 blocks long).
    """
    dx, dy = field.dx[k], field.dy[k]
    length = np.hypot(dx, dy)
    ok = np.isfinite(length)
    longest = float(length[ok].max() * 1e3) if ok.any() else 0.0
    scale = 1.5 * field.block / longest if longest > 0 else 0.0
    if window is not None:
        i0, i1, j0, j1 = window
        inside = np.zeros_like(ok)
        inside[i0:i1, j0:j1] = True
        ok &= inside
    ii, jj = np.nonzero(ok)
    x0, y0 = field.cols[jj], field.rows[ii]
    x1, y1 = x0 + dx[ii, jj] * 1e3 * scale, y0 + dy[ii, jj] * 1e3 * scale
    return np.column_stack([x0, x1]).ravel(), np.column_stack([y0, y1]).ravel(), scale


class ResidualPanel(QGroupBox):
    """One position's residual arrows, the positions worst first, the worst pixels."""

    def __init__(self, parent=None):
        super().__init__("Residuals per position (sample − LUT), worst first", parent)
        self.field: ResidualField | None = None
        lay = QVBoxLayout(self)
        row = QHBoxLayout()
        self.position = QComboBox()
        self.position.setSizeAdjustPolicy(QComboBox.AdjustToMinimumContentsLengthWithIcon)
        self.position.setMinimumContentsLength(24)  # long items must not widen the page
        self.position.setToolTip("Positions by their residual RMS, largest first; held-out positions are marked")
        row.addWidget(QLabel("position"))
        row.addWidget(self.position, 1)
        lay.addLayout(row)
        self.plot = pg.PlotWidget()
        self.plot.invertY(True)
        self.plot.setAspectLocked(True)
        axis_label(self.plot, "bottom", "column", "px")
        axis_label(self.plot, "left", "row", "px")
        self.arrows = self.plot.plot(pen=pg.mkPen("#0072b2", width=1.5), connect="pairs")
        self.bases = self.plot.plot(pen=None, symbol="o", symbolSize=3, symbolBrush="#0072b2", symbolPen=None)
        lay.addWidget(self.plot, 1)
        self.worst = QLabel()
        self.worst.setWordWrap(True)
        lay.addWidget(self.worst)
        self.position.currentIndexChanged.connect(lambda _i: self.show_position(self.position.currentData()))
        self._k: int | None = None
        self._merged: dict = {}  # group -> the field with that many blocks merged per side
        self._drawn = None  # (position, group, window) of the arrows shown
        self.plot.getViewBox().sigRangeChanged.connect(self._redraw)

    def set_field(self, field: ResidualField | None) -> None:
        """Show a new field (None: clear)."""
        self.field = field
        self._k, self._merged, self._drawn = None, {}, None
        self.position.blockSignals(True)
        self.position.clear()
        if field is not None:
            for k in field.worst_positions:
                if np.isfinite(field.rms_um[k]):
                    held = "" if field.used[k] else ", held out"
                    self.position.addItem(f"{position_label(k, field.z[k])}{held}: RMS (X and Y)"
                                          f" {field.rms_um[k]:.3f} µm",
                                          int(k))
        self.position.blockSignals(False)
        self.worst.setText("<br>".join(field.lines()) if field is not None else "")
        if field is not None and self.position.count():
            self.show_position(self.position.itemData(0))
        else:
            self.arrows.setData([], [])
            self.bases.setData([], [])

    def show_position(self, k) -> None:
        """Draw position ``k``'s arrows over the whole image (the view reset to it)."""
        if self.field is None or k is None:
            return
        self._k = int(k)
        self._drawn = None
        self.plot.disableAutoRange()  # the view follows the user, not the arrows' extent
        self.plot.setRange(xRange=(0, self.field.cols[-1] + self.field.block / 2),
                           yRange=(0, self.field.rows[-1] + self.field.block / 2), padding=0.02)
        self._redraw()

    def _window(self, field: ResidualField) -> tuple[int, int, int, int]:
        """The block rows and columns of ``field`` in view (one block of margin)."""
        (x0, x1), (y0, y1) = self.plot.getViewBox().viewRange()
        b = field.block
        i0, i1 = np.searchsorted(field.rows, [y0 - b, y1 + b])
        j0, j1 = np.searchsorted(field.cols, [x0 - b, x1 + b])
        return int(i0), int(i1), int(j0), int(j1)

    def _redraw(self, *_) -> None:
        """The arrows in view, blocks merged so that at most :data:`MAX_ARROWS` are drawn."""
        if self.field is None or self._k is None:
            return
        i0, i1, j0, j1 = self._window(self.field)
        group = arrow_group(i1 - i0, j1 - j0)
        while True:  # the merged blocks the window touches (partly, at its edges) within the limit too
            window = (i0 // group, -(-i1 // group), j0 // group, -(-j1 // group))
            if (window[1] - window[0]) * (window[3] - window[2]) <= MAX_ARROWS:
                break
            group += 1
        if group not in self._merged:
            self._merged = {group: self.field.merged(group)}  # one level kept: a few MB at 12 MP
        field = self._merged[group]
        if self._drawn == (self._k, group, window):
            return
        self._drawn = (self._k, group, window)
        x, y, scale = arrow_segments(field, self._k, window)
        self.arrows.setData(x, y, connect="pairs")
        self.bases.setData(x[::2], y[::2])
        merged = f", blocks of {field.block} px" if group > 1 else ""
        self.plot.setTitle(f"{position_label(self._k, field.z[self._k])}: arrows {scale:.3g} px per µm{merged}",
                           size="9pt")
