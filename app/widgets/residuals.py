"""The Calibrate page's residual diagnostics: per position the field of (sample - LUT) as arrows.

The engine computes the field (:func:`ptpcore.evaluate.residuals.residual_field`);
this panel draws one position's arrows (a segment from each block's centre, a dot
at its base), lists the positions worst first and names the worst pixels.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6.QtWidgets import QComboBox, QGroupBox, QHBoxLayout, QLabel, QVBoxLayout

from ptpcore.evaluate.residuals import ResidualField

from .maps import axis_label

__all__ = ["ResidualPanel", "arrow_segments"]


def arrow_segments(field: ResidualField, k: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Position ``k``'s arrows as segment end points in image coordinates (col, row; px).

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

    def set_field(self, field: ResidualField | None) -> None:
        """Show a new field (None: clear)."""
        self.field = field
        self.position.blockSignals(True)
        self.position.clear()
        if field is not None:
            for k in field.worst_positions:
                if np.isfinite(field.rms_um[k]):
                    held = "" if field.used[k] else ", held out"
                    self.position.addItem(f"{k + 1}: z = {field.z[k]:g} mm{held}, RMS {field.rms_um[k]:.3f} µm",
                                          int(k))
        self.position.blockSignals(False)
        self.worst.setText("<br>".join(field.lines()) if field is not None else "")
        if field is not None and self.position.count():
            self.show_position(self.position.itemData(0))
        else:
            self.arrows.setData([], [])
            self.bases.setData([], [])

    def show_position(self, k) -> None:
        if self.field is None or k is None:
            return
        x, y, scale = arrow_segments(self.field, int(k))
        self.arrows.setData(x, y, connect="pairs")
        self.bases.setData(x[::2], y[::2])
        self.plot.setTitle(f"position {int(k) + 1}: arrows {scale:.3g} px per µm")
