"""Session files in the wizard: open one, save one, and autosave after each completed stage.

The file is the engine's ``ptp-session/1`` (:mod:`ptpcore.run.session`); this
module only translates between it and the wizard's :class:`~ptp_studio.session.Session`:

- :func:`to_engine` — the wizard's session as a ``ptpcore.run.session.Session`` (GUI thread);
- :func:`read_session_file` — load a file and build a wizard session from it
  (worker thread: ground truth, position statuses);
- :class:`Autosave` — once the user has chosen a session file (Export's
  "Session", or Open session), rewrite it atomically in a worker job after
  every completed stage: samples decoded, LUT fitted, comparison done.

Only the comparison's JSON report is stored in a session file, not its arrays:
an opened comparison is kept as :attr:`Session.saved_comparison` (its verdict
shows on the Compare page, it is written again with the session) until the
comparison is run again.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from PySide6.QtCore import QObject, Signal

from ptpcore import run as engine
from ptpcore.errors import FileFormatError
from ptpcore.fit import FIT_SETTINGS_KEY, FitSettings, lut_model
from ptpcore.simulate import PRESETS, preset, settings_from_json

from .session import PositionStatus, Session, SessionModel, session_truth
from .worker import Job

__all__ = ["Autosave", "OpenedSession", "STEP_PAGES", "read_session_file", "to_engine"]

#: :func:`ptpcore.run.session.next_step` -> the page the wizard lands on after opening a file.
STEP_PAGES = {"decode": "acquire", "fit": "calibrate", "compare": "compare", None: "export"}


def to_engine(s: Session, *, out=None, settings: FitSettings | None = None) -> engine.Session:
    """The wizard's session as an engine session (for :func:`ptpcore.run.session.save_session`).

    ``settings``: the fit's settings (the Calibrate page's) to record when no LUT is fitted yet;
    a fitted LUT records its own (``/provenance`` ``fit_settings``; a LUT of an older file: its model
    and degree over ``settings``). ``out``: the LUT file (default: the one the session already names).
    """
    settings = lut_fit_settings(s.lut, settings or FitSettings())
    sim = json.dumps({"seed": s.seed, **asdict(s.sim_settings)}) if s.source_kind == "simulated" else None
    comparison = s.compare.to_json_dict() if s.compare is not None else s.saved_comparison
    if out is not None:
        s.lut_file = str(out)
    es = engine.Session(
        rig=s.rig, dataset=str(s.dataset_folder) if s.dataset_folder else None, settings=settings,
        options=s.decode_options, positions=None if s.lut_positions is None else tuple(s.lut_positions),
        out=s.lut_file, sim_settings=sim, samples=s.samples, lut=s.lut, comparison=comparison)
    if s.created:
        es.created = s.created
    else:
        s.created = es.created
    return es


def lut_fit_settings(lut, fallback: FitSettings) -> FitSettings:
    """The settings ``lut`` was fitted with: its ``/provenance`` ``fit_settings``; for a LUT written before
    the record, ``fallback`` with the LUT's model and degree; ``fallback`` without a LUT."""
    if lut is None:
        return fallback
    text = lut.provenance.get(FIT_SETTINGS_KEY) if lut.provenance else None
    if text:
        try:
            return FitSettings.from_json(text)
        except ValueError:
            pass  # unreadable: fall back on what the LUT itself says
    model = "auto" if lut.extra_attrs.get("chosen_by") else lut_model(lut)  # an auto LUT reopened: auto again
    degree = int(lut.degree or 3) if 1 <= int(lut.degree or 3) <= 5 else 3
    return fallback.with_changes(model=model, degree=degree)


@dataclass
class OpenedSession:
    """A session file read for the wizard: where it came from, what to show, where to land."""

    path: Path
    session: Session
    settings: FitSettings
    step: str | None  # ptpcore.run.session.next_step

    @property
    def page(self) -> str:
        return STEP_PAGES[self.step]


