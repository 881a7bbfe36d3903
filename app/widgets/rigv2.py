"""The Rig page's ptp-dataset/2 settings: camera bit shift, LCD flatness, display response,
repeated stage readings and the decoding thresholds (FORMATS.md, ``ptp-dataset/2``).

Each field is text or a spin box whose empty / zero state means "key absent", so a rig that
uses none of them is still written as ``ptp-dataset/1`` (:func:`ptpcore.rig.rig_to_toml`).
"""

from __future__ import annotations

from dataclasses import replace

from PySide6.QtCore import Signal
from PySide6.QtWidgets import QFormLayout, QGroupBox, QLabel, QLineEdit, QSpinBox, QVBoxLayout, QWidget

from ptpcore.decode import DecodeOptions
from ptpcore.rig import DecodeSettings, Display, Rig

__all__ = ["RigV2Form", "TIPS", "numbers_text", "parse_list", "parse_rows"]

_D = DecodeOptions()

TIPS = {
    "bit_shift": ("[camera] bit_shift: how many bits the camera's samples are shifted up in the files\n"
                  "(16-bit files holding 12-bit data MSB-aligned: 4). value >> bit_shift = camera counts.\n"
                  "0: the values are the counts. `ptp calibrate` suggests it when the low bits are all zero."),
    "flatness_u_px": ("[lcd] flatness_u_px: the LCD columns (px) of the grid the panel's measured shape is given on,\n"
                      "increasing, e.g. 0, 1920, 3840. Empty: the panel is taken as flat."),
    "flatness_v_px": "[lcd] flatness_v_px: the LCD rows (px) of that grid, increasing, e.g. 0, 1080, 2160.",
    "flatness_um": ("[lcd] flatness_um: the measured height of the pixel plane at the grid points (µm),\n"
                    "one row per v, rows separated by ';' (e.g. 0 5 0; 5 12 5; 0 5 0); + = farther from\n"
                    "the camera. Interpolated bilinearly between the points."),
    "display_levels": ("[display] levels: displayed grey levels (0..255, increasing) at which the display's\n"
                       "luminance was measured, e.g. 0, 64, 128, 192, 255. With a response the patterns are\n"
                       "generated through its inverse and [fringes] gamma is ignored. Empty: no measured response."),
    "display_luminance": ("[display] luminance: the measured relative luminance at those levels (monotonic,\n"
                          "e.g. 0, 0.05, 0.22, 0.53, 1), as many values as levels."),
    "repeat_z_mm": ("[stage] repeat_z_mm: stage readings (mm) captured again after the sweep, stored as\n"
                    "positions K, K+1, ... after the K sweep positions. They measure drift and are not fitted.\n"
                    "Empty: none."),
    "min_modulation": (f"[decode] min_modulation: a pixel whose fringe modulation is below this fraction of\n"
                       f"the camera's full scale (at any period) is invalid: 'low modulation'.\n"
                       f"Empty: the engine's default {_D.min_modulation:g}."),
    "border_margin_px": (f"[decode] border_margin_px: camera pixels kept away from the LCD's edge (blur mixes the\n"
                         f"bezel into them): 'near the LCD border'. Empty: the engine's default {_D.border_margin_px}."),
    "unwrap_tolerance": (f"[decode] unwrap_tolerance: how far (in periods of the finer level, above 0 and at most\n"
                         f"0.5) two levels may disagree before the pixel is 'unwrapping disagreement'.\n"
                         f"Empty: the engine's default {_D.unwrap_tolerance:g}."),
}


def numbers_text(values) -> str:
    """``(1.0, 2.5)`` -> ``"1, 2.5"``."""
    return ", ".join(f"{v:g}" for v in values)


def parse_list(text: str, what: str, kind=float) -> tuple:
    """Numbers separated by commas or blanks; ValueError naming ``what`` and the bad item."""
    out = []
    for t in text.replace(",", " ").split():
        try:
            out.append(kind(t))
        except ValueError:
            raise ValueError(f"{what}: '{t}' is not {'an integer' if kind is int else 'a number'}") from None
    return tuple(out)


def parse_rows(text: str, what: str) -> tuple:
    """Rows of numbers separated by ``;`` (or new lines)."""
    rows = [r for r in text.replace("\n", ";").split(";") if r.strip()]
    return tuple(parse_list(r, what) for r in rows)


def _optional(text: str, what: str, kind=float):
    text = text.strip()
    if not text:
        return None
    try:
        return kind(text)
    except ValueError:
        raise ValueError(f"{what}: '{text}' is not {'an integer' if kind is int else 'a number'}") from None


