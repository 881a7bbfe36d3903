"""Live capture in the wizard: the device choices, the engineer's stage readings, the capture job.

- :class:`LivePanel` — the Acquire page's "Live capture" controls: capture
  folder (and resume), camera, exposure, stage, LCD screen and settle time.
  They edit the session's :class:`~ptp_studio.session.LiveSettings`.
- :func:`build_devices` — the devices those settings name, built on the GUI
  thread (the LCD window must be): simulated, OpenCV or GenICam camera;
  simulated, manual or serial stage; simulated display or :class:`QtDisplay`.
- :class:`StageAsker` — a manual stage's ``ask``: a non-modal dialog on the
  GUI thread that the capture's worker thread waits for (and a Cancel of the
  job dismisses).
- :func:`live_capture_job` — :func:`ptpcore.capture.sequence.capture` then the decode
  of the captured folder, as one :class:`~ptp_studio.worker.Job`.
"""

from __future__ import annotations

import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import QObject, Qt, Signal, Slot
from PySide6.QtWidgets import (QCheckBox, QComboBox, QDialog, QDialogButtonBox, QDoubleSpinBox, QFileDialog,
                               QFormLayout, QHBoxLayout, QLabel, QLineEdit, QPushButton, QVBoxLayout, QWidget)

from ptpcore.capture import (HarvestersCamera, ManualStage, OpenCVCamera, SerialStage, SimulatedCamera,
                             SimulatedDisplay, SimulatedStage, capture, capture_state, load_capture_config,
                             simulated_meta)
from ptpcore.io import DatasetSource
from ptpcore.errors import ConfigError, PtpError
from ptpcore.simulate import TRUTH_FILE, VirtualRig, save_truth

from .lcd_window import QtDisplay, list_screens, screen_mismatch
from .widgets.maps import axis_label
from .session import FramePreview, LiveSettings, decode_samples
from .worker import Job

__all__ = ["LivePanel", "StageAsker", "ReadingDialog", "build_devices", "live_capture_job",
           "CAMERA_CHOICES", "STAGE_CHOICES"]

CAMERA_CHOICES = {
    "sim": "Simulated camera (the virtual rig of the Rig page)",
    "opencv": "OpenCV camera (index, video file or stream URL)",
    "genicam": "GenICam camera through harvesters (GenTL .cti producer)",
}
STAGE_CHOICES = {
    "sim": "Simulated stage",
    "manual": "Manual stage (you move it and type each reading)",
    "serial": "Serial stage (protocol from a capture.toml)",
}


# --------------------------------------------------------------------------- manual stage

class ReadingDialog(QDialog):
    """Asks the engineer to move the stage and type the reading (non-modal)."""

    def __init__(self, z_mm: float, prompt: str, parent: QWidget | None = None):
        super().__init__(parent)
        self.setWindowTitle("Move the stage")
        lay = QVBoxLayout(self)
        lab = QLabel(prompt)
        lab.setWordWrap(True)
        lay.addWidget(lab)
        self.reading = QDoubleSpinBox()
        self.reading.setRange(-100_000.0, 100_000.0)
        self.reading.setDecimals(4)
        self.reading.setSuffix(" mm")
        self.reading.setValue(z_mm)
        lay.addWidget(self.reading)
        buttons = QDialogButtonBox(QDialogButtonBox.Ok | QDialogButtonBox.Cancel)
        buttons.button(QDialogButtonBox.Ok).setText("At this reading")
        buttons.button(QDialogButtonBox.Cancel).setText("Stop the capture")
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        lay.addWidget(buttons)


