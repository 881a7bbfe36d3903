"""The one session model every page of the wizard sees.

:class:`Session` is a plain Python object (engine dataclasses and arrays, no
Qt): the rig, the simulator settings or the dataset folder, the decoded
samples, the LUT and the comparison. :class:`SessionModel` is a thin
``QObject`` around it that performs every change and emits a signal for it, so
views subscribe instead of polling.

An edit upstream never discards results: when the rig, the simulator or the
source no longer match the :class:`Inputs` the results were computed from,
the results (samples, LUT, comparison) are set aside as :class:`StaleResults`
with the reason, and come back as they were when the values are set back; the
next acquisition replaces them. New samples drop the LUT and the comparison.
Opening a session file replaces everything at once (:meth:`SessionModel.restore`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from PySide6.QtCore import QObject, Signal

from ptpcore.io import DatasetSource, SimulatedSource
from ptpcore.decode import DecodeOptions
from ptpcore.rig import Camera, Rig
from ptpcore.simulate import SimSettings, VirtualRig, load_truth, preset
from ptpcore.fit import FitSettings
from ptpcore.progress import sub_progress
from ptpcore.run import Session as EngineSession, calibrate_session
from ptpcore.evaluate import DISPLAY_PIXELS, display_step, mask_rgba, reason_counts, reduce_for_display

__all__ = ["Inputs", "LiveSettings", "PositionStatus", "Session", "SessionModel", "SOURCE_KINDS", "StaleResults",
           "calibration_session", "decode_samples", "describe_change", "tour_session"]

SOURCE_KINDS = ("simulated", "folder", "live")
_DECODED_CACHE = 2  # decoded positions kept for the phase-map page (each holds every level's maps)
_DECODED_CACHE_PIXELS = 2_000_000
"""Above this many camera pixels only one decoded position is kept (at 5 MP one holds several hundred MB of maps)."""


@dataclass
class PositionStatus:
    """What the acquisition knows about one stage position.

    ``state`` is ``pending``, ``running``, ``done`` or ``cancelled``;
    ``counts`` maps 0 (valid) and every Reason flag to a pixel count.
    """

    index: int
    z_mm: float
    state: str = "pending"
    valid_fraction: float | None = None
    counts: dict = field(default_factory=dict)

    @classmethod
    def decoded(cls, index: int, z_mm: float, reasons: np.ndarray) -> "PositionStatus":
        """A decoded position's status from its (H, W) reason flags."""
        counts = reason_counts(reasons)
        return cls(index, z_mm, "done", counts[0] / reasons.size, counts)


#: Overlay colour of saturated pixels in the frame previews.
SATURATION_RGBA = (255, 30, 30, 220)


class FramePreview:
    """Sends at most one frame every ``interval`` seconds to the GUI, with its saturation overlay.

    Called on the worker thread as ``preview(k, spec, frame)``; emits
    ``("frame", k, spec, image, overlay RGBA or None, saturated fraction, step, (H, W))`` through
    ``ctx``: the image and its saturation overlay reduced ``step`` times (a saturated pixel keeps
    its block red; no overlay when nothing saturates) to at most ``max_pixels()`` (the view's own
    size: :meth:`ptp_studio.widgets.maps.MapView.preview_pixels`; at most
    :data:`~ptpcore.evaluate.views.DISPLAY_PIXELS`), the fraction and the camera shape ``(H, W)``
    from the whole frame. The GUI thread then only draws what the screen shows: a 12 MP frame at
    a megapixel still cost it 40-130 ms a frame (pyqtgraph's own reduction and colour lookup).

    Parameters
    ----------
    ctx : the job's context (``emit``)
    max_level : int
        Saturation grey level.
    interval : float, s
    max_pixels : callable returning int, optional
        Read at every frame (the window may be resized during the job); default
        :data:`~ptpcore.evaluate.views.DISPLAY_PIXELS`.
    """

    def __init__(self, ctx, max_level: int, interval: float = 0.12, max_pixels=None):
        self.ctx = ctx
        self.max_level = max_level
        self.interval = interval
        self.max_pixels = max_pixels or (lambda: DISPLAY_PIXELS)
        self._last = 0.0

    def __call__(self, k: int, spec, frame: np.ndarray) -> None:
        now = time.monotonic()
        if now - self._last >= self.interval:
            self._last = now
            sat = frame >= self.max_level
            step = display_step(frame.shape, max(1, min(DISPLAY_PIXELS, int(self.max_pixels()))))
            image = reduce_for_display(frame, step) if step > 1 else frame.copy()  # a new array, or the reader's buffer copied
            overlay = mask_rgba(reduce_for_display(sat, step, "any"), SATURATION_RGBA) if sat.any() else None
            self.ctx.emit(("frame", k, spec, image, overlay, float(sat.mean()), step, frame.shape[:2]))


