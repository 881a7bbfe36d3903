"""Use the LUT: a height map (or one height) through the LUT into a point cloud, shown and saved; with the
scanner's height map (``/height``), a scan folder (``ptp-scan/1``) reconstructed as ``ptp reconstruct`` does.

The Export page holds one :class:`PointCloudPanel`. The engine does the work
(``Lut.points``, ``read_height_map``, ``write_point_cloud``) on a worker
thread; the panel draws a top view, X right and Y up in mm, coloured by Z,
binned into an image so millions of points stay fluid.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QRectF, Qt, Signal
from PySide6.QtWidgets import (QButtonGroup, QCheckBox, QDoubleSpinBox, QFileDialog, QGridLayout, QGroupBox,
                               QHBoxLayout, QLabel, QLineEdit, QPushButton, QRadioButton, QStackedWidget)

from ptpcore.errors import OutputError
from ptpcore.io import Output, PointCloud, guard_outputs, read_height_map, write_point_cloud
from ptpcore.run import reconstruct

from ..worker import Job
from .jobpanel import JobPanel
from .maps import PEN, axis_label, colormap, plain_axes

__all__ = ["PointCloudPanel", "top_view"]

_MAX_BINS = 600  # top-view resolution along the longer side, at most


def top_view(cloud: PointCloud, bins: int | None = None) -> tuple[np.ndarray, QRectF]:
    """The cloud seen from above: mean Z per (X, Y) bin, NaN where empty.

    By default about one bin per point spacing (``0.9 sqrt(N)`` along the longer
    side, 16 to 600), so a small camera's cloud shows no gaps between points.

    Returns
    -------
    image : (ny, nx) float32, mm, row 0 at the smallest Y
    rect : QRectF
        The image's extent in X, Y (mm).
    """
    if bins is None:
        bins = int(np.clip(0.9 * np.sqrt(cloud.n_points), 16, _MAX_BINS))
    x0, x1 = float(cloud.x.min()), float(cloud.x.max())
    y0, y1 = float(cloud.y.min()), float(cloud.y.max())
    span = max(x1 - x0, y1 - y0, 1e-6)
    step = span / bins
    nx = max(1, int(np.ceil((x1 - x0) / step)) + 1)
    ny = max(1, int(np.ceil((y1 - y0) / step)) + 1)
    ix = np.minimum(((cloud.x - x0) / step).astype(np.int64), nx - 1)
    iy = np.minimum(((cloud.y - y0) / step).astype(np.int64), ny - 1)
    flat = iy * nx + ix
    total = np.bincount(flat, weights=cloud.z, minlength=nx * ny)
    count = np.bincount(flat, minlength=nx * ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        image = np.where(count > 0, total / count, np.nan).astype(np.float32).reshape(ny, nx)
    return image, QRectF(x0, y0, nx * step, ny * step)


class PointCloudPanel(QGroupBox):
    """Apply the session's LUT to a height map file or a constant height; show and save the cloud.

    Parameters
    ----------
    lut : callable
        Returns the current :class:`ptpcore.lut.Lut` or None.
    folder : callable
        Returns the default folder for saving.

    Signals
    -------
    cloudChanged(object)
        The new :class:`PointCloud` (or None when the LUT changes).
    """

    cloudChanged = Signal(object)

    def __init__(self, lut: Callable, folder: Callable[[], Path], parent=None):
        super().__init__("Use the LUT: point cloud from a height map", parent)
        self._lut = lut
        self._folder = folder
        self.cloud: PointCloud | None = None
        self.saved: Path | None = None
        grid = QGridLayout(self)

        self.use_constant = QRadioButton("One height for every pixel")
        self.use_file = QRadioButton("Height map file (32-bit float TIFF or .npy, mm, NaN = none)")
        self.use_scan = QRadioButton("Scan folder (ptp-scan/1): heights from the projector")
        self.use_scan.setToolTip("Reconstruct a scan as ptp reconstruct does: u_p decoded per pixel, Z from the LUT's"
                                 " height map (/height), X and Y from the LUT; pixels outside either map's calibrated"
                                 " range have no point (a scan of several views: the first). Shown when the LUT has a height map.")
        group = QButtonGroup(self)
        group.addButton(self.use_constant)
        group.addButton(self.use_file)
        group.addButton(self.use_scan)
        self.use_constant.setChecked(True)
        self.height = QDoubleSpinBox()
        self.height.setRange(-1e5, 1e5)
        self.height.setDecimals(4)
        self.height.setSuffix(" mm")
        self.height_file = QLineEdit()
        self.height_file.setPlaceholderText("height map: .tif / .tiff / .npy")
        self.height_file.textEdited.connect(lambda _t: self.use_file.setChecked(True))
        browse = QPushButton("Browse…")
        browse.clicked.connect(self._browse_height)
        grid.addWidget(self.use_constant, 0, 0)
        grid.addWidget(self.height, 0, 1)
        grid.addWidget(self.use_file, 1, 0)
        row = QHBoxLayout()
        row.addWidget(self.height_file, 1)
        row.addWidget(browse)
        grid.addLayout(row, 1, 1)
        self.scan_folder = QLineEdit()
        self.scan_folder.setPlaceholderText("scan folder with scan.toml")
        self.scan_folder.textEdited.connect(lambda _t: self.use_scan.setChecked(True))
        self.scan_browse = QPushButton("Browse…")
        self.scan_browse.clicked.connect(self._browse_scan)
        scan_row = QHBoxLayout()
        scan_row.addWidget(self.scan_folder, 1)
        scan_row.addWidget(self.scan_browse)
        grid.addWidget(self.use_scan, 2, 0)
        grid.addLayout(scan_row, 2, 1)
        self._scan_widgets = (self.use_scan, self.scan_folder, self.scan_browse)
        self.extrapolate = QCheckBox("Keep pixels outside their calibrated z range (flagged as extrapolated)")
        grid.addWidget(self.extrapolate, 3, 0, 1, 2)

        buttons = QHBoxLayout()
        self.apply_button = QPushButton("Apply the LUT")
        self.save_button = QPushButton("Save point cloud…")
        self.save_button.setEnabled(False)
        self.apply_button.clicked.connect(self.apply)
        self.save_button.clicked.connect(self._save_dialog)
        buttons.addWidget(self.apply_button)
        buttons.addWidget(self.save_button)
        self.jobs = JobPanel(self)
        buttons.addWidget(self.jobs, 1)
        grid.addLayout(buttons, 4, 0, 1, 2)
        self.summary = QLabel("no point cloud yet")
        self.summary.setWordWrap(True)
        grid.addWidget(self.summary, 5, 0, 1, 2)

        self.plot = pg.PlotWidget(background="w")
        self.plot.setMinimumHeight(220)
        pi = self.plot.getPlotItem()
        # a title says what is drawn (and leaves room above the colour bar's top value, which was cut)
        pi.setTitle("Top view: X right, Y up, coloured by Z", size="9pt")
        axis_label(pi, "bottom", "X", "mm")
        axis_label(pi, "left", "Y", "mm")
        pi.setAspectLocked(True)
        for axis in ("bottom", "left"):
            pi.getAxis(axis).setPen(PEN)
            pi.getAxis(axis).setTextPen(PEN)
        self.image = pg.ImageItem()
        pi.addItem(self.image)
        self.colorbar = pg.ColorBarItem(values=(0.0, 1.0), colorMap=colormap("viridis"), label="Z (mm)",
                                        interactive=False)
        self.colorbar.setImageItem(self.image, insert_in=pi)
        plain_axes(self.colorbar)
        # Until a cloud is made, the view's place says what will be drawn there (an empty plot said nothing).
        self.placeholder = QLabel()
        self.placeholder.setObjectName("hint")
        self.placeholder.setWordWrap(True)
        self.placeholder.setAlignment(Qt.AlignCenter)
        self.placeholder.setMinimumHeight(220)
        self.view = QStackedWidget()
        self.view.addWidget(self.placeholder)
        self.view.addWidget(self.plot)
        grid.addWidget(self.view, 6, 0, 1, 2)
        grid.setRowStretch(6, 1)
        self._show_placeholder()
        self._show_scan_choice()

    def _show_scan_choice(self) -> None:
        """The scan source only for a LUT with a height map."""
        lut = self._lut()
        has = lut is not None and getattr(lut, "height", None) is not None
        for w in self._scan_widgets:
            w.setVisible(has)
        if not has and self.use_scan.isChecked():
            self.use_constant.setChecked(True)

    def _show_placeholder(self) -> None:
        """No cloud: say what the view will show and how to make it (with the LUT's z range when there is one)."""
        lut = self._lut()
        heights = (f"one height in the LUT's range, z = {lut.z_min:g} … {lut.z_max:g} mm," if lut is not None
                   else "one height")
        self.placeholder.setText(
            "No point cloud yet.\n\nChoose " + heights + " or a height-map file and press Apply the LUT: the "
            "points are drawn here seen from above (X right, Y up, in mm), coloured by their height Z. "
            "Save point cloud… then writes them as PLY, NumPy or HDF5." + ("" if lut is not None else
                                                                          "\n\nFit a LUT on the Calibrate page first."))
        self.view.setCurrentWidget(self.placeholder)

    # ---- inputs ----------------------------------------------------------------------------
    def _browse_height(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Height map", str(self._folder()),
                                              "Height maps (*.tif *.tiff *.npy)")
        if path:
            self.height_file.setText(path)
            self.use_file.setChecked(True)

    def _browse_scan(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Scan folder (scan.toml)", str(self._folder()))
        if folder:
            self.set_scan_folder(folder)

    def set_scan_folder(self, path) -> None:
        self.scan_folder.setText(str(path))
        self.use_scan.setChecked(True)

    def set_constant(self, z_mm: float) -> None:
        self.height.setValue(z_mm)
        self.use_constant.setChecked(True)

    def set_height_file(self, path) -> None:
        self.height_file.setText(str(path))
        self.use_file.setChecked(True)

    def reset(self) -> None:
        """The LUT changed: the cloud is gone; the height defaults to the middle of the range."""
        self.cloud = None
        self.saved = None
        self.save_button.setEnabled(False)
        self.image.clear()
        self.summary.setText("no point cloud yet")
        lut = self._lut()
        if lut is not None:
            self.height.setValue(0.5 * (lut.z_min + lut.z_max))
        self._show_placeholder()
        self._show_scan_choice()
        self.cloudChanged.emit(None)

    # ---- jobs ------------------------------------------------------------------------------
    def apply(self) -> Job | None:
        lut = self._lut()
        if self.jobs.busy:
            return None
        if lut is None:
            self.jobs.show_error("There is no LUT yet: fit one on the Calibrate page.")
            return None
        extrapolate = self.extrapolate.isChecked()
        if self.use_scan.isChecked():
            return self._reconstruct(lut)
        if self.use_file.isChecked():
            source = self.height_file.text().strip()
            if not source:
                self.jobs.show_error("Choose a height-map file, or use one height for every pixel.")
                return None
        else:
            source = float(self.height.value())

        def run(ctx):
            ctx.progress(0.1, "reading the height map" if isinstance(source, str) else "evaluating the LUT")
            z = read_height_map(source, lut.shape) if isinstance(source, str) else source
            ctx.check()
            ctx.progress(0.4, "evaluating the LUT")
            cloud = lut.points(z, extrapolate=extrapolate)
            if cloud.n_points == 0:
                raise ValueError(f"no point: {cloud.summary()}; the LUT covers z {lut.z_min:g} … {lut.z_max:g} mm"
                                 + ("" if extrapolate else " (keep pixels outside their range to extrapolate)"))
            ctx.progress(0.8, "drawing the top view")
            return cloud, top_view(cloud)

        job = Job(run, "applying the LUT")
        job.finished.connect(self._show)
        return self.jobs.run(job)

    def _reconstruct(self, lut) -> Job | None:
        """The scan folder through the LUT's height map and the LUT (``ptp reconstruct``): its first view shown."""
        folder = self.scan_folder.text().strip()
        if not folder:
            self.jobs.show_error("Choose a scan folder (with scan.toml), or another source of heights.")
            return None

        def run(ctx):
            views = reconstruct(folder, lut, progress=ctx.progress)
            cloud = views[0].cloud
            if cloud.n_points == 0:
                raise ValueError(f"{folder}: no point ({cloud.summary()})")
            ctx.progress(0.95, "drawing the top view")
            return cloud, top_view(cloud)

        job = Job(run, "reconstructing the scan")
        job.finished.connect(self._show)
        return self.jobs.run(job)

    def _show(self, result) -> None:
        cloud, (image, rect) = result
        self.cloud = cloud
        self.saved = None
        finite = image[np.isfinite(image)]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        if hi <= lo:
            lo, hi = lo - 0.5, hi + 0.5
        self.image.setImage(image, levels=(lo, hi))
        self.image.setRect(rect)
        self.colorbar.setLevels((lo, hi))
        self.view.setCurrentWidget(self.plot)
        self.plot.getPlotItem().autoRange()
        self.summary.setText(cloud.summary())
        self.save_button.setEnabled(True)
        self.cloudChanged.emit(cloud)

    def _save_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save point cloud", str(self._folder() / "points.ply"),
                                              "PLY (*.ply);;NumPy (*.npy);;HDF5 ptp-points/1 (*.h5)")
        if path:
            self.save(path)

    def save(self, path) -> Job | None:
        """Write the shown cloud (format from the suffix: .ply, .npy, .h5)."""
        if self.cloud is None or self.jobs.busy:
            return None
        cloud, path = self.cloud, Path(path)
        height = self.height_file.text().strip()
        try:  # the output guard, before the job: the dialog has asked before replacing a file (force)
            guard_outputs([Output(path, "points")], inputs=[height] if height else [], force=True)
        except OutputError as exc:
            self.jobs.show_error(f"Nothing saved: {exc}")
            return None
        note = "ptp-studio point cloud" + (" (extrapolated points flagged)" if cloud.n_extrapolated else "")

        def run(ctx):
            ctx.progress(0.2, f"writing {path.name}")
            return write_point_cloud(cloud, path, comment=note)

        job = Job(run, "saving the point cloud")
        job.finished.connect(self._saved)
        return self.jobs.run(job)

    def _saved(self, path) -> None:
        self.saved = Path(path)
        self.summary.setText(f"{self.cloud.summary()}\n✔ saved {self.saved}")