class StageAsker(QObject):
    """A :class:`ManualStage`'s ``ask`` for the GUI, called on the worker thread.

    Signals
    -------
    dialogOpened(object)
        The :class:`ReadingDialog` just shown (GUI thread).
    """

    dialogOpened = Signal(object)
    _ask = Signal(float, str, object)
    _dismiss = Signal(object)

    def __init__(self, parent_widget: QWidget | None, cancel_event: threading.Event | None = None):
        super().__init__()
        self.parent_widget = parent_widget
        self.cancel_event = cancel_event
        self.dialog: ReadingDialog | None = None
        self._ask.connect(self._open, Qt.QueuedConnection)
        self._dismiss.connect(self._close, Qt.QueuedConnection)

    def __call__(self, z_mm: float, prompt: str) -> float | None:
        box = {"done": threading.Event(), "value": None}
        self._ask.emit(float(z_mm), prompt, box)
        while not box["done"].wait(0.05):
            if self.cancel_event is not None and self.cancel_event.is_set():
                self._dismiss.emit(box)
                return None
        return box["value"]

    @Slot(float, str, object)
    def _open(self, z_mm: float, prompt: str, box: dict) -> None:
        dlg = ReadingDialog(z_mm, prompt, self.parent_widget)
        dlg.setAttribute(Qt.WA_DeleteOnClose, True)
        box["dialog"] = dlg

        def finished(result: int) -> None:
            box["value"] = dlg.reading.value() if result == QDialog.Accepted else None
            if self.dialog is dlg:
                self.dialog = None
            box["done"].set()

        dlg.finished.connect(finished)
        self.dialog = dlg
        dlg.show()
        self.dialogOpened.emit(dlg)

    @Slot(object)
    def _close(self, box: dict) -> None:
        dlg = box.get("dialog")
        if dlg is not None and dlg.isVisible():
            dlg.reject()


# --------------------------------------------------------------------------- devices

def build_devices(session, parent_widget: QWidget | None = None):
    """``(camera, stage, display, asker)`` for the session's live settings; on the GUI thread.

    Raises
    ------
    PtpError, ValueError
        A setting that cannot work (no folder, a bad capture.toml, a screen that is not there).
    """
    lv: LiveSettings = session.live
    rig = session.rig
    config = load_capture_config(lv.config) if lv.config else None
    if lv.screen is None:
        display = SimulatedDisplay(rig.lcd.width, rig.lcd.height, 0.0)
    else:
        if not any(info.index == lv.screen for info in list_screens()):
            raise ConfigError(f"screen {lv.screen + 1} is not connected: choose the LCD's screen again")
        display = QtDisplay(lv.screen, rig.lcd.width, rig.lcd.height, lv.settle_ms / 1000.0)
    asker = None
    if lv.stage == "sim":
        stage = SimulatedStage()
    elif lv.stage == "manual":
        asker = StageAsker(parent_widget)
        stage = ManualStage(asker)
    elif lv.stage == "serial":
        if config is None or config.stage.serial is None:
            raise ConfigError("the serial stage needs a capture.toml with a [stage.serial] table"
                              " (the controller's text protocol): choose it beside the stage")
        stage = SerialStage(config.stage.serial)
    else:
        raise ValueError(f"unknown stage {lv.stage!r}")
    if lv.camera == "sim":
        camera = SimulatedCamera(VirtualRig(rig, session.sim_settings, session.seed), display, stage)
    elif lv.camera == "opencv":
        src = lv.camera_source.strip() or "0"
        camera = OpenCVCamera(int(src) if src.isdigit() else src, width=rig.camera.width, height=rig.camera.height)
    elif lv.camera == "genicam":
        cfg = config.camera if config is not None else None
        cti = lv.camera_source.strip() or (cfg.cti if cfg else "")
        if not cti:
            raise ConfigError("the GenICam camera needs its GenTL producer (.cti file) in the camera's field")
        device = {"serial_number": cfg.serial_number} if cfg and cfg.serial_number else (cfg.device if cfg else 0)
        camera = HarvestersCamera(cti, device, cfg.timeout_s if cfg else 5.0, (cfg.pixel_format or None) if cfg
                                  else None)
    else:
        raise ValueError(f"unknown camera {lv.camera!r}")
    return camera, stage, display, asker


