"""Trust the LUT: the session's LUT against a reference LUT (``ptp diff`` in the Export page).

The engine does the work (:func:`ptpcore.evaluate.diff.diff_luts`) on a worker
thread; the panel draws the per-pixel difference as a heatmap (µm) and the
histogram of the differences with the tolerance marked, and says the verdict.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import (QFileDialog, QGridLayout, QGroupBox, QHBoxLayout, QLabel, QLineEdit, QPushButton,
                               QStackedWidget, QWidget)

from ptpcore.evaluate import LutDiff, diff_luts
from ptpcore.io import load_lut

from ..worker import Job
from .jobpanel import JobPanel
from .maps import HeatmapPanel, axis_label

__all__ = ["LutDiffPanel", "verdict_text"]


def verdict_text(r: LutDiff, reference: str) -> str:
    """The numbers of a :class:`LutDiff` in words (rich text: a paragraph, then the common mode's line)."""
    text = (f"<b>{r.verdict_words()}</b> with {reference}: {r.n_pixels} common pixels, z {r.z[0]:g} … {r.z[-1]:g} mm."
            f" Difference RMS {r.rms_um:.3f} µm, 95th percentile {r.p95_um:.3f} µm, max {r.max_um:.3f} µm.")
    if np.isfinite(r.predicted_rms_um):
        text += f" Predicted by the sigma maps {r.predicted_rms_um:.3f} µm (observed / predicted {r.ratio:.2f})."
    text += (f" {100 * r.fraction_beyond:.2f} % of the pixels beyond {r.tolerance_sigma:g} σ"
             + (f" (at least {r.tolerance_um:g} µm)" if r.tolerance_um else "")
             + f" (per-pixel false-alarm rate at most {100 * r.pixel_false_alarm:.2g} %);"
             f" the LUTs differ above {100 * r.max_fraction:g} %.")
    if r.common_x is not None and not r.common_x.assessed:
        text += (f"<br>Common mode: not assessed (its standard error needs 4 × 4 blocks of {r.common_x.block_px} px"
                 f" at the LUTs' smoothing scale; the image is smaller). Mean shift X {r.common_x.shift_um:+.3f} µm,"
                 f" Y {r.common_y.shift_um:+.3f} µm.")
    elif r.common_x is not None and r.common_y is not None:
        cx, cy = r.common_x, r.common_y
        word = "FLAGGED" if r.common_flagged else "no shift"
        text += (f"<br>Common mode (mean shift of the image, false-alarm rate {100 * r.common_false_alarm:g} %):"
                 f" <b>{word}</b>; X {cx.shift_um:+.3f} ± {cx.se_um:.3f} µm (t = {cx.t:+.1f}),"
                 f" Y {cy.shift_um:+.3f} ± {cy.se_um:.3f} µm (t = {cy.t:+.1f}), limit |t| {cx.critical:.2f}.")
    return text


class LutDiffPanel(QGroupBox):
    """Pick a reference LUT file; show the difference of the session's LUT to it.

    Parameters
    ----------
    lut : callable
        Returns the current :class:`ptpcore.io.lutfile.Lut` or None.

    Signals
    -------
    diffChanged(object)
        The new :class:`LutDiff` (None when the LUT changes).
    """

    diffChanged = Signal(object)

    def __init__(self, lut: Callable, parent=None):
        super().__init__("Trust the LUT: difference to a reference LUT (ptp diff)", parent)
        self._lut = lut
        self.result: LutDiff | None = None
        grid = QGridLayout(self)
        row = QHBoxLayout()
        self.reference = QLineEdit()
        self.reference.setPlaceholderText("reference LUT (.lut.h5): a second sweep, or last month's calibration")
        browse = QPushButton("Browse…")
        browse.clicked.connect(self._browse)
        self.compare_button = QPushButton("Compare")
        self.compare_button.setToolTip("Per-pixel difference over the pixels and heights both LUTs cover, against"
                                       " the difference their sigma maps predict")
        # clicked(bool) would hand its ``checked`` (False) to compare's ``reference``: no argument.
        self.compare_button.clicked.connect(lambda: self.compare())
        self.reference.returnPressed.connect(lambda: self.compare())  # Return in the field compares
        self.jobs = JobPanel(self)
        for w in (self.reference, browse, self.compare_button):
            row.addWidget(w, 1 if w is self.reference else 0)
        row.addWidget(self.jobs, 1)
        grid.addLayout(row, 0, 0, 1, 2)
        self.verdict = QLabel()  # the verdict once compared; until then the placeholder below says what to do
        self.verdict.setWordWrap(True)
        grid.addWidget(self.verdict, 1, 0, 1, 2)
        self.heatmap = HeatmapPanel(histogram=False)
        self.hist = pg.PlotWidget()
        self.hist.setTitle("Per-pixel difference (RMS over heights, X and Y)")
        axis_label(self.hist, "bottom", "difference", "µm")
        axis_label(self.hist, "left", "pixels")
        self.bars = pg.BarGraphItem(x=[], height=[], width=1.0, brush="#2b6cb0")
        self.hist.addItem(self.bars)
        self.tol_line = pg.InfiniteLine(angle=90, pen=pg.mkPen("#c0392b", width=2, style=pg.QtCore.Qt.DashLine))
        self.tol_line.setVisible(False)
        self.hist.addItem(self.tol_line)
        # Until a comparison is made, the views' place says what they will show (empty axes said nothing).
        self.views = QWidget()
        vl = QHBoxLayout(self.views)
        vl.setContentsMargins(0, 0, 0, 0)
        vl.addWidget(self.heatmap, 1)
        vl.addWidget(self.hist, 1)
        self.placeholder = QLabel(
            "No comparison yet.\n\nPick a reference LUT of the same camera (a second sweep of the stage, last "
            "month's calibration) and press Compare: here the per-pixel difference between the two LUTs is mapped "
            "over the sensor, beside its histogram and the difference their sigma maps predict (the dashed line).")
        self.placeholder.setObjectName("hint")
        self.placeholder.setWordWrap(True)
        self.placeholder.setAlignment(Qt.AlignCenter)
        self.stack = QStackedWidget()
        self.stack.addWidget(self.placeholder)
        self.stack.addWidget(self.views)
        grid.addWidget(self.stack, 2, 0, 1, 2)
        grid.setRowStretch(2, 1)

    def _browse(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Reference LUT", self.reference.text(),
                                              "PTP LUT (*.lut.h5 *.h5);;All files (*)")
        if path:
            self.reference.setText(path)

    def reset(self) -> None:
        """Forget the result (the session's LUT changed)."""
        self.result = None
        self.bars.setOpts(x=[], height=[], width=1.0)
        self.tol_line.setVisible(False)
        self.stack.setCurrentWidget(self.placeholder)
        self.verdict.setText("")
        self.diffChanged.emit(None)

    def compare(self, reference=None) -> Job | None:
        """Start the comparison with ``reference`` (default: the path typed in); None if nothing to do."""
        lut = self._lut()
        if reference is not None:
            self.reference.setText(str(reference))
        path = Path(self.reference.text().strip())
        if self.jobs.busy or lut is None:
            return None
        if not str(path) or not path.is_file():
            self.jobs.show_error(f"{path}: no such LUT file")
            return None
        job = Job(lambda ctx: diff_luts(lut, load_lut(path)), f"comparing with {path.name}")
        job.finished.connect(lambda r: self.show_result(r, path.name))
        return self.jobs.run(job)

    def show_result(self, r: LutDiff, reference: str = "the reference") -> None:
        """Draw the heatmap and the histogram of ``r`` and say the verdict."""
        self.result = r
        self.verdict.setText(verdict_text(r, reference))
        self.stack.setCurrentWidget(self.views)
        d_um = np.where(r.common, r.diff * 1e3, np.nan).astype(np.float32)
        self.heatmap.set_map(d_um, title="|difference| per pixel (RMS over heights, X and Y)", unit="µm",
                             cmap="inferno")
        counts, edges = r.histogram()
        width = float(edges[1] - edges[0]) if edges.size > 1 else 1.0
        self.bars.setOpts(x=0.5 * (edges[:-1] + edges[1:]), height=counts, width=width)
        tol = np.fmax(r.tolerance_sigma * r.predicted, r.tolerance_um * 1e-3)[r.common]
        if np.isfinite(tol).any():
            self.tol_line.setValue(float(np.nanmedian(tol)) * 1e3)
            self.tol_line.setVisible(True)
        self.diffChanged.emit(r)
