"""The refined stage pose of every position: a table and two plots with 1-sigma error bars (issue 14).

What ``ptp calibrate --refine-stage`` prints (``describe_stage_pose``) and the
LUT stores in ``/provenance/stage_pose`` and ``_sigma``: per position ``dx, dy,
dz`` (um) and ``pitch, yaw, roll`` (urad), up to a common offset, scale and
linear trend (docs/method.md section 8).
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6.QtWidgets import QGroupBox, QHBoxLayout, QLabel, QTableWidget, QTableWidgetItem, QVBoxLayout

from ptpcore.fit import POSE_NAMES

from .maps import axis_label

__all__ = ["StagePosePanel", "pose_cells"]

_COLOURS = ("#2b6cb0", "#e69f00", "#1b7f4c")
_HEADERS = ["z (mm)", "dx (µm)", "dy (µm)", "dz (µm)", "pitch (µrad)", "yaw (µrad)", "roll (µrad)"]


def pose_cells(z_mm, pose: np.ndarray, sigma: np.ndarray | None) -> list[list[str]]:
    """Table text: one row per position, ``z`` then each value ``±`` its 1-sigma."""
    sig = np.full_like(pose, np.nan) if sigma is None else sigma
    return [[f"{z:g}"] + [f"{pose[k, j]:+.2f} ± {sig[k, j]:.2f}" for j in range(len(POSE_NAMES))]
            for k, z in enumerate(z_mm)]


class StagePosePanel(QGroupBox):
    """Table and plots of a LUT's refined stage pose; hidden while the LUT has none."""

    def __init__(self, parent=None):
        super().__init__("Stage pose per position (refined)", parent)
        lay = QVBoxLayout(self)
        self.note = QLabel("Estimated from the straightness of the rays, up to a common offset, scale and linear"
                           " trend (no data can tell those apart); ± is 1σ. The samples were corrected by them,"
                           " and their σ is in the predicted σ maps.")
        self.note.setWordWrap(True)
        self.note.setObjectName("hint")
        lay.addWidget(self.note)
        row = QHBoxLayout()
        self.table = QTableWidget(0, len(_HEADERS))
        self.table.setHorizontalHeaderLabels(_HEADERS)
        self.table.setEditTriggers(QTableWidget.NoEditTriggers)
        self.table.verticalHeader().setVisible(False)
        row.addWidget(self.table, 3)
        self.plots = {}
        for key, title, unit, names in (("shift", "Translation", "µm", ("dx", "dy", "dz")),
                                        ("angle", "Rotation", "µrad", ("pitch", "yaw", "roll"))):
            p = pg.PlotWidget()
            p.setTitle(f"{title} per position (±1σ)")
            axis_label(p, "left", title.lower(), unit)
            axis_label(p, "bottom", "z", "mm")
            p.addLegend(offset=(5, 5))
            p.series = []
            for name, colour in zip(names, _COLOURS):
                curve = p.plot(pen=pg.mkPen(colour, width=1.5), symbol="o", symbolSize=6, symbolBrush=colour,
                               symbolPen=colour, name=name)
                bars = pg.ErrorBarItem(x=np.zeros(0), y=np.zeros(0), height=np.zeros(0), beam=0.0,
                                       pen=pg.mkPen(colour))
                p.addItem(bars)
                p.series.append((curve, bars))
            self.plots[key] = p
            row.addWidget(p, 2)
        lay.addLayout(row)
        self.setVisible(False)

    def set_pose(self, z_mm, pose: np.ndarray | None, sigma: np.ndarray | None) -> None:
        """Show ``pose`` (K, 6) and ``sigma`` (K, 6) at readings ``z_mm`` (K,); hide with ``pose`` None."""
        self.setVisible(pose is not None)
        if pose is None:
            self.table.setRowCount(0)
            for p in self.plots.values():
                for curve, bars in p.series:
                    curve.setData([], [])
                    bars.setData(x=np.zeros(0), y=np.zeros(0), height=np.zeros(0))
            return
        z = np.asarray(z_mm, dtype=float)
        if z.size != len(pose):
            z = np.arange(len(pose), dtype=float)  # positions by index
        rows = pose_cells(z, pose, sigma)
        self.table.setRowCount(len(rows))
        for i, cells in enumerate(rows):
            for j, text in enumerate(cells):
                self.table.setItem(i, j, QTableWidgetItem(text))
        self.table.resizeColumnsToContents()
        sig = np.nan_to_num(sigma) if sigma is not None else np.zeros_like(pose)
        width = 0.3 * (float(np.min(np.abs(np.diff(z)))) if z.size > 1 else 1.0)
        for key, cols in (("shift", (0, 1, 2)), ("angle", (3, 4, 5))):
            for (curve, bars), j in zip(self.plots[key].series, cols):
                curve.setData(z, pose[:, j])
                bars.setData(x=z, y=pose[:, j], height=2 * sig[:, j], beam=width)
