"""Page 3, Acquire: run the simulated capture, the import or the live capture, position by position."""

from __future__ import annotations

from pathlib import Path

from PySide6.QtGui import QBrush, QColor
from PySide6.QtWidgets import (QCheckBox, QFileDialog, QGroupBox, QHBoxLayout, QHeaderView, QLabel, QLineEdit,
                               QPushButton, QTableWidget, QTableWidgetItem, QVBoxLayout, QWidget)

from ptpcore.io import DatasetSource
from ptpcore.simulate import simulate_dataset
from ptpcore.evaluate import REASON_ORDER
from ptpcore.decode import REASON_NAMES
from ptpcore.rig import position_label

from ..session import FramePreview, PositionStatus, decode_samples, session_truth
from ..widgets.maps import MapView
from ..worker import Job
from .base import StudioPage

__all__ = ["AcquirePage", "acquisition_job", "frame_tap"]

def frame_tap(ctx, max_level: int, interval: float = 0.12, max_pixels=None):
    """The ``on_frame`` of the composer's decode (:func:`ptpcore.run.calibrate_session`) for a job: says which position
    started (``("start", k)``), lets the job be cancelled between frames and shows at most one
    frame every ``interval`` seconds (:class:`~ptp_studio.session.FramePreview`, reduced on the
    worker thread). The frames come from the engine's own readers (a dataset folder's: threaded,
    buffers reused), as ``ptp calibrate`` reads them. ``max_pixels``: the preview's size
    (:class:`~ptp_studio.session.FramePreview`)."""
    preview = FramePreview(ctx, max_level, interval, max_pixels)
    started = [None]

    def on_frame(k: int, spec, img) -> None:
        if started[0] != k:
            started[0] = k
            ctx.emit(("start", k))
        ctx.check()
        preview(k, spec, img)

    return on_frame


def acquisition_job(session, write_folder: Path | None = None, preview_pixels=None) -> Job:
    """The acquisition as one job: (optionally write the simulated dataset,) decode every position.

    Everything the worker needs is captured here, on the GUI thread. ``preview_pixels``: a
    callable, the size of the frame previews (:meth:`ptp_studio.widgets.maps.MapView.preview_pixels`).
    Returns ``(samples, truth)``.
    """
    source = session.make_source()
    rig, settings, seed = session.rig, session.sim_settings, session.seed
    kind = session.source_kind
    folder = session.dataset_folder

    def run(ctx):
        src = source
        split = 0.0
        if kind == "simulated" and write_folder is not None:
            split = 0.5
            simulate_dataset(write_folder, rig, settings, seed,
                             progress=lambda f, m: ctx.progress(split * f, m))
            src = DatasetSource(write_folder)

        def on_position(pos):
            ctx.emit(session.position_message(pos))

        samples = decode_samples(session, src, ctx, split, on_position,
                                 frame_tap(ctx, rig.camera.max_level, max_pixels=preview_pixels))
        ctx.progress(1.0, "loading the ground truth" if kind == "simulated" else "done")
        truth = session_truth(kind, rig, settings, seed, folder if kind == "folder" else write_folder)
        return samples, truth

    return Job(run, "acquisition")


