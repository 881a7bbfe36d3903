"""Page 1, Rig: camera, LCD, stage positions, and where the images come from; or open a saved session."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import (QButtonGroup, QComboBox, QDoubleSpinBox, QFileDialog, QFormLayout,
                               QGroupBox, QHBoxLayout, QLabel, QLineEdit, QPushButton,
                               QRadioButton, QSpinBox, QVBoxLayout, QWidget)

from ptpcore.errors import PtpError
from ptpcore.rig import Camera, Rig, Stage, load_rig, rig_from_toml, rig_to_toml, save_rig
from ptpcore.simulate import PRESETS, preset

from ..assets import default_rigs
from ..sessionfile import read_session_file
from ..widgets.confirm import confirm
from ..widgets.rigv2 import RigV2Form
from ..worker import Job
from .base import StudioPage

__all__ = ["RigPage", "parse_numbers"]

PRESET_NOTES = {
    "ideal": "noise-free, continuous fringes: decoding is exact",
    "mild": "a lens Brown describes exactly, light noise",
    "realistic": "strong distortion, non-central pupil, gamma, noise, stage errors",
    "rough": "stronger still, 8-bit, near saturation",
}


def parse_numbers(text: str, kind=float) -> list:
    """``"1, 2 3;4"`` -> numbers; ValueError naming the bad item."""
    items = [t for t in text.replace(";", " ").replace(",", " ").split() if t]
    out = []
    for t in items:
        try:
            out.append(kind(t))
        except ValueError:
            raise ValueError(f"'{t}' is not {'an integer' if kind is int else 'a number'}") from None
    return out


GLASS_UNDECLARED = -0.001
"""The cover glass field's minimum, shown as "not declared": ``[lcd] cover_glass_mm`` absent."""


def _dspin(lo, hi, value, decimals=3, step=0.1, suffix=""):
    s = QDoubleSpinBox()
    s.setRange(lo, hi)
    s.setDecimals(decimals)
    s.setSingleStep(step)
    s.setValue(value)
    if suffix:
        s.setSuffix(suffix)
    s.setKeyboardTracking(False)
    return s


def _ispin(lo, hi, value, suffix=""):
    s = QSpinBox()
    s.setRange(lo, hi)
    s.setValue(value)
    if suffix:
        s.setSuffix(suffix)
    s.setKeyboardTracking(False)
    return s


