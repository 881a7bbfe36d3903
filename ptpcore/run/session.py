"""Calibration sessions: everything computed so far, in one versioned HDF5 file.

A calibration lasts hours; a session file keeps each completed stage so a
crash, a cancel or a reboot costs at most the stage that was running.

Stages, in order (:attr:`Session.stage`):

``"new"``
    The rig is read and the dataset validated; nothing decoded yet.
``"samples"``
    Every position decoded: each pixel's samples, validity reasons,
    modulation and background (:class:`~ptpcore.io.SampleStack`).
``"lut"``
    The per-pixel LUT is fitted.

File layout, ``ptp-session/1`` (``*.ptps.h5``)
-----------------------------------------------
``/`` attrs
    ``format = "ptp-session/1"``, ``software``, ``created``, ``saved`` (ISO 8601), ``stage``.
``/rig`` attrs
    ``toml``: the dataset's ``rig.toml`` text.
``/fringes`` attrs
    The fringe design (a copy of ``[fringes]`` for readers that do not parse
    TOML; must agree with ``/rig``).
``/calibration`` attrs
    ``dataset`` (folder), ``model``, ``degree``, ``out`` (LUT file to write),
    ``min_modulation``, ``border_margin_px``; dataset ``positions`` (int64
    ``[P]``) when only some positions are calibrated on.
``/sim`` attrs
    Optional: ``settings``, the simulator's settings JSON.
``/samples``
    ``z`` float64 ``[K]`` stage readings (mm); ``x``, ``y`` float32
    ``[K, H, W]`` mm relative to ``x_ref``, ``y_ref`` (float64 ``[H, W]``),
    NaN where ``reasons != 0``; ``reasons`` uint8 ``[K, H, W]``
    (:class:`~ptpcore.decode.phase.Reason` flags, 0 where valid, 255 where the
    position was not decoded); optional ``modulation``, ``background``
    float32 ``[K, H, W]`` grey levels; optional attrs ``noise_read_var``,
    ``noise_gain`` (the camera noise model measured from the data).
``/lut``
    A complete ``ptp-lut/1`` tree (FORMATS.md) with its own ``format`` attribute.
``/comparison`` attrs
    Optional: ``json``, the comparison results as JSON text.

Versions and migrations
-----------------------
The ``format`` attribute carries the version. A file written by a newer
version is refused ("too new"). An older file is copied into memory and
upgraded one step at a time by the functions in :data:`_MIGRATIONS`
(``_MIGRATIONS[1]`` would be ``_migrate_v1_to_v2(f)``, editing an in-memory
``h5py.File`` in place), then read as the current version. The file on disk
is never changed by reading it.
"""

from __future__ import annotations

import datetime as _dt
import itertools
import json
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from ptpcore import __version__
from ptpcore.errors import ConfigError, DatasetError, FileFormatError
from ptpcore.io.lutfile import (LUT_FORMAT, Lut, _lut_root_attrs, _nbytes, _read_lut_group, _str_attr,
    _write_lut_group, check_format, open_hdf5, write_hdf5_atomic)
from ptpcore.io.samples import SampleStack
from ptpcore.fit.corrected import fit_corrected
from ptpcore.fit.models import LUT_MODELS, check_positions_for_model
from ptpcore.decode.phase import DecodeOptions
from ptpcore.rig.rigfile import Rig, rig_from_toml, rig_to_toml

__all__ = [
    "SESSION_FORMAT",
    "SESSION_VERSION",
    "SESSION_SUFFIX",
    "STAGES",
    "Session",
    "next_step",
    "new_session",
    "save_session",
    "load_session",
    "run_session",
]

SESSION_FAMILY = "ptp-session"
SESSION_VERSION = 1
SESSION_FORMAT = f"{SESSION_FAMILY}/{SESSION_VERSION}"
SESSION_SUFFIX = ".ptps.h5"
STAGES = ("new", "samples", "lut")

Progress = Callable[[float, str], None]


