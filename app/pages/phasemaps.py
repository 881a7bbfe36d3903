"""Page 4, Phase maps: per position and direction, every map the decoder made."""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6.QtWidgets import QComboBox, QFormLayout, QGroupBox, QLabel, QVBoxLayout, QWidget

from ptpcore.decode import REASON_NAMES
from ptpcore.rig import format_period, position_label
from ptpcore.run import decode_position, direction_reasons
from ptpcore.evaluate import (REASON_COLOURS, REASON_ORDER, VALID_COLOUR, reason_counts, reason_rgba,
    reason_text)

from ..widgets.maps import Legend, MapView, axis_label, line_profile, plain_axes
from ..worker import Job
from .base import StudioPage

__all__ = ["PhaseMapsPage", "MAP_KINDS"]

MAP_KINDS = {
    "wrapped": "Wrapped phase",
    "coord": "Unwrapped LCD coordinate",
    "modulation": "Modulation",
    "background": "Background",
    "validity": "Validity mask",  # coloured by rejection reason (the key beside the map says which)
}
_PER_LEVEL = ("wrapped", "modulation", "background")


class _CountingSource:
    """Passes frames through, reporting progress per frame and honouring cancel."""

    def __init__(self, source, ctx):
        self.source = source
        self.rig = source.rig
        self.ctx = ctx

    def frames(self, k):
        total = self.rig.fringes.frames_per_position
        for i, (spec, img) in enumerate(self.source.frames(k)):
            self.ctx.progress(i / total, f"decoding {position_label(k, self.rig.stage.z_mm[k])}: frame {i + 1}/{total}")
            yield spec, img

    def __getattr__(self, name: str):
        # Gray-code and reference frames (ptp-dataset/2) straight from the source, when it has them.
        if name in ("gray_frames", "reference_frames"):
            return getattr(self.source, name)
        raise AttributeError(name)