class RigPage(StudioPage):
    """Signals: ``sessionOpened(OpenedSession)`` once a session file is read (the wizard restores it)."""

    key = "rig"
    heading = "Rig"
    subheading = "The camera, the LCD on its stage, the stage positions, and where the images come from."

    sessionOpened = Signal(object)

    def __init__(self, model, parent=None):
        super().__init__(model, parent)
        self._error: str | None = None
        self._loading = False
        cols = QHBoxLayout(self.body)
        left, right = QVBoxLayout(), QVBoxLayout()
        cols.addLayout(left, 1)
        cols.addLayout(right, 1)
        self.v2 = RigV2Form(self)  # ptp-dataset/2: real rigs (bit shift, flatness, display, repeats) and [decode]
        self.v2.hide()  # its two boxes go into the columns
        for box in (self._build_source(), self._build_simulator(), self._build_template(), self._build_session_box(),
                    self.v2.real_box):
            left.addWidget(box)
        left.addStretch(1)
        for box in (self._build_hardware(), self._build_stage(), self.v2.decode_box):
            right.addWidget(box)
        right.addStretch(1)
        self._connect(model)
        self._show_source()
        self._show_rig()

    def _build_source(self) -> QGroupBox:
        """Where the images come from: the simulator, a dataset folder, or the live devices."""
        src = QGroupBox("Source of images")
        sl = QVBoxLayout(src)
        self.src_sim = QRadioButton("Simulated rig (virtual camera with exact ground truth)")
        self.src_folder = QRadioButton("Import a ptp-dataset folder")
        self.src_live = QRadioButton("Live capture: LCD, camera and stage")
        self.src_live.setToolTip("Show the patterns on the LCD, move the stage, photograph every pattern and write"
                                 " a ptp-dataset folder (/1 or /2); the devices are chosen on the Acquire page, and"
                                 " simulated devices need no hardware.")
        self.src_group = QButtonGroup(self)
        for i, b in enumerate((self.src_sim, self.src_folder, self.src_live)):
            self.src_group.addButton(b, i)
            sl.addWidget(b)
        fl = QHBoxLayout()
        self.folder_edit = QLineEdit()
        self.folder_edit.setPlaceholderText("folder holding rig.toml and the images")
        self.browse = QPushButton("Browse…")
        fl.addWidget(self.folder_edit, 1)
        fl.addWidget(self.browse)
        sl.addLayout(fl)
        return src

    def _build_simulator(self) -> QGroupBox:
        """The simulated rig's preset, seed and view offset."""
        self.sim_box = QGroupBox("Simulator")
        sf = QFormLayout(self.sim_box)
        self.preset = QComboBox()
        for i, name in enumerate(PRESETS):
            self.preset.addItem(name, name)
            self.preset.setItemData(i, PRESET_NOTES.get(name, ""), Qt.ToolTipRole)
        # The preset's note on its own line under the box (in the box, "realistic — strong distortion, …" was cut)
        self.preset_note = QLabel()
        self.preset_note.setObjectName("hint")
        self.preset_note.setWordWrap(True)
        self.preset.currentIndexChanged.connect(
            lambda _i: self.preset_note.setText(PRESET_NOTES.get(self.preset.currentData(), "")))
        self.preset_note.setText(PRESET_NOTES.get(self.preset.currentData(), ""))
        self.seed = _ispin(0, 2 ** 31 - 1, 0)
        off = QWidget()
        ol = QHBoxLayout(off)
        ol.setContentsMargins(0, 0, 0, 0)
        self.off_x = _dspin(-500, 500, 0.0, 1, 5.0, " mm")
        self.off_y = _dspin(-500, 500, 0.0, 1, 5.0, " mm")
        ol.addWidget(QLabel("x"))
        ol.addWidget(self.off_x)
        ol.addWidget(QLabel("y"))
        ol.addWidget(self.off_y)
        self.off_x.setToolTip("Shift the camera's view across the LCD (e.g. to see its corner and bezel)")
        self.off_y.setToolTip(self.off_x.toolTip())
        sf.addRow("Preset", self.preset)
        sf.addRow("", self.preset_note)
        sf.addRow("Seed", self.seed)
        sf.addRow("View offset", off)
        return self.sim_box

    def _build_template(self) -> QGroupBox:
        """The rig description: a shipped rig, or load / save a rig.toml."""
        tpl = QGroupBox("Rig description (rig.toml)")
        tl = QHBoxLayout(tpl)
        self.template = QComboBox()
        self.template.addItem("— start from a shipped rig —", None)
        for name, path in default_rigs().items():
            self.template.addItem(name, str(path))
        self.load_button = QPushButton("Load rig.toml…")
        self.save_button = QPushButton("Save rig.toml…")
        tl.addWidget(self.template, 1)
        tl.addWidget(self.load_button)
        tl.addWidget(self.save_button)
        return tpl

    def _build_session_box(self) -> QGroupBox:
        """Open a saved session (ptp-session/1), with the reading job's progress."""
        ses = QGroupBox("Saved session (ptp-session/1)")
        sv = QVBoxLayout(ses)
        srow = QHBoxLayout()
        self.open_button = QPushButton("Open session…")
        self.open_button.setToolTip("Resume a saved calibration: its rig, samples, LUT and comparison; the wizard "
                                    "goes on where it stopped and saves the file again after each stage.")
        srow.addWidget(self.open_button)
        srow.addWidget(self.make_job_panel(), 1)
        sv.addLayout(srow)
        return ses

    def _build_hardware(self) -> QGroupBox:
        """The camera and the LCD (sizes, bit depth, pitch, cover glass)."""
        hw = QGroupBox("Camera and LCD")
        hf = QFormLayout(hw)
        self.cam_w = _ispin(1, 100_000, 640, " px")
        self.cam_h = _ispin(1, 100_000, 480, " px")
        self.cam_bits = _ispin(8, 16, 8, " bit")
        self.lcd_w = _ispin(1, 100_000, 3840, " px")
        self.lcd_h = _ispin(1, 100_000, 2160, " px")
        self.pitch_x = _dspin(0.0001, 10.0, 0.05, 5, 0.001, " mm")
        self.pitch_y = _dspin(0.0001, 10.0, 0.05, 5, 0.001, " mm")
        hf.addRow("Camera width", self.cam_w)
        hf.addRow("Camera height", self.cam_h)
        hf.addRow("Camera bit depth", self.cam_bits)
        hf.addRow("LCD width", self.lcd_w)
        hf.addRow("LCD height", self.lcd_h)
        hf.addRow("LCD pitch x (columns)", self.pitch_x)
        hf.addRow("LCD pitch y (rows)", self.pitch_y)
        self._glass_rows(hf)
        return hw

    def _build_stage(self) -> QGroupBox:
        """The stage positions: regular (start, step, count) or a list of readings, and the travel skew."""
        st = QGroupBox("Stage positions")
        sv = QVBoxLayout(st)
        self.stage_regular = QRadioButton("Regular: start, step, count")
        self.stage_list = QRadioButton("List of readings (mm)")
        self.stage_group = QButtonGroup(self)
        self.stage_group.addButton(self.stage_regular, 0)
        self.stage_group.addButton(self.stage_list, 1)
        sv.addWidget(self.stage_regular)
        rl = QHBoxLayout()
        self.z_start = _dspin(-1000, 1000, 0.0, 3, 1.0, " mm")
        self.z_step = _dspin(-1000, 1000, 4.0, 3, 0.5, " mm")
        self.z_count = _ispin(2, 1000, 11)
        for lab, w in (("start", self.z_start), ("step", self.z_step), ("count", self.z_count)):
            rl.addWidget(QLabel(lab))
            rl.addWidget(w, 1)
        sv.addLayout(rl)
        sv.addWidget(self.stage_list)
        self.z_list = QLineEdit()
        self.z_list.setPlaceholderText("e.g. 0, 4, 8, 12")
        sv.addWidget(self.z_list)
        sk = QHBoxLayout()
        self.skew_a = _dspin(-1, 1, 0.0, 5, 0.001)
        self.skew_b = _dspin(-1, 1, 0.0, 5, 0.001)
        sk.addWidget(QLabel("Travel skew a"))
        sk.addWidget(self.skew_a, 1)
        sk.addWidget(QLabel("b"))
        sk.addWidget(self.skew_b, 1)
        sv.addLayout(sk)
        self.stage_summary = QLabel()
        self.stage_summary.setObjectName("hint")
        sv.addWidget(self.stage_summary)
        return st

    def _connect(self, model) -> None:
        self.src_group.idToggled.connect(self._source_toggled)
        self.folder_edit.editingFinished.connect(self._folder_edited)
        self.browse.clicked.connect(self._browse)
        self.preset.currentIndexChanged.connect(self._preset_chosen)
        for w in (self.seed, self.off_x, self.off_y):
            w.valueChanged.connect(self._sim_edited)
        self.template.activated.connect(self._template_chosen)
        self.load_button.clicked.connect(self._load_dialog)
        self.save_button.clicked.connect(self._save_dialog)
        self.open_button.clicked.connect(self._open_dialog)
        for w in (self.cam_w, self.cam_h, self.cam_bits, self.lcd_w, self.lcd_h, self.pitch_x, self.pitch_y,
                  self.glass_t, self.glass_n, self.z_start, self.z_step, self.z_count, self.skew_a, self.skew_b):
            w.valueChanged.connect(self._edited)
        self.z_list.editingFinished.connect(self._edited)
        self.v2.edited.connect(self._edited)
        self.stage_group.idToggled.connect(lambda _i, on: on and self._edited())
        model.rigChanged.connect(self._show_rig)
        model.sourceChanged.connect(self._show_source)

    def _glass_rows(self, hf) -> None:
        """Cover glass thickness and index, with the datasheet tooltip and the bare-panel hint."""
        # The cover glass (docs/method.md section 8): removed from every sample before any fit.
        glass_tip = ("Everything between the LCD's pixel plane and the air, as one plate: top substrate,\n"
                     "polarizer and any cover glass (thickness in mm, refractive index). Find them in the\n"
                     "panel's datasheet (glass plus polarizer; often 0.7-1.5 mm, index about 1.5).\n"
                     "Nothing in the data reveals them: left 'not declared', a bare panel is assumed and the\n"
                     "LUT is off by the refraction, tens to hundreds of µm at oblique pixels. 0 declares a\n"
                     "panel without glass.")
        self.glass_t = _dspin(GLASS_UNDECLARED, 20.0, GLASS_UNDECLARED, 3, 0.1, " mm")
        self.glass_t.setSpecialValueText("not declared")  # shown at the minimum: the key is absent
        self.glass_n = _dspin(1.0, 3.0, 1.52, 3, 0.01)
        self.glass_t.setToolTip(glass_tip)
        self.glass_n.setToolTip(glass_tip)
        hf.addRow("Cover glass thickness", self.glass_t)
        hf.addRow("Cover glass index", self.glass_n)
        self.glass_hint = QLabel()
        self.glass_hint.setObjectName("hint")
        self.glass_hint.setWordWrap(True)
        self.glass_hint.setToolTip(glass_tip)
        hf.addRow(self.glass_hint)

    # ---- model -> widgets ---------------------------------------------------
    def _show_source(self) -> None:
        s = self.model.session
        self._loading = True
        try:
            {"simulated": self.src_sim, "folder": self.src_folder, "live": self.src_live}[s.source_kind].setChecked(True)
            self.folder_edit.setText(str(s.dataset_folder) if s.dataset_folder and s.source_kind == "folder" else "")
            i = self.preset.findData(s.preset_name)
            if i >= 0:
                self.preset.setCurrentIndex(i)
            self.seed.setValue(s.seed)
            self.off_x.setValue(s.sim_settings.offset_mm[0])
            self.off_y.setValue(s.sim_settings.offset_mm[1])
        finally:
            self._loading = False
        # A live capture describes its hardware here; its simulated camera uses the simulator settings.
        sim = s.source_kind in ("simulated", "live")
        self.sim_box.setEnabled(sim)
        self.folder_edit.setEnabled(s.source_kind == "folder")
        self.browse.setEnabled(s.source_kind == "folder")
        # A dataset's rig is what its rig.toml says.
        for w in self._rig_widgets():
            w.setEnabled(sim)
        self.template.setEnabled(sim)
        self.load_button.setEnabled(sim)

    def _rig_widgets(self):
        return (self.cam_w, self.cam_h, self.cam_bits, self.lcd_w, self.lcd_h, self.pitch_x, self.pitch_y,
                self.glass_t, self.glass_n, self.stage_regular, self.stage_list, self.z_start, self.z_step, self.z_count, self.z_list,
                self.skew_a, self.skew_b, *self.v2.widgets())

    def _show_rig(self) -> None:
        rig = self.model.session.rig
        self._loading = True
        try:
            c, lcd, st = rig.camera, rig.lcd, rig.stage
            self.cam_w.setValue(c.width)
            self.cam_h.setValue(c.height)
            self.cam_bits.setValue(c.bit_depth)
            self.lcd_w.setValue(lcd.width)
            self.lcd_h.setValue(lcd.height)
            self.pitch_x.setValue(lcd.pitch_mm[0])
            self.pitch_y.setValue(lcd.pitch_mm[1])
            self.glass_t.setValue(GLASS_UNDECLARED if lcd.cover_glass_mm is None else lcd.cover_glass_mm)
            self.glass_n.setValue(lcd.cover_glass_index)
            self._update_glass_hint()
            z = np.asarray(st.z_mm)
            steps = np.diff(z)
            regular = len(z) >= 2 and np.allclose(steps, steps[0], rtol=0, atol=1e-9)
            self.z_list.setText(", ".join(f"{v:g}" for v in z))
            if regular:
                self.z_start.setValue(z[0])
                self.z_step.setValue(steps[0])
                self.z_count.setValue(len(z))
            (self.stage_regular if regular else self.stage_list).setChecked(True)
            self.skew_a.setValue(st.direction[0])
            self.skew_b.setValue(st.direction[1])
            self.v2.show_rig(rig)
        finally:
            self._loading = False
        self._error = None
        self._update_stage_summary()
        self.update_complete()

    def _update_glass_hint(self) -> None:
        lcd = self.model.session.rig.lcd
        if lcd.cover_glass_mm:
            tol = (f" (± {lcd.cover_glass_mm_sigma:g} mm)" if lcd.cover_glass_mm_sigma else "")
            self.glass_hint.setText(f"Cover glass {lcd.cover_glass_mm:g} mm{tol}, n {lcd.cover_glass_index:g}:"
                                    " removed from every sample before fitting.")
        elif lcd.cover_glass_mm == 0:
            self.glass_hint.setText("No cover glass (declared): nothing to remove.")
        else:
            self.glass_hint.setText("No cover glass declared: a bare panel is assumed (see the tooltip).")

    def _update_stage_summary(self) -> None:
        z = self.model.session.rig.stage.z_mm
        self.stage_summary.setText(f"{len(z)} positions, z = {min(z):g} … {max(z):g} mm")

    # ---- widgets -> model ---------------------------------------------------
    # ---- replacing a session's results -----------------------------------------------
    def _saved_where(self) -> str:
        """Where the present results are saved, in words (for the questions)."""
        autosave = getattr(self.wizard(), "autosave", None)
        path = getattr(autosave, "path", None)
        if self.model.unsaved_work:
            return "They are not saved in a session file."
        if path is not None:
            return f"They are saved in {path}, which stays as it is."
        return "They were opened from a session file, which stays as it is."

    def confirm_replace(self, what: str) -> bool:
        """Ask before ``what`` replaces the session's results (True: go ahead; True too when there are none)."""
        if not self.model.has_results:
            return True
        s = self.model.session
        return confirm(self, "Replace this session?",
                       f"{what} replaces {self.model.describe_results()} of the present session"
                       f" ({s.describe_source()}). {self._saved_where()}",
                       "Replace them?")

    def _source_toggled(self, idx: int, on: bool) -> None:
        if self._loading or not on:
            return
        kind = ("simulated", "folder", "live")[idx]
        folder = self.folder_edit.text().strip() or None
        if kind == "folder" and folder:
            self._import_folder(folder)
        else:
            if kind != self.model.session.source_kind and not self.confirm_replace(
                    {"simulated": "The simulated rig", "folder": "Importing a dataset",
                     "live": "A live capture"}[kind]):
                self._show_source()  # the choice goes back to what the session is
                return
            self._error = None
            self.model.set_source(kind, folder if kind == "folder" else None)
            if kind == "simulated":
                self._preset_chosen()
        self._show_source()
        self.update_complete()

    def _browse(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Dataset folder (holding rig.toml)",
                                                  self.folder_edit.text())
        if folder:
            self.folder_edit.setText(folder)
            self._import_folder(folder)

    def _folder_edited(self) -> None:
        # editingFinished also comes when the field only loses focus: import only what was typed.
        if self.src_folder.isChecked() and self.folder_edit.isModified():
            self.folder_edit.setModified(False)
            self._import_folder(self.folder_edit.text().strip())

    def _import_folder(self, folder: str) -> bool:
        """Read the dataset's rig.toml; its rig replaces the form. False if refused or not imported.

        A session with results asks first (a new import, even of the same folder, replaces them);
        a folder that cannot be read leaves such a session as it was.
        """
        if not folder:
            self._error = "Choose the dataset folder to import."
            self.update_complete()
            return False
        try:
            if not Path(folder).is_dir():
                raise PtpError(f"{folder}: folder not found")
            rig = load_rig(folder)
        except PtpError as exc:
            if self.model.has_results:
                self.jobs.show_error(f"Cannot import this folder: {exc}")
                self._show_source()
                return False
            self.model.set_source("folder", Path(folder))
            self._error = f"Cannot import this folder: {exc}"
            self.update_complete()
            return False
        if not self.confirm_replace(f"Importing {folder}"):
            self._show_source()
            return False
        self.model.import_dataset(Path(folder), rig)
        self._error = None
        self._show_rig()
        self._show_source()
        return True

    def import_folder(self, folder) -> bool:
        """Choose 'Import a folder' with ``folder`` (as the user would); False if refused or unreadable."""
        self.folder_edit.setText(str(folder))
        self._loading = True  # one import, below (not a second one from the radio button)
        try:
            self.src_folder.setChecked(True)
        finally:
            self._loading = False
        return self._import_folder(str(folder))

    def _preset_chosen(self, *_):
        if self._loading:
            return
        name = self.preset.currentData()
        rig, settings = preset(name)
        s = self.model.session
        settings = replace(settings, offset_mm=(self.off_x.value(), self.off_y.value()))
        # Keep the camera size the user chose; the rest of the rig is the preset's.
        cam = Camera(self.cam_w.value(), self.cam_h.value(), rig.camera.bit_depth)
        self.model.set_simulator(name, settings, self.seed.value())
        self.model.set_rig(replace(rig, camera=cam))
        self._show_rig()
        del s

    def _sim_edited(self, *_):
        if self._loading:
            return
        s = self.model.session
        settings = replace(s.sim_settings, offset_mm=(self.off_x.value(), self.off_y.value()))
        self.model.set_simulator(s.preset_name, settings, self.seed.value())

    def _template_chosen(self, *_):
        path = self.template.currentData()
        if path:
            self._load_rig_file(path)

    def _load_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Load rig.toml", "", "rig files (*.toml)")
        if path:
            self._load_rig_file(path)

    def _load_rig_file(self, path) -> None:
        try:
            rig = load_rig(path)
        except PtpError as exc:
            self._error = str(exc)
            self.update_complete()
            return
        self._error = None
        self.model.set_rig(rig)
        self._show_rig()

    def _save_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save rig.toml", "rig.toml", "rig files (*.toml)")
        if path:
            save_rig(self.model.session.rig, path)

    def form_rig(self) -> Rig:
        """The rig the form describes, validated like a loaded rig.toml.

        Raises
        ------
        ValueError
            (ConfigError) naming the field at fault.
        """
        old = self.model.session.rig
        if self.stage_regular.isChecked():
            z = self.z_start.value() + self.z_step.value() * np.arange(self.z_count.value())
            if self.z_step.value() == 0:
                raise ValueError("stage step must not be 0")
        else:
            z = parse_numbers(self.z_list.text())
        rig = replace(
            old,
            camera=Camera(self.cam_w.value(), self.cam_h.value(), self.cam_bits.value(), old.camera.bit_shift),
            lcd=replace(old.lcd, width=self.lcd_w.value(), height=self.lcd_h.value(),
                        pitch_mm=(self.pitch_x.value(), self.pitch_y.value()),
                        cover_glass_mm=None if self.glass_t.value() < 0 else self.glass_t.value(),
                        cover_glass_index=self.glass_n.value()),
            stage=Stage(tuple(float(v) for v in z), (self.skew_a.value(), self.skew_b.value(), 1.0),
                        old.stage.repeat_z_mm),
        )
        rig = self.v2.apply(rig)  # the ptp-dataset/2 keys of the form
        # The same validation as a rig.toml on disk, with the same messages.
        return rig_from_toml(rig_to_toml(rig), "rig")

    def _edited(self, *_):
        if self._loading or not (self.src_sim.isChecked() or self.src_live.isChecked()):
            return
        try:
            rig = self.form_rig()
        except ValueError as exc:
            self._error = str(exc)
        else:
            self._error = None
            self.model.set_rig(rig)
            self._update_stage_summary()
            self._update_glass_hint()
        self.update_complete()

    # ---- session files -------------------------------------------------------
    def _open_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open session", "",
                                              "PTP sessions (*.ptps.h5);;HDF5 files (*.h5);;All files (*)")
        if path:
            self.open_session(path)

    def open_session(self, path) -> Job | None:
        """Read a session file in the background; on success emit ``sessionOpened``.

        A file that cannot be read leaves everything as it was and shows the reason here.
        """
        if self.jobs.busy:
            return None
        if self.model.unsaved_work and not confirm(
                self, "Open another session?",
                f"Opening {Path(path).name} replaces {self.model.describe_results()} of the present session,"
                " which are not saved in a session file.", "Open it anyway?"):
            return None
        wiz = self.wizard()
        busy = [p for p in getattr(wiz, "pages", ()) if p is not self and p.jobs is not None and p.jobs.busy]
        if busy:
            self.jobs.show_error(f"Wait for '{busy[0].jobs.job.name}' ({busy[0].heading} page) to finish, or"
                                 " cancel it, before opening a session.")
            return None
        job = Job(lambda ctx: read_session_file(path, ctx.progress), "opening the session")
        job.finished.connect(self.sessionOpened.emit)
        return self.run_job(job)

    # ---- why can't I go on? -------------------------------------------------
    def blocker(self) -> str | None:
        s = self.model.session
        if s.source_kind == "folder" and not s.dataset_folder:
            return "Choose the dataset folder to import."
        if self._error:
            return self._error
        return None
