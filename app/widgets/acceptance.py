"""Accept the scanner: VDI/VDE 2634-2 on both of its calibrations, as ``ptp acceptance`` does (issue 35).

The Export page holds one :class:`AcceptancePanel`, shown when the session's LUT has the scanner's
height map. The engine does the work on a worker thread
(:func:`ptpcore.run.acceptance.reconstruct_scans`, :func:`ptpcore.evaluate.vdi2634.evaluate_acceptance`,
the conventional calibration of the dataset); the panel shows each figure's largest magnitude per
method with its pose and verdict, and the engine's page of plots; Save report… writes the JSON and
the page as the command does.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QImage, QPixmap
from PySide6.QtWidgets import (QCheckBox, QFileDialog, QGridLayout, QGroupBox, QHBoxLayout, QLabel, QLineEdit,
                               QPushButton, QScrollArea, QTableWidget, QTableWidgetItem)

from ptpcore.atomic import write_text_atomic
from ptpcore.errors import OutputError
from ptpcore.io import Output, guard_outputs
from ptpcore.evaluate import FIGURES, acceptance_page, evaluate_acceptance, parse_mpe, write_png
from ptpcore.run import conventional_calibration, reconstruct_scans, scan_folders

from ..worker import Job
from .jobpanel import JobPanel

__all__ = ["AcceptancePanel"]

FIGURE_WORDS = {"PF": "PF, probing error form", "PS": "PS, probing error size", "SD": "SD, sphere spacing",
                "F": "F, flatness"}
METHOD_TITLES = {"ptp": "PTP (per pixel)", "conventional": "Conventional (two pinholes)"}
"""Column titles of the report's methods (its keys stay as the JSON has them)."""