def read_session_file(path, progress: Callable[[float, str], None] | None = None) -> OpenedSession:
    """Load a ``ptp-session/1`` file into a wizard session (runs on a worker thread).

    Raises
    ------
    FileFormatError
        The engine's one-line message: not a session, truncated, too new, damaged;
        or simulator settings this version cannot rebuild.
    """
    path = Path(path)
    report = progress or (lambda f, m: None)
    report(0.0, f"reading {path.name}")
    es = engine.load_session(path)
    report(0.5, "restoring the session")
    folder = Path(es.dataset) if es.dataset else None
    settings, seed = None, 0
    if es.sim_settings:
        try:
            settings, seed = settings_from_json(es.sim_settings)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            if folder is None:
                raise FileFormatError(f"{path}: attribute 'settings' of /sim: not simulator settings this version"
                                      f" reads ({type(exc).__name__}: {exc})") from None
    if folder is not None and (settings is None or (folder / "rig.toml").is_file()):
        kind = "folder"
    else:
        kind = "simulated"
        folder = None
    if settings is None:  # a dataset's session: the simulator is not its source; keep a default one
        settings = preset("realistic")[1]
    s = Session(rig=es.rig, sim_settings=settings, source_kind=kind, seed=int(seed), dataset_folder=folder,
                preset_name=settings.name if settings.name in PRESETS else "custom",
                samples=es.samples, lut=es.lut, lut_positions=None if es.positions is None else list(es.positions),
                saved_comparison=es.comparison, decode_options=es.options, created=es.created, lut_file=es.out)
    s.reset_positions()
    if es.samples is not None:
        for i, (st, reasons) in enumerate(zip(s.positions, es.samples.reasons)):
            if not (reasons == 255).all():  # decoded
                s.positions[i] = PositionStatus.decoded(st.index, st.z_mm, reasons)
        report(0.7, "ground truth" if kind == "simulated" else "looking for truth.h5")
        try:
            s.truth = session_truth(kind, s.rig, settings, seed, folder)
        except (OSError, ValueError, KeyError):
            s.truth = None  # optional: the comparison then judges against the measured samples
    report(1.0, f"opened {path.name} (stage '{es.stage}')")
    return OpenedSession(path, s, es.settings, engine.next_step(es))


class Autosave(QObject):
    """Rewrites the chosen session file after every completed stage, one save at a time.

    Parameters
    ----------
    model : SessionModel
    fit_choice : callable, optional
        ``() -> FitSettings``: the settings to record before a LUT is fitted (:func:`to_engine`).

    Signals
    -------
    status(str)
        A short line for the window ("session saved 14:02:11", "saving the session …").
    saved(object)
        The path, after each successful save.
    """

    status = Signal(str)
    saved = Signal(object)

    def __init__(self, model: SessionModel, fit_choice: Callable[[], FitSettings] | None = None,
                 parent: QObject | None = None):
        super().__init__(parent)
        self.model = model
        self.fit_choice = fit_choice
        self.path: Path | None = None
        self.job: Job | None = None
        self._again = False
        # (the stale results, the file they belong to): the file to take up again if they come back
        self._parked: tuple | None = None
        model.samplesChanged.connect(lambda: self._completed(model.session.samples))
        model.lutChanged.connect(lambda: self._completed(model.session.lut))
        model.compareChanged.connect(lambda: self._completed(model.session.compare))
        model.datasetReplaced.connect(self._dataset_replaced)
        model.staleChanged.connect(self._stale_changed)

    def _dataset_replaced(self) -> None:
        """Another dataset: its results are a new session, never written over the chosen file. When
        the results were set aside as stale (an edit of the inputs), the file is kept for their return."""
        if self.path is not None:
            name = self.path.name
            if self.model.stale is not None:
                self._parked = (self.model.stale, self.path)
            self.path = None
            self.status.emit(f"session file {name} left as it was: the dataset changed"
                             " (choose a session file at Export to save this one)")

    def _stale_changed(self) -> None:
        """Stale results came back (the inputs were set back): autosave to their file again; dropped (a
        new run): forget it."""
        if self._parked is None or self.model.stale is self._parked[0]:
            return
        stale, path = self._parked
        self._parked = None
        back = self.model.stale is None and self.model.session.samples is stale.values["samples"]
        if back and self.path is None:
            self.set_path(path)
            if self.model.unsaved_work:  # changed since the file was written: bring it up to date
                self.save()

    def set_path(self, path, just_saved: bool = False) -> None:
        """Autosave to ``path`` from now on (None: stop)."""
        self.path = None if path is None else Path(path)
        if self.path is None:
            self.status.emit("")
        elif just_saved:
            self._saved(self.path)
        else:
            self.status.emit(f"session file {self.path.name}: autosaved after each stage")

    def _completed(self, result) -> None:
        if result is not None and self.path is not None:
            self.save()

    def save(self) -> Job | None:
        """Save now (in a worker job); while one runs, save once more after it."""
        if self.path is None:
            return None
        if self.job is not None and self.job.running:
            self._again = True
            return self.job
        fit = self.fit_choice() if self.fit_choice else None
        es, path, work = to_engine(self.model.session, settings=fit), self.path, self.model.work
        job = Job(lambda ctx: engine.save_session(es, path), "saving the session", self)
        job.finished.connect(lambda _r: (self.model.mark_saved(work), self._saved(path)))
        job.errored.connect(lambda msg: self.status.emit(f"session NOT saved: {msg}"))
        job.done.connect(self._done)
        self.job = job
        self.status.emit(f"saving the session to {path.name} …")
        return job.start()

    def _saved(self, path: Path) -> None:
        self.status.emit(f"session saved {_dt.datetime.now():%H:%M:%S}: {path.name}")
        self.saved.emit(path)

    def _done(self) -> None:
        self.job.fn = None  # let the snapshot (samples, LUT) go
        if self._again:
            self._again = False
            self.save()