def calibration_session(s: "Session", settings: FitSettings | None = None, positions=None) -> EngineSession:
    """The wizard's session as the composer's (:func:`ptpcore.run.calibrate_session`): the rig, the dataset
    folder (for a folder or live capture: its height sweep and repeats), the decode options, the samples
    decoded so far, ``settings`` and the fit ``positions`` (None: all)."""
    folder = s.dataset_folder if s.source_kind in ("folder", "live") and s.dataset_folder is not None else None
    return EngineSession(rig=s.rig, dataset=str(folder) if folder is not None else None,
                         settings=settings or FitSettings(), options=s.decode_options,
                         positions=None if positions is None else tuple(int(p) for p in positions),
                         samples=s.samples)


def decode_samples(s: "Session", source, ctx, lo: float = 0.0, on_position=None, on_frame=None):
    """A job's decode through the one door: the composer's decode stage on ``source`` (the data checks
    included), its progress in ``[lo, 1]`` of the job's bar; what the checks found goes to the page as a
    ``("warnings", [...])`` partial result. Returns the :class:`~ptpcore.io.SampleStack`."""
    es = EngineSession(rig=source.rig, dataset=None if s.dataset_folder is None else str(s.dataset_folder),
                       options=s.decode_options)
    result = calibrate_session(es, source=source, stop_after="samples", validate=False,
                               progress=sub_progress(ctx.progress, lo, 1.0), on_position=on_position,
                               on_frame=on_frame, full_positions=s.full_positions(), warn=lambda _m: None)
    if result.warnings:
        ctx.emit(("warnings", result.warnings))
    return es.samples


@dataclass
class LiveSettings:
    """The devices of a live capture, chosen on the Acquire page (``ptp_studio.live``).

    ``camera``: ``sim`` (the virtual rig of the Rig page), ``opencv`` or
    ``genicam``; ``camera_source``: the OpenCV index, file or URL, or the
    GenTL producer (``.cti``); ``stage``: ``sim``, ``manual`` or ``serial``
    (protocol from the ``capture.toml`` in ``config``); ``screen``: the LCD
    window's screen index, ``None`` for the simulated display. The capture
    folder is the session's ``dataset_folder``.
    """

    camera: str = "sim"
    camera_source: str = "0"
    exposure_us: float | None = None
    stage: str = "sim"
    config: Path | None = None
    screen: int | None = None
    settle_ms: float = 100.0
    resume: bool = False
    accept_exposure: bool = False
    measure_display: bool = False  # the display's response (a ramp at the first position), patterns through its inverse


