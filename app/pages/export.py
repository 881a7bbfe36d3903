"""Page 7, Export: the LUT file, the comparison report (JSON + PNG plots), the session, and the LUT in use
(a height map through it into a point cloud: :class:`ptp_studio.widgets.pointcloud.PointCloudPanel`)."""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

import numpy as np
from PySide6.QtCore import Signal
from PySide6.QtWidgets import (QCheckBox, QFileDialog, QGroupBox, QHBoxLayout, QLabel, QLineEdit, QPushButton,
                               QTabWidget, QVBoxLayout, QWidget)

from ptpcore.atomic import atomic_path, write_text_atomic
from ptpcore.errors import OutputError
from ptpcore.evaluate import residual_png
from ptpcore.io import PLAIN_FOLDER, Output, guard_outputs, save_lut
from ptpcore.fit import describe_lut
from ptpcore.rig import rig_to_toml
from ptpcore.run import save_session

from ..sessionfile import to_engine
from ..widgets.confirm import confirm
from ..widgets.acceptance import AcceptancePanel
from ..widgets.lutdiff import LutDiffPanel
from ..widgets.pointcloud import PointCloudPanel
from ..worker import Job
from .base import StudioPage

__all__ = ["ExportPage", "LUT_NAME", "REPORT_NAME", "SESSION_NAME", "quality_png"]

LUT_NAME = "calibration.lut.h5"
REPORT_NAME = "comparison.json"
SESSION_NAME = "session.ptps.h5"
N_RESIDUAL_PNGS = 3


def quality_png(key: str) -> str:
    """The file name of one Calibrate map (``rms_x``, ``sigma_y``, …): ``lut_quality_<key>.png``."""
    return f"lut_quality_{key}.png"


def _kind(path: Path) -> str:
    """What Export writes at ``path`` (:data:`ptpcore.io.outputs.KINDS`)."""
    return {LUT_NAME: "lut", REPORT_NAME: "report", SESSION_NAME: "session", "rig.toml": "rig"}.get(path.name, "png")


def _save_png(image, path: Path) -> None:
    """Write a QImage as PNG atomically (QImage is safe to use off the GUI thread)."""
    with atomic_path(path) as tmp:
        if not image.save(str(tmp), "PNG"):
            raise OSError(f"{path}: could not write the PNG")


def _map_image(maps: dict, key: str, size: tuple[int, int] = (900, 720)):
    """One of the Calibrate page's maps rendered off screen at report size, as a QImage.

    (Grabbing the page's own panel while another page is shown gives whatever
    squeezed geometry the hidden page has.)
    """
    from ..widgets.maps import HeatmapPanel

    title, data, unit, cmap, integer = maps[key]
    panel = HeatmapPanel()
    try:
        panel.resize(*size)
        panel.set_map(data, title=title, unit=unit, cmap=cmap, integer=integer)
        panel.readout.setText("")
        return panel.grab().toImage()
    finally:
        panel.deleteLater()