class RigV2Form(QWidget):
    """Two group boxes ("Real rig" and "Decoding thresholds") editing the ``/2`` keys of a rig.

    ``real_box`` and ``decode_box`` may be placed apart in another layout (the Rig page does).

    Signals: ``edited()`` when the user finished changing a field.
    """

    edited = Signal()

    def __init__(self, parent=None):
        super().__init__(parent)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        self.real_box = real = QGroupBox("Real rig (ptp-dataset/2; empty = not used)")
        rf = QFormLayout(real)
        self.bit_shift = QSpinBox()
        self.bit_shift.setRange(0, 15)
        self.bit_shift.setSuffix(" bit")
        self.bit_shift.setKeyboardTracking(False)
        self.flat_u = QLineEdit()
        self.flat_v = QLineEdit()
        self.flat_um = QLineEdit()
        self.disp_levels = QLineEdit()
        self.disp_lum = QLineEdit()
        self.repeat_z = QLineEdit()
        for w, key, ph in ((self.bit_shift, "bit_shift", None), (self.flat_u, "flatness_u_px", "e.g. 0, 1920, 3840"),
                           (self.flat_v, "flatness_v_px", "e.g. 0, 1080, 2160"),
                           (self.flat_um, "flatness_um", "e.g. 0 5 0; 5 12 5; 0 5 0"),
                           (self.disp_levels, "display_levels", "e.g. 0, 64, 128, 192, 255"),
                           (self.disp_lum, "display_luminance", "e.g. 0, 0.05, 0.22, 0.53, 1"),
                           (self.repeat_z, "repeat_z_mm", "e.g. 0, 20")):
            w.setToolTip(TIPS[key])
            if ph:
                w.setPlaceholderText(ph)
        rf.addRow("Camera bit shift", self.bit_shift)
        rf.addRow("Flatness grid u (px)", self.flat_u)
        rf.addRow("Flatness grid v (px)", self.flat_v)
        rf.addRow("Flatness (µm)", self.flat_um)
        note = QLabel("Flatness is recorded in rig.toml; how it enters the heights is the calibration's.")
        note.setObjectName("hint")
        note.setWordWrap(True)
        rf.addRow(note)
        rf.addRow("Display levels", self.disp_levels)
        rf.addRow("Display luminance", self.disp_lum)
        rf.addRow("Repeated readings (mm)", self.repeat_z)
        lay.addWidget(real)

        self.decode_box = dec = QGroupBox("Decoding thresholds ([decode]; empty = engine default)")
        df = QFormLayout(dec)
        self.min_mod = QLineEdit()
        self.min_mod.setPlaceholderText(f"{_D.min_modulation:g}")
        self.border = QLineEdit()
        self.border.setPlaceholderText(f"{_D.border_margin_px}")
        self.unwrap_tol = QLineEdit()
        self.unwrap_tol.setPlaceholderText(f"{_D.unwrap_tolerance:g}")
        for w, key in ((self.min_mod, "min_modulation"), (self.border, "border_margin_px"),
                       (self.unwrap_tol, "unwrap_tolerance")):
            w.setToolTip(TIPS[key])
        df.addRow("Min. modulation (of full scale)", self.min_mod)
        df.addRow("Border margin (camera px)", self.border)
        df.addRow("Unwrapping tolerance (periods)", self.unwrap_tol)
        lay.addWidget(dec)

        self.bit_shift.valueChanged.connect(lambda *_: self.edited.emit())
        for w in self.line_edits():
            w.editingFinished.connect(self._finished)

    def line_edits(self) -> tuple:
        return (self.flat_u, self.flat_v, self.flat_um, self.disp_levels, self.disp_lum, self.repeat_z,
                self.min_mod, self.border, self.unwrap_tol)

    def widgets(self) -> tuple:
        """Every input (to enable or disable together)."""
        return (self.bit_shift, *self.line_edits())

    def _finished(self) -> None:
        w = self.sender()
        if w is None or w.isModified():
            if w is not None:
                w.setModified(False)
            self.edited.emit()

    def show_rig(self, rig: Rig) -> None:
        """Fill the fields from ``rig`` (no signal)."""
        widgets = self.widgets()
        for w in widgets:
            w.blockSignals(True)
        try:
            self.bit_shift.setValue(rig.camera.bit_shift)
            lcd = rig.lcd
            self.flat_u.setText(numbers_text(lcd.flatness_u_px))
            self.flat_v.setText(numbers_text(lcd.flatness_v_px))
            self.flat_um.setText("; ".join(" ".join(f"{v:g}" for v in row) for row in lcd.flatness_um))
            self.disp_levels.setText("" if rig.display is None else numbers_text(rig.display.levels))
            self.disp_lum.setText("" if rig.display is None else numbers_text(rig.display.luminance))
            self.repeat_z.setText(numbers_text(rig.stage.repeat_z_mm))
            d = rig.decode
            self.min_mod.setText("" if d.min_modulation is None else f"{d.min_modulation:g}")
            self.border.setText("" if d.border_margin_px is None else str(d.border_margin_px))
            self.unwrap_tol.setText("" if d.unwrap_tolerance is None else f"{d.unwrap_tolerance:g}")
        finally:
            for w in widgets:
                w.blockSignals(False)

    def apply(self, rig: Rig) -> Rig:
        """``rig`` with the form's ``/2`` settings (not yet validated: the caller round-trips it
        through rig.toml, whose checks name the key at fault).

        Raises
        ------
        ValueError
            A field that is not a number (naming the field), or flatness / display lists that do
            not go together.
        """
        u = parse_list(self.flat_u.text(), "flatness grid u")
        v = parse_list(self.flat_v.text(), "flatness grid v")
        um = parse_rows(self.flat_um.text(), "flatness")
        if (u or v or um) and not (u and v and um):
            raise ValueError("flatness needs the grid u, the grid v and the heights together (or none of them)")
        levels = parse_list(self.disp_levels.text(), "display levels")
        lum = parse_list(self.disp_lum.text(), "display luminance")
        if bool(levels) != bool(lum):
            raise ValueError("display levels and luminance go together (or leave both empty)")
        display = Display(levels, lum) if levels else None
        decode = DecodeSettings(_optional(self.min_mod.text(), "min. modulation"),
                                _optional(self.border.text(), "border margin", int),
                                _optional(self.unwrap_tol.text(), "unwrapping tolerance"))
        return replace(rig, camera=replace(rig.camera, bit_shift=self.bit_shift.value()),
                       lcd=replace(rig.lcd, flatness_u_px=u, flatness_v_px=v, flatness_um=um),
                       stage=replace(rig.stage, repeat_z_mm=parse_list(self.repeat_z.text(), "repeated readings")),
                       display=display, decode=decode)