class PhaseMapsPage(StudioPage):
    key = "phase"
    heading = "Phase maps"
    subheading = ("Per position and direction: wrapped phase, unwrapped LCD coordinate, modulation, "
                  "background and the validity mask coloured by rejection reason. Hover for values; "
                  "drag the red line for a profile.")

    def __init__(self, model, parent=None):
        super().__init__(model, parent)
        ctl = QGroupBox("Show")
        cf = QFormLayout(ctl)
        cf.setRowWrapPolicy(QFormLayout.WrapLongRows)
        self.pos_combo = QComboBox()
        self.dir_combo = QComboBox()
        self.kind_combo = QComboBox()
        for k, label in MAP_KINDS.items():
            self.kind_combo.addItem(label, k)
        self.level_combo = QComboBox()
        for combo in (self.pos_combo, self.dir_combo, self.kind_combo, self.level_combo):
            combo.setSizeAdjustPolicy(QComboBox.AdjustToMinimumContentsLengthWithIcon)
            combo.setMinimumContentsLength(14)  # long names show in the open list, not in the panel's width
        cf.addRow("Position", self.pos_combo)
        cf.addRow("Direction", self.dir_combo)
        cf.addRow("Map", self.kind_combo)
        cf.addRow("Period", self.level_combo)
        cf.addRow(self.make_job_panel())
        left = QVBoxLayout()
        left.addWidget(ctl)
        leg_box = QGroupBox("Validity (this position, direction)")
        ll = QVBoxLayout(leg_box)
        self.legend = Legend()
        ll.addWidget(self.legend)
        note = QLabel("A pixel with several reasons takes the colour of the first one listed; "
                      "hovering it lists them all.")
        note.setWordWrap(True)
        note.setObjectName("hint")
        ll.addWidget(note)
        left.addWidget(leg_box)
        left.addStretch(1)
        side = QWidget()
        side.setLayout(left)
        left.setContentsMargins(0, 0, 4, 0)

        view = QWidget()
        right = QVBoxLayout(view)
        right.setContentsMargins(0, 0, 0, 0)
        self.title = QLabel()
        self.title.setObjectName("panelTitle")
        self.title.setWordWrap(True)  # a long title wraps; it never widens the page
        right.addWidget(self.title)
        self.view = MapView(colour_bar=True)
        right.addWidget(self.view, 3)
        self.readout = QLabel("move the cursor over the map")
        self.readout.setObjectName("readout")
        right.addWidget(self.readout)
        self.profile = pg.PlotWidget()
        self.profile.setMinimumHeight(140)
        axis_label(self.profile, "bottom", "distance along the line", "px")
        plain_axes(self.profile)
        self.profile.setTitle("Line profile", size="9pt")
        self.profile_curve = self.profile.plot(pen=pg.mkPen("#c0392b", width=1.5))
        right.addWidget(self.profile, 1)
        self.split_body(side, view, controls_width=320)

        self.roi = pg.LineSegmentROI([[0, 0], [10, 10]], pen=pg.mkPen("#e8333a", width=2))
        self.roi.setZValue(20)
        self.view.plot.addItem(self.roi)
        self.roi.sigRegionChanged.connect(self._update_profile)
        self._roi_placed_for = None

        self.decoded = None
        self._per_direction = (None, {})  # (position, {direction: reasons of that direction alone})
        self.current = None  # (k, d, kind, level)
        self.shown: np.ndarray | None = None  # the map shown, display units
        self.unit = ""
        for c in (self.pos_combo, self.dir_combo, self.kind_combo, self.level_combo):
            c.currentIndexChanged.connect(self._selection_changed)
        self.view.hovered.connect(self._hovered)
        model.samplesChanged.connect(self._fill_choices)
        model.decodedChanged.connect(self._decoded_arrived)
        model.decodedReleased.connect(self._released)
        model.rigChanged.connect(self._fill_choices)
        self._fill_choices()

    # ---- choices ----------------------------------------------------------------
    def _fill_choices(self) -> None:
        rig = self.model.session.rig
        for c in (self.pos_combo, self.dir_combo, self.level_combo):
            c.blockSignals(True)
        k_prev = self.pos_combo.currentIndex()
        self.pos_combo.clear()
        for k, z in enumerate(rig.stage.z_mm):
            self.pos_combo.addItem(position_label(k, z), k)
        self.dir_combo.clear()
        for d in rig.fringes.directions:
            self.dir_combo.addItem(f"{d} ({'u, columns' if d == 'x' else 'v, rows'})", d)
        self.level_combo.clear()
        for j, t in enumerate(rig.fringes.periods_px):
            self.level_combo.addItem(f"T = {t} px" + (" (finest)" if j == len(rig.fringes.periods_px) - 1 else ""), j)
        self.level_combo.setCurrentIndex(len(rig.fringes.periods_px) - 1)
        if 0 <= k_prev < self.pos_combo.count():
            self.pos_combo.setCurrentIndex(k_prev)
        for c in (self.pos_combo, self.dir_combo, self.level_combo):
            c.blockSignals(False)
        self.decoded = None

    def _released(self) -> None:
        """The session let its decoded maps go (a long job on a big sensor): so does the page;
        :meth:`on_enter` decodes the chosen position again."""
        self.decoded = None
        self._per_direction = (None, {})
        self.shown = None
        self.current = None
        self.view.clear_map()

    def dataset_changed(self) -> None:
        # Maps of another dataset's positions: gone (on_enter decodes the chosen one again).
        self._fill_choices()
        self.shown = None
        self.current = None
        self.view.clear_map()
        self.title.setText("")
        self.readout.setText("move the cursor over the map")
        self.profile_curve.setData([], [])
        self._roi_placed_for = None

    def on_enter(self) -> None:
        # Start on the most recently decoded position (the acquisition's last).
        if self.model.session.decoded:
            k = next(reversed(self.model.session.decoded))
            self.pos_combo.setCurrentIndex(k)
        self._selection_changed()

    def select(self, position: int | None = None, direction: str | None = None, kind: str | None = None,
               level: int | None = None) -> None:
        """Choose what to show (the tour and tests use it)."""
        if position is not None:
            self.pos_combo.setCurrentIndex(position)
        if direction is not None:
            self.dir_combo.setCurrentIndex(self.dir_combo.findData(direction))
        if kind is not None:
            self.kind_combo.setCurrentIndex(self.kind_combo.findData(kind))
        if level is not None:
            self.level_combo.setCurrentIndex(level)
        self._selection_changed()

    def _selection_changed(self, *_):
        k = self.pos_combo.currentData()
        if k is None:
            return
        self.level_combo.setEnabled(self.kind_combo.currentData() in _PER_LEVEL)
        cached = self.model.session.decoded.get(k)
        if cached is None:
            self._decode(k)
            return
        self.decoded = cached
        self._show()

    def _decode(self, k: int) -> None:
        if self.jobs.busy:
            if self._decoding == k:
                return
            self.jobs.job.cancel()
            self.jobs.job.done.connect(lambda: self._selection_changed())
            return
        try:
            source = self.model.session.make_source()
        except Exception as exc:  # noqa: BLE001
            self.jobs.show_error(str(exc))
            return
        self._decoding = k
        job = Job(lambda ctx: decode_position(_CountingSource(source, ctx), k), f"decoding {position_label(k)}")
        job.finished.connect(self.model.set_decoded)
        self.run_job(job)

    _decoding = None

    def _decoded_arrived(self, k: int) -> None:
        if self.isVisible() and k == self.pos_combo.currentData():
            self.decoded = self.model.session.decoded[k]
            self._say_what_is_wrong(self.decoded)
            self._show()

    def _say_what_is_wrong(self, pos) -> None:
        """What ``ptp decode`` says of this position: a wrong phase convention (naming the
        setting), or too few valid pixels with the dominant reason."""
        from ptpcore.run import convention_check, position_report

        rig = self.model.session.rig
        try:
            lines = [fd.message() for fd in convention_check(rig, pos)]
        except Exception as exc:  # noqa: BLE001 - a diagnosis must never break the page
            lines = [f"convention check failed: {exc}"]
        line = position_report(position_label(pos.index, pos.z_mm), pos.reasons)
        if line:
            lines.append(line)
        if lines:
            self.jobs.show_error("; ".join(lines))

    # ---- drawing ------------------------------------------------------------------
    def reasons_of(self, direction: str):
        """(H, W) uint8: the invalid-pixel reasons of ``direction`` alone at the shown position."""
        pos = self.decoded
        if self._per_direction[0] is not pos:
            self._per_direction = (pos, direction_reasons(self.model.session.rig, pos))
        return self._per_direction[1][direction]

    def _show(self) -> None:
        pos = self.decoded
        if pos is None:
            return
        rig = self.model.session.rig
        d = self.dir_combo.currentData() or rig.fringes.directions[0]
        kind = self.kind_combo.currentData()
        j = self.level_combo.currentData()
        periods = rig.fringes.periods(d)
        j = len(periods) - 1 if j is None else min(j, len(periods) - 1)
        dec = pos.directions[d]
        period = format_period(periods[j])
        where = f"{position_label(pos.index, pos.z_mm)}, direction {d}"
        self.current = (pos.index, d, kind, j)
        reasons = self.reasons_of(d)
        self._reasons = reasons
        self.view.set_overlay(None)
        if kind == "validity":
            self.view.set_rgba(reason_rgba(reasons))
            self.shown = reasons
            self.unit = ""
            both = float(np.mean(pos.reasons == 0))
            self.title.setText(f"Validity mask — {where} alone ({100 * both:.1f} % valid in both directions)")
            self.view.bar.hide()
        else:
            self.view.bar.show()
            if kind == "wrapped":
                data, unit, cmap = dec.wrapped[j].phase, "rad", "CET-C6"
                levels = (-np.pi, np.pi)
                label = f"Wrapped phase, T = {period} px"
            elif kind == "coord":
                data, unit, cmap, levels = dec.coord, "LCD px", "viridis", None
                data = np.where(reasons == 0, dec.coord, np.nan)
                label = f"Unwrapped LCD coordinate {'u' if d == 'x' else 'v'} (carrier removed; invalid pixels blank)"
            elif kind == "modulation":
                data, unit, cmap, levels = dec.wrapped[j].modulation, "grey levels", "CET-L3", None
                label = f"Modulation B, T = {period} px"
            else:
                data, unit, cmap, levels = dec.wrapped[j].background, "grey levels", "CET-L1", None
                label = f"Background A, T = {period} px"
            self.shown = data
            self.unit = unit
            self.view.set_map(data, levels=levels, cmap=cmap, label=unit)
            self.title.setText(f"{label} — {where}")
        self._show_legend(reasons)
        self._place_roi()
        self._update_profile()

    def _show_legend(self, reasons) -> None:
        counts = reason_counts(reasons)
        n = reasons.size
        entries = [("valid", VALID_COLOUR, f"{100 * counts[0] / n:.1f} %")]
        for f in REASON_ORDER:
            entries.append((REASON_NAMES[f], REASON_COLOURS[f], f"{100 * counts[f] / n:.1f} %"))
        self.legend.set_entries(entries)

    def _place_roi(self) -> None:
        h, w = self.decoded.reasons.shape
        if self._roi_placed_for == (h, w):
            return
        self._roi_placed_for = (h, w)
        self.set_line((0.1 * w, 0.5 * h), (0.9 * w, 0.5 * h))

    def set_line(self, p0, p1) -> None:
        """Put the profile line from ``p0`` to ``p1`` ((col, row) pixel coordinates)."""
        h0, h1 = self.roi.getHandles()
        self.roi.movePoint(h0, pg.Point(*p0), finish=False, coords="parent")
        self.roi.movePoint(h1, pg.Point(*p1), finish=True, coords="parent")
        self._update_profile()

    def line_endpoints(self):
        """The profile line's ends in (col, row) pixel coordinates."""
        pts = [self.roi.mapToParent(h.pos()) for h in self.roi.getHandles()]
        return (pts[0].x(), pts[0].y()), (pts[1].x(), pts[1].y())

    def _update_profile(self, *_):
        if self.shown is None:
            return
        p0, p1 = self.line_endpoints()
        if self.current and self.current[2] == "validity":
            dist, vals = line_profile((self.shown != 0).astype(float), p0, p1)
            # 0 or 1 only: those two ticks, named (a label "rejected (1) / valid (0)" was longer than the axis)
            self.profile.setLabel("left", "")
            self.profile.getAxis("left").setTicks([[(0.0, "valid"), (1.0, "rejected")]])
            self.profile.setYRange(-0.1, 1.1, padding=0)
        else:
            dist, vals = line_profile(self.shown, p0, p1)
            self.profile.getAxis("left").setTicks(None)
            self.profile.setLabel("left", self.unit)
            self.profile.enableAutoRange(axis="y")
        self.profile_x, self.profile_y = dist, vals
        self.profile_curve.setData(dist, vals, connect="finite")

    def _hovered(self, row: int, col: int) -> None:
        if row < 0 or self.shown is None:
            return
        why = reason_text(self._reasons[row, col])
        if self.current[2] == "validity":
            text = why
        else:
            v = float(self.shown[row, col])
            text = (f"{v:.5g} {self.unit}" if np.isfinite(v) else "no value") + f"  ({why})"
        self.readout.setText(f"row {row}, col {col}: {text}")

    def blocker(self) -> str | None:
        if self.model.session.samples is None:
            return "Acquire the images first (Acquire page)."
        return None