@dataclass
class Session:
    """One calibration, as far as it got.

    Attributes
    ----------
    rig : Rig
    dataset : str or None
        The dataset folder the images come from (absolute path).
    model : {"poly", "pchip", "linear", "smooth"}
        One of :data:`ptpcore.fit.models.LUT_MODELS`.
    degree : int
        Polynomial degree (``poly``, ``smooth``).
    stage_sigma_um : float
        1-sigma error of the stage readings (um), for the predicted sigma maps.
    level_bias : bool
        ``smooth``: remove the display's level bias (:mod:`ptpcore.decode.display`).
    footprint : bool
        ``smooth``: remove the footprint-centroid bias (:func:`ptpcore.fit.smooth.footprint_bias`).
    refine_stage : bool
        Estimate each position's pose errors and correct the samples before fitting
        (:mod:`ptpcore.fit.stage_pose`).
    robust : bool
        Leave out samples far outside their pixel's curve (:mod:`ptpcore.fit.robust`); stored as
        ``/calibration`` attribute ``robust`` (0 when absent: files written before it).
    options : DecodeOptions
        Pixel validity thresholds used when decoding.
    positions : tuple of int or None
        Positions the LUT is fitted on (None: all).
    out : str or None
        The LUT file to write when the session completes.
    sim_settings : str or None
        The simulator's settings JSON (as in ``truth.h5``) for simulated datasets.
    samples : SampleStack or None
        Set once every position is decoded.
    lut : Lut or None
        Set once the LUT is fitted.
    comparison : dict or None
        Comparison results (anything JSON can hold).
    created : str
        ISO 8601 time the session started.
    """

    rig: Rig
    dataset: str | None = None
    model: str = "auto"
    degree: int = 3
    stage_sigma_um: float = 0.0
    refine_stage: bool = False
    level_bias: bool = True
    footprint: bool = True
    robust: bool = True
    options: DecodeOptions = field(default_factory=DecodeOptions)
    positions: tuple[int, ...] | None = None
    out: str | None = None
    sim_settings: str | None = None
    samples: SampleStack | None = None
    lut: Lut | None = None
    comparison: dict | None = None
    created: str = field(default_factory=lambda: _now())

    @property
    def stage(self) -> str:
        """The last completed stage: ``"new"``, ``"samples"`` or ``"lut"``."""
        if self.lut is not None:
            return "lut"
        if self.samples is not None:
            return "samples"
        return "new"


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def next_step(session: Session) -> str | None:
    """What resuming ``session`` does next.

    ``"decode"`` (stage ``new``), ``"fit"`` (stage ``samples``), ``"compare"``
    (the LUT is fitted, no comparison results yet; optional), or None when
    everything the session file holds is done.
    """
    if session.samples is None and session.lut is None:
        return "decode"
    if session.lut is None:
        return "fit"
    if session.comparison is None:
        return "compare"
    return None


def new_session(dataset, *, model: str = "auto", degree: int = 3, out=None,
                options: DecodeOptions = DecodeOptions(), positions=None, validate: bool = True,
                full_check: bool = False, stage_sigma_um: float = 0.0, level_bias: bool = True,
                footprint: bool = True, refine_stage: bool = False,
                robust: bool = True) -> Session:
    """Start a session on a dataset folder, validating it first.

    Parameters
    ----------
    dataset : path
        A ``ptp-dataset/1`` folder.
    model, degree : see :func:`ptpcore.fit.models.fit_model`
    stage_sigma_um, level_bias, footprint, refine_stage, robust : see :class:`Session`
    out : path, optional
        LUT file to write at the end.
    options : DecodeOptions
    positions : sequence of int, optional
    validate : bool
        Run :func:`ptpcore.io.dataset.validate_dataset` (every image, the design).
    full_check : bool
        Decode every image's pixels while validating.

    Raises
    ------
    ConfigError, DatasetError
        ``rig.toml`` invalid or not calibratable; unusable images (all listed).
    ValueError
        Bad model or degree.
    """
    from ptpcore.io.dataset import DatasetSource

    _check_model(model, degree)
    if not (np.isfinite(stage_sigma_um) and stage_sigma_um >= 0):
        raise ValueError(f"stage sigma must be a finite number >= 0 µm, got {stage_sigma_um}")
    source = DatasetSource(dataset)
    if positions is not None:
        positions = tuple(int(p) for p in positions)
        bad = [p for p in positions if not 0 <= p < source.rig.stage.n_positions]
        if bad:
            raise ValueError(f"positions {bad} do not exist (the rig has {source.rig.stage.n_positions})")
    n_cal = source.rig.stage.n_positions if positions is None else len(positions)
    check_positions_for_model(model, degree, n_cal, str(source.folder / "rig.toml"))
    if validate:
        source.validate(full=full_check)
    return Session(rig=source.rig, dataset=str(Path(dataset).resolve()), model=model, degree=int(degree),
                   stage_sigma_um=float(stage_sigma_um), level_bias=bool(level_bias), footprint=bool(footprint),
                   refine_stage=bool(refine_stage), robust=bool(robust),
                   options=options, positions=positions, out=None if out is None else str(out),
                   sim_settings=_sim_settings_of(source.folder))