def live_capture_job(session, camera, stage, display, asker=None, frame_interval: float = 0.12,
                     preview_pixels=None) -> Job:
    """The live capture, then the decode of what it wrote, as one job.

    Everything the worker needs is taken here, on the GUI thread. The job
    returns ``(samples, truth, rig)``: ``truth`` is the exact rays for the
    simulated camera (else None); ``rig`` is the captured ``rig.toml`` (the
    stage readings as recorded). Partial results: ``("start", k)``,
    ``("captured", k)``, ``("kept", k)``, ``("frame", ...)``, ``("exposure", ok, message)``,
    ``("position", status, decoded)``, ``("display", levels, luminance)`` (the measured response).
    ``preview_pixels``: a callable, the size of the frame previews (:class:`~ptp_studio.session.FramePreview`).
    """
    if session.dataset_folder is None:
        raise ConfigError("choose the folder the capture writes to")
    folder = Path(session.dataset_folder)
    rig, lv = session.rig, replace(session.live)
    sim = isinstance(camera, SimulatedCamera)
    meta = simulated_meta(session.preset_name, session.seed, session.sim_settings) if sim else {"camera": lv.camera}
    def run(ctx):
        for dev in (display, asker):
            if dev is not None and hasattr(dev, "cancel_event"):
                dev.cancel_event = ctx.cancel_event
        on_frame = FramePreview(ctx, rig.camera.max_level, frame_interval, preview_pixels)

        def on_position(k, state):
            ctx.emit({"capturing": ("start", k), "done": ("captured", k), "kept": ("kept", k)}[state])

        result = capture(folder, rig, camera, stage, display, resume=lv.resume, exposure_us=lv.exposure_us,
                         accept_exposure=lv.accept_exposure, meta=meta, measure_display=lv.measure_display,
                         progress=lambda f, m: ctx.progress(0.7 * f, m), on_frame=on_frame,
                         on_exposure=lambda r: ctx.emit(("exposure", r.ok, r.message)), on_position=on_position)
        if result.rig.display is not None:
            ctx.emit(("display", list(result.rig.display.levels), list(result.rig.display.luminance)))
        truth = None
        if sim:
            if not (folder / TRUTH_FILE).exists():
                save_truth(folder / TRUTH_FILE, camera._base)
            truth = camera._base.truth()

        def decoded(pos):
            ctx.emit(session.position_message(pos))

        samples = decode_samples(session, DatasetSource(folder), ctx, 0.7, on_position=decoded)
        ctx.progress(1.0, "done")
        return samples, truth, result.rig

    return Job(run, "live capture")


# --------------------------------------------------------------------------- the panel