class AcceptancePanel(QGroupBox):
    """Run VDI/VDE 2634-2 on the acceptance scans with the session's LUT and the dataset's conventional
    calibration; show and save the report.

    Parameters
    ----------
    lut : callable
        The current :class:`ptpcore.io.lutfile.Lut` or None.
    dataset : callable
        The session's dataset folder (Path) or None.
    folder : callable
        The default folder for saving.

    Signals
    -------
    reportChanged(object)
        The new :class:`ptpcore.evaluate.vdi2634.AcceptanceReport` (None when the LUT changes).
    """

    reportChanged = Signal(object)

    def __init__(self, lut: Callable, dataset: Callable, folder: Callable[[], Path], parent=None):
        super().__init__("Accept the scanner: VDI/VDE 2634-2, PTP and the conventional calibration", parent)
        self._lut, self._dataset, self._folder = lut, dataset, folder
        self.report = None
        self.page = None  # (H, W, 3) uint8 BGR, the engine's page of plots
        grid = QGridLayout(self)
        self.scans = QLineEdit()
        self.scans.setPlaceholderText("scan folder, or a folder of scan folders (e.g. DATASET/acceptance)")
        browse = QPushButton("Browse…")
        browse.clicked.connect(self._browse)
        row = QHBoxLayout()
        row.addWidget(self.scans, 1)
        row.addWidget(browse)
        grid.addWidget(QLabel("Scans"), 0, 0)
        grid.addLayout(row, 0, 1)
        self.mpe = QLineEdit()
        self.mpe.setPlaceholderText("e.g. PF=0.05,PS=0.03,SD=0.08,F=0.06 (mm, or 12µm)")
        self.mpe.setToolTip("Maximum permissible errors the maker states: any of PF, PS, SD, F")
        grid.addWidget(QLabel("MPE"), 1, 0)
        grid.addWidget(self.mpe, 1, 1)
        self.conventional = QCheckBox("Also the conventional camera-projector calibration of the dataset")
        self.conventional.setChecked(True)
        grid.addWidget(self.conventional, 2, 0, 1, 2)
        buttons = QHBoxLayout()
        self.run_button = QPushButton("Run acceptance")
        self.run_button.clicked.connect(self.run)
        self.save_button = QPushButton("Save report…")
        self.save_button.setEnabled(False)
        self.save_button.clicked.connect(self._save_dialog)
        self.jobs = JobPanel(self)
        buttons.addWidget(self.run_button)
        buttons.addWidget(self.save_button)
        buttons.addWidget(self.jobs, 1)
        grid.addLayout(buttons, 3, 0, 1, 2)
        self.table = QTableWidget(len(FIGURES), 0)
        self.table.setVerticalHeaderLabels([FIGURE_WORDS[k] for k in FIGURES])
        self.table.setEditTriggers(QTableWidget.NoEditTriggers)
        self.table.setMaximumHeight(150)
        grid.addWidget(self.table, 4, 0, 1, 2)
        self.summary = QLabel("no acceptance report yet")
        self.summary.setWordWrap(True)
        grid.addWidget(self.summary, 5, 0, 1, 2)
        self.image = QLabel()
        self.image.setAlignment(Qt.AlignHCenter | Qt.AlignTop)
        scroll = QScrollArea()
        scroll.setWidget(self.image)
        scroll.setWidgetResizable(True)
        grid.addWidget(scroll, 6, 0, 1, 2)
        grid.setRowStretch(6, 1)

    # ---- inputs ----------------------------------------------------------------------------
    def _browse(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Acceptance scans", str(self._dataset() or self._folder()))
        if folder:
            self.scans.setText(folder)

    def set_scans(self, path) -> None:
        self.scans.setText(str(path))

    def reset(self) -> None:
        """The LUT changed: the report is gone."""
        self.report, self.page = None, None
        self.table.setColumnCount(0)
        self.image.clear()
        self.summary.setText("no acceptance report yet")
        self.save_button.setEnabled(False)
        self.reportChanged.emit(None)

    # ---- jobs ------------------------------------------------------------------------------
    def run(self) -> Job | None:
        """Start the acceptance on a worker; a missing input says what to do instead."""
        if self.jobs.busy:
            return None
        lut, dataset = self._lut(), self._dataset()
        if lut is None or getattr(lut, "height", None) is None:
            self.jobs.show_error("The LUT has no height map (/height): calibrate a dataset with a height sweep.")
            return None
        try:
            mpe = parse_mpe(self.mpe.text())
            scans = scan_folders([self.scans.text().strip()]) if self.scans.text().strip() else None
        except ValueError as exc:
            self.jobs.show_error(str(exc))
            return None
        if scans is None:
            self.jobs.show_error("Choose the scans: a scan folder, or a folder of them.")
            return None
        with_conventional = self.conventional.isChecked()
        if with_conventional and dataset is None:
            self.jobs.show_error("The conventional calibration needs the dataset folder (Rig page), or untick it.")
            return None

        def work(ctx):
            conv = None
            if with_conventional:
                conv = conventional_calibration(dataset, progress=lambda f, m: ctx.progress(0.3 * f, m))
            points = reconstruct_scans(scans, lut, conventional=conv,
                                       progress=lambda f, m: ctx.progress(0.3 + 0.6 * f, m))
            ctx.progress(0.92, "fitting spheres and planes")
            report = evaluate_acceptance(points, mpe_mm=mpe)
            return report, {sp.name: sp.counts for sp in points}, acceptance_page(report)

        job = Job(work, "VDI/VDE 2634-2 acceptance")
        job.finished.connect(self._show)
        return self.jobs.run(job)

    def _show(self, result) -> None:
        report, counts, page = result
        self.report, self.page, self._counts = report, page, counts
        self.table.setColumnCount(len(report.methods))
        self.table.setHorizontalHeaderLabels([METHOD_TITLES.get(m, m) for m in report.methods])
        for j, m in enumerate(report.methods):
            big, verdicts = report.largest(m), report.verdicts(m)
            for i, k in enumerate(FIGURES):
                if k not in big:
                    text = "no pose"
                else:
                    text = f"{1e3 * big[k]['value_mm']:+.1f} µm ({big[k]['pose']})"
                    text += f"  {verdicts[k]}" if k in verdicts else ""
                self.table.setItem(i, j, QTableWidgetItem(text))
        self.table.resizeColumnsToContents()
        lines = [f"{len({p.pose for p in report.poses})} poses; up to {100 * report.leave_out:g} % of each fit's"
                 " points left out (the largest residuals)."]
        for m, d in report.distance.items():
            lines.append(f"{m}: 3D point error RMS {d.point.rms_um:.1f} µm against the simulator's truth")
        self.summary.setText("\n".join(lines))
        rgb = np.ascontiguousarray(page[..., ::-1])
        h, w = rgb.shape[:2]
        self._qimage = QImage(rgb.data, w, h, 3 * w, QImage.Format_RGB888).copy()
        self.image.setPixmap(QPixmap.fromImage(self._qimage))
        self.save_button.setEnabled(True)
        self.reportChanged.emit(report)

    def _save_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save acceptance report", str(self._folder() / "acceptance.json"),
                                              "JSON (*.json)")
        if path:
            self.save(path)

    def save(self, path) -> Job | None:
        """Write the report (JSON, as ``ptp acceptance``) and its page beside it (same name, ``.png``)."""
        if self.report is None or self.jobs.busy:
            return None
        report, page, counts, path = self.report, self.page, self._counts, Path(path)
        inputs = [p for p in (self._dataset(), self.scans.text().strip()) if p]
        try:  # the output guard, before the job (the dialog has asked before replacing the report: force)
            guard_outputs([Output(path, "report", "the report"), Output(path.with_suffix(".png"), "png", "its page")],
                          inputs=inputs, force=True)
        except OutputError as exc:
            self.jobs.show_error(f"Nothing saved: {exc}")
            return None

        def work(ctx):
            ctx.progress(0.2, f"writing {path.name}")
            js = {**report.to_json_dict(), "points": counts}
            write_text_atomic(path, json.dumps(js, indent=1, allow_nan=False) + "\n")
            write_png(page, path.with_suffix(".png"))
            return path

        job = Job(work, "saving the acceptance report")
        job.finished.connect(lambda p: self.summary.setText(self.summary.text() + f"\n✔ saved {p}"))
        return self.jobs.run(job)
