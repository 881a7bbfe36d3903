"""Page 6, Compare: the point-to-point LUTs (plain and smooth) against 3DSTC on held-out heights."""

from __future__ import annotations

import math

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QCheckBox, QComboBox, QFormLayout, QGroupBox, QHBoxLayout, QHeaderView, QLabel,
                               QPushButton, QSpinBox, QSplitter, QTableWidget, QTableWidgetItem, QTabWidget,
                               QVBoxLayout, QWidget)

from ptpcore.fit import FitSettings, correct_all, corrected_samples, describe_corrections
from ptpcore.evaluate import (METHOD_LABELS, METHODS, PAIR_KINDS, compare, histogram, prepare_display,
                              robust_levels, smooth_degree_for, split_positions)

from ..widgets.maps import PEN, MapView, axis_label, colormap, plain_axes
from ..worker import Job
from .base import StudioPage

__all__ = ["ComparePage", "saved_verdict"]

COLOURS = {"ptp": "#1b7f4c", "smooth": "#2b6cb0", "3dstc": "#c0392b"}
MAP_SHARE = (0.3, 0.55)
"""The least and the most of the view's height the error maps get when the page is first shown (the
splitter moves it): between them, as much as three maps side by side need at the camera's aspect."""
COLOUR_BAR_WIDTH = 66
"""The maps' shared colour bar column (px)."""
MAP_CHROME = (60, 140)
"""Pixels around each map's image across (row axis and its label) and down (title, column axis and its
label, the box's title and margins)."""
REF_LABELS = {"truth": "the simulator's exact truth", "measured": "the measured held-out samples"}


def _fmt(v: float, digits: int = 3) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v:.{digits}g}"


def saved_verdict(report) -> str:
    """The verdict line of a comparison report read from a session file (only its JSON is saved)."""
    refs = report.get("references") if isinstance(report, dict) else None
    for ref in ("truth", "measured"):
        entry = refs.get(ref) if isinstance(refs, dict) else None
        verdict = entry.get("verdict") if isinstance(entry, dict) else None
        if isinstance(verdict, dict) and isinstance(verdict.get("text"), str):
            return (f"<b>Saved comparison (from the session file), against {REF_LABELS[ref]}:</b> {verdict['text']}"
                    " Run the comparison again to see its plots.")
    return "A comparison is saved in the session file: run it again to see it here."