def _sim_settings_of(folder: Path) -> str | None:
    """The simulator settings JSON of a simulated dataset (``truth.h5``), if any."""
    truth = folder / "truth.h5"
    if not truth.is_file():
        return None
    try:
        with h5py.File(truth, "r") as f:
            return _str_attr(f.attrs.get("settings"))
    except OSError:
        return None


def _check_model(model: str, degree: int) -> None:
    if model not in LUT_MODELS:
        raise ValueError(f"model must be one of {LUT_MODELS}, got {model!r}")
    if model in ("poly", "smooth", "auto") and not 1 <= int(degree) <= 5:
        raise ValueError(f"{model} degree must be 1 to 5, got {degree}")


def run_session(session: Session, path=None, *, progress: Progress | None = None, source=None,
                validate: bool = True, stop_after: str | None = None) -> Session:
    """Carry a session on from its last completed stage, saving after each stage.

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

    Raises
    ------
    DatasetError
        The dataset is gone, unusable, or its ``rig.toml`` no longer matches
        the session's.
    ConfigError
        The decoded samples contradict the stage readings' sense (``z_mm``
        listed in reverse); positions that look stuck are a ``DataWarning``.
    """
    from ptpcore.io.dataset import DatasetSource
    from ptpcore.store import release_free_memory
    from ptpcore.run.pipeline import collect_samples

    def sub(lo, hi):
        if progress is None:
            return None
        return lambda f, msg: progress(lo + (hi - lo) * f, msg)

    if session.lut is None and session.samples is None:
        if source is None:
            if not session.dataset:
                raise DatasetError("the session names no dataset folder to decode")
            source = DatasetSource(session.dataset)
            if source.rig != session.rig:
                raise DatasetError(f"{source.folder / 'rig.toml'}: differs from the rig saved in the session"
                                   " (the dataset changed since the session started)")
            if validate:
                source.validate()
            _check_conventions(source, session)
        samples = collect_samples(source, options=session.options, positions=session.positions,
                                  progress=sub(0.0, 0.9))
        from ptpcore.run.diagnose import check_valid_fractions

        check_valid_fractions(samples, session.positions)  # warns per position; no valid pixel: an error
        _check_decoded(samples, session)
        release_free_memory()  # the checks' reads of the spilled samples leave the process (they stay in the file)
        session.samples = samples
        if path is not None:
            save_session(session, path)
    if stop_after == "samples":
        return session
    if session.lut is None:
        # The cover glass (and any other correction rig.toml asks for) leaves the
        # samples here, before any fit; the session keeps them as decoded.
        # The stage pose too (refine_stage); their uncertainty widens the sigma maps.
        session.lut = fit_corrected(session.samples, session.rig, session.model, session.degree,
                                    positions=session.positions, refine_stage=session.refine_stage,
                                    progress=sub(0.9, 1.0), stage_sigma_mm=session.stage_sigma_um * 1e-3,
                                    level_bias=session.level_bias, footprint=session.footprint,
                                    robust=session.robust).lut
        release_free_memory()
        if path is not None:
            save_session(session, path)
    if progress:
        progress(1.0, "session complete")
    return session


def _check_decoded(samples: SampleStack, session: Session) -> None:
    """The readings' sense and stuck positions (:func:`ptpcore.run.sanity.check_samples`)."""
    from ptpcore.run.sanity import check_samples

    where = str(Path(session.dataset) / "rig.toml") if session.dataset else "rig.toml"
    check_samples(samples, positions=session.positions, source=where)


def _check_conventions(source, session: Session) -> None:
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
        warnings.warn(fd.message(where), stacklevel=2)