@dataclass
class Session:
    """Everything one calibration session holds (plain data, no Qt).

    Attributes
    ----------
    rig : Rig
    source_kind : {"simulated", "folder", "live"}
    preset_name : str
        The simulator preset the settings came from.
    sim_settings : SimSettings
    seed : int
    dataset_folder : Path or None
        The ``ptp-dataset`` folder (``/1`` or ``/2``) to import (``source_kind == "folder"``).
    samples : SampleStack or None
    positions : list of PositionStatus
    decoded : dict int -> DecodedPosition
        A small cache of fully decoded positions (phase maps).
    lut : Lut or None
    lut_positions : list of int or None
        Positions the LUT was fitted on (None: all).
    compare : object or None
        The comparison result (``ptpcore.evaluate.protocol``).
    saved_comparison : dict or None
        The comparison report (JSON) read from a session file; replaced when
        the comparison runs again.
    truth : GroundTruth or None
        Exact rays when the data are simulated.
    exports : dict str -> Path
    decode_options : DecodeOptions
        How the samples were decoded (a session file may say otherwise than the default).
    created : str or None
        ISO 8601 time the session started (kept in its session file).
    lut_file : str or None
        The LUT file the session writes (kept in its session file).
    """

    rig: Rig
    sim_settings: SimSettings
    preset_name: str = "realistic"
    source_kind: str = "simulated"
    seed: int = 0
    dataset_folder: Path | None = None
    samples: Any = None
    positions: list = field(default_factory=list)
    decoded: dict = field(default_factory=dict)
    lut: Any = None
    lut_positions: list | None = None
    compare: Any = None
    saved_comparison: dict | None = None
    truth: Any = None
    exports: dict = field(default_factory=dict)
    live: LiveSettings = field(default_factory=LiveSettings)
    decode_options: DecodeOptions = field(default_factory=DecodeOptions)
    created: str | None = None
    lut_file: str | None = None

    @classmethod
    def from_preset(cls, name: str = "realistic", size: tuple[int, int] | None = None) -> "Session":
        """A simulated session of a preset; ``size`` (width, height) replaces its camera's, same bit depth."""
        rig, settings = preset(name)
        if size is not None:
            rig = replace(rig, camera=Camera(int(size[0]), int(size[1]), rig.camera.bit_depth))
        return cls(rig=rig, sim_settings=settings, preset_name=name)

    # ---- sources -------------------------------------------------------
    def make_source(self):
        """A frame source for the current choice.

        Raises
        ------
        ptpcore.errors.PtpError
            If the dataset folder is unusable.
        """
        if self.source_kind == "simulated":
            return SimulatedSource(VirtualRig(self.rig, self.sim_settings, self.seed))
        if self.source_kind == "folder":
            if self.dataset_folder is None:
                raise ValueError("no dataset folder chosen")
            return DatasetSource(self.dataset_folder)
        if self.source_kind == "live":
            # What the live capture wrote (Acquire page); complete once its rig.toml is there.
            if self.dataset_folder is None or not (Path(self.dataset_folder) / "rig.toml").is_file():
                raise ValueError("nothing captured yet: run the live capture on the Acquire page")
            return DatasetSource(self.dataset_folder)
        raise ValueError(f"source {self.source_kind!r} is not available")

    def describe_source(self) -> str:
        if self.source_kind == "simulated":
            c = self.rig.camera
            return (f"simulated rig, preset '{self.preset_name}', seed {self.seed},"
                    f" camera {c.width}x{c.height} {c.bit_depth}-bit")
        if self.source_kind == "folder":
            return f"dataset folder {self.dataset_folder}"
        lv = self.live
        screen = "simulated display" if lv.screen is None else f"LCD window on screen {lv.screen + 1}"
        folder = self.dataset_folder or "(choose the capture folder below)"
        return f"live capture into {folder}: {lv.camera} camera, {lv.stage} stage, {screen}"

    def reset_positions(self) -> None:
        self.positions = [PositionStatus(k, float(z)) for k, z in enumerate(self.rig.stage.z_mm)]

    def decoded_cache_size(self) -> int:
        """How many decoded positions :meth:`cache_decoded` keeps: 2, or 1 above :data:`_DECODED_CACHE_PIXELS`."""
        h, w = self.rig.camera.shape
        return 1 if h * w > _DECODED_CACHE_PIXELS else _DECODED_CACHE

    def position_message(self, pos) -> tuple:
        """The ``("position", status, decoded)`` message of a decoded position for the GUI thread.

        ``decoded`` is the :class:`ptpcore.decode.phase.DecodedPosition` for the Phase maps page,
        or None above :data:`_DECODED_CACHE_PIXELS`: there every level's maps of one position are
        617 MB at 5 MP (1.5 GB at 12 MP), so the acquisition decodes none in full
        (:meth:`full_positions`) and the page decodes the one it shows when it is opened.
        """
        status = PositionStatus.decoded(pos.index, pos.z_mm, pos.reasons)
        return ("position", status, pos if self.decoded_cache_size() > 1 else None)

    def full_positions(self):
        """``collect_samples``'s ``full_positions`` for the wizard: None (every position, for the
        Phase maps page) on small sensors, none above :data:`_DECODED_CACHE_PIXELS`."""
        return None if self.decoded_cache_size() > 1 else []

    def release_decoded(self) -> None:
        """Before a long fit on a big sensor: let the cached decoded positions go (the Phase maps
        page decodes again when it is shown); below :data:`_DECODED_CACHE_PIXELS` they stay."""
        if self.decoded_cache_size() == 1:
            self.decoded.clear()

    def cache_decoded(self, decoded) -> None:
        """Keep ``decoded`` (a :class:`ptpcore.decode.phase.DecodedPosition`), dropping the oldest first."""
        self.decoded.pop(decoded.index, None)
        limit = self.decoded_cache_size()
        while self.decoded and len(self.decoded) >= limit:
            self.decoded.pop(next(iter(self.decoded)))
        self.decoded[decoded.index] = decoded


