"""Page 2, Fringes: the fringe design, a preview of the LCD patterns, the design check."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (QCheckBox, QComboBox, QDoubleSpinBox, QFormLayout, QGridLayout, QGroupBox,
                               QHBoxLayout, QHeaderView, QLabel, QLineEdit, QSlider, QSpinBox, QTableWidget,
                               QTableWidgetItem, QVBoxLayout, QWidget)

from ptpcore.decode import (GRAY_TEMPLATE, design_check, fringe_image, fringe_profile, gray_bits_needed,
    measured_harmonics)
from ptpcore.rig import DirectionFringes, FringeDesign, format_period, position_label, rig_from_toml, rig_to_toml
from ptpcore.evaluate import predicted_signal

from ..widgets.maps import MapView, axis_label, plain_axes
from .base import StudioPage
from .rig import parse_numbers

__all__ = ["FringesPage"]

OK_COLOUR = QColor("#1b7f4c")
BAD_COLOUR = QColor("#c0392b")


def _dspin(lo, hi, value, decimals=2, step=1.0):
    s = QDoubleSpinBox()
    s.setRange(lo, hi)
    s.setDecimals(decimals)
    s.setSingleStep(step)
    s.setValue(value)
    s.setKeyboardTracking(False)
    return s


def _gray_bits(f: FringeDesign, direction: str) -> int:
    """``gray_bits`` of ``direction`` as written (also while unwrapping by periods, unlike ``f.bits``)."""
    o = dict(f.per_direction).get(direction)
    return int(o.gray_bits if o is not None and o.gray_bits is not None else f.gray_bits)


def _slider(maximum: int) -> QSlider:
    s = QSlider(Qt.Horizontal)
    s.setRange(0, max(0, maximum))
    s.setPageStep(1)
    return s


class FringesPage(StudioPage):
    key = "fringes"
    heading = "Fringes"
    subheading = ("What the LCD shows at every position: directions, periods (coarse to fine), steps, "
                  "carrier and gamma. Scrub through the patterns; the design check says whether "
                  "unwrapping will be unambiguous and what noise floor to expect.")

    def __init__(self, model, parent=None):
        super().__init__(model, parent)
        self._error: str | None = None
        self._loading = False
        self._stale = False  # a position was decoded while the page was hidden: refresh when shown
        self.report = None
        side = QWidget()
        sl = QVBoxLayout(side)
        sl.setContentsMargins(0, 0, 4, 0)
        sl.addWidget(self._build_design_form())
        sl.addWidget(self._build_design_check())
        sl.addWidget(self._frames_panel())
        sl.addStretch(1)
        self.split_body(side, self._build_preview(), controls_width=300)
        self._connect(model)
        self._show_rig()

    def _build_design_form(self) -> QGroupBox:
        """The fringe design: directions, periods, steps, conventions, levels, carrier, gamma."""
        form_box = QGroupBox("Design")
        form = QFormLayout(form_box)
        form.setRowWrapPolicy(QFormLayout.WrapLongRows)  # fields under their labels in a narrow panel
        dirs = QWidget()
        dl = QHBoxLayout(dirs)
        dl.setContentsMargins(0, 0, 0, 0)
        self.dir_x = QCheckBox("x (columns)")
        self.dir_x.setToolTip("Patterns whose phase varies along the LCD's columns u")
        self.dir_y = QCheckBox("y (rows)")
        self.dir_y.setToolTip("Patterns whose phase varies along the LCD's rows v")
        dl.addWidget(self.dir_x)
        dl.addWidget(self.dir_y)
        self.periods = QLineEdit()
        self.periods.setToolTip("LCD pixels, coarse to fine; the coarsest must span the LCD plus the carrier")
        self.steps = QLineEdit()
        self.steps.setToolTip("N per period (one number: the same for all)")
        self.offset = _dspin(0, 255, 127.5, 1, 1)
        self.amplitude = _dspin(0.1, 127.5, 100.0, 1, 1)
        self.carrier_x = _dspin(-100, 100, 0.0, 3, 0.1)
        self.carrier_y = _dspin(-100, 100, 0.0, 3, 0.1)
        self.gamma = _dspin(0.1, 5.0, 1.0, 2, 0.1)
        # ptp-dataset/2 conventions (docs/method.md section 3)
        self.periods_y = QLineEdit()
        self.periods_y.setPlaceholderText("as x")
        self.periods_y.setToolTip("Periods of the y patterns when they differ from x ([fringes.y]); may be fractional")
        self.steps_y = QLineEdit()
        self.steps_y.setPlaceholderText("as x")
        self.steps_y.setToolTip("Steps of the y periods when they differ from x ([fringes.y])")
        self.origin = _dspin(-7.0, 7.0, 0.0, 5, 0.1)
        self.origin.setToolTip("phase_origin_rad: the phase every pattern starts at (e.g. 3.14159);\n"
                               "x, and y unless 'Phase origin y' says otherwise")
        self.sign = QComboBox()
        self.sign.addItems(["+1", "-1"])
        self.sign.setToolTip("shift_sign: the direction the phase steps run in (x, and y unless 'Shift sign y' says"
                             " otherwise)")
        self.unwrap = QComboBox()
        self.unwrap.addItems(["periods", "gray", "heterodyne"])
        self.unwrap.setToolTip("Temporal unwrapping by the period list (coarse to fine), by Gray-code images, or by\n"
                               "the beats of two or three close periods (heterodyne: any order; the beats must\n"
                               "cover the LCD plus the carrier, the design check shows them and their noise margin)")
        self.gray_bits = QSpinBox()
        self.gray_bits.setRange(0, 24)
        self.gray_bits.setToolTip("Gray-code bits counting cycles of the coarsest period (x, and y unless"
                                  " 'Gray-code bits y' says otherwise)")
        self._y_convention_widgets()
        self.gray_inverse = QCheckBox("each bit followed by its inverse")
        form.addRow("Directions", dirs)
        form.addRow("Periods (px)", self.periods)
        form.addRow("Steps N", self.steps)
        form.addRow("Periods y (px)", self.periods_y)
        form.addRow("Steps N y", self.steps_y)
        form.addRow("Phase origin (rad)", self.origin)
        form.addRow("Phase origin y (rad)", self.origin_y)
        form.addRow("Shift sign", self.sign)
        form.addRow("Shift sign y", self.sign_y)
        form.addRow("Unwrapping", self.unwrap)
        form.addRow("Gray-code bits", self.gray_bits)
        form.addRow("Gray-code bits y", self.gray_bits_y)
        form.addRow("", self.gray_inverse)
        form.addRow("Offset (grey level)", self.offset)
        form.addRow("Amplitude (grey levels)", self.amplitude)
        form.addRow("Carrier x (px/mm)", self.carrier_x)
        form.addRow("Carrier y (px/mm)", self.carrier_y)
        form.addRow("Gamma pre-compensation", self.gamma)
        self.frames_label = QLabel()
        self.frames_label.setObjectName("hint")
        form.addRow(self.frames_label)
        # A field never narrower than a few numbers: a row whose label and field do not fit side by side in
        # the panel puts the field under its label (WrapLongRows) instead of squeezing it.
        for w in (self.periods, self.steps, self.periods_y, self.steps_y, self.origin_y, self.unwrap, self.sign,
                  self.sign_y, self.gray_bits, self.gray_bits_y, self.origin):
            w.setMinimumWidth(150)
        return form_box

    def _build_design_check(self) -> QGroupBox:
        """The design check's verdict, its table and the predicted noise floor per position."""
        check_box = QGroupBox("Design check")
        cl = QVBoxLayout(check_box)
        self.verdict = QLabel()
        self.verdict.setObjectName("verdict")
        self.verdict.setWordWrap(True)
        cl.addWidget(self.verdict)
        self.table = QTableWidget(0, 3)
        self.table.setHorizontalHeaderLabels(["", "Check", "Result"])
        self.table.verticalHeader().hide()
        self.table.horizontalHeader().setSectionResizeMode(0, QHeaderView.ResizeToContents)
        # The check and its result share the panel's width and wrap (no scrolling across a narrow panel).
        self.table.horizontalHeader().setSectionResizeMode(1, QHeaderView.Stretch)
        self.table.horizontalHeader().setSectionResizeMode(2, QHeaderView.Stretch)
        self.table.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        self.table.verticalHeader().setSectionResizeMode(QHeaderView.ResizeToContents)  # rows as tall as they wrap
        self.table.setWordWrap(True)
        self.table.setEditTriggers(QTableWidget.NoEditTriggers)
        self.table.setMinimumHeight(160)
        cl.addWidget(self.table, 2)
        self.floor_plot = pg.PlotWidget()
        self.floor_plot.setMinimumHeight(120)
        axis_label(self.floor_plot, "left", "noise floor", "µm")
        axis_label(self.floor_plot, "bottom", "z", "mm")
        self.floor_plot.setTitle("Predicted 1σ noise per position", size="9pt")
        self.floor_bars = pg.BarGraphItem(x=[0], height=[0], width=1, brush="#2b6cb0")
        self.floor_plot.addItem(self.floor_bars)
        cl.addWidget(self.floor_plot, 1)
        return check_box

    def _build_preview(self) -> QGroupBox:
        """The main view: the LCD pattern at a chosen direction, period, step and position, and its profile."""
        prev_box = QGroupBox("LCD pattern preview")
        pl = QVBoxLayout(prev_box)
        scrub = QGridLayout()
        self.s_dir = QComboBox()
        self.s_pos = _slider(0)
        self.s_level = _slider(0)
        self.s_step = _slider(0)
        scrub.addWidget(QLabel("Direction"), 0, 0)
        scrub.addWidget(self.s_dir, 0, 1)
        scrub.addWidget(QLabel("Position"), 0, 2)
        scrub.addWidget(self.s_pos, 0, 3)
        scrub.addWidget(QLabel("Period"), 1, 0)
        scrub.addWidget(self.s_level, 1, 1)
        scrub.addWidget(QLabel("Step"), 1, 2)
        scrub.addWidget(self.s_step, 1, 3)
        pl.addLayout(scrub)
        self.preview_label = QLabel()
        self.preview_label.setObjectName("panelTitle")
        self.preview_label.setWordWrap(True)
        pl.addWidget(self.preview_label)
        self.preview = MapView(colour_bar=True)
        axis_label(self.preview.plot, "bottom", "LCD column u", "px")
        axis_label(self.preview.plot, "left", "LCD row v", "px")
        pl.addWidget(self.preview, 3)
        self.profile = pg.PlotWidget()
        self.profile.setMinimumHeight(130)
        self.profile.setLabel("left", "displayed level")
        plain_axes(self.profile)
        self.profile.setTitle("Displayed levels along the pattern axis", size="9pt")
        self.profile_curve = self.profile.plot(pen=pg.mkPen("#2b6cb0", width=1.5), stepMode=None)
        pl.addWidget(self.profile, 1)
        return prev_box

    def _connect(self, model) -> None:
        for w in (self.dir_x, self.dir_y):
            w.toggled.connect(self._edited)
        for w in (self.periods, self.steps, self.periods_y, self.steps_y, self.origin_y):
            w.editingFinished.connect(self._edited)
        for w in (self.offset, self.amplitude, self.carrier_x, self.carrier_y, self.gamma, self.origin,
                  self.gray_bits, self.gray_bits_y):
            w.valueChanged.connect(self._edited)
        for w in (self.sign, self.sign_y, self.unwrap):
            w.currentIndexChanged.connect(self._edited)
        self.gray_inverse.toggled.connect(self._edited)
        for w in (self.s_pos, self.s_level, self.s_step):
            w.valueChanged.connect(self._scrubbed)
        self.s_dir.currentIndexChanged.connect(self._scrubbed)
        model.rigChanged.connect(self._show_rig)
        model.sourceChanged.connect(self._show_rig)
        if hasattr(model, "decodedChanged"):
            model.decodedChanged.connect(self._decoded_arrived)

    def _y_convention_widgets(self) -> None:
        """The ``[fringes.y]`` overrides of phase origin, shift sign and Gray bits ("as x" when empty)."""
        self.origin_y = QLineEdit()
        self.origin_y.setPlaceholderText("as x")
        self.origin_y.setToolTip("phase_origin_rad of the y patterns when it differs from x ([fringes.y]), radians")
        self.sign_y = QComboBox()
        self.sign_y.addItems(["as x", "+1", "-1"])
        self.sign_y.setToolTip("shift_sign of the y patterns when it differs from x ([fringes.y])")
        self.gray_bits_y = QSpinBox()
        self.gray_bits_y.setRange(-1, 24)
        self.gray_bits_y.setSpecialValueText("as x")
        self.gray_bits_y.setValue(-1)
        self.gray_bits_y.setToolTip("Gray-code bits of the y patterns when they differ from x ([fringes.y])")

    def _frames_panel(self) -> QGroupBox:
        """The read-only list of an imported dataset's ``[[images.frames]]``."""
        self.frames_box = QGroupBox("Frames named one by one ([[images.frames]], read-only; kept as they are)")
        fl = QVBoxLayout(self.frames_box)
        self.frames_table = QTableWidget(0, 4)
        self.frames_table.setHorizontalHeaderLabels(["Position", "Direction", "Frame", "File"])
        self.frames_table.verticalHeader().hide()
        self.frames_table.horizontalHeader().setSectionResizeMode(3, QHeaderView.Stretch)
        self.frames_table.setEditTriggers(QTableWidget.NoEditTriggers)
        self.frames_table.setMaximumHeight(160)
        fl.addWidget(self.frames_table)
        return self.frames_box

    def _decoded_arrived(self, *_):
        """A decoded position brings the display's measured harmonics to the design check.

        A hidden page only notes it: the check (harmonics, pattern previews) costs the GUI thread
        tens of ms per position while the acquisition runs (issue 15); :meth:`refresh` catches up.
        """
        if self._loading:
            return
        if not self.isVisible():
            self._stale = True
            return
        self._refresh()

    def refresh(self) -> None:
        """Bring the page up to date when it is shown (forward, Back or a jump)."""
        super().refresh()
        if self._stale:
            self._refresh()

    # ---- model -> widgets -------------------------------------------------
    @property
    def editable(self) -> bool:
        # A live capture shows the patterns it designs; an imported dataset's are fixed.
        return self.model.session.source_kind in ("simulated", "live")

    def _show_rig(self) -> None:
        rig = self.model.session.rig
        f = rig.fringes
        self._loading = True
        try:
            self.dir_x.setChecked("x" in f.directions)
            self.dir_y.setChecked("y" in f.directions)
            self.periods.setText(", ".join(str(format_period(p)) for p in f.periods_px))
            # One number when every period has the same N: it follows the period list.
            self.steps.setText(str(f.steps[0]) if len(set(f.steps)) == 1 else ", ".join(str(n) for n in f.steps))
            oy = dict(f.per_direction).get("y", DirectionFringes())
            self.periods_y.setText("" if oy.periods_px is None else
                                   ", ".join(str(format_period(p)) for p in oy.periods_px))
            self.steps_y.setText("" if oy.steps is None else ", ".join(str(n) for n in oy.steps))
            # x's values (y's where they differ): what the patterns of each direction use.
            dx = "x" if "x" in f.directions else f.directions[0]
            ox, sx, bx = f.origin(dx), f.sign(dx), _gray_bits(f, dx)
            oy_, sy_, by_ = f.origin("y"), f.sign("y"), _gray_bits(f, "y")
            self.origin.setValue(ox)
            self.sign.setCurrentIndex(0 if sx == 1 else 1)
            self.origin_y.setText("" if oy_ == ox else f"{oy_:.10g}")
            self.sign_y.setCurrentIndex(0 if sy_ == sx else (1 if sy_ == 1 else 2))
            self.unwrap.setCurrentText(f.unwrap)
            self.gray_bits.setValue(bx)
            self.gray_bits_y.setValue(-1 if by_ == bx else by_)
            self.gray_inverse.setChecked(f.gray_inverse)
            self.offset.setValue(f.offset)
            self.amplitude.setValue(f.amplitude)
            self.carrier_x.setValue(f.carrier_px_per_mm[0])
            self.carrier_y.setValue(f.carrier_px_per_mm[1])
            self.gamma.setValue(f.gamma)
            for w in (self.dir_x, self.dir_y, self.periods, self.steps, self.offset, self.amplitude,
                      self.carrier_x, self.carrier_y, self.gamma, self.periods_y, self.steps_y, self.origin,
                      self.sign, self.unwrap, self.gray_bits, self.gray_inverse, self.origin_y, self.sign_y,
                      self.gray_bits_y):
                w.setEnabled(self.editable)
            self._show_frames(rig)
            cur_dir = self.s_dir.currentText()
            self.s_dir.clear()
            self.s_dir.addItems(list(f.directions))
            if cur_dir in f.directions:
                self.s_dir.setCurrentText(cur_dir)
            self.s_pos.setMaximum(rig.stage.n_positions - 1)
            self.s_level.setMaximum(max(len(f.periods(d)) for d in f.directions) - 1)
        finally:
            self._loading = False
        self._error = None
        self._refresh()

    def _show_frames(self, rig) -> None:
        """List the rig's ``[[images.frames]]`` (hidden when the images are named by templates)."""
        frames = rig.frame_list
        self.frames_box.setVisible(bool(frames))
        self.frames_table.setRowCount(len(frames))
        for i, e in enumerate(frames):
            if e.reference is not None:
                what = f"{e.reference} reference"
            elif e.gray_bit is not None:
                what = f"Gray-code bit {e.gray_bit}" + (" (inverse)" if e.inverse else "")
            else:
                what = f"period {e.period_index}, step {e.step}"
            for c, text in enumerate((str(e.pos), e.dir or "", what, e.file)):
                self.frames_table.setItem(i, c, QTableWidgetItem(text))
        self.frames_box.setTitle(f"{len(frames)} frames named one by one ([[images.frames]], read-only;"
                                 " kept as they are)")

    def dataset_changed(self) -> None:
        self._show_rig()  # the design and its check are the (new) dataset's

    def _refresh(self) -> None:
        self._stale = False
        rig = self.model.session.rig
        f = rig.fringes
        self.frames_label.setText(
            f"{f.frames_per_position} frames per position, "
            f"{f.frames_per_position * rig.stage.n_positions} in all")
        s = self.model.session
        measured = self.measured_harmonics()
        if measured is not None:
            k, m = measured
            self.report = design_check(rig, modulation_dn=m.modulation_dn, noise_dn=m.noise_dn,
                                       harmonic_dn=m.harmonic_dn)
            z = rig.stage.z_mm[k] if k < rig.stage.n_positions else None
            basis = (f"measured at {position_label(k, z)}: modulation {m.modulation_dn:.0f}, noise {m.noise_dn:.2g},"
                     f" display harmonics {m.harmonic_dn:.2g} grey levels")
        elif s.source_kind == "simulated":
            mod, noise = predicted_signal(rig, s.sim_settings)
            self.report = design_check(rig, modulation_dn=mod, noise_dn=noise)
            basis = f"predicted for the simulated rig: modulation {mod[0]:.0f}, noise {noise:.1f} grey levels"
        else:
            self.report = design_check(rig)
            basis = "default signal assumptions (half range modulation, 1 % noise)"
        self._basis = basis
        self._show_report(basis)
        self._scrubbed()
        self.update_complete()

    def measured_harmonics(self):
        """``(k, MeasuredHarmonics)`` of the latest decoded position of this design, or None."""
        decoded = getattr(self.model.session, "decoded", None) or {}
        for k in reversed(list(decoded)):
            pos = decoded[k]
            samples = pos.info.get("noise_samples") if pos is not None else None
            if samples:
                m = measured_harmonics(samples)
                if m is not None:
                    return k, m
        return None

    def _show_report(self, basis: str) -> None:
        rep = self.report
        self.table.setRowCount(len(rep.items))
        for i, item in enumerate(rep.items):
            # a failure says so in words; a pass is its mark alone (the check's name needs the room)
            mark = QTableWidgetItem("✔" if item.ok else "✘ FAIL")
            mark.setForeground(OK_COLOUR if item.ok else BAD_COLOUR)
            font = mark.font()
            font.setBold(True)
            mark.setFont(font)
            self.table.setItem(i, 0, mark)
            name = QTableWidgetItem(item.name)
            name.setToolTip(item.requirement)
            self.table.setItem(i, 1, name)
            res = QTableWidgetItem(item.message)
            res.setToolTip(item.requirement)
            self.table.setItem(i, 2, res)
        self.table.resizeRowsToContents()
        fails = rep.failures()
        if not fails:
            self.verdict.setText(f"<b style='color:#1b7f4c'>Design OK</b> — every check passes ({basis}).")
        else:
            self.verdict.setText(f"<b style='color:#c0392b'>{len(fails)} check(s) fail</b> — "
                                 + "; ".join(i.message for i in fails))
        z = np.asarray(self.model.session.rig.stage.z_mm)
        width = float(np.min(np.abs(np.diff(z)))) * 0.7 if z.size > 1 else 1.0
        self.floor_bars.setOpts(x=z, height=rep.noise_floor_um, width=width)

    # ---- preview ------------------------------------------------------------
    def _scrubbed(self, *_):
        if self._loading:
            return
        rig = self.model.session.rig
        f = rig.fringes
        d = self.s_dir.currentText() or f.directions[0]
        periods, steps = f.periods(d), f.steps_of(d)
        j = min(self.s_level.value(), len(periods) - 1)
        n_steps = steps[j]
        self.s_step.setMaximum(n_steps - 1)
        step = min(self.s_step.value(), n_steps - 1)
        k = min(self.s_pos.value(), rig.stage.n_positions - 1)
        z = rig.stage.z_mm[k]
        period = periods[j]
        img = fringe_image(rig.lcd, f, d, period, step, n_steps, z)
        self.preview.set_map(img, levels=(0, 255), cmap="CET-L1", label="level")
        shift = f.carrier(d) * z
        self.preview_label.setText(
            f"{d}, T = {format_period(period)} px ({j + 1}/{len(periods)}), step {step + 1}/{n_steps},"
            f" {position_label(k, z)} (of 0 … {rig.stage.n_positions - 1}), carrier shift {shift:.1f} px")
        prof = fringe_profile(rig.lcd, f, d, period, step, n_steps, z)
        span = min(prof.size, max(int(2 * period), 256))
        self.profile_curve.setData(np.arange(span), prof[:span].astype(float))
        axis_label(self.profile, "bottom", "LCD column u" if d == "x" else "LCD row v", "px")
        self.profile.setTitle(f"Displayed levels along {'u' if d == 'x' else 'v'} (first {span} px)", size="9pt")

    def scrub(self, direction: str, level: int, step: int, position: int) -> None:
        """Set the preview scrubbers (the tour and tests use it)."""
        self.s_dir.setCurrentText(direction)
        self.s_level.setValue(level)
        self.s_step.setValue(step)
        self.s_pos.setValue(position)

    # ---- widgets -> model ---------------------------------------------------
    def _edited(self, *_):
        if self._loading or not self.editable:
            return
        try:
            directions = tuple(d for d, w in (("x", self.dir_x), ("y", self.dir_y)) if w.isChecked())
            periods = [format_period(p) for p in parse_numbers(self.periods.text(), float)]
            steps = parse_numbers(self.steps.text(), int)
            if len(steps) == 1:
                steps = steps * len(periods)
            per_direction = ()
            py_text, sy_text = self.periods_y.text().strip(), self.steps_y.text().strip()
            py = tuple(format_period(p) for p in parse_numbers(py_text, float)) if py_text else None
            sy = parse_numbers(sy_text, int) if sy_text else None
            if sy is not None and len(sy) == 1:
                sy = sy * len(py or periods)
            elif sy is None and py is not None and len(py) != len(periods):
                sy = [steps[0]] * len(py)
            oy_text = self.origin_y.text().strip()
            try:
                oy = float(oy_text) if oy_text else None
            except ValueError:
                raise ValueError(f"phase origin y: '{oy_text}' is not a number") from None
            sgn_y = (None, 1, -1)[self.sign_y.currentIndex()]
            by = None if self.gray_bits_y.value() < 0 else self.gray_bits_y.value()
            y = DirectionFringes(py, None if sy is None else tuple(sy), oy, sgn_y, by)
            if y != DirectionFringes():
                per_direction = (("y", y),)
            design = FringeDesign(directions, tuple(periods), tuple(steps), self.offset.value(),
                                  self.amplitude.value(), (self.carrier_x.value(), self.carrier_y.value()),
                                  self.gamma.value(), self.origin.value(), 1 if self.sign.currentIndex() == 0 else -1,
                                  self.unwrap.currentText(), self.gray_bits.value(), self.gray_inverse.isChecked(),
                                  per_direction)
            rig = replace(self.model.session.rig, fringes=design)
            if design.unwrap == "gray":
                # Gray-code frames need names; a first switch to Gray gets the bits that cover the LCD.
                rig = replace(rig, gray_template=rig.gray_template or GRAY_TEMPLATE)
                if design.gray_bits == 0:
                    bits = max(gray_bits_needed(rig, d) for d in directions or ("x",))
                    rig = replace(rig, fringes=replace(design, gray_bits=bits))
                    self.gray_bits.blockSignals(True)
                    self.gray_bits.setValue(bits)
                    self.gray_bits.blockSignals(False)
            else:
                rig = replace(rig, gray_template=None)
            rig = rig_from_toml(rig_to_toml(rig), "fringes")
        except ValueError as exc:
            self._error = str(exc).replace("fringes: key 'fringes.", "'")
            self.update_complete()
            return
        self._error = None
        self.model.set_rig(rig)

    def blocker(self) -> str | None:
        if self._error:
            return f"The design is invalid: {self._error}"
        rig = self.model.session.rig
        if set(rig.fringes.directions) != {"x", "y"}:
            return "Calibration needs fringes in both directions x and y."
        if self.report is not None and not self.report.ok and self.editable:
            return "The design check fails: " + "; ".join(i.name for i in self.report.failures()) + \
                   ". Fix the design (see the check's advice)."
        return None