# --------------------------------------------------------------------------- writing

_OPTS = dict(chunks=True, compression="gzip", compression_opts=1, shuffle=True)


def _fringe_attrs(rig: Rig) -> dict:
    f = rig.fringes
    return {"directions": list(f.directions), "periods_px": np.asarray(f.periods_px, np.int64 if all(isinstance(t, int) for t in f.periods_px)
                                           else np.float64),
            "steps": np.asarray(f.steps, np.int64), "offset": f.offset, "amplitude": f.amplitude,
            "carrier_px_per_mm": np.asarray(f.carrier_px_per_mm, float), "gamma": f.gamma}


def _check_session(session: Session) -> None:
    """Refuse to write what :func:`load_session` would refuse to read."""
    _check_model(session.model, session.degree)
    shape = session.rig.camera.shape
    k = session.rig.stage.n_positions
    s = session.samples
    if s is not None:
        if s.x.shape != (k, *shape) or len(s.z) != k:
            raise ValueError(f"samples have shape {s.x.shape}, the rig needs {(k, *shape)}")
    if session.lut is not None and session.lut.shape != shape:
        raise ValueError(f"LUT has shape {session.lut.shape}, the rig's camera is {shape}")


def save_session(session: Session, path) -> None:
    """Write a session file (``ptp-session/1``) atomically.

    A process killed during the write leaves the previous session file intact.

    Raises
    ------
    ValueError
        The session is inconsistent (shapes differ from the rig).
    """
    _check_session(session)

    def fill(f) -> None:
        f.attrs["format"] = SESSION_FORMAT
        f.attrs["software"] = f"ptpcore {__version__}"
        f.attrs["created"] = session.created
        f.attrs["saved"] = _now()
        f.attrs["stage"] = session.stage
        f.create_group("rig").attrs["toml"] = rig_to_toml(session.rig)
        f.create_group("fringes").attrs.update(_fringe_attrs(session.rig))
        c = f.create_group("calibration")
        c.attrs.update({"dataset": session.dataset or "", "model": session.model,
                        "degree": int(session.degree), "out": session.out or "",
                        "stage_sigma_um": float(session.stage_sigma_um),
                        "level_bias": int(bool(session.level_bias)),
                        "footprint": int(bool(session.footprint)),
                        "refine_stage": int(bool(session.refine_stage)),
                        "robust": int(bool(session.robust)),
                        "min_modulation": float(session.options.min_modulation),
                        "border_margin_px": int(session.options.border_margin_px)})
        if session.positions is not None:
            c["positions"] = np.asarray(session.positions, np.int64)
        if session.sim_settings:
            f.create_group("sim").attrs["settings"] = session.sim_settings
        s = session.samples
        if s is not None:
            g = f.create_group("samples")
            g["z"] = np.asarray(s.z, np.float64)
            g.create_dataset("x", data=np.asarray(s.x, np.float32), **_OPTS)
            g.create_dataset("y", data=np.asarray(s.y, np.float32), **_OPTS)
            g.create_dataset("x_ref", data=np.asarray(s.x_ref, np.float64), **_OPTS)
            g.create_dataset("y_ref", data=np.asarray(s.y_ref, np.float64), **_OPTS)
            g.create_dataset("reasons", data=np.asarray(s.reasons, np.uint8), **_OPTS)
            for name in ("modulation", "background"):
                arr = getattr(s, name)
                if arr is not None:
                    g.create_dataset(name, data=np.asarray(arr, np.float32), **_OPTS)
            noise = getattr(s, "noise", None)
            if noise is not None:
                g.attrs.update({"noise_read_var": float(noise.read_var), "noise_gain": float(noise.gain)})
        if session.lut is not None:
            g = f.create_group("lut")
            _lut_root_attrs(g)
            _write_lut_group(g, session.lut)
        if session.comparison is not None:
            text = (session.comparison if isinstance(session.comparison, str)
                    else json.dumps(session.comparison, default=_json_default))
            f.create_group("comparison").attrs["json"] = text

    s = session.samples
    size = 0 if s is None else _nbytes(s.x, s.y, s.x_ref, s.y_ref, s.reasons, s.modulation, s.background)
    if session.lut is not None:
        size += _nbytes(session.lut.x, session.lut.y)
    write_hdf5_atomic(path, fill, size)