class LivePanel(QWidget):
    """The live capture's settings on the Acquire page (edits ``session.live`` and the capture folder).

    Signals
    -------
    changed()
        A setting changed.
    """

    changed = Signal()

    def __init__(self, model, parent: QWidget | None = None):
        super().__init__(parent)
        self.model = model
        self._loading = False
        form = QFormLayout(self)
        form.setContentsMargins(0, 0, 0, 0)

        row = QHBoxLayout()
        self.folder_edit = QLineEdit()
        self.folder_edit.setPlaceholderText("folder the capture writes (new, empty, or a partial capture)")
        self.folder_browse = QPushButton("Browse…")
        row.addWidget(self.folder_edit, 1)
        row.addWidget(self.folder_browse)
        form.addRow("Capture folder", row)
        self.folder_state = QLabel()
        self.folder_state.setObjectName("hint")
        self.folder_state.setWordWrap(True)
        self.resume_check = QCheckBox("Resume the partial capture in this folder")
        form.addRow("", self.resume_check)
        form.addRow("", self.folder_state)

        row = QHBoxLayout()
        self.camera_combo = QComboBox()
        for k, text in CAMERA_CHOICES.items():
            self.camera_combo.addItem(text, k)
        self.camera_source = QLineEdit()
        row.addWidget(self.camera_combo, 1)
        row.addWidget(self.camera_source, 1)
        form.addRow("Camera", row)
        self.exposure = QDoubleSpinBox()
        self.exposure.setRange(0.0, 10_000_000.0)
        self.exposure.setDecimals(0)
        self.exposure.setSingleStep(500.0)
        self.exposure.setSuffix(" µs")
        self.exposure.setSpecialValueText("camera's setting")
        self.exposure.setKeyboardTracking(False)
        self.accept_check = QCheckBox("Capture even if the exposure check fails")
        row = QHBoxLayout()
        row.addWidget(self.exposure)
        row.addWidget(self.accept_check, 1)
        form.addRow("Exposure", row)

        row = QHBoxLayout()
        self.stage_combo = QComboBox()
        for k, text in STAGE_CHOICES.items():
            self.stage_combo.addItem(text, k)
        self.config_edit = QLineEdit()
        self.config_edit.setPlaceholderText("capture.toml")
        self.config_browse = QPushButton("Browse…")
        row.addWidget(self.stage_combo, 1)
        row.addWidget(self.config_edit, 1)
        row.addWidget(self.config_browse)
        form.addRow("Stage", row)

        row = QHBoxLayout()
        self.screen_combo = QComboBox()
        self.settle = QDoubleSpinBox()
        self.settle.setRange(0.0, 10_000.0)
        self.settle.setDecimals(0)
        self.settle.setSuffix(" ms settle")
        self.settle.setToolTip("Wait after each pattern change (LCD response plus one camera frame);"
                               " the simulated display does not wait")
        self.settle.setKeyboardTracking(False)
        row.addWidget(self.screen_combo, 1)
        row.addWidget(self.settle)
        form.addRow("LCD", row)
        self.screen_warning = QLabel()
        self.screen_warning.setObjectName("errorText")
        self.screen_warning.setWordWrap(True)
        form.addRow("", self.screen_warning)
        self.exposure_label = QLabel("Exposure check: runs at the first position, before the long run.")
        self.exposure_label.setWordWrap(True)
        form.addRow("", self.exposure_label)
        self.display_check = QCheckBox("Measure the display's response and pre-compensate the patterns")
        self.display_check.setToolTip("At the first position, after the exposure check: a ramp of 17 uniform levels,"
                                      " the camera's mean at each gives the display's response (rig.toml"
                                      " [display]); every pattern is then shown through its inverse, so the"
                                      " fringes carry no harmonics above the noise (ptp capture --measure-display).")
        form.addRow("", self.display_check)
        self.display_plot = pg.PlotWidget()
        self.display_plot.setTitle("Measured display response")
        axis_label(self.display_plot, "left", "relative luminance")
        axis_label(self.display_plot, "bottom", "level")
        self.display_plot.setMaximumHeight(180)
        self.display_plot.plot([0, 255], [0, 1], pen=pg.mkPen("#999999", style=Qt.DashLine))
        self.display_curve = self.display_plot.plot(pen=pg.mkPen("#2b6cb0", width=2), symbol="o", symbolSize=5,
                                                    symbolBrush="#2b6cb0")
        self.display_plot.setVisible(False)
        form.addRow("", self.display_plot)

        self.refresh_screens()
        self.folder_browse.clicked.connect(self._browse_folder)
        self.config_browse.clicked.connect(self._browse_config)
        self.folder_edit.editingFinished.connect(self._folder_edited)
        for w in (self.camera_combo, self.stage_combo, self.screen_combo):
            w.currentIndexChanged.connect(self._edited)
        for w in (self.camera_source, self.config_edit):
            w.editingFinished.connect(self._edited)
        for w in (self.exposure, self.settle):
            w.valueChanged.connect(self._edited)
        for w in (self.resume_check, self.accept_check, self.display_check):
            w.toggled.connect(self._edited)
        model.rigChanged.connect(self._show_warning)
        model.sourceChanged.connect(self.load)
        self.load()

    def refresh_screens(self) -> None:
        """List the screens again (one may have been plugged in)."""
        current = self.screen_combo.currentData()
        self._loading = True
        try:
            self.screen_combo.clear()
            self.screen_combo.addItem("Simulated display (no window)", None)
            self.screens = list_screens()
            for s in self.screens:
                self.screen_combo.addItem(s.label(), s.index)
            i = self.screen_combo.findData(current)
            self.screen_combo.setCurrentIndex(max(i, 0))
        finally:
            self._loading = False

    # ---- model -> widgets ---------------------------------------------------
    def load(self) -> None:
        s = self.model.session
        lv = s.live
        self._loading = True
        try:
            self.folder_edit.setText(str(s.dataset_folder) if s.source_kind == "live" and s.dataset_folder else "")
            self.resume_check.setChecked(lv.resume)
            self.camera_combo.setCurrentIndex(max(self.camera_combo.findData(lv.camera), 0))
            self.camera_source.setText(lv.camera_source)
            self.exposure.setValue(lv.exposure_us or 0.0)
            self.accept_check.setChecked(lv.accept_exposure)
            self.display_check.setChecked(lv.measure_display)
            self.stage_combo.setCurrentIndex(max(self.stage_combo.findData(lv.stage), 0))
            self.config_edit.setText(str(lv.config) if lv.config else "")
            self.screen_combo.setCurrentIndex(max(self.screen_combo.findData(lv.screen), 0))
            self.settle.setValue(lv.settle_ms)
        finally:
            self._loading = False
        self._show_kinds()
        self._show_warning()
        self._show_folder_state()

    def _show_kinds(self) -> None:
        cam = self.camera_combo.currentData()
        self.camera_source.setVisible(cam != "sim")
        self.camera_source.setPlaceholderText({"opencv": "camera index, file or URL",
                                               "genicam": "GenTL producer (.cti)"}.get(cam, ""))
        serial = self.stage_combo.currentData() == "serial"
        self.config_edit.setEnabled(serial)
        self.config_browse.setEnabled(serial)
        self.settle.setEnabled(self.screen_combo.currentData() is not None)

    def _show_warning(self) -> None:
        idx = self.screen_combo.currentData()
        text = ""
        if idx is not None:
            info = next((s for s in self.screens if s.index == idx), None)
            text = screen_mismatch(info, self.model.session.rig.lcd) if info else "this screen is gone"
        self.screen_warning.setText(text or "")
        self.screen_warning.setVisible(bool(text))

    def _show_folder_state(self) -> None:
        folder = self.model.session.dataset_folder if self.model.session.source_kind == "live" else None
        text = ""
        if folder is not None:
            try:
                st = capture_state(folder)
            except PtpError as exc:
                st, text = None, str(exc)
            if st is not None:
                if st["complete"]:
                    text = f"This folder holds a complete capture ({st['total']} positions)."
                else:
                    text = (f"This folder holds a partial capture: {st['done']} of {st['total']} positions done"
                            " — tick Resume to continue it.")
            elif Path(folder).is_dir() and any(Path(folder).iterdir()) and not text:
                text = "This folder is not empty: the capture needs a new or empty folder."
        self.folder_state.setText(text)
        self.folder_state.setVisible(bool(text))

    # ---- widgets -> model ---------------------------------------------------
    def settings(self) -> LiveSettings:
        cfg = self.config_edit.text().strip()
        return LiveSettings(
            camera=self.camera_combo.currentData(), camera_source=self.camera_source.text().strip() or "0",
            exposure_us=self.exposure.value() or None, stage=self.stage_combo.currentData(),
            config=Path(cfg) if cfg else None, screen=self.screen_combo.currentData(),
            settle_ms=self.settle.value(), resume=self.resume_check.isChecked(),
            accept_exposure=self.accept_check.isChecked(), measure_display=self.display_check.isChecked())

    def _edited(self, *_):
        if self._loading:
            return
        self.model.session.live = self.settings()
        self._show_kinds()
        self._show_warning()
        self.changed.emit()

    def set_folder(self, folder) -> None:
        """Choose the capture folder (as the user would)."""
        self.folder_edit.setText(str(folder))
        self._folder_edited()

    def _folder_edited(self) -> None:
        text = self.folder_edit.text().strip()
        folder = Path(text) if text else None
        if self.model.session.source_kind == "live" and folder != self.model.session.dataset_folder:
            self.model.set_source("live", folder)
        self._show_folder_state()

    def _browse_folder(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Capture into folder", self.folder_edit.text())
        if folder:
            self.set_folder(folder)

    def _browse_config(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Capture configuration", "", "capture files (*.toml)")
        if path:
            self.config_edit.setText(path)
            self._edited()

    def show_display(self, levels, luminance) -> None:
        """Plot the measured display response (levels 0..255 -> relative luminance; dashed: linear)."""
        self.display_curve.setData(np.asarray(levels, float), np.asarray(luminance, float))
        self.display_plot.setVisible(True)

    def show_exposure(self, ok: bool, message: str) -> None:
        self.exposure_label.setText(f"Exposure check: {message}")
        self.exposure_label.setObjectName("" if ok else "errorText")
        self.exposure_label.setStyleSheet("" if ok else "color: #c0392b;")