def compare_heatmaps(rr, methods) -> tuple[dict, tuple[float, float], dict]:
    """Every method's per-pixel error map against one reference, ready to draw (no widget: any thread).

    Parameters
    ----------
    rr : the reference's report (``CompareResult.references[ref]``)
    methods : the methods compared

    Returns
    -------
    maps : dict method -> (H, W) float32, µm
    levels : (0, hi), the colour levels all methods share (99th percentile of their values)
    displays : dict method -> :class:`ptpcore.evaluate.views.DisplayMap` (no histogram)
    """
    maps = {m: (rr.methods[m].heatmap_mm * 1e3).astype(np.float32) for m in methods}
    every = np.concatenate([v[np.isfinite(v)].ravel()[:: max(1, v.size // 200_000)] for v in maps.values()])
    levels = robust_levels(every, 0.0, 99.0) if every.size else (0.0, 1.0)
    levels = (0.0, levels[1])
    return maps, levels, {m: prepare_display(maps[m], levels=levels, with_histogram=False) for m in methods}


class ComparePage(StudioPage):
    key = "compare"
    heading = "Compare"
    subheading = ("The traditional 3D-target pinhole calibration (3DSTC) against the point-to-point LUT and "
                  "the smooth LUT (regularised across pixels), all calibrated on the same positions and judged "
                  "at the held-out heights.")

    def __init__(self, model, parent=None):
        super().__init__(model, parent)
        self._prepared_for = None  # the comparison whose heatmaps the job prepared
        self._prepared: dict = {}  # reference -> compare_heatmaps(...)
        self.calibrate_page = None  # set by the wizard: the LUT settings to compare with
        self.settings_note = ""
        side = QWidget()
        sl = QVBoxLayout(side)
        sl.setContentsMargins(0, 0, 4, 0)
        sl.addWidget(self._build_run_controls())
        self._build_results(sl)
        sl.addStretch(1)
        # The maps over the plots and the error table (tabs, full width: every row name and number whole);
        # the maps get what they need at the camera's aspect (the table under them left each map ~110x90 px).
        self.view_split = view = QSplitter(Qt.Vertical)
        view.setObjectName("compareViewSplitter")
        view.addWidget(self._build_heatmaps())
        self.result_tabs = QTabWidget()
        self.result_tabs.setObjectName("compareResultTabs")
        self.result_tabs.addTab(self._build_plots(), "Error plots")
        self.result_tabs.addTab(self.st_box, "Error table")
        view.addWidget(self.result_tabs)
        view.setStretchFactor(0, 1)
        view.setStretchFactor(1, 1)
        view.setChildrenCollapsible(False)
        self._view_shares = True  # set the maps' share of the view's height when first shown
        self.split_body(side, view, controls_width=350)
        self._connect(model)

    def showEvent(self, event) -> None:  # noqa: N802 - Qt API
        super().showEvent(event)
        height = self.view_split.height() - self.view_split.handleWidth()
        if self._view_shares is not None and height > 0:  # first shown: the maps what they need, the tabs the rest
            self._view_shares = None
            h, w = self.model.session.rig.camera.shape
            across = (self.view_split.width() - COLOUR_BAR_WIDTH - 20) / 3 - MAP_CHROME[0]  # one map's image, at most
            need = across * h / max(w, 1) + MAP_CHROME[1]
            maps = int(min(max(need, MAP_SHARE[0] * height), MAP_SHARE[1] * height))
            self.view_split.setSizes([maps, height - maps])

    def _build_run_controls(self) -> QGroupBox:
        """The comparison's settings and Run comparison with the job's progress."""
        ctl = QGroupBox("Run")
        form = QFormLayout(ctl)
        form.setRowWrapPolicy(QFormLayout.WrapLongRows)
        self.split = QComboBox()
        self.split.addItem("every second position held out", "alternate")
        self.split.addItem("leave one position out", "loo")
        self.points = QSpinBox()
        self.points.setRange(20, 1_000_000)
        self.points.setValue(2000)
        self.points.setSuffix(" feature points")
        self.rational = QCheckBox("rational k4..k6")
        self.with_smooth = QCheckBox("PTP smooth")
        self.with_smooth.setChecked(True)
        self.with_smooth.setToolTip("Also compare the smooth LUT: a global pinhole + Brown model plus a per-pixel "
                                    "correction smoothed across pixels")
        self.seed = QSpinBox()
        self.seed.setRange(0, 2 ** 31 - 1)
        self.run_button = QPushButton("Run comparison")
        self.run_button.setObjectName("primary")
        form.addRow("Held out", self.split)
        form.addRow("3DSTC target", self.points)
        boxes = QHBoxLayout()
        boxes.addWidget(self.rational)
        boxes.addWidget(self.with_smooth)
        boxes.addStretch(1)
        form.addRow(boxes)
        form.addRow("Seed", self.seed)
        form.addRow(self.run_button)
        form.addRow(self.make_job_panel())
        return ctl

    def _build_results(self, lay: QVBoxLayout) -> None:
        """The verdict, the reference it is judged against, the 3DSTC camera and the error table."""
        self.verdict = QLabel()
        self.verdict.setObjectName("verdict")
        self.verdict.setWordWrap(True)
        lay.addWidget(self.verdict)
        rl = QHBoxLayout()
        rl.addWidget(QLabel("Reference"))
        self.reference = QComboBox()
        self.reference.setSizeAdjustPolicy(QComboBox.AdjustToMinimumContentsLengthWithIcon)
        self.reference.setMinimumContentsLength(16)
        rl.addWidget(self.reference, 1)
        lay.addLayout(rl)
        self.coverage = QLabel()
        self.coverage.setWordWrap(True)
        self.coverage.setObjectName("hint")
        lay.addWidget(self.coverage)
        self.st_box = st_box = QGroupBox("Errors at the held-out heights (µm)")
        sl = QVBoxLayout(st_box)
        sl.setContentsMargins(4, 4, 4, 4)
        self.stats = QTableWidget(0, 5)
        self.stats.setHorizontalHeaderLabels(["error", "RMS", "mean", "p95", "max"])
        self.stats.horizontalHeaderItem(0).setToolTip("coord.: coordinate error |(dX, dY)|; same z, across z: the"
                                                      " error of distances between points at one height, across"
                                                      " heights")
        self.stats.verticalHeader().hide()
        self.stats.verticalHeader().setDefaultSectionSize(20)
        self.stats.setEditTriggers(QTableWidget.NoEditTriggers)
        # The row names (first column) as wide as they need: the numbers share the rest.
        self.stats.horizontalHeader().setSectionResizeMode(QHeaderView.Stretch)
        self.stats.horizontalHeader().setSectionResizeMode(0, QHeaderView.ResizeToContents)
        self.stats.setMinimumHeight(9 * 20 + 32)  # the nine rows (three per method) and the header
        sl.addWidget(self.stats)
        par_box = QGroupBox("3DSTC camera (pinhole + Brown)")
        pl = QVBoxLayout(par_box)
        self.reproj = QLabel()
        self.reproj.setWordWrap(True)
        pl.addWidget(self.reproj)
        self.params = QTableWidget(0, 3)
        self.params.setHorizontalHeaderLabels(["parameter", "value", "± 1σ"])
        self.params.verticalHeader().hide()
        self.params.verticalHeader().setDefaultSectionSize(20)
        self.params.setEditTriggers(QTableWidget.NoEditTriggers)
        self.params.horizontalHeader().setSectionResizeMode(QHeaderView.Stretch)
        self.params.setMinimumHeight(15 * 20 + 28)
        pl.addWidget(self.params)
        lay.addWidget(par_box)

    def _build_heatmaps(self) -> QGroupBox:
        """The three methods' coordinate error maps on one colour scale; zooming one zooms all."""
        heat_box = QGroupBox("Coordinate error per pixel: RMS over the held-out heights, one colour scale")
        hl = QHBoxLayout(heat_box)
        self.heat = {}
        for m in METHODS:
            v = MapView(colour_bar=False)
            v.plot.setTitle(METHOD_LABELS[m], size="9pt")
            self.heat[m] = v
            hl.addWidget(v, 1)
        # the shared colour bar in its own narrow column: inside the last map's plot it made that map the
        # smallest of the three
        self.heat_bar = pg.ColorBarItem(values=(0, 1), colorMap=colormap("inferno"), width=16, pen=PEN,
                                        interactive=True, colorMapMenu=False, label="µm")
        self.heat_bar.setImageItem([self.heat[m].image for m in METHODS])
        plain_axes(self.heat_bar)
        bar_view = pg.GraphicsLayoutWidget()
        bar_view.setObjectName("compareColourBar")
        bar_view.addItem(self.heat_bar)
        bar_view.setFixedWidth(COLOUR_BAR_WIDTH)
        hl.addWidget(bar_view)
        # Zoom and pan one map, the others follow. Not pyqtgraph's setXLink/setYLink: it lines linked views up
        # on the screen (side by side, at their boxes' heights), which unframed the maps (rows -15..86 of 72).
        for m in METHODS:
            self.heat[m].plot.vb.sigRangeChangedManually.connect(lambda _mask, m=m: self._follow_map(m))
        return heat_box

    def _follow_map(self, source: str) -> None:
        """Show the part of the camera that the map ``source`` was zoomed or panned to on the other maps."""
        x_range, y_range = self.heat[source].plot.vb.viewRange()
        for m, view in self.heat.items():
            if m != source:
                view.plot.vb.setRange(xRange=x_range, yRange=y_range, padding=0)

    def _build_plots(self) -> QWidget:
        """Distance error against distance, the distance error histogram and the RMS per held-out height,
        under one colour key (a legend in each plot sat on its data, one under each was cut at 1366x768)."""
        box = QWidget()
        lay = QVBoxLayout(box)
        lay.setContentsMargins(0, 0, 0, 0)
        self.colour_key = QLabel("  ".join(f"<span style='color:{COLOURS[m]}'>■</span> {METHOD_LABELS[m]}" for m in METHODS)
                          + "  <span style='color:#666'>— distance error: solid, pairs at one height; dashed,"
                            " across heights</span>")
        self.colour_key.setWordWrap(True)
        lay.addWidget(self.colour_key)
        plots = QHBoxLayout()
        self.vs_dist = pg.PlotWidget()
        self.vs_dist.setTitle("Distance error vs distance", size="9pt")
        axis_label(self.vs_dist, "left", "RMS error", "µm")
        axis_label(self.vs_dist, "bottom", "distance", "mm")
        self.hist = pg.PlotWidget()
        self.hist.setTitle("Distance errors (all pairs)", size="9pt")
        self.hist.setLabel("left", "pairs")
        plain_axes(self.hist)
        axis_label(self.hist, "bottom", "error", "µm")
        self.per_pos = pg.PlotWidget()
        self.per_pos.setTitle("Coordinate RMS per held-out z", size="9pt")
        axis_label(self.per_pos, "left", "RMS", "µm")
        axis_label(self.per_pos, "bottom", "z", "mm")
        for p in (self.vs_dist, self.hist, self.per_pos):
            p.setMinimumHeight(150)
            plots.addWidget(p, 1)
        lay.addLayout(plots, 1)
        return box

    def _connect(self, model) -> None:
        self.run_button.clicked.connect(self.run)
        self.reference.currentIndexChanged.connect(lambda _i: self._show())
        model.compareChanged.connect(self._result_changed)
        model.samplesChanged.connect(self.update_complete)

    @property
    def plot_widgets(self) -> dict[str, QWidget]:
        """The report's plots by file stem (the Export page saves them as PNG)."""
        return {"compare_heatmaps": self.heat["ptp"].parentWidget(), "distance_vs_distance": self.vs_dist,
                "distance_histogram": self.hist, "per_position": self.per_pos}

    # ---- running -------------------------------------------------------------------
    def run(self) -> Job | None:
        s = self.model.session
        if self.jobs.busy or s.samples is None:
            return None
        fit = self.lut_settings()
        split = self.split.currentData()
        args = dict(truth=s.truth, seed=self.seed.value(), split=split, n_points=self.points.value(),
                    rational=self.rational.isChecked(), with_smooth=self.with_smooth.isChecked(), **fit)
        # The smooth LUT of the comparison has Calibrate's degree, unless a fold has too few calibration
        # positions to fit it (D + 2): then the largest it can cross-validate, and the page says so.
        n_cal = min(len(f[0]) for f in split_positions(s.rig.stage.n_positions, split)) \
            if s.rig.stage.n_positions >= 3 else 0
        want = args["smooth_degree"]
        if args["with_smooth"] and want is not None and n_cal and n_cal < want + 2:
            args["smooth_degree"] = smooth_degree_for(want, n_cal)
            self.settings_note = (f" Calibrate's degree {want} needs {want + 2} calibration positions per fold,"
                                  f" this split has {n_cal}: the smooth LUT here has degree {args['smooth_degree']}.")
        else:
            self.settings_note = ""
        samples, rig = s.samples, s.rig
        gen = self.model.generation
        cal = self.calibrate_page.lut_settings() if self.calibrate_page is not None else FitSettings()
        refine = cal.refine_stage  # the stage pose as Calibrate's LUT had it

        def work(ctx):
            fixed = correct_all(samples, rig, refine=refine, progress=ctx.progress)[0] if refine else \
                corrected_samples(samples, rig)
            result = compare(fixed, rig, progress=ctx.progress, **args)
            # The heatmaps of the reference shown first, ready to draw: not on the GUI thread (issue 15).
            ref = "truth" if "truth" in result.references else "measured"
            return result, {ref: compare_heatmaps(result.references[ref], result.methods)}

        self.model.release_decoded()  # 617 MB of phase maps at 5 MP, not needed by the fit
        job = Job(work, "running the comparison")
        job.finished.connect(lambda out: gen == self.model.generation and self._compared(*out))
        return self.run_job(job)

    def _compared(self, result, prepared: dict) -> None:
        self._prepared_for, self._prepared = result, prepared
        self.model.set_compare(result)

    def lut_settings(self) -> dict:
        """compare()'s model keywords from the Calibrate page's LUT (its model, degree and corrections)."""
        fit = self.calibrate_page.lut_settings() if self.calibrate_page is not None else FitSettings(model="poly")
        kind, degree = fit.model, fit.degree
        # auto: the plain LUT's degree is chosen per fold (poly 1-3), the smooth LUT keeps its default degree
        return {"model": "poly" if kind == "smooth" else kind, "degree": degree,
                "smooth_degree": None if kind == "auto" else degree,
                "level_bias": fit.level_bias, "footprint": fit.footprint}

    def _result_changed(self) -> None:
        r = self.model.session.compare
        self.reference.blockSignals(True)
        self.reference.clear()
        if r is not None:
            for ref in ("truth", "measured"):
                if ref in r.references:
                    self.reference.addItem(f"against {REF_LABELS[ref]}", ref)
        else:
            saved = self.model.session.saved_comparison
            refs = saved.get("references") if isinstance(saved, dict) else None
            for ref in ("truth", "measured"):
                if isinstance(refs, dict) and ref in refs:
                    self.reference.addItem(f"against {REF_LABELS[ref]}", ref)
        self.reference.blockSignals(False)
        self._show()
        self.update_complete()

    def dataset_changed(self) -> None:
        self._result_changed()  # a comparison of another dataset is gone: clear what it drew

    # ---- drawing ---------------------------------------------------------------------
    def _clear(self) -> None:
        for p in (self.vs_dist, self.hist, self.per_pos):
            p.clear()
        for m in METHODS:
            self.heat[m].clear_map()
            self.heat[m].plot.setTitle(METHOD_LABELS[m], size="9pt")
        self.heat_maps = {}
        self.params.setRowCount(0)
        self.stats.setRowCount(0)
        self.reproj.setText("")
        self.coverage.setText("")
        self.verdict.setText("")

    def _fill_params(self, names, values, stds) -> None:
        self.params.setRowCount(len(names))
        for i, (n, v, sd) in enumerate(zip(names, values, stds)):
            for c, text in enumerate((n, f"{v:.6g}", _fmt(sd, 2))):
                item = QTableWidgetItem(text)
                if c:
                    item.setTextAlignment(Qt.AlignRight | Qt.AlignVCenter)
                self.params.setItem(i, c, item)

    def _fill_stats(self, rows) -> None:
        """``rows``: (label, rms, mean, p95, max) in µm."""
        self.stats.setRowCount(len(rows))
        for i, (label, *vals) in enumerate(rows):
            for c, text in enumerate((label, *(_fmt(v) for v in vals))):
                item = QTableWidgetItem(text)
                if c:
                    item.setTextAlignment(Qt.AlignRight | Qt.AlignVCenter)
                else:  # the row's name in full
                    item.setToolTip(label.replace("coord.", "coordinate error").replace(" same z", " distance error,"
                                    " pairs at the same height").replace(" across z", " distance error, pairs across"
                                                                          " heights"))
                self.stats.setItem(i, c, item)

    def _show_saved(self, report: dict) -> None:
        """A comparison opened from a session file: its verdict, camera and statistics (its JSON report).

        The arrays behind the plots are not stored; the controls take the saved settings, so
        Run comparison redraws the same comparison.
        """
        ref = self.reference.currentData()
        refs = report.get("references") if isinstance(report, dict) else None
        rr = refs.get(ref) if isinstance(refs, dict) and ref else None
        verdict = rr.get("verdict") if isinstance(rr, dict) else None
        if isinstance(verdict, dict) and isinstance(verdict.get("text"), str):
            self.verdict.setText(f"<b>Saved comparison (from the session file), against {REF_LABELS[ref]}:</b>"
                                 f" {verdict['text']}")
        else:
            self.verdict.setText(saved_verdict(report))
        cfg = report.get("config") if isinstance(report, dict) else None
        if isinstance(cfg, dict):
            for combo, value in ((self.split, cfg.get("split")),):
                i = combo.findData(value)
                if i >= 0:
                    combo.setCurrentIndex(i)
            if isinstance(cfg.get("seed"), int):
                self.seed.setValue(cfg["seed"])
            if isinstance(cfg.get("n_points"), int):
                self.points.setValue(cfg["n_points"])
            self.rational.setChecked(bool(cfg.get("rational")))
            self.with_smooth.setChecked(cfg.get("smooth") is not None)
        pin = report.get("pinhole") if isinstance(report, dict) else None
        if isinstance(pin, dict) and isinstance(pin.get("param_names"), list):
            self._fill_params(pin["param_names"], pin.get("param_values", []),
                              [math.nan if v is None else v for v in pin.get("param_std", [])])
            rms = pin.get("reprojection_rms_px")
            self.reproj.setText(f"Reprojection RMS <b>{_fmt(rms if rms is not None else math.nan)} px</b> per"
                                f" coordinate, from {pin.get('n_points', '?')} feature points")
        rows = []
        methods = cfg.get("methods", []) if isinstance(cfg, dict) else []
        for m in methods:
            mr = rr.get(m) if isinstance(rr, dict) else None
            if not isinstance(mr, dict) or m not in METHOD_LABELS:
                continue
            lab = METHOD_LABELS[m]

            def vals(st):
                st = st if isinstance(st, dict) else {}
                return tuple(math.nan if st.get(k) is None else st.get(k) for k in ("rms_um", "mean_um", "p95_um",
                                                                                      "max_um"))
            rows.append((f"{lab} coord.", *vals(mr.get("coordinate"))))
            dist = mr.get("distance") if isinstance(mr.get("distance"), dict) else {}
            for kind, text in zip(PAIR_KINDS, ("same z", "across z")):
                rows.append((f"{lab} {text}", *vals((dist.get(kind) or {}).get("stats"))))
        self._fill_stats(rows)
        self.coverage.setText("Restored from the session file, which keeps the comparison's report but not its"
                              " arrays: press Run comparison to redraw the plots (the controls hold the saved"
                              " settings).")

    def _show(self) -> None:
        r = self.model.session.compare
        self._clear()
        if r is None:
            saved = self.model.session.saved_comparison
            if saved is not None:
                self._show_saved(saved)
            return
        ref = self.reference.currentData() or "measured"
        rr = r.references[ref]
        self.verdict.setText(f"<b>Verdict against {REF_LABELS[ref]}:</b> {rr.verdict.text}")
        fit = r.pinhole
        self.reproj.setText(f"Reprojection RMS <b>{fit.reprojection_rms_px:.3g} px</b> per coordinate, "
                            f"from {fit.n_points} feature points" +
                            (f" (fold 1 of {len(r.folds)})" if len(r.folds) > 1 else ""))
        self._fill_params(list(fit.param_names), fit.param_values, fit.param_std)
        methods = r.methods
        rows = []
        for m in methods:
            mr = rr.methods[m]
            lab = METHOD_LABELS[m]
            for label, st in ((f"{lab} coord.", mr.coordinate),
                              (f"{lab} same z", mr.distance["same_height"].stats),
                              (f"{lab} across z", mr.distance["across_heights"].stats)):
                rows.append((label, st.rms_um, st.mean_um, st.p95_um, st.max_um))
        self._fill_stats(rows)
        c = r.coverage
        nm = max(int(c.n_measured.sum()), 1)
        noise = ""
        if r.reference_noise is not None and ref == "measured":
            noise = f" The measured reference carries its own noise: {r.reference_noise.rms_um:.3g} µm RMS."
        smooth = ""
        if "smooth" in methods:
            scales = sorted({f.smooth_scale_px for f in r.folds})
            scale = f"{scales[0]:g}" if len(scales) == 1 else f"{scales[0]:g} … {scales[-1]:g}"
            smooth = (f" PTP smooth: poly degree {r.smooth_degree}, smoothing scale {scale} px (cross-validated)."
                      f"{self.settings_note}")
        notes = "".join(f" {n}." for n in r.notes)
        notes += "".join(f" {line[0].upper()}{line[1:]}." for line in describe_corrections(r.corrections))
        self.coverage.setText(
            f"Held-out positions {', '.join(str(int(k)) for k in r.held_positions)}"
            f" (z = {', '.join(f'{z:g}' for z in r.z_held)} mm); pixels compared"
            f" {100 * c.n_compared.sum() / nm:.1f} % of the valid held-out samples; pairs "
            f"{len(r.pairs['same_height'])} same height, {len(r.pairs['across_heights'])} across heights."
            f"{smooth}{notes}{noise}")

        # heatmaps on one shared scale across every method (drawn as the job prepared them, when it did)
        ready = self._prepared.get(ref) if self._prepared_for is r else None
        maps, levels, displays = ready if ready is not None else compare_heatmaps(rr, methods)
        self.heat_maps = maps
        for m in METHODS:
            self.heat[m].setVisible(m in methods)
        for m in methods:
            d = displays[m]
            self.heat[m].set_map(d.image, levels=levels, cmap="inferno", step=d.step, extent=d.extent, full=maps[m])
            # "RMS" is in the box's title: a longer title was cut over a narrow map
            self.heat[m].plot.setTitle(f"{METHOD_LABELS[m]} {_fmt(rr.methods[m].coordinate.rms_um)} µm", size="9pt")
        self.heat_bar.setLevels(levels)
        self.heat_bar.rounding = max(levels[1] / 1000, 1e-9)

        # distance error against distance, histogram, per position
        errs = {}
        for m in methods:
            pen_style = {"same_height": Qt.SolidLine, "across_heights": Qt.DashLine}
            named = False  # one legend entry per method; the line style tells the pair kind (see the title)
            for kind, d in rr.methods[m].distance.items():
                cv = d.curve
                if cv.edges_mm.size < 2:
                    continue
                centres = 0.5 * (cv.edges_mm[1:] + cv.edges_mm[:-1])
                self.vs_dist.plot(centres, cv.rms_um, connect="finite", symbol="o", symbolSize=5,
                                  symbolBrush=COLOURS[m], symbolPen=COLOURS[m],
                                  pen=pg.mkPen(COLOURS[m], width=2, style=pen_style[kind]),
                                  name=None if named else METHOD_LABELS[m])
                named = True
            errs[m] = np.concatenate([d.error_mm for d in rr.methods[m].distance.values()]) * 1e3
        allv = np.concatenate(list(errs.values())) if errs else np.zeros(0)
        if allv.size:
            lo, hi = robust_levels(allv, 0.5, 99.5)
            edges = None
            for m in methods:
                edges, counts = histogram(errs[m], (lo, hi), bins=60)
                self.hist.plot(edges, counts, stepMode="center", pen=pg.mkPen(COLOURS[m], width=2),
                               name=METHOD_LABELS[m])
        z = r.z_held
        dz = float(np.min(np.diff(np.unique(r.z_mm)))) if r.z_mm.size > 1 else 1.0
        w = 0.7 * dz / len(methods)
        for i, m in enumerate(methods):
            vals = np.array([s.rms_um for s in rr.methods[m].per_position], float)
            bars = pg.BarGraphItem(x=z + (i - (len(methods) - 1) / 2) * w, height=np.nan_to_num(vals), width=w,
                                   brush=COLOURS[m], name=METHOD_LABELS[m])
            self.per_pos.addItem(bars)
        if z.size:  # every height's bars whole in view (the auto range cut the last one)
            half = 0.5 * w * len(methods)
            self.per_pos.setXRange(float(z.min()) - half, float(z.max()) + half, padding=0.05)

    def on_enter(self) -> None:
        s = self.model.session
        if s.compare is None and s.saved_comparison is not None:
            self._show()
        elif s.compare is None:
            self.verdict.setText("Optional: run the comparison to see how 3DSTC does on the same data and to "
                                 "include it in the report. Next works without it.")

    def blocker(self) -> str | None:
        if self.model.session.samples is None:
            return "Acquire the images first (Acquire page)."
        return None