def _json_default(obj):
    """numpy scalars and arrays in comparison results become plain JSON numbers and lists."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"comparison results hold a {type(obj).__name__}, which JSON cannot store")


# --------------------------------------------------------------------------- versions

#: ``from_version -> function(h5py.File)`` upgrading an in-memory copy by one version.
_MIGRATIONS: dict[int, Callable[[h5py.File], None]] = {}

_mem_files = itertools.count()


def _file_version(f: h5py.File, where: str) -> int:
    fmt = _str_attr(f.attrs.get("format"))
    if not isinstance(fmt, str):
        raise FileFormatError(f"{where}: attribute 'format' is {fmt!r}, expected {SESSION_FORMAT!r}"
                              " (not a session file)")
    family, _, tail = fmt.rpartition("/")
    if family != SESSION_FAMILY or not tail.isdigit():
        hint = " (a LUT file: use it directly, not as a session)" if fmt == LUT_FORMAT else ""
        raise FileFormatError(f"{where}: attribute 'format' is {fmt!r}, expected {SESSION_FORMAT!r}{hint}")
    version = int(tail)
    if version > SESSION_VERSION:
        raise FileFormatError(f"{where}: format {fmt!r} is newer than this software reads ({SESSION_FORMAT});"
                              " update PTP Studio")
    if version < 1:
        raise FileFormatError(f"{where}: format {fmt!r} is not supported")
    return version


def _migrate(f: h5py.File, version: int, where: str) -> h5py.File:
    """An in-memory copy of ``f`` upgraded step by step to :data:`SESSION_VERSION`."""
    mem = h5py.File(f"ptp-session-migration-{next(_mem_files)}.h5", "w", driver="core", backing_store=False)
    try:
        for key in f:
            f.copy(f[key], mem, name=key)
        mem.attrs.update(dict(f.attrs))
        for v in range(version, SESSION_VERSION):
            step = _MIGRATIONS.get(v)
            if step is None:
                raise FileFormatError(f"{where}: no migration from {SESSION_FAMILY}/{v} to {SESSION_FAMILY}/{v + 1}")
            try:
                step(mem)
            except FileFormatError:
                raise
            except Exception as exc:
                raise FileFormatError(f"{where}: cannot upgrade from {SESSION_FAMILY}/{v} ({exc})") from None
            mem.attrs["format"] = f"{SESSION_FAMILY}/{v + 1}"
    except BaseException:
        mem.close()
        raise
    return mem


# --------------------------------------------------------------------------- reading

def load_session(path) -> Session:
    """Read and check a session file, upgrading an older version in memory.

    Raises
    ------
    FileFormatError
        Naming the file and the dataset or attribute at fault: not HDF5 or
        truncated, not a session, too new, missing or wrongly shaped datasets,
        NaN where a valid sample needs a number, values out of range.
    """
    f, where = open_hdf5(path)
    with f:
        version = _file_version(f, where)
        if version == SESSION_VERSION:
            return _read(f, where)
        with _migrate(f, version, where) as mem:
            return _read(mem, where)


def _read(f: h5py.File, where: str) -> Session:
    try:
        return _read_checked(f, where)
    except OSError as exc:
        raise FileFormatError(f"{where}: truncated or damaged ({exc})") from None


def _attr(f, group: str, key: str, where: str, kind, default=...):
    obj = f[group] if group in f else None
    if obj is None or key not in obj.attrs:
        if default is not ...:
            return default
        raise FileFormatError(f"{where}: missing attribute {key!r} of /{group}")
    val = obj.attrs[key]
    label = f"{where}: attribute {key!r} of /{group}"
    if kind is str:
        s = _str_attr(val)
        if s is None:
            raise FileFormatError(f"{label} must be text, got {val!r}"[:300])
        return s
    if isinstance(val, np.ndarray) and val.size == 1:
        val = val.reshape(())[()]
    if isinstance(val, (bool, np.bool_)) or not isinstance(val, (int, float, np.integer, np.floating)):
        raise FileFormatError(f"{label} must be a number, got {val!r}"[:300])
    if not np.isfinite(val):
        raise FileFormatError(f"{label} must be finite, got {val}")
    if kind is int:
        if float(val) != int(val):
            raise FileFormatError(f"{label} must be an integer, got {val}")
        return int(val)
    return float(val)


def _dataset(f, name: str, where: str, shape, kinds: str):
    if name not in f:
        raise FileFormatError(f"{where}: missing dataset /{name}")
    obj = f[name]
    if not isinstance(obj, h5py.Dataset):
        raise FileFormatError(f"{where}: /{name} is not a dataset")
    if obj.dtype.kind not in kinds:
        raise FileFormatError(f"{where}: /{name} has type {obj.dtype}, expected"
                              f" {'floating-point numbers' if kinds == 'f' else 'integers'}")
    if shape is not None and obj.shape != tuple(shape):
        raise FileFormatError(f"{where}: /{name} has shape {obj.shape}, expected {tuple(shape)}")
    return obj[()]


def _read_checked(f: h5py.File, where: str) -> Session:
    toml = _attr(f, "rig", "toml", where, str)
    try:
        rig = rig_from_toml(toml, f"{where}: /rig")
    except ConfigError as exc:
        raise FileFormatError(str(exc)) from None
    if "fringes" in f:
        stored = dict(f["fringes"].attrs)
        want = _fringe_attrs(rig)
        for key, val in want.items():
            got = stored.get(key)
            if isinstance(val, list):
                same = got is not None and [_str_attr(v) or str(v) for v in np.atleast_1d(got)] == val
            else:
                same = got is not None and np.array_equal(np.asarray(got), np.asarray(val))
            if not same:
                raise FileFormatError(f"{where}: attribute {key!r} of /fringes ({got!r}) disagrees with /rig")

    model = _attr(f, "calibration", "model", where, str, "poly")
    degree = _attr(f, "calibration", "degree", where, int, 3)
    try:
        _check_model(model, degree)
    except ValueError as exc:
        raise FileFormatError(f"{where}: /calibration: {exc}") from None
    min_mod = _attr(f, "calibration", "min_modulation", where, float, DecodeOptions.min_modulation)
    border = _attr(f, "calibration", "border_margin_px", where, int, DecodeOptions.border_margin_px)
    if not 0 <= min_mod < 1 or border < 0:
        raise FileFormatError(f"{where}: /calibration min_modulation {min_mod} or border_margin_px {border}"
                              " out of range")
    stage_sigma_um = _attr(f, "calibration", "stage_sigma_um", where, float, 0.0)
    level_bias = _attr(f, "calibration", "level_bias", where, int, 1)
    footprint = _attr(f, "calibration", "footprint", where, int, 1)
    refine = _attr(f, "calibration", "refine_stage", where, int, 0)
    robust = _attr(f, "calibration", "robust", where, int, 0)  # files before the robust fit: without it
    if robust not in (0, 1):
        raise FileFormatError(f"{where}: /calibration robust {robust} (0 or 1) out of range")
    if not (np.isfinite(stage_sigma_um) and stage_sigma_um >= 0) or level_bias not in (0, 1) or footprint not in (0, 1):
        raise FileFormatError(f"{where}: /calibration stage_sigma_um {stage_sigma_um} (must be >= 0),"
                              f" level_bias {level_bias} or footprint {footprint} (0 or 1) out of range")
    positions = None
    if "calibration/positions" in f:
        pos = _dataset(f, "calibration/positions", where, None, "iu")
        if pos.ndim != 1 or np.any(pos < 0) or np.any(pos >= rig.stage.n_positions):
            raise FileFormatError(f"{where}: /calibration/positions must list positions 0 to"
                                  f" {rig.stage.n_positions - 1}")
        positions = tuple(int(p) for p in pos)
    dataset = _attr(f, "calibration", "dataset", where, str, "") or None
    out = _attr(f, "calibration", "out", where, str, "") or None
    sim = _attr(f, "sim", "settings", where, str, None) if "sim" in f else None
    if sim is not None:
        try:
            json.loads(sim)
        except ValueError:
            raise FileFormatError(f"{where}: attribute 'settings' of /sim is not valid JSON") from None

    samples = _read_samples(f, rig, where) if "samples" in f else None

    lut = None
    if "lut" in f:
        check_format(f["lut"], f"{where}: /lut", LUT_FORMAT)
        lut = _read_lut_group(f["lut"], where)
        if lut.shape != rig.camera.shape:
            raise FileFormatError(f"{where}: /lut is {lut.shape[1]}x{lut.shape[0]} px, /rig says camera"
                                  f" {rig.camera.width}x{rig.camera.height}")

    comparison = None
    if "comparison" in f:
        text = _attr(f, "comparison", "json", where, str)
        try:
            comparison = json.loads(text)
        except ValueError:
            raise FileFormatError(f"{where}: attribute 'json' of /comparison is not valid JSON") from None

    stage = _str_attr(f.attrs.get("stage"))
    session = Session(rig=rig, dataset=dataset, model=model, degree=degree, stage_sigma_um=stage_sigma_um,
                      level_bias=bool(level_bias), footprint=bool(footprint), refine_stage=bool(refine), robust=bool(robust), options=DecodeOptions(min_mod, border), positions=positions, out=out,
                      sim_settings=sim, samples=samples, lut=lut, comparison=comparison,
                      created=_str_attr(f.attrs.get("created")) or _now())
    if stage is not None and stage != session.stage:
        if stage not in STAGES:
            raise FileFormatError(f"{where}: attribute 'stage' is {stage!r}, not one of {STAGES}")
        missing = [f"/{g}" for g in ("samples", "lut")[:STAGES.index(stage)] if g not in f]
        if missing:
            raise FileFormatError(f"{where}: attribute 'stage' says {stage!r} but {' and '.join(missing)}"
                                  f" {'is' if len(missing) == 1 else 'are'} missing (incomplete file?)")
        raise FileFormatError(f"{where}: attribute 'stage' says {stage!r} but the file holds stage"
                              f" {session.stage!r}")
    return session


def _read_samples(f, rig: Rig, where: str) -> SampleStack:
    k = rig.stage.n_positions
    h, w = rig.camera.shape
    z = _dataset(f, "samples/z", where, (k,), "f")
    if not np.all(np.isfinite(z)):
        raise FileFormatError(f"{where}: /samples/z holds NaN or infinite heights")
    if not np.allclose(z, rig.stage.z_mm, rtol=0, atol=1e-9):
        raise FileFormatError(f"{where}: /samples/z disagrees with stage.z_mm of /rig")
    reasons = _dataset(f, "samples/reasons", where, (k, h, w), "u")
    x = _dataset(f, "samples/x", where, (k, h, w), "f")
    y = _dataset(f, "samples/y", where, (k, h, w), "f")
    x_ref = _dataset(f, "samples/x_ref", where, (h, w), "f")
    y_ref = _dataset(f, "samples/y_ref", where, (h, w), "f")
    valid = reasons == 0
    for name, arr in (("x", x), ("y", y)):
        if not np.all(np.isfinite(arr[valid])):
            raise FileFormatError(f"{where}: /samples/{name} holds NaN or infinite values at valid samples"
                                  " (reasons == 0)")
    ever = valid.any(axis=0)
    for name, arr in (("x_ref", x_ref), ("y_ref", y_ref)):
        if not np.all(np.isfinite(arr[ever])):
            raise FileFormatError(f"{where}: /samples/{name} holds NaN for pixels with valid samples")
    extra = {}
    for name in ("modulation", "background"):
        if f"samples/{name}" in f:
            arr = _dataset(f, f"samples/{name}", where, (k, h, w), "f")
            with np.errstate(invalid="ignore"):
                if np.any(arr < 0) or np.any(np.isinf(arr)):
                    raise FileFormatError(f"{where}: /samples/{name} holds negative or infinite values")
            extra[name] = arr
        else:
            extra[name] = None
    stack = SampleStack(z.astype(np.float64), x.astype(np.float32), y.astype(np.float32),
                        x_ref.astype(np.float64), y_ref.astype(np.float64), reasons.astype(np.uint8),
                        extra["modulation"], extra["background"])
    if "noise_read_var" in f["samples"].attrs:
        from ptpcore.decode.noise import NoiseModel

        read_var = _attr(f, "samples", "noise_read_var", where, float)
        gain = _attr(f, "samples", "noise_gain", where, float)
        if read_var < 0 or gain < 0:
            raise FileFormatError(f"{where}: /samples noise_read_var and noise_gain must not be negative")
        stack.noise = NoiseModel(read_var, gain)
    return stack