_RESULT_FIELDS = ("samples", "truth", "decode_options", "positions", "lut", "lut_positions", "compare",
                  "saved_comparison", "exports")
"""The :class:`Session` fields computed from its :class:`Inputs` (set aside together when they go stale)."""


@dataclass(frozen=True)
class Inputs:
    """What a session's results are computed from; equal inputs give the same results.

    The simulator's settings count for simulated and live sources (the live capture's simulated camera),
    the folder for the others. Stage readings are compared to 1 nm: the Rig form recomputes them as
    ``start + step * k``.
    """

    rig: Rig
    source_kind: str
    dataset_folder: Path | None
    preset_name: str | None
    sim_settings: SimSettings | None
    seed: int | None

    @classmethod
    def of(cls, s: "Session") -> "Inputs":
        rig = replace(s.rig, stage=replace(s.rig.stage, z_mm=tuple(round(float(z), 6) for z in s.rig.stage.z_mm)))
        sim = s.source_kind in ("simulated", "live")
        return cls(rig, s.source_kind, None if s.source_kind == "simulated" else s.dataset_folder,
                   s.preset_name if sim else None, s.sim_settings if sim else None, s.seed if sim else None)


_RIG_PARTS = {"camera": "the camera", "lcd": "the LCD", "fringes": "the fringe design", "display": "the display",
              "decode": "the decode settings"}


def _z_range(z) -> str:
    return f"{len(z)} positions, z = {min(z):g} … {max(z):g} mm" if len(z) else "no positions"


def describe_change(old: Inputs, new: Inputs) -> str:
    """What differs between the inputs ``old`` (the results') and ``new`` (now), in words.

    e.g. ``"the stage positions (11 positions, z = 0 … 40 mm then, 9 positions, z = 0 … 32 mm now)"``.
    """
    parts = []
    if (old.source_kind, old.dataset_folder) != (new.source_kind, new.dataset_folder):
        parts.append(f"the source ({old.source_kind} then, {new.source_kind} now)")
    if (old.preset_name, old.seed) != (new.preset_name, new.seed) or old.sim_settings != new.sim_settings:
        parts.append("the simulator (preset, seed or view offset)")
    zo, zn = old.rig.stage.z_mm, new.rig.stage.z_mm
    if zo != zn:
        parts.append(f"the stage positions ({_z_range(zo)} then, {_z_range(zn)} now)")
    elif old.rig.stage != new.rig.stage:
        parts.append("the stage travel")
    for f in fields(Rig):
        if f.name != "stage" and getattr(old.rig, f.name) != getattr(new.rig, f.name):
            parts.append(_RIG_PARTS.get(f.name, f"the rig's {f.name.replace('_', ' ')}"))
    parts = list(dict.fromkeys(parts))
    return ", ".join(parts[:-1]) + " and " + parts[-1] if len(parts) > 1 else (parts[0] if parts else "nothing")


@dataclass
class StaleResults:
    """Results set aside because the inputs changed: the :data:`_RESULT_FIELDS` of the session as they were.

    Attributes
    ----------
    inputs : Inputs
        What they were computed from; setting the inputs back to these restores them.
    values : dict
        Session field name -> value.
    saved : bool
        A session file held them as they are when they were set aside.
    """

    inputs: Inputs
    values: dict
    saved: bool