class AcquirePage(StudioPage):
    key = "acquire"
    heading = "Acquire"
    subheading = ("Capture (or import) every position: the frames stream through the decoder one "
                  "position at a time. Watch the latest frame, its saturated pixels and each position's status.")

    def __init__(self, model, parent=None):
        super().__init__(model, parent)
        top = QGroupBox("Run")
        tl = QVBoxLayout(top)
        self.source_label = QLabel()
        self.source_label.setWordWrap(True)
        tl.addWidget(self.source_label)
        self.write_check = QCheckBox("Also write the images to a folder:")
        tl.addWidget(self.write_check)
        wl = QHBoxLayout()
        self.write_edit = QLineEdit()
        self.write_edit.setPlaceholderText("folder (created if needed)")
        self.write_browse = QPushButton("Browse…")
        wl.addWidget(self.write_edit, 1)
        wl.addWidget(self.write_browse)
        tl.addLayout(wl)
        from ..live import LivePanel

        self.live = LivePanel(model)
        tl.addWidget(self.live)
        self.start_button = QPushButton("Start acquisition")
        self.start_button.setObjectName("primary")
        tl.addWidget(self.start_button)
        tl.addWidget(self.make_job_panel())

        frame_box = QGroupBox("Latest frame")
        fl = QVBoxLayout(frame_box)
        self.frame_label = QLabel("no frame yet")
        self.frame_label.setObjectName("panelTitle")
        self.frame_label.setWordWrap(True)
        fl.addWidget(self.frame_label)
        self.frame_view = MapView(colour_bar=True)
        fl.addWidget(self.frame_view, 1)
        self.sat_check = QCheckBox("Show saturated pixels (red)")
        self.sat_check.setChecked(True)
        fl.addWidget(self.sat_check)

        pos_box = QGroupBox("Positions")
        pl = QVBoxLayout(pos_box)
        self.table = QTableWidget(0, 5)
        self.table.setHorizontalHeaderLabels(["#", "z (mm)", "status", "valid", "rejection"])
        self.table.horizontalHeaderItem(4).setToolTip("The most frequent reason a pixel was rejected")
        self.table.verticalHeader().hide()
        self.table.setEditTriggers(QTableWidget.NoEditTriggers)
        hh = self.table.horizontalHeader()
        for c in range(4):
            hh.setSectionResizeMode(c, QHeaderView.ResizeToContents)
        hh.setSectionResizeMode(4, QHeaderView.Stretch)
        # the rejection's words wrap in its narrow column: rows fit them again when the column's width changes
        hh.sectionResized.connect(lambda col, _old, _new: col == 4 and self.table.resizeRowsToContents())
        self.table.setMinimumHeight(12 * 30)
        pl.addWidget(self.table)
        self.summary = QLabel()
        self.summary.setWordWrap(True)
        pl.addWidget(self.summary)
        side = QWidget()
        sl = QVBoxLayout(side)
        sl.setContentsMargins(0, 0, 4, 0)
        sl.addWidget(top)
        sl.addWidget(pos_box, 1)
        self.split_body(side, frame_box, controls_width=350)

        self._overlay = None
        self._outcome: str | None = None
        self.start_button.clicked.connect(self.start)
        self.write_browse.clicked.connect(self._browse)
        self.sat_check.toggled.connect(self._overlay_toggled)
        model.positionsChanged.connect(self._show_positions)
        model.sourceChanged.connect(self._show_source)
        model.rigChanged.connect(self._show_source)
        model.samplesChanged.connect(self.update_complete)
        self.live.changed.connect(self._show_source)
        self._show_source()
        self._show_positions()

    def on_enter(self) -> None:
        self._show_source()

    def dataset_changed(self) -> None:
        if self.model.session.samples is None and not self.jobs.busy:
            # The last frame and verdict were another dataset's.
            self._outcome = None
            self._overlay = None
            self.frame_view.clear_map()
            self.frame_label.setText("no frame yet")
        self._show_positions()

    def _show_source(self) -> None:
        s = self.model.session
        self.source_label.setText(f"<b>Source:</b> {s.describe_source()} "
                                  f"— {s.rig.stage.n_positions} positions × {s.rig.fringes.frames_per_position}"
                                  " frames (change it on the Rig page)")
        sim = s.source_kind == "simulated"
        for w in (self.write_check, self.write_edit, self.write_browse):
            w.setVisible(sim)
        self.live.setVisible(s.source_kind == "live")
        self.start_button.setText("Start live capture" if s.source_kind == "live" else "Start acquisition")
        if self.frame_view.data is None:
            h, w = s.rig.camera.shape
            self.frame_view.plot.setRange(xRange=(-0.5, w - 0.5), yRange=(-0.5, h - 0.5), padding=0.02)
        if not s.positions or len(s.positions) != s.rig.stage.n_positions:
            s.reset_positions()
            self._show_positions()
        self.update_complete()

    def _browse(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Write the simulated dataset to")
        if folder:
            self.write_edit.setText(folder)
            self.write_check.setChecked(True)

    # ---- running ---------------------------------------------------------------
    def start(self) -> Job | None:
        """Start the acquisition (the Start button)."""
        if self.jobs.busy:
            return None
        if self.model.session.source_kind == "live":
            return self._start_live()
        write = None
        if self.write_check.isChecked() and self.model.session.source_kind == "simulated":
            text = self.write_edit.text().strip()
            if not text:
                self.jobs.show_error("Choose the folder to write the simulated images to.")
                return None
            write = Path(text)
        self.model.start_acquisition()
        gen = self.model.generation
        try:
            self.frame_view.note_size()  # the page may be shown for the first time just now
            job = acquisition_job(self.model.session, write, self.frame_view.preview_pixels)
        except Exception as exc:  # noqa: BLE001 - a bad folder must reach the user
            return self._not_started(exc)
        return self._launch(job, gen)

    def _not_started(self, exc: Exception) -> None:
        """The job could not even be built: say why, here, and stay as we are."""
        from ..worker import error_message

        self._outcome = "errored"
        self.jobs.show_error(error_message(exc))
        self.update_complete()
        return None

    def _launch(self, job: Job, gen: int, then=None) -> Job:
        """Wire an acquisition job to this page (``then()`` after it ends, if given) and run it."""
        self._outcome = None
        job.partial.connect(self._partial)
        job.finished.connect(lambda result: self._finished(result, gen))
        job.done.connect(lambda: self._ended(job))
        if then is not None:
            job.done.connect(then)
        return self.run_job(job)

    def _partial(self, payload) -> None:
        kind = payload[0]
        s = self.model.session
        if kind == "start":
            k = payload[1]
            if k < len(s.positions):
                st = s.positions[k]
                self.model.update_position(PositionStatus(k, st.z_mm, "running"))
        elif kind == "frame":
            _, k, spec, img, overlay, sat_frac, step, camera_shape = payload
            d, j, t, n, big_n = spec
            self.frame_view.set_map(img, levels=(0, s.rig.camera.max_level), cmap="CET-L1", label="grey level",
                                    step=step, extent=camera_shape)
            self._overlay = overlay
            self._overlay_toggled()
            self.frame_label.setText(
                f"{position_label(k, s.rig.stage.z_mm[k])}, direction {d}, period {t} px,"
                f" step {n + 1}/{big_n} — {100 * sat_frac:.2f} % saturated")
        elif kind in ("captured", "kept"):
            k = payload[1]
            if k < len(s.positions):
                self.model.update_position(PositionStatus(k, s.positions[k].z_mm, kind))
        elif kind == "exposure":
            self.live.show_exposure(payload[1], payload[2])
        elif kind == "warnings":
            self.jobs.show_warning("Warning: " + "\n".join(payload[1]))
        elif kind == "display":
            self.live.show_display(payload[1], payload[2])
        elif kind == "position":
            _, status, decoded = payload
            self.model.update_position(status)
            if decoded is not None:
                self.model.set_decoded(decoded)

    def _start_live(self) -> Job | None:
        """Build the devices (GUI thread), then capture and decode in one job."""
        from ..live import build_devices, live_capture_job

        s = self.model.session
        s.live = self.live.settings()
        self.model.start_acquisition()
        gen = self.model.generation
        try:
            camera, stage, display, asker = build_devices(s, self)
            self.frame_view.note_size()
            job = live_capture_job(s, camera, stage, display, asker, preview_pixels=self.frame_view.preview_pixels)
        except Exception as exc:  # noqa: BLE001 - a bad setting must reach the user
            return self._not_started(exc)
        self._live_devices = (camera, stage, display, asker)
        self.asker = asker
        return self._launch(job, gen, then=self.live.load)

    def _overlay_toggled(self, *_):
        self.frame_view.set_overlay(self._overlay if self.sat_check.isChecked() else None)

    def _finished(self, result, gen) -> None:
        if gen != self.model.generation:
            return  # the rig changed meanwhile: these samples are stale
        samples, truth = result[:2]
        if len(result) > 2 and result[2] != self.model.session.rig:
            # A live capture records the stage readings: the dataset's rig is what it says.
            statuses = list(self.model.session.positions)
            self.model.set_rig(result[2])
            for st, z in zip(statuses, result[2].stage.z_mm):
                st.z_mm = float(z)
            self.model.session.positions = statuses
            self.model.positionsChanged.emit()
        self.model.set_samples(samples, truth)

    def _ended(self, job) -> None:
        self._outcome = job.outcome
        if job.outcome != "finished":
            s = self.model.session
            for st in s.positions:
                if st.state in ("running", "pending"):
                    st.state = "cancelled" if job.outcome == "cancelled" else "not reached"
            self._show_positions()
        self.update_complete()

    # ---- status ------------------------------------------------------------------
    def _show_positions(self) -> None:
        s = self.model.session
        self.table.setRowCount(len(s.positions))
        colours = {"done": "#1b7f4c", "running": "#2b6cb0", "captured": "#2b6cb0", "kept": "#2b6cb0",
                   "cancelled": "#c0392b", "not reached": "#c0392b"}
        for i, st in enumerate(s.positions):
            cells = [str(st.index), f"{st.z_mm:g}", st.state,  # counted from 0, as the dataset's folders
                     "" if st.valid_fraction is None else f"{100 * st.valid_fraction:.1f} %",
                     self._main_reason(st)]
            for c, text in enumerate(cells):
                self._set_cell(i, c, text, colours.get(st.state) if c == 2 else None)
        done = [st for st in s.positions if st.state == "done"]
        if done:
            vf = [st.valid_fraction for st in done]
            self.summary.setText(f"{len(done)}/{len(s.positions)} positions decoded; valid pixels "
                                 f"{100 * min(vf):.1f} … {100 * max(vf):.1f} % per position.")
        else:
            self.summary.setText("")

    def _set_cell(self, row: int, col: int, text: str, colour: str | None) -> None:
        """Set one cell, touching the table only when it changes.

        Every position update redraws the table; new items (each re-measuring the columns sized to
        their contents) cost the GUI thread ~30 ms per update while the acquisition runs (issue 15).
        """
        item = self.table.item(row, col)
        if item is None:
            item = QTableWidgetItem(text)
            self.table.setItem(row, col, item)
        elif item.text() != text:
            item.setText(text)
        else:
            text = None  # unchanged
        if text is not None and col == 4:  # the rejection's words wrap: its row grows to them (not every row
            item.setToolTip(text)  # on every update: issue 15)
            self.table.resizeRowToContents(row)
        brush = QBrush(QColor(colour)) if colour else QBrush()  # QBrush(): the table's own text colour
        if item.foreground() != brush:
            item.setForeground(brush)

    @staticmethod
    def _main_reason(st: PositionStatus) -> str:
        if not st.counts:
            return ""
        rejected = [(st.counts.get(f, 0), f) for f in REASON_ORDER if st.counts.get(f, 0)]
        if not rejected:
            return "none"
        n, f = max(rejected)
        return f"{REASON_NAMES[f]} ({n} px)"

    def blocker(self) -> str | None:
        s = self.model.session
        if s.samples is not None:
            return None
        if self._outcome == "cancelled":
            return f"The acquisition was cancelled: press {self.start_button.text()} to run it again."
        if self._outcome == "errored":
            return "The acquisition failed (see the message above): fix the cause and press Start again."
        if self.model.stale is not None:
            return (f"Acquire the images first: press {self.start_button.text()} (the previous results are"
                    " stale: see above).")
        return f"Acquire the images first: press {self.start_button.text()}."