class ExportPage(StudioPage):
    """Signals: ``sessionWritten(Path)`` after an export that wrote the session file (autosave goes there)."""

    key = "export"
    heading = "Export"
    subheading = ("Write what this session produced: the LUT a scanner loads (ptp-lut/1), the comparison "
                  "report (JSON plus PNG plots) and the session itself, to resume later; try the LUT on a "
                  "height map and save the point cloud; check it against a reference LUT.")

    sessionWritten = Signal(object)

    def __init__(self, model, parent=None):
        super().__init__(model, parent)
        self.compare_page = None  # set by the wizard: the plots to save
        self.calibrate_page = None
        box = QGroupBox("Output folder")
        bl = QHBoxLayout(box)
        self.folder = QLineEdit(str(Path.cwd() / f"ptp-calibration-{_dt.datetime.now():%Y%m%d-%H%M}"))
        browse = QPushButton("Browse…")
        browse.clicked.connect(self._browse)
        bl.addWidget(self.folder, 1)
        bl.addWidget(browse)

        what = QGroupBox("What to write")
        wl = QVBoxLayout(what)
        self.do_lut = QCheckBox(f"LUT file {LUT_NAME}")
        self.do_lut.setToolTip("ptp-lut/1, HDF5: what a scanner loads")
        self.do_lut.setChecked(True)
        self.do_lut.setEnabled(False)  # the product of the session: always written
        self.do_report = QCheckBox("Comparison report (JSON, PNG plots)")
        self.do_report.setToolTip(f"{REPORT_NAME} and the Compare page's plots as PNG")
        self.do_quality = QCheckBox("LUT quality heatmaps (PNG)")
        self.do_quality.setToolTip("One PNG per map of the Calibrate page, named after it: lut_quality_rms_x.png,"
                                   " lut_quality_loo_x.png, … and lut_quality_sigma_x.png when the LUT has"
                                   " predicted uncertainty maps; the residual arrows of the"
                                   f" {N_RESIDUAL_PNGS} worst positions, residuals_position_K.png.")
        self.do_session = QCheckBox(f"Session {SESSION_NAME}")
        self.do_session.setToolTip("ptp-session/1: open it on the Rig page to resume")
        self.do_rig = QCheckBox("rig.toml")
        for w in (self.do_report, self.do_quality, self.do_session, self.do_rig):
            w.setChecked(True)
        for w in (self.do_lut, self.do_report, self.do_quality, self.do_session, self.do_rig):
            wl.addWidget(w)
        self.export_button = QPushButton("Export")
        self.export_button.setObjectName("primary")
        wl.addWidget(self.export_button)
        wl.addWidget(self.make_job_panel())

        done = QGroupBox("Written")
        dl = QVBoxLayout(done)
        self.written = QLabel("nothing yet")
        self.written.setWordWrap(True)
        self.written.setObjectName("written")
        dl.addWidget(self.written)
        self.summary = QLabel()
        self.summary.setWordWrap(True)
        side = QWidget()
        sl = QVBoxLayout(side)
        sl.setContentsMargins(0, 0, 4, 0)
        for w in (box, what, done, self.summary):
            sl.addWidget(w)
        sl.addStretch(1)
        # The views: the LUT in use (a height map, or one height, into a point cloud, shown and saved) and
        # trusting it (its difference to a reference LUT: a second sweep, last month's).
        # One tab each: both as tall as the page (one above the other, neither had room for its plot).
        self.view_tabs = view = QTabWidget()
        self.cloud_panel = PointCloudPanel(lambda: self.model.session.lut,
                                           lambda: Path(self.folder.text().strip() or "."))
        self.diff_panel = LutDiffPanel(lambda: self.model.session.lut)
        view.addTab(self.cloud_panel, "Use the LUT: point cloud")
        view.addTab(self.diff_panel, "Trust the LUT: against a reference LUT")
        # The whole scanner's acceptance (VDI/VDE 2634-2): only for a LUT with the scanner's height map.
        self.acceptance_panel = AcceptancePanel(lambda: self.model.session.lut,
                                                lambda: self.model.session.dataset_folder,
                                                lambda: Path(self.folder.text().strip() or "."))
        self._acceptance_tab = view.addTab(self.acceptance_panel, "Accept the scanner: VDI/VDE 2634-2")
        view.setTabVisible(self._acceptance_tab, False)
        self.split_body(side, view, controls_width=330)
        self.files: list[Path] = []
        self._outcome = None
        self.export_button.clicked.connect(self.export)
        model.lutChanged.connect(self._reset)
        model.lutChanged.connect(self.cloud_panel.reset)
        model.lutChanged.connect(self.diff_panel.reset)
        model.lutChanged.connect(self.acceptance_panel.reset)
        model.lutChanged.connect(self._show_acceptance)
        model.compareChanged.connect(self.on_enter)

    def _show_acceptance(self, *_args) -> None:
        """The acceptance tab only for a LUT with the scanner's height map (/height)."""
        lut = self.model.session.lut
        self.view_tabs.setTabVisible(self._acceptance_tab, lut is not None and getattr(lut, "height", None) is not None)

    def _browse(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Export to", self.folder.text())
        if folder:
            self.folder.setText(folder)

    def _reset(self) -> None:
        self.files = []
        self.written.setText("nothing yet")
        self.update_complete()

    def dataset_changed(self) -> None:
        self._outcome = None
        self.summary.setText("")
        if self.model.session.lut is None:
            self._reset()

    def on_enter(self) -> None:
        s = self.model.session
        has_cmp = s.compare is not None or s.saved_comparison is not None
        self.do_report.setEnabled(has_cmp)
        self.do_report.setToolTip("" if has_cmp else "No comparison was run (Compare page).")
        if not has_cmp:
            self.do_report.setChecked(False)
        self.do_session.setToolTip("Rig, samples, LUT and comparison; saved again after each completed stage"
                                   " from now on (autosave).")
        lut = s.lut
        if lut is not None:
            self.summary.setText(f"LUT: {describe_lut(lut)}, {lut.shape[1]}x{lut.shape[0]} px, "
                                 f"{100 * lut.valid.mean():.1f} % of pixels valid, z {lut.z_min:g} … {lut.z_max:g} mm."
                                 f" Source: {s.describe_source()}."
                                 + (f" With the scanner's height map /height (degree {lut.height.degree},"
                                    f" {100 * lut.height.valid.mean():.1f} % of pixels): a scan folder can be"
                                    " reconstructed in the point-cloud tab."
                                    if getattr(lut, "height", None) is not None else ""))

    # ---- export ----------------------------------------------------------------------
    def set_folder(self, folder) -> None:
        self.folder.setText(str(folder))

    def export(self) -> Job | None:
        s = self.model.session
        if self.jobs.busy or s.lut is None:
            return None
        out = Path(self.folder.text().strip())
        if not str(out):
            self.jobs.show_error("Choose the output folder.")
            return None
        # Everything the worker writes is captured now, on the GUI thread
        # (widget grabs included: QImages are safe to save from a worker).
        lut, rig, result = s.lut, s.rig, s.compare
        images = {}
        if self.do_report.isChecked() and result is not None and self.compare_page is not None:
            for stem, widget in self.compare_page.plot_widgets.items():
                images[out / f"comparison_{stem}.png"] = widget.grab().toImage()
        if self.do_quality.isChecked() and self.calibrate_page is not None and self.calibrate_page.maps:
            for key in self.calibrate_page.maps:  # every tab, each named after its map
                images[out / quality_png(key)] = _map_image(self.calibrate_page.maps, key)
        residuals = None  # the worst positions' residual arrows, drawn by the engine in the worker
        if self.do_quality.isChecked() and self.calibrate_page is not None:
            residuals = self.calibrate_page.residual_field
        worst = [] if residuals is None else [int(k) for k in residuals.worst_positions[:N_RESIDUAL_PNGS]
                                              if np.isfinite(residuals.rms_um[k])]
        report = None
        if self.do_report.isChecked():  # an opened session's comparison: its report, without plots
            report = result.to_json_dict() if result is not None else s.saved_comparison
        fit = self.calibrate_page.lut_settings() if self.calibrate_page is not None else None
        session_obj = to_engine(s, out=out / LUT_NAME, settings=fit) if self.do_session.isChecked() else None
        write_rig = self.do_rig.isChecked()
        targets = [out / LUT_NAME, *([out / REPORT_NAME] if report is not None else []), *images,
                   *([out / "rig.toml"] if write_rig else []), *([out / SESSION_NAME] if session_obj else []),
                   *(out / f"residuals_position_{k}.png" for k in worst)]  # k from 0, as the dataset's folders
        if not self._guard(out, targets):
            return None
        # Files this session wrote itself (an earlier export, its autosaved session file) are replaced
        # without asking; anything else already there is another session's.
        own = {Path(p) for p in s.exports.values()}
        autosave = getattr(self.wizard(), "autosave", None)
        if getattr(autosave, "path", None) is not None:
            own.add(Path(autosave.path))
        existing = [p for p in targets if p.exists() and p not in own]
        if existing and not self._confirm_overwrite(out, existing):
            return None
        work = self.model.work

        def run(ctx):
            written = []
            steps = 1 + len(images) + len(worst) + (report is not None) + (session_obj is not None) + write_rig
            done = 0

            def step(msg):
                nonlocal done
                ctx.progress(done / steps, msg)
                done += 1

            out.mkdir(parents=True, exist_ok=True)
            step(f"writing {LUT_NAME}")
            save_lut(lut, out / LUT_NAME)
            written.append(out / LUT_NAME)
            if report is not None:
                step(f"writing {REPORT_NAME}")
                write_text_atomic(out / REPORT_NAME, json.dumps(report, indent=1))
                written.append(out / REPORT_NAME)
            for path, image in images.items():
                step(f"writing {path.name}")
                _save_png(image, path)
                written.append(path)
            for k in worst:
                path = out / f"residuals_position_{k}.png"
                step(f"writing {path.name}")
                residual_png(residuals, k, path)
                written.append(path)
            if write_rig:
                step("writing rig.toml")
                write_text_atomic(out / "rig.toml", rig_to_toml(rig))
                written.append(out / "rig.toml")
            if session_obj is not None:
                step(f"writing {SESSION_NAME}")
                save_session(session_obj, out / SESSION_NAME)
                written.append(out / SESSION_NAME)
            ctx.progress(1.0, f"wrote {len(written)} files to {out}")
            return written

        job = Job(run, "exporting")
        if session_obj is not None:
            job.finished.connect(lambda _f: self.model.mark_saved(work))
        job.finished.connect(self._written)
        job.done.connect(lambda: setattr(self, "_outcome", job.outcome))
        return self.run_job(job)

    def _guard(self, out: Path, targets: list[Path]) -> bool:
        """The output guard over every file the export would write (a missing folder: its parent), before
        anything is written; a refusal is one message and False.

        Never the session's dataset or a file in it, never a file of another kind (by its content), never
        a folder that does not take files. Replacing an existing file of the same kind is what the
        question after this asks (the wizard's ``--force``).
        """
        dataset = self.model.session.dataset_folder
        try:
            if out.is_dir():
                guard_outputs([Output(p, _kind(p)) for p in targets], inputs=[dataset] if dataset else [],
                              force=True)
            else:
                guard_outputs([Output(out, PLAIN_FOLDER)], inputs=[dataset] if dataset else [])
        except OutputError as exc:
            self.jobs.show_error(f"Nothing written: {exc}")
            return False
        return True

    def _confirm_overwrite(self, out: Path, existing: list[Path]) -> bool:
        """Ask before replacing files already in the output folder (a finished session's above all)."""
        names = ", ".join(p.name for p in existing[:6]) + (f" and {len(existing) - 6} more" if len(existing) > 6 else "")
        session = any(p.name == SESSION_NAME for p in existing)
        ok = confirm(self, "Replace files?",
                     f"{out} already holds {names}." + (" Its session file is a finished session of its own."
                                                        if session else ""),
                     "Replace them with this session's files? (No: choose another folder.)")
        if not ok:
            self.jobs.show_error(f"Nothing written: {out} already holds {names}. Choose another folder.")
        return ok

    def _written(self, files) -> None:
        self.files = list(files)
        for f in self.files:
            self.model.add_export(f.name, f)
        lines = []
        for f in self.files:
            size = f.stat().st_size if f.exists() else 0
            # The name only (the folder is above): a long path would widen the panel.
            lines.append(f"✔ {f.name}  ({size / 1e6:.2f} MB)" if size > 1e5 else f"✔ {f.name}  ({size / 1e3:.1f} kB)")
        where = str(self.files[0].parent) if self.files else ""
        self.written.setText("\n".join(lines))
        self.written.setToolTip(f"in {where}" if where else "")
        self.update_complete()
        for f in self.files:
            if f.name == SESSION_NAME:
                self.sessionWritten.emit(f)

    def blocker(self) -> str | None:
        if self.model.session.lut is None:
            return "There is no LUT to export: fit one on the Calibrate page."
        if not any(f.name == LUT_NAME for f in self.files):
            if self._outcome == "errored":
                return "The export failed (see the message above): choose another folder and press Export."
            return "Export the LUT file (press Export) before finishing."
        return None