class SessionModel(QObject):
    """Qt wrapper of a :class:`Session`: every change goes through it and is signalled.

    Signals
    -------
    rigChanged, sourceChanged, samplesChanged, positionsChanged, lutChanged, compareChanged
    datasetReplaced
        The images now come from another dataset (a new import, another rig or simulator):
        what was computed belongs to the previous one (the autosave lets go of its file).
    staleChanged
        Results were set aside as stale, or brought back, or the stale ones were dropped
        (:attr:`stale`, :meth:`stale_reason`).

    Attributes
    ----------
    version : int
        Bumped whenever the dataset or its samples change (a new rig, source, import,
        acquisition or opened session). Pages remember the version they showed and
        recompute or clear what depends on the dataset when it differs.
    work, saved_work : int
        ``work`` counts changes of the results (samples, LUT, comparison); ``saved_work``
        is its value when they were last written to a session file.
    results_inputs : Inputs or None
        What the present samples (and the LUT and comparison from them) were computed from.
    stale : StaleResults or None
        Results set aside because the inputs changed since; back when the inputs are set back to
        theirs, dropped by the next acquisition, import or opened session.
    """

    rigChanged = Signal()
    sourceChanged = Signal()
    samplesChanged = Signal()
    positionsChanged = Signal()
    decodedChanged = Signal(int)
    decodedReleased = Signal()
    lutChanged = Signal()
    compareChanged = Signal()
    exportsChanged = Signal()
    datasetReplaced = Signal()
    staleChanged = Signal()

    def __init__(self, session: Session, parent: QObject | None = None):
        super().__init__(parent)
        self.session = session
        # Bumped whenever the samples are dropped: a job that started under an
        # older generation finishes into the void instead of overwriting newer state.
        self.generation = 0
        self.version = 0
        self.work = 0
        self.saved_work = 0
        self.results_inputs: Inputs | None = None
        self.stale: StaleResults | None = None

    # ---- what would be lost ------------------------------------------------------
    @property
    def has_results(self) -> bool:
        """Samples, a LUT or a comparison (fresh or opened from a file) exist."""
        s = self.session
        return s.samples is not None or s.lut is not None or s.compare is not None or s.saved_comparison is not None

    @property
    def unsaved_work(self) -> bool:
        """Results exist that no session file holds in their present state (stale ones included)."""
        return (self.has_results and self.work != self.saved_work) or (self.stale is not None and not self.stale.saved)

    def mark_saved(self, work: int | None = None) -> None:
        """The results as they were at ``work`` (default: now) are in a session file."""
        self.saved_work = self.work if work is None else int(work)

    def describe_results(self) -> str:
        """'the decoded samples, the LUT and the comparison' (what exists), for questions; the stale
        ones when none are current ('... (stale, set aside)')."""
        s = self.session
        if not self.has_results and self.stale is not None:
            return f"{_describe(self.stale.values)} (stale, set aside)"
        return _describe({f: getattr(s, f) for f in _RESULT_FIELDS})

    def stale_reason(self) -> str | None:
        """Why results are set aside, in words (None: none are)."""
        if self.stale is None:
            return None
        return (f"{_describe(self.stale.values).capitalize()} are stale, set aside: computed before"
                f" {describe_change(self.stale.inputs, Inputs.of(self.session))} changed. Set the values back"
                " to restore them; acquiring again replaces them.")

    # Upstream changes drop what was computed from them.
    def _drop_samples(self) -> None:
        s = self.session
        self.generation += 1
        self.version += 1
        had = s.samples is not None
        s.samples = None
        s.truth = None
        s.decode_options = DecodeOptions()
        s.decoded.clear()
        s.reset_positions()
        if had:
            self.work += 1
        self.samplesChanged.emit()
        self.positionsChanged.emit()
        self._drop_lut()
        self._drop_compare()

    def _drop_lut(self) -> None:
        if self.session.lut is not None:
            self.work += 1
            self.session.lut = None
            self.session.lut_positions = None
            self.lutChanged.emit()

    def _drop_compare(self) -> None:
        if self.session.compare is not None or self.session.saved_comparison is not None:
            self.work += 1
            self.session.compare = None
            self.session.saved_comparison = None
            self.compareChanged.emit()

    def _replaced(self) -> None:
        """The dataset is another one: what this session exported belongs to the previous one."""
        if self.session.exports:
            self.session.exports = {}
            self.exportsChanged.emit()
        self.datasetReplaced.emit()

    def _inputs_changed(self) -> None:
        """After an edit of the inputs: set the results aside (stale) if they no longer match, bring
        stale ones back if the inputs are theirs again, else (no results) start afresh."""
        now = Inputs.of(self.session)
        if self.has_results and self.results_inputs is not None:
            if now == self.results_inputs:
                return
            self._set_aside()
        elif self.stale is not None and now == self.stale.inputs:
            self._bring_back()
            return
        else:
            self._drop_samples()
        self._replaced()

    def _set_aside(self) -> None:
        s = self.session
        # The values as they are; _drop_samples and _replaced then put new objects in the session's
        # fields (a new positions list, exports dict, decode options), never change these.
        self.stale = StaleResults(self.results_inputs, {f: getattr(s, f) for f in _RESULT_FIELDS},
                                  saved=self.work == self.saved_work)
        self.results_inputs = None
        self._drop_samples()  # as before: a new generation and version, every signal
        self.staleChanged.emit()

    def _bring_back(self) -> None:
        s, stale = self.session, self.stale
        self.stale = None
        self.generation += 1  # a job started before finishes into the void
        self.version += 1
        for f, value in stale.values.items():
            setattr(s, f, value)
        s.decoded.clear()  # not kept aside: the Phase maps page decodes again what it shows
        self.results_inputs = stale.inputs
        self.work += 1
        if stale.saved:
            self.saved_work = self.work
        for signal in (self.samplesChanged, self.positionsChanged, self.lutChanged, self.compareChanged,
                       self.exportsChanged, self.staleChanged):
            signal.emit()

    def restore_stale_inputs(self) -> None:
        """Set the rig, simulator and source back to those of the stale results: they come back."""
        if self.stale is None:
            return
        s, old = self.session, self.stale.inputs
        s.rig = old.rig
        s.source_kind = old.source_kind
        if old.source_kind != "simulated":
            s.dataset_folder = old.dataset_folder
        if old.sim_settings is not None:
            s.preset_name, s.sim_settings, s.seed = old.preset_name, old.sim_settings, old.seed
        self._inputs_changed()
        self.rigChanged.emit()
        self.sourceChanged.emit()

    def _drop_stale(self) -> None:
        if self.stale is not None:
            self.stale = None
            self.staleChanged.emit()

    def set_rig(self, rig: Rig) -> None:
        if rig == self.session.rig:
            return
        self.session.rig = rig
        self._inputs_changed()  # first: the results are set aside (or back) before a view reacts to the rig
        self.rigChanged.emit()

    def set_simulator(self, preset_name: str, settings: SimSettings, seed: int) -> None:
        s = self.session
        if (preset_name, settings, seed) == (s.preset_name, s.sim_settings, s.seed):
            return
        s.preset_name, s.sim_settings, s.seed = preset_name, settings, int(seed)
        self._inputs_changed()
        self.sourceChanged.emit()

    def set_source(self, kind: str, folder: Path | None = None) -> None:
        if kind not in SOURCE_KINDS:
            raise ValueError(f"source must be one of {SOURCE_KINDS}, got {kind!r}")
        s = self.session
        folder = Path(folder) if folder else None
        if (kind, folder) == (s.source_kind, s.dataset_folder):
            return
        s.source_kind, s.dataset_folder = kind, folder
        self._inputs_changed()
        self.sourceChanged.emit()

    def import_dataset(self, folder: Path, rig: Rig) -> None:
        """Take the ``ptp-dataset`` folder ``folder`` (whose rig.toml says ``rig``) as the source.

        Always a new dataset, even at the same path (its images may have been rewritten):
        every result is dropped.
        """
        s = self.session
        folder = Path(folder)
        source_changed = (s.source_kind, s.dataset_folder) != ("folder", folder)
        rig_changed = rig != s.rig
        s.source_kind, s.dataset_folder, s.rig = "folder", folder, rig
        if source_changed:
            self.sourceChanged.emit()
        if rig_changed:
            self.rigChanged.emit()
        self._drop_stale()
        self._drop_samples()
        self._replaced()

    def start_acquisition(self) -> None:
        self._drop_stale()  # "until the next run"
        self._drop_samples()

    def update_position(self, status: PositionStatus) -> None:
        self.session.positions[status.index] = status
        self.positionsChanged.emit()

    def set_decoded(self, decoded) -> None:
        self.session.cache_decoded(decoded)
        self.decodedChanged.emit(decoded.index)

    def release_decoded(self) -> None:
        """Before a long job on a big sensor: the decoded positions' maps go (:meth:`Session.release_decoded`);
        ``decodedReleased`` tells the pages that hold one."""
        if self.session.decoded and self.session.decoded_cache_size() == 1:
            self.session.release_decoded()
            self.decodedReleased.emit()

    def set_samples(self, samples, truth=None) -> None:
        self.version += 1
        self.work += 1
        self._drop_stale()
        self.session.samples = samples
        self.session.truth = truth
        self.results_inputs = Inputs.of(self.session)
        self._drop_lut()
        self._drop_compare()
        self.samplesChanged.emit()

    def set_lut(self, lut, positions=None) -> None:
        self.session.lut = lut
        self.session.lut_positions = None if positions is None else list(positions)
        self.work += 1
        self.lutChanged.emit()

    def set_compare(self, result) -> None:
        self.session.compare = result
        self.session.saved_comparison = None
        self.work += 1
        self.compareChanged.emit()

    def restore(self, other: Session) -> None:
        """Replace everything with ``other`` (an opened session file); the live-capture settings stay.

        Every signal is emitted once; jobs started before finish into the void.
        """
        s = self.session
        self.generation += 1
        self.version += 1
        self.work += 1
        self.saved_work = self.work  # as the file holds it
        for f in fields(Session):
            if f.name != "live":
                setattr(s, f.name, getattr(other, f.name))
        self.stale = None
        self.results_inputs = Inputs.of(s)
        for signal in (self.rigChanged, self.sourceChanged, self.samplesChanged, self.positionsChanged,
                       self.lutChanged, self.compareChanged, self.exportsChanged, self.staleChanged):
            signal.emit()

    def add_export(self, what: str, path: Path) -> None:
        self.session.exports[what] = Path(path)
        self.exportsChanged.emit()


