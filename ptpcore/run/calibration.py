"""One door to a calibration: the stages every front end runs, in one order, with one error policy.

``ptp calibrate``, ``ptp resume``, ``ptp demo``, the wizard's Acquire and Calibrate jobs and
:func:`ptpcore.calibrate` all run :func:`calibrate_session`; they differ only in where they stop
and what they do with the result, so they write the same LUT by construction.

The stages, each skipped when the session already holds its product (a resumed session
carries on where it stopped):

``decode``
    Every position's frames -> each pixel's samples (:func:`ptpcore.run.pipeline.collect_samples`),
    after the dataset's validation and its phase-convention check; then the checks of the
    decoded data (no valid pixel is an error; positions keeping few pixels, stuck positions are
    warnings; readings in reverse are an error). The session is saved (stage ``samples``).
``fit``
    The corrections and the LUT (:func:`ptpcore.fit.corrected.fit_corrected`), with the fit
    settings and the decode options recorded in its ``/provenance``.
``drift``
    The sweep's repeat positions (``[stage] repeat_z_mm``) decoded and compared with their
    sweep positions; the record goes into ``/provenance`` ``drift``.
``height``
    The scanner's height sweep (``[projector]``, ``[height]``; docs/method.md section 9) -> the
    LUT's ``/height``. The session is saved (stage ``lut``).
``write``
    The LUT file, atomically (when an output is given).

Error policy: a stage that fails raises, and nothing of it is written (a saved session keeps
the last completed stage). The one exception is the height map: the XY LUT stands on its own,
so a height sweep that cannot be fitted leaves the LUT complete without ``/height``, the reason
in :attr:`Calibration.height_error` (the command line prints it and exits 3, "partial"; the
wizard shows the same words).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

from ptpcore.decode.options import DECODE_OPTIONS_KEY, decode_options_json
from ptpcore.errors import DatasetError, DataWarning, PtpError
from ptpcore.fit.settings import FIT_SETTINGS_KEY, FitSettings
from ptpcore.progress import Progress, StagedProgress
from ptpcore.run.session import Session, save_session

__all__ = ["Calibration", "calibrate_session", "run_session", "calibrate", "write_lut", "PIPELINE_STAGES", "FIT_COST"]

PIPELINE_STAGES = ("decode", "fit", "drift", "height", "write")

FIT_COST = {"linear": 0.3, "pchip": 0.3, "poly": 1.0, "smooth": 4.0, "auto": 7.0}
"""Each model's fit in units of the sweep's decode (measured at 5 MP x 21 positions, issue 42's table:
poly's fit about as long as the decode, smooth's 4x, auto's 7x). The progress bar gives each stage a
share in proportion: a bar does not sit at 90 % after the decode of a calibration that has most of its
work ahead."""

Warn = Callable[[str], None]


@dataclass
class Calibration:
    """What :func:`calibrate_session` did.

    Attributes
    ----------
    session : Session
        Advanced in place: its samples and LUT (height map and drift record included).
    fitted : SampleStack or None
        The samples as the LUT was fitted to them (every correction applied), when fitted in this run.
    drift : ptpcore.fit.drift.Drift or None
        The drift of the repeat positions, when the sweep has them and they were decoded in this run.
    height_error : str or None
        Why the scanner's height map could not be made (the XY LUT is complete without it).
    warnings : list of str
        What the data checks found (also issued as warnings, or to the ``warn`` callback).
    """

    session: Session
    fitted: object = None
    drift: object = None
    height_error: str | None = None
    warnings: list = field(default_factory=list)

    @property
    def lut(self):
        """The session's LUT (None before the fit)."""
        return self.session.lut

    @property
    def partial(self) -> bool:
        """True when the height map failed and the LUT has only its XY part."""
        return self.height_error is not None

    def fitted_samples(self):
        """The samples as fitted: this run's, or computed again from the session's (a resumed LUT)."""
        if self.fitted is None and self.session.samples is not None and self.session.lut is not None:
            from ptpcore.fit.corrected import samples_as_fitted

            s = self.session
            self.fitted = samples_as_fitted(s.samples, s.rig, s.lut, s.positions)
        return self.fitted


def calibrate_session(session: Session, path=None, *, source=None, validate: bool = True,
                      stop_after: str | None = None, out=None, progress: Progress | None = None,
                      on_position=None, on_frame=None, full_positions=None, warn: Warn | None = None) -> Calibration:
    """Run a session's remaining stages (decode, fit, drift, height, write), saving after each.

    Parameters
    ----------
    session : Session
        Advanced in place.
    path : path, optional
        Session file, written atomically after the decode and after the height map.
    source : FrameSource, optional
        Frames to decode (default: the session's dataset folder); also the repeat positions' frames.
    validate : bool
        Validate the dataset folder before decoding (skip only when just done).
    stop_after : {"samples", "lut"}, optional
        Stop after the decode (the wizard's Acquire), or before writing.
    out : path, optional
        Write the LUT there at the end (``ptp-lut/1``, atomically).
    progress : callable, optional
        ``progress(fraction, message)`` over every stage (weighted by :data:`FIT_COST`); may raise to cancel.
    on_position, on_frame, full_positions
        The decode's listeners (:func:`ptpcore.run.pipeline.collect_samples`).
    warn : callable, optional
        ``warn(message)`` for each finding of the data checks (default: a :class:`DataWarning`).

    Returns
    -------
    Calibration

    Raises
    ------
    DatasetError, ConfigError, ValueError
        A stage failed (nothing of it kept; the session file holds the stage before).
    """
    if stop_after not in (None, "samples", "lut"):
        raise ValueError(f"stop_after must be 'samples' or 'lut', got {stop_after!r}")
    result = Calibration(session)
    say = _warner(result, warn)
    bar = StagedProgress(progress, _stage_costs(session, stop_after))
    if session.samples is None and session.lut is None:
        _decode_stage(session, source, validate, bar.stage("decode"), say,
                      dict(on_position=on_position, on_frame=on_frame, full_positions=full_positions))
        _save(session, path)
    if stop_after == "samples":
        bar.done("decoding done")
        return result
    _finish_lut(result, source, bar)
    _save(session, path)
    if out is not None and stop_after is None:
        write_lut(result, out)
    bar.done("calibration complete")
    return result


def _finish_lut(result: Calibration, source, bar: StagedProgress) -> None:
    """The fit, drift and height stages, each where the session lacks its product."""
    session = result.session
    if session.lut is None:
        lut = _fit_stage(result, bar.stage("fit"))
        _drift_stage(result, lut, source, bar.stage("drift", "drift: "))
        _height_stage(result, lut, bar.stage("height", "height sweep: "))
        session.lut = lut
        return
    lut = session.lut  # a resumed LUT: what an older run did not add
    if session.rig.stage.repeat_z_mm and "drift" not in lut.provenance:
        _drift_stage(result, lut, source, bar.stage("drift", "drift: "))
    if lut.height is None:
        _height_stage(result, lut, bar.stage("height", "height sweep: "))


def _warner(result: Calibration, warn: Warn | None) -> Warn:
    def say(message: str) -> None:
        result.warnings.append(message)
        if warn is not None:
            warn(message)
        else:
            warnings.warn(message, DataWarning, stacklevel=3)
    return say


def _stage_costs(session: Session, stop_after: str | None) -> dict[str, float]:
    """Every stage's expected cost in position decodes (:data:`FIT_COST`)."""
    rig = session.rig
    k = len(session.positions) if session.positions is not None else rig.stage.n_positions
    decode = 0.0 if session.samples is not None or session.lut is not None else float(k)
    if stop_after == "samples":
        return {"decode": decode or 1.0}
    fit = 0.0 if session.lut is not None else FIT_COST.get(session.settings.model, 1.0) * k
    drift = float(len(rig.stage.repeat_z_mm))
    height = float(len(rig.height.z_mm)) if rig.height is not None and session.dataset else 0.0
    return {"decode": decode, "fit": fit, "drift": drift, "height": height}


def _save(session: Session, path) -> None:
    if path is not None:
        save_session(session, path)


# --------------------------------------------------------------------------- stages

def _decode_stage(session: Session, source, validate: bool, progress, say: Warn, listeners: dict) -> None:
    """Validate, check the convention, decode every position, check the decoded data."""
    from ptpcore.io.dataset import DatasetSource
    from ptpcore.run.diagnose import check_valid_fractions
    from ptpcore.run.pipeline import collect_samples
    from ptpcore.run.sanity import check_samples
    from ptpcore.store import release_free_memory

    if source is None:
        if not session.dataset:
            raise DatasetError("the session names no dataset folder to decode")
        source = DatasetSource(session.dataset)
        if source.rig != session.rig:
            raise DatasetError(f"{source.folder / 'rig.toml'}: differs from the rig saved in the session"
                               " (the dataset changed since the session started)")
        if validate:
            source.validate()
    if type(source) is DatasetSource:
        _check_conventions(source, session, say)
    samples = collect_samples(source, options=session.options, positions=session.positions, progress=progress,
                              **listeners)
    for line in check_valid_fractions(samples, session.positions, warn=False):  # no valid pixel: an error
        say(line)
    where = str(Path(session.dataset) / "rig.toml") if session.dataset else "rig.toml"
    for line in check_samples(samples, positions=session.positions, source=where, warn=False):
        say(line)
    release_free_memory()  # the checks' reads of the spilled samples leave the process (they stay in the file)
    session.samples = samples


def _check_conventions(source, session: Session, say: Warn) -> None:
    """Before the long decode: one position decoded and checked for a wrong ``phase_origin_rad``
    or ``shift_sign`` (:func:`ptpcore.run.diagnose.convention_check`), named if found."""
    from ptpcore.run.diagnose import convention_check
    from ptpcore.run.pipeline import decode_position

    rig = source.rig
    if rig.fringes.unwrap != "periods":
        return
    positions = session.positions or range(rig.stage.n_positions)
    k = list(positions)[len(positions) // 2]
    # The check reads the wrapped phases only: the spatial-consistency pass (about half of a
    # position's decode) is left to the decode proper.
    wrapped_only = replace(session.options, spatial_k=None)
    findings = convention_check(rig, decode_position(source, k, wrapped_only), session.options)
    where = str(getattr(source, "folder", "dataset")) + "/rig.toml"
    if any(fd.fatal for fd in findings):
        raise DatasetError("; ".join(fd.message(where) for fd in findings if fd.fatal))
    for fd in findings:
        say(fd.message(where))


def _fit_stage(result: Calibration, progress):
    """The corrections and the LUT, the settings recorded in its ``/provenance``."""
    from ptpcore.fit.corrected import fit_corrected
    from ptpcore.store import release_free_memory

    s = result.session
    # The cover glass (and any other correction rig.toml asks for) leaves the samples here, before
    # any fit; the session keeps them as decoded. The stage pose too (refine_stage).
    fit = fit_corrected(s.samples, s.rig, s.settings, s.positions, progress=progress)
    fit.lut.provenance[FIT_SETTINGS_KEY] = s.settings.to_json()
    fit.lut.provenance[DECODE_OPTIONS_KEY] = decode_options_json(s.options)
    result.fitted = fit.samples
    release_free_memory()
    return fit.lut


def _drift_stage(result: Calibration, lut, source, progress) -> None:
    """The repeat positions against their sweep positions (``/provenance`` ``drift``); none without repeats."""
    s = result.session
    if not s.rig.stage.repeat_z_mm or s.samples is None:
        return
    if source is None:
        if not s.dataset:
            return
        from ptpcore.io.dataset import DatasetSource

        source = DatasetSource(s.dataset)
    from ptpcore.fit.drift import RepeatSource, sweep_drift
    from ptpcore.run.pipeline import collect_samples

    repeats = collect_samples(RepeatSource(source), options=s.options, progress=progress)
    result.drift = sweep_drift(s.samples, repeats, s.rig, stage_sigma_mm=s.settings.stage_sigma_mm)
    lut.provenance["drift"] = result.drift.to_json()


def _height_stage(result: Calibration, lut, progress) -> None:
    """The scanner's height map into ``lut.height``; a failure is kept as :attr:`Calibration.height_error`."""
    s = result.session
    if s.rig.height is None or not s.dataset:
        return
    from ptpcore.errors import Cancelled
    from ptpcore.run.scanner import calibrate_height

    try:
        lut.height = calibrate_height(s.dataset, options=s.options, progress=progress)
    except Cancelled:
        raise
    except (PtpError, ValueError) as exc:  # the XY LUT stands on its own: kept, the reason said
        result.height_error = f"the scanner's height map was not made: {exc}"


def write_lut(result: Calibration, out) -> None:
    """The ``write`` stage: the session's LUT to ``out`` (``ptp-lut/1``, atomically)."""
    from ptpcore.io.lutfile import save_lut

    save_lut(result.session.lut, out)


def run_session(session: Session, path=None, *, progress: Progress | None = None, source=None,
                validate: bool = True, stop_after: str | None = None) -> Session:
    """Carry a session on from its last completed stage, saving after each stage.

    The stages are the composer's (:func:`ptpcore.run.calibration.calibrate_session`: decode,
    fit, drift, height); this is that call for a caller that wants the session back.

    Parameters
    ----------
    session : Session
        Advanced in place (and returned).
    path : path, optional
        Session file, written atomically after each completed stage.
    progress : callable, optional
        ``progress(fraction, message)``; may raise to cancel. The file then
        holds the last completed stage.
    source : FrameSource, optional
        Frames to decode (default: the session's dataset folder).
    validate : bool
        Validate the dataset before decoding (skip only if just done).
    stop_after : {"samples", "lut"}, optional
        Stop after this stage.
    """
    calibrate_session(session, path, progress=progress, source=source, validate=validate, stop_after=stop_after)
    return session


# --------------------------------------------------------------------------- Python's door

def calibrate(dataset, settings: FitSettings | None = None, *, out=None, options=None, positions=None,
              progress: Progress | None = None):
    """Images to the LUT ``ptp calibrate`` writes, in one call.

    Parameters
    ----------
    dataset : path or FrameSource
        A ``ptp-dataset`` folder, or any frame source (e.g. the simulator's; without a folder
        there is no height sweep).
    settings : FitSettings, optional
        Default: ``ptp calibrate``'s defaults (``FitSettings()``: model auto, robust, ...).
    out : path, optional
        Also write the LUT file.
    options : DecodeOptions, optional
    positions : sequence of int, optional
        Fit on these positions only (default all).
    progress : callable, optional

    Returns
    -------
    Lut
        With its height map (``/height``) and drift record when the dataset has them. A height
        sweep that cannot be fitted leaves the LUT without ``/height`` and issues a
        :class:`~ptpcore.errors.DataWarning` with the reason.
    """
    from ptpcore.decode.phase import DecodeOptions
    from ptpcore.run.session import new_session

    settings = FitSettings() if settings is None else settings
    options = DecodeOptions() if options is None else options
    if isinstance(dataset, (str, Path)):
        session = new_session(dataset, settings, options=options, positions=positions)
        source = None
    else:
        source = dataset
        folder = getattr(source, "folder", None)
        session = Session(rig=source.rig, dataset=str(Path(folder).resolve()) if folder else None,
                          settings=settings, options=options,
                          positions=None if positions is None else tuple(int(p) for p in positions))
    result = calibrate_session(session, source=source, validate=False, out=out, progress=progress)
    if result.height_error:
        warnings.warn(result.height_error, DataWarning, stacklevel=2)
    return result.lut
