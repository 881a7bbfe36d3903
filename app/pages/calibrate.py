"""Page 5, Calibrate: fit the per-pixel LUT and inspect its quality, down to one pixel."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QButtonGroup, QCheckBox, QComboBox, QDoubleSpinBox, QFormLayout, QGridLayout,
                               QGroupBox, QHBoxLayout, QLabel, QPushButton, QSpinBox, QSplitter, QTableWidget,
                               QTableWidgetItem, QTabWidget, QVBoxLayout, QWidget)

from ptpcore.fit import FitSettings, ModelChoice, samples_as_fitted, sigma_parts
from ptpcore.evaluate import ScaledMap, pixel_series, prepare_display, reason_text
from ptpcore.evaluate import DriftRecord, HeightSummary, LutReport, RobustFit
from ptpcore.evaluate import residual_field
from ptpcore.run import calibrate_session

from ..session import calibration_session
from ..widgets.maps import HeatmapPanel, axis_label
from ..widgets.residuals import ResidualPanel
from ..widgets.stagepose import StagePosePanel
from ..worker import Job
from .base import StudioPage

__all__ = ["CalibratePage", "LutView", "lut_view", "quality_maps", "robust_text", "drift_text", "drift_map",
           "height_sweep_folder", "height_text"]

MODELS = {"auto": "Auto (best held out)", "poly": "Polynomial", "pchip": "PCHIP (table)",
          "linear": "Linear (table)", "smooth": "Smooth (across pixels)"}
"""Short names: the box in the side panel shows them whole (the long ones were cut); MODEL_NOTES says more."""
MODEL_NOTES = {"auto": "Auto: the model best at held-out positions",
               "poly": "Polynomial in z per pixel (least squares)", "pchip": "PCHIP interpolation of the table",
               "linear": "Linear interpolation of the table",
               "smooth": "Smooth: polynomial regularised across neighbouring pixels"}
DEGREE_MODELS = ("poly", "smooth")
SIGMA_TIP = ("Predicted 1σ uncertainty of the LUT: the propagated noise and the model's own error (estimated"
             " from held-out positions) in quadrature; the statistics line gives both parts")
SIGMA_Z_TIP = ("The scanner's height map (u_p → Z, from the height sweep): predicted 1σ of its Z, the noise of"
               " the decoded projector coordinate and the map's own error in quadrature; blank where the pixel has"
               " no height map")
OPTIONAL_MAPS = {"sigma_x": SIGMA_TIP, "sigma_y": SIGMA_TIP,
                 "drift": "|repeat − sweep| per pixel at the position captured again after the sweep"
                          " ([stage] repeat_z_mm)",
                 "sigma_z": SIGMA_Z_TIP}
CORRECTION_MODELS = ("smooth", "auto")  # the fits that apply the level-bias and footprint corrections


def quality_maps(lut) -> dict[str, tuple[str, np.ndarray, str, str, bool]]:
    """The heatmaps of a LUT in display units: key -> (title, (H, W) map, unit, colour map, integer).

    The maps are the LUT's own, scaled where they are read (:class:`~ptpcore.evaluate.views.ScaledMap`):
    no copy of each beside the LUT (290 MB at 12 MP).
    """
    def um(a):
        return ScaledMap(a, np.float32(1000.0))

    return {
        "rms_x": ("Fit residual RMS, X", um(lut.rms_x), "µm", "viridis", False),
        "rms_y": ("Fit residual RMS, Y", um(lut.rms_y), "µm", "viridis", False),
        "loo_x": ("Leave-one-position-out RMS, X", um(lut.loo_x), "µm", "viridis", False),
        "loo_y": ("Leave-one-position-out RMS, Y", um(lut.loo_y), "µm", "viridis", False),
        "n_positions": ("Positions used per pixel", lut.n_positions, "positions", "CET-L4", True),
        "valid": ("Validity: 1 where the pixel has a usable LUT", ScaledMap(lut.valid, np.uint8(1)), "valid",
                  "CET-L15", True),
        **{f"sigma_{a}": (f"Predicted 1σ uncertainty of {a.upper()} (noise and model error)",
                          um(getattr(lut, f"sigma_{a}")), "µm", "viridis", False)
           for a in "xy" if getattr(lut, f"sigma_{a}", None) is not None},
        **({"sigma_z": ("Height map: predicted 1σ of Z from the projector coordinate u_p", um(lut.height.sigma_z),
                        "µm", "viridis", False)} if getattr(lut, "height", None) is not None else {}),
    }


def height_sweep_folder(session):
    """The dataset folder whose height sweep the Calibrate job fits (``[projector]`` and ``[height]`` in its
    rig.toml, docs/method.md section 9), or None: a simulated session has no height sweep."""
    rig = session.rig
    if session.source_kind not in ("folder", "live") or session.dataset_folder is None:
        return None
    return session.dataset_folder if rig.projector is not None and rig.height is not None else None


def height_text(hm: HeightSummary | None) -> str:
    """The height map in one sentence (degree, coverage, median sigma_z); empty without ``/height``."""
    if hm is None:
        return ""
    sigma = f", median predicted 1σ of Z {hm.sigma_z.median_um:.1f} µm" if hm.sigma_z is not None else ""
    chosen = f", chosen by {hm.chosen_by}" if hm.chosen_by else ""
    return (f" <b>Height map</b> (projector u_p → Z): rational of degree {hm.degree}{chosen};"
            f" {hm.n_valid} of {hm.n_pixels} pixels covered ({100 * hm.fraction:.1f} %){sigma}.")


def robust_text(robust: RobustFit | None) -> str:
    """What the robust fit left out (:attr:`LutReport.robust`), suspect positions named; empty without it."""
    if robust is None:
        return ""
    n = robust.n_rejected
    out = f" Robust fit: {n} sample{'' if n == 1 else 's'} left out (beyond {robust.k_sigma:g} predicted σ)."
    for s in robust.suspects:
        out += (f" <b>SUSPECT {s.label}</b>: {100 * s.fraction:.0f} % of its samples far from the others' curves"
                " (wrong images? a stage glitch?), left out everywhere.")
    return out


def drift_text(drift: DriftRecord | None) -> str:
    """The drift of the sweep's repeat positions (:attr:`LutReport.drift`) in words, warnings in bold red
    first; empty without repeats."""
    if drift is None:
        return ""
    out = "".join(f" <b style='color:#c53030'>DRIFT WARNING: {w}</b>" for w in drift.warnings)
    return out + "".join(f" {t[0].upper()}{t[1:]}." for t in (r.text() for r in drift.repeats))


def drift_map(drift, index: int = 0) -> np.ndarray | None:
    """Per-pixel drift magnitude ``|d|`` (µm, (H, W), NaN where not compared) of repeat ``index``, or None."""
    if drift is None or index >= drift.z.size or drift.matched[index] < 0:
        return None
    return np.hypot(drift.dx[index], drift.dy[index]) * 1e3


@dataclass
class LutView:
    """What the Calibrate page shows of one LUT, ready for the widgets.

    Built by :func:`lut_view` on the fit job's thread: at 5 MP the statistics and the
    residual field take seconds that the GUI thread must not spend (issue 15).

    Attributes
    ----------
    lut : the LUT it describes
    maps : dict
        :func:`quality_maps` (and the drift map when the sweep was repeated).
    stats : str
        The statistics line under the heatmap (from ``report``).
    residual_field : ResidualField or None
    first_pixel : (row, col) or None
        The valid pixel nearest the sensor's centre, selected first.
    displays : dict
        Each map of ``maps`` ready to draw (:func:`ptpcore.evaluate.views.prepare_display`): at 5-12 MP
        reducing a map and its histogram on the GUI thread blocked it 0.1-0.3 s.
    report : LutReport
        What the LUT says of itself (:class:`ptpcore.evaluate.LutReport`, as ``ptp inspect`` prints it).
    """

    lut: object
    maps: dict
    stats: str
    residual_field: object
    first_pixel: tuple[int, int] | None
    displays: dict = field(default_factory=dict)
    report: LutReport | None = None


def lut_view(lut, fitted_samples, positions=None, drift=None) -> LutView:
    """The maps, statistics, residual field and first pixel of ``lut`` (no widget: any thread).

    Parameters
    ----------
    lut : the fitted LUT
    fitted_samples : SampleStack or None
        The samples as fitted (corrections applied), or None when the session has none.
    positions : list of int, optional
        The positions the fit used (None: all).
    drift : ptpcore.fit.drift.Drift, optional
    """
    maps = quality_maps(lut)
    dmap = drift_map(drift) if drift is not None else None
    if dmap is not None:
        maps["drift"] = ("Drift: |repeat − sweep| per pixel", dmap, "µm", "viridis", False)
    arrows = (residual_field(lut, fitted_samples, positions)
              if fitted_samples is not None and fitted_samples.shape == lut.shape else None)
    displays = {key: prepare_display(data, integer=integer) for key, (_t, data, _u, _c, integer) in maps.items()}
    report = LutReport.of(lut)
    return LutView(lut, maps, _stats_text(report), arrows, _central_pixel(lut.valid), displays, report)


def _stats_text(report: LutReport) -> str:
    """The statistics line: validity, median residual, LOO and predicted 1σ, corrections, height map, robust,
    drift, and any record of the LUT that could not be read."""
    r = report
    text = (f"<b>{r.model}</b>: {r.n_valid} of {r.n_pixels} pixels valid ({100 * r.fraction:.1f} %), "
            f"z {r.z_min:g} … {r.z_max:g} mm.")
    if {"x", "y"} <= set(r.rms) and "x" in r.loo:
        text += (f" Median residual RMS X {r.rms['x'].median_um:.2f} µm, Y {r.rms['y'].median_um:.2f} µm;"
                 f" median LOO RMS X {r.loo['x'].median_um:.2f} µm.")
    if r.sigma:
        text += " Predicted 1σ (median) " + ", ".join(
            f"{s.axis.upper()} {s.total.median_um:.2f} µm"
            + (f" (noise {s.noise.median_um:.2f}, model {s.model.median_um:.2f})"
               if s.model is not None and s.noise is not None else "") for s in r.sigma) + "."
    for line in r.corrections:
        text += f" {line[0].upper()}{line[1:]}."
    text += height_text(r.height_map) + robust_text(r.robust) + drift_text(r.drift)
    return text + "".join(f" <i>Note: {n}.</i>" for n in r.notes)


def _sigma_text(lut, axis: str, where) -> str:
    """``X 0.71 µm`` and, when the fit estimated its model's part, ``(noise 0.52, model 0.48)`` at one pixel
    (``where`` its ``(row, col)``; the summary's medians are the report's)."""
    total, noise, model = sigma_parts(lut, axis)

    def um(a):
        return 1e3 * float(np.nanmedian(a[where]))

    text = f"{axis.upper()} {um(total):.2f} µm"
    return text if model is None else text + f" (noise {um(noise):.2f}, model {um(model):.2f})"


_CENTRE_ROWS = 256
"""Rows per band in which :func:`_central_pixel` looks (the whole image's indices and distances of its
valid pixels were 430 MB at 12 MP, the wizard's peak at the end of the fit job)."""


def _central_pixel(valid: np.ndarray) -> tuple[int, int] | None:
    """The valid pixel nearest the sensor's centre (the first in row order of those as near), or None."""
    h, w = valid.shape
    best, best_d2 = None, np.inf
    for r0 in range(0, h, _CENTRE_ROWS):
        rows, cols = np.nonzero(valid[r0:r0 + _CENTRE_ROWS])
        if not rows.size:
            continue
        d2 = (rows + r0 - h / 2) ** 2 + (cols - w / 2) ** 2
        i = int(np.argmin(d2))
        if d2[i] < best_d2:  # strictly: an earlier band keeps a tie, as one argmin over the image does
            best, best_d2 = (int(rows[i]) + r0, int(cols[i])), d2[i]
    return best


class CalibratePage(StudioPage):
    key = "calibrate"
    heading = "Calibrate"
    subheading = ("Fit every pixel's look-up table Z → (X, Y). The heatmaps show its quality over the whole "
                  "sensor; click a pixel to see its samples, fitted curves and residuals.")

    def __init__(self, model, parent=None):
        super().__init__(model, parent)
        side = QWidget()
        sl = QVBoxLayout(side)
        sl.setContentsMargins(0, 0, 4, 0)
        sl.addWidget(self._build_model_controls())
        sl.addWidget(self._build_map_choice())
        sl.addWidget(self._build_summary())
        self.stage_pose = StagePosePanel()  # shown when the LUT carries a refined stage pose
        sl.addWidget(self.stage_pose)
        sl.addStretch(1)
        view = QSplitter(Qt.Horizontal)
        view.addWidget(self._build_maps_view())
        view.addWidget(self._build_pixel_view())
        view.setStretchFactor(0, 3)
        view.setStretchFactor(1, 2)
        view.setSizes([600, 400])
        self.split_body(side, view, controls_width=300)

        self.maps: dict = {}
        self.displays: dict = {}  # key -> DisplayMap of self.maps (LutView.displays)
        self.fitted: FitSettings | None = None  # fit_settings() of the LUT the session holds
        self.residual_field = None
        self._view: LutView | None = None  # what the fit job computed for the LUT it hands over
        self.series = None
        self.selected: tuple[int, int] | None = None
        self._outcome = None
        self.drift = None  # ptpcore.fit.drift.Drift of the LUT the session holds, when fitted here
        self._connect(model)

    def _build_model_controls(self) -> QGroupBox:
        """The model, its options and the Fit button with the job's progress (the side panel's top)."""
        ctl = QGroupBox("Model")
        form = QFormLayout(ctl)
        form.setRowWrapPolicy(QFormLayout.WrapLongRows)
        self.model_combo = QComboBox()
        self.model_combo.setToolTip("Auto: polynomial degrees 1-3 and smooth, each fitted without some positions and"
                                    " judged at them; the most accurate is chosen (a simpler one within 5 %)")
        for i, (k, label) in enumerate(MODELS.items()):
            self.model_combo.addItem(label, k)
            self.model_combo.setItemData(i, MODEL_NOTES[k], Qt.ToolTipRole)
        self.model_combo.setSizeAdjustPolicy(QComboBox.AdjustToMinimumContentsLengthWithIcon)
        self.model_combo.setMinimumContentsLength(16)
        self.degree = QSpinBox()
        self.degree.setRange(1, 5)
        self.degree.setValue(3)
        self.positions_combo = QComboBox()
        self.positions_combo.addItem("all positions", "all")
        self.positions_combo.addItem("every second position", "half")
        self.positions_combo.setItemData(1, "Fit to every second position, holding out the others", Qt.ToolTipRole)
        self.positions_combo.setSizeAdjustPolicy(QComboBox.AdjustToMinimumContentsLengthWithIcon)
        self.positions_combo.setMinimumContentsLength(16)
        self.stage_sigma = QDoubleSpinBox()
        self.stage_sigma.setRange(0.0, 100.0)
        self.stage_sigma.setDecimals(2)
        self.stage_sigma.setSingleStep(0.1)
        self.stage_sigma.setSuffix(" µm")
        self.stage_sigma.setToolTip("1-sigma error of the stage readings (its specification). It moves every pixel"
                                    " of a position at once, so it enters the predicted σ maps through each"
                                    " pixel's slope and is not averaged away by the smooth LUT.")
        self.level_bias = QCheckBox("level bias")
        self.level_bias.setChecked(True)
        self.level_bias.setToolTip("Smooth: remove the bias the LCD's integer levels put into the decoded coordinates"
                                   " (about -0.0015 LCD px). Off for a display that dithers.")
        self.footprint = QCheckBox("footprint")
        self.footprint.setChecked(True)
        self.footprint.setToolTip("Smooth: move each sample from where its pixel's footprint decodes (its average fringe,"
                                  " off the centre ray where the lens bends) to the pixel's centre ray (size read"
                                  " from the fringe contrast). Off when ambient light or a camera black level"
                                  " lower the contrast.")
        self.refine_stage = QCheckBox("refine stage")
        self.refine_stage.setToolTip("Estimate each position's stage pose errors (dx, dy, dz; pitch, yaw, roll) from"
                                     " the straightness of the rays many pixels see, up to a common offset, scale"
                                     " and linear trend, and correct the samples before fitting (docs/method.md section 8)."
                                     " The estimates and their 1-sigma go into the LUT's /provenance/stage_pose.")
        self.robust = QCheckBox("robust")
        self.robust.setChecked(True)
        self.robust.setToolTip("Leave out samples beyond 5 predicted σ of their pixel's curve (counted); a position"
                               " rejected at most pixels is named suspect and left out. Off: keep every sample.")
        self.fit_button = QPushButton("Fit LUT")
        self.fit_button.setObjectName("primary")
        form.addRow("Model", self.model_combo)
        form.addRow("Degree", self.degree)
        form.addRow("Fit to", self.positions_combo)
        form.addRow("Stage 1σ", self.stage_sigma)
        corrections = QHBoxLayout()
        for box in (self.level_bias, self.footprint):
            corrections.addWidget(box)
        corrections.addStretch(1)
        form.addRow(corrections)
        checks = QHBoxLayout()
        for box in (self.refine_stage, self.robust):
            checks.addWidget(box)
        checks.addStretch(1)
        form.addRow(checks)
        form.addRow(self.fit_button)
        form.addRow(self.make_job_panel())
        return ctl

    def _build_map_choice(self) -> QGroupBox:
        """The quality map shown (segmented buttons, three a row so the side panel stays narrow)."""
        box = QGroupBox("Map")
        grid = QGridLayout(box)
        grid.setSpacing(3)
        self.map_buttons = QButtonGroup(self)
        self.map_buttons.setExclusive(True)
        self._map_keys = ["rms_x", "rms_y", "loo_x", "loo_y", "n_positions", "valid", "sigma_x", "sigma_y", "drift",
                          "sigma_z"]
        labels = ["RMS X", "RMS Y", "LOO X", "LOO Y", "positions", "validity", "σ X", "σ Y", "drift", "σ Z"]
        for i, (key, lab) in enumerate(zip(self._map_keys, labels)):
            b = QPushButton(lab)
            b.setCheckable(True)
            b.setObjectName("segment")
            self.map_buttons.addButton(b, i)
            grid.addWidget(b, i // 3, i % 3)
        self.map_buttons.button(self._map_keys.index("n_positions")).setToolTip("Positions used per pixel")
        self.map_buttons.button(0).setChecked(True)
        for key, tip in OPTIONAL_MAPS.items():  # shown when the LUT has them
            self.map_buttons.button(self._map_keys.index(key)).setToolTip(tip)
            self.map_buttons.button(self._map_keys.index(key)).setVisible(False)
        return box

    def _build_summary(self) -> QGroupBox:
        """The LUT's statistics line and, for an ``auto`` fit, the table of candidates."""
        box = QGroupBox("Summary")
        lay = QVBoxLayout(box)
        self.stats = QLabel()
        self.stats.setWordWrap(True)
        lay.addWidget(self.stats)
        self.choice_table = QTableWidget(0, 4)
        self.choice_table.setHorizontalHeaderLabels(["candidate", "held-out RMS (µm)", "model error (µm)", "note"])
        self.choice_table.setEditTriggers(QTableWidget.NoEditTriggers)
        self.choice_table.verticalHeader().setVisible(False)
        self.choice_table.horizontalHeader().setStretchLastSection(True)
        self.choice_table.setToolTip("Auto: every candidate fitted without the held-out positions and judged at them;"
                                     " the most accurate is chosen, a simpler one within 5 % of it preferred")
        self.choice_table.setMinimumHeight(150)
        self.choice_table.setVisible(False)
        lay.addWidget(self.choice_table)
        return box

    def _build_maps_view(self) -> QTabWidget:
        """The quality heatmap (with its histogram) and the residual arrows, one tab each."""
        self.view_tabs = QTabWidget()
        self.heatmap = HeatmapPanel()
        self.heatmap.title.setWordWrap(True)
        self.view_tabs.addTab(self.heatmap, "Quality over the sensor")
        self.residuals = ResidualPanel()
        self.view_tabs.addTab(self.residuals, "Residual arrows")
        return self.view_tabs

    def _build_pixel_view(self) -> QGroupBox:
        """One pixel: its samples and fitted curves X(z), Y(z) and its residual per position."""
        px_box = QGroupBox("Pixel")
        pl = QVBoxLayout(px_box)
        self.pixel_label = QLabel("click a pixel in the heatmap")
        self.pixel_label.setWordWrap(True)
        pl.addWidget(self.pixel_label)
        self.plot_x = self._curve_plot("X", pl)
        self.plot_y = self._curve_plot("Y", pl)
        self.plot_r = pg.PlotWidget()
        # The key in the title, not a legend over the bars.
        self.plot_r.setTitle("Residual (sample − LUT): <span style='color:#2b6cb0'>■ X</span>"
                             " <span style='color:#e69f00'>■ Y</span>", size="9pt")
        axis_label(self.plot_r, "left", "residual", "µm")
        axis_label(self.plot_r, "bottom", "z", "mm")
        self.bars_x = pg.BarGraphItem(x=[], height=[], width=0.4, brush="#2b6cb0", name="X")
        self.bars_y = pg.BarGraphItem(x=[], height=[], width=0.4, brush="#e69f00", name="Y")
        self.plot_r.addItem(self.bars_x)
        self.plot_r.addItem(self.bars_y)
        pl.addWidget(self.plot_r, 1)
        return px_box

    def _connect(self, model) -> None:
        self.model_combo.currentIndexChanged.connect(self._model_changed)
        self._model_changed()
        self.fit_button.clicked.connect(self.fit)
        self.map_buttons.idClicked.connect(lambda _i: self._show_map())
        self.heatmap.pixelClicked.connect(self.select_pixel)
        model.lutChanged.connect(self._lut_changed)
        model.samplesChanged.connect(self.update_complete)

    def _model_changed(self, _index: int = 0) -> None:
        kind = self.model_combo.currentData()
        self.degree.setEnabled(kind in DEGREE_MODELS)
        for box in (self.level_bias, self.footprint):  # corrections only the smooth fit applies
            box.setEnabled(kind in CORRECTION_MODELS)

    def _curve_plot(self, axis: str, layout) -> pg.PlotWidget:
        p = pg.PlotWidget()
        # The key in the title, not a legend over the samples.
        p.setTitle(f"{axis}(z): <span style='color:#2b6cb0'>— LUT</span>"
                   " <span style='color:#1b7f4c'>● fitted</span> <span style='color:#c0392b'>○ held out</span>",
                   size="9pt")
        axis_label(p, "left", axis, "mm")
        axis_label(p, "bottom", "z", "mm")
        p.curve = p.plot(pen=pg.mkPen("#2b6cb0", width=2), name="LUT")
        p.used = p.plot(pen=None, symbol="o", symbolSize=8, symbolBrush="#1b7f4c", symbolPen="#1b7f4c",
                        name="sample (fitted)")
        p.held = p.plot(pen=None, symbol="o", symbolSize=8, symbolBrush=None, symbolPen=pg.mkPen("#c0392b", width=1.5),
                        name="sample (held out)")
        layout.addWidget(p, 1)
        return p

    def on_enter(self) -> None:
        if self.model.session.lut is None and not self.jobs.busy and self._outcome is None:
            self.heatmap.title.setText("Choose a model and press Fit LUT.")

    def dataset_changed(self) -> None:
        # A LUT of another dataset's samples is gone (SessionModel drops it); so is what it showed.
        self._outcome = None
        if self.model.session.lut is None:
            self._clear()
        self.update_complete()

    def _clear(self) -> None:
        self.maps = {}
        self.displays = {}
        self.series = None
        self.selected = None
        self.heatmap.clear("Choose a model and press Fit LUT.")
        self.stats.setText("")
        self.pixel_label.setText("click a pixel in the heatmap")
        for plot in (self.plot_x, self.plot_y):
            for item in (plot.curve, plot.used, plot.held):
                item.setData([], [])
        for bars in (self.bars_x, self.bars_y):
            bars.setOpts(x=[], height=[])

    # ---- fitting --------------------------------------------------------------------
    def configure(self, settings: FitSettings | str = FitSettings(), degree: int | None = None,
                  positions: str = "all", *, fitted: bool = False, **fields) -> None:
        """Set the model controls from fit settings (the tour, an opened session file and tests use it).

        ``settings``: a :class:`FitSettings`, or a model name with ``degree`` and any other ``fields``
        of one (``configure("poly", 2, "half")``). ``positions``: ``"all"`` or ``"half"``.
        ``fitted``: these are the settings the session's LUT was fitted with (an opened file).
        """
        if isinstance(settings, str):
            settings = FitSettings(model=settings, degree=3 if degree is None else degree, **fields)
        self.model_combo.setCurrentIndex(self.model_combo.findData(settings.model))
        self.degree.setValue(settings.degree)
        self.stage_sigma.setValue(settings.stage_sigma_um)
        self.level_bias.setChecked(settings.level_bias)
        self.footprint.setChecked(settings.footprint)
        self.refine_stage.setChecked(settings.refine_stage)
        self.robust.setChecked(settings.robust)
        self.positions_combo.setCurrentIndex(self.positions_combo.findData(positions))
        if fitted:
            self.fitted = self.fit_settings() if self.model.session.lut is not None else None

    def fit_settings(self) -> FitSettings:
        """The fit's settings from the controls: the one :class:`~ptpcore.fit.settings.FitSettings` the
        composer, the session file and the LUT's provenance hold."""
        return FitSettings(model=self.model_combo.currentData(), degree=self.degree.value(),
                           stage_sigma_um=self.stage_sigma.value(), level_bias=self.level_bias.isChecked(),
                           footprint=self.footprint.isChecked(), refine_stage=self.refine_stage.isChecked(),
                           robust=self.robust.isChecked())

    def fit(self) -> Job | None:
        s = self.model.session
        if self.jobs.busy or s.samples is None:
            return None
        fit = self.fit_settings()
        k = s.rig.stage.n_positions
        positions = None if self.positions_combo.currentData() == "all" else list(range(0, k, 2))
        engine_session = calibration_session(s, fit, positions)
        source = s.make_source() if s.rig.stage.repeat_z_mm else None
        gen = self.model.generation

        def work(ctx):
            # The one door (ptpcore.run.calibration): corrections, fit, drift, height map, as ptp calibrate.
            result = calibrate_session(engine_session, source=source, stop_after="lut", progress=ctx.progress)
            self._corrected_cache = (s.samples, s.rig, result.lut, result.fitted)
            # What the page shows, computed here: on the GUI thread it would freeze the window (issue 15).
            ctx.progress(0.995, "computing the quality maps and residuals")
            return result.lut, result.drift, lut_view(result.lut, result.fitted, positions, result.drift), \
                result.height_error

        self.model.release_decoded()  # 617 MB of phase maps at 5 MP, not needed by the fit
        what = "choosing the model and fitting the LUT" if fit.model == "auto" else f"fitting the {fit.model} LUT"
        has_height = engine_session.dataset is not None and s.rig.height is not None
        job = Job(work, what + (" and the height map" if has_height else ""))
        job.finished.connect(lambda out: gen == self.model.generation
                             and self._fitted(*out[:3], positions, fit, height_error=out[3]))
        job.done.connect(lambda: setattr(self, "_outcome", job.outcome))
        return self.run_job(job)

    def _corrected(self, samples, rig):
        """The samples the session's LUT was fitted to: the corrections ``rig`` asks for and the LUT's stage
        pose (cached per stack, rig and LUT)."""
        lut = self.model.session.lut
        cached = getattr(self, "_corrected_cache", None)
        if cached is None or cached[0] is not samples or cached[1] != rig or cached[2] is not lut:
            cached = self._corrected_cache = (samples, rig, lut, samples_as_fitted(samples, rig, lut))
        return cached[3]

    def _fitted(self, lut, drift, view: LutView, positions, fit: FitSettings, height_error: str | None = None) -> None:
        self.fitted = fit
        self.drift = (lut, drift) if drift is not None else None
        self._view = view
        self.model.set_lut(lut, positions)
        if height_error is not None:
            self.jobs.show_warning(f"The LUT is fitted (XY only): {height_error}")

    def lut_settings(self) -> FitSettings:
        """The settings of the LUT the session holds (as it was fitted or opened), else the controls'.

        The Compare page fits its LUTs with them, so both pages judge the same model.
        """
        if self.model.session.lut is not None and self.fitted is not None:
            return self.fitted
        return self.fit_settings()

    def _lut_changed(self) -> None:
        lut = self.model.session.lut
        self.selected = None
        if lut is None:
            self._clear()
            self.residual_field = None
            self.residuals.set_field(None)
            self.stage_pose.set_pose((), None, None)
            self.update_complete()
            return
        view = self._view
        if view is None or view.lut is not lut:  # a LUT not fitted here (an opened session): build it now
            s = self.model.session
            drift = self.drift[1] if self.drift is not None and self.drift[0] is lut else None
            fitted = self._corrected(s.samples, s.rig) if s.samples is not None else None
            view = lut_view(lut, fitted, s.lut_positions, drift)
        self._view = None  # shown: the page keeps its parts, not the view
        self.maps = view.maps
        self.displays = view.displays
        for key in OPTIONAL_MAPS:
            self.map_buttons.button(self._map_keys.index(key)).setVisible(key in self.maps)
        if self.current_map not in self.maps:
            self.map_buttons.button(0).setChecked(True)
        self._show_map()
        self.stats.setText(view.stats)
        self._show_choice(view.report.choice if view.report is not None else None)
        self.stage_pose.set_pose(self.model.session.rig.stage.z_mm, lut.stage_pose, lut.stage_pose_sigma)
        self.residual_field = view.residual_field
        self.residuals.set_field(self.residual_field)
        if view.first_pixel is not None:  # start with the valid pixel nearest the sensor's centre
            self.select_pixel(*view.first_pixel)
        self.update_complete()

    def _show_choice(self, choice: ModelChoice | None) -> None:
        """Fill the table of candidates behind an ``auto`` LUT (hidden for a fixed model)."""
        self.choice_table.setVisible(choice is not None)
        if choice is None:
            self.choice_table.setRowCount(0)
            return
        self.choice_table.setRowCount(len(choice.candidates))
        for i, c in enumerate(choice.candidates):
            cells = [c.name + ("  ← chosen" if i == choice.chosen else ""),
                     "-" if c.note else f"{c.held_out_rms_um:.3f}", "-" if c.note else f"{c.model_error_um:.3f}",
                     c.note]
            for j, text in enumerate(cells):
                item = QTableWidgetItem(text)
                if i == choice.chosen:
                    f = item.font()
                    f.setBold(True)
                    item.setFont(f)
                self.choice_table.setItem(i, j, item)
        self.choice_table.resizeColumnsToContents()

    # ---- maps ---------------------------------------------------------------------------
    def show_map(self, key: str) -> None:
        self.map_buttons.button(self._map_keys.index(key)).setChecked(True)
        self._show_map()

    @property
    def current_map(self) -> str:
        return self._map_keys[self.map_buttons.checkedId()]

    def _show_map(self) -> None:
        if not self.maps:
            return
        key = self.current_map
        title, data, unit, cmap, integer = self.maps[key]
        samples = self.model.session.samples

        def value_text(row, col, data=data, unit=unit, key=key):
            v = data[row, col]
            hm = getattr(self.model.session.lut, "height", None)
            if key == "sigma_z" and hm is not None and not hm.valid[row, col]:
                return "no height map at this pixel"
            if self.model.session.lut is not None and not self.model.session.lut.valid[row, col]:
                n = int((samples.reasons[:, row, col] == 0).sum()) if samples is not None else 0
                return f"no LUT ({n} valid samples; too few for this model)"
            return f"{v:.4g} {unit}"

        self.heatmap.set_map(data, title=title, unit=unit, cmap=cmap, integer=integer, value_text=value_text,
                             prepared=self.displays.get(key))
        if self.selected:
            self.heatmap.view.set_marker(*self.selected)

    # ---- one pixel ------------------------------------------------------------------------
    def select_pixel(self, row: int, col: int) -> None:
        s = self.model.session
        if s.lut is None or s.samples is None:
            return
        self.selected = (row, col)
        self.heatmap.view.set_marker(row, col)
        ps = pixel_series(s.lut, self._corrected(s.samples, s.rig), row, col, s.lut_positions)
        self.series = ps
        for plot, vals, curve in ((self.plot_x, ps.x, ps.x_curve), (self.plot_y, ps.y, ps.y_curve)):
            plot.curve.setData(ps.z_curve, curve, connect="finite")
            used = ps.used
            held = (ps.reasons == 0) & ~ps.used
            plot.used.setData(ps.z[used], vals[used])
            plot.held.setData(ps.z[held], vals[held])
        dz = float(np.min(np.abs(np.diff(ps.z)))) if ps.z.size > 1 else 1.0
        w = 0.35 * dz
        ok_x = np.isfinite(ps.resid_x)
        ok_y = np.isfinite(ps.resid_y)
        self.bars_x.setOpts(x=ps.z[ok_x] - w / 2, height=ps.resid_x[ok_x] * 1e3, width=w)
        self.bars_y.setOpts(x=ps.z[ok_y] + w / 2, height=ps.resid_y[ok_y] * 1e3, width=w)
        lut = s.lut
        if ps.lut_valid:
            text = (f"<b>pixel row {row}, col {col}</b>: {int(ps.used.sum())} positions fitted, "
                    f"z {lut.pixel_z_min[row, col]:g} … {lut.pixel_z_max[row, col]:g} mm; "
                    f"RMS X {1e3 * lut.rms_x[row, col]:.2f} µm, Y {1e3 * lut.rms_y[row, col]:.2f} µm; "
                    f"LOO X {1e3 * lut.loo_x[row, col]:.2f} µm, Y {1e3 * lut.loo_y[row, col]:.2f} µm")
            if lut.sigma_x is not None and lut.sigma_y is not None:
                text += "; predicted 1σ " + ", ".join(_sigma_text(lut, a, (row, col)) for a in "xy")
        else:
            bad = [reason_text(r) for r in ps.reasons if r]
            text = (f"<b>pixel row {row}, col {col}</b>: no usable LUT "
                    f"({int((ps.reasons == 0).sum())} valid samples; rejections: "
                    f"{', '.join(sorted(set(bad))) or 'none'})")
        self.pixel_label.setText(text)

    def blocker(self) -> str | None:
        s = self.model.session
        if s.samples is None:
            return "Acquire the images first (Acquire page)."
        if s.lut is None:
            if self._outcome == "errored":
                return "Fitting failed (see the message above): change the model and press Fit LUT again."
            if self._outcome == "cancelled":
                return "Fitting was cancelled: press Fit LUT to run it again."
            return "Fit the LUT first: choose a model and press Fit LUT."
        if not s.lut.valid.any():
            return "The LUT has no valid pixel: use a model that needs fewer positions, or acquire more."
        return None