def _describe(values: dict) -> str:
    """'the decoded samples, the LUT and the comparison': those of ``values`` (Session fields) that exist."""
    have = [name for name, v in (("the decoded samples", values.get("samples")), ("the LUT", values.get("lut")),
                                 ("the comparison", values.get("compare") if values.get("compare") is not None
                                  else values.get("saved_comparison")))
            if v is not None]
    return " and ".join([", ".join(have[:-1]), have[-1]] if len(have) > 1 else have) or "nothing"


def session_truth(kind: str, rig: Rig, settings: SimSettings, seed: int, folder):
    """The exact truth of a session's source: the simulator's rays, or a dataset's ``truth.h5``; else None."""
    if kind == "simulated":
        return VirtualRig(rig, settings, seed).truth()
    if folder is not None and (Path(folder) / "truth.h5").is_file():
        return load_truth(folder)[0]
    return None


def tour_session(width: int = 320, height: int = 240, positions: int = 11,
                 view_offset_mm=(75.0, 35.0), preset_name: str = "realistic") -> Session:
    """A small simulated session whose view includes a corner of the LCD.

    With the view offset the camera sees the LCD's corner and bezel, so the
    validity masks show every kind of rejection, not only valid pixels.
    """
    s = Session.from_preset(preset_name, (width, height))
    if positions != s.rig.stage.n_positions:
        z = s.rig.stage.z_mm
        s.rig = s.rig.with_z(np.linspace(min(z), max(z), positions))
    s.sim_settings = replace(s.sim_settings, offset_mm=tuple(float(v) for v in view_offset_mm))
    s.reset_positions()
    return s
