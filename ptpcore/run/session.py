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
    ``dataset`` (folder), ``out`` (LUT file to write), ``fit_settings`` (JSON: the whole
    :class:`~ptpcore.fit.settings.FitSettings`), ``decode_options`` (JSON: the whole
    :class:`~ptpcore.decode.phase.DecodeOptions`), and for readers that do not parse JSON
    ``model``, ``degree``, ``min_modulation``, ``border_margin_px``; dataset ``positions``
    (int64 ``[P]``) when only some positions are calibrated on. Files written before the
    records hold each fit setting as an attribute of its own (``stage_sigma_um``,
    ``level_bias``, ...): they are read as such.
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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from ptpcore import __version__
from ptpcore.errors import ConfigError, FileFormatError
from ptpcore.io.lutfile import (LUT_FORMAT, Lut, write_lut_attrs, arrays_nbytes, read_lut_group, str_attr,
    write_lut_group, check_format, open_hdf5, write_hdf5_atomic)
from ptpcore.io.samples import SampleStack
from ptpcore.fit.models import check_positions_for_model
from ptpcore.fit.settings import FIT_SETTINGS_KEY, FitSettings
from ptpcore.decode.phase import DecodeOptions
from ptpcore.decode.options import DECODE_OPTIONS_KEY, decode_options_from_json, decode_options_json
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
]

SESSION_FAMILY = "ptp-session"
SESSION_VERSION = 1
SESSION_FORMAT = f"{SESSION_FAMILY}/{SESSION_VERSION}"
SESSION_SUFFIX = ".ptps.h5"
STAGES = ("new", "samples", "lut")


@dataclass
class Session:
    """One calibration, as far as it got.

    Attributes
    ----------
    rig : Rig
    dataset : str or None
        The dataset folder the images come from (absolute path).
    settings : FitSettings
        How the LUT is fitted (model, degree, corrections; :class:`~ptpcore.fit.settings.FitSettings`),
        saved whole as ``/calibration`` attribute ``fit_settings``.
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
    settings: FitSettings = field(default_factory=FitSettings)
    options: DecodeOptions = field(default_factory=DecodeOptions)
    positions: tuple[int, ...] | None = None
    out: str | None = None
    sim_settings: str | None = None
    samples: SampleStack | None = None
    lut: Lut | None = None
    comparison: dict | None = None
    created: str = field(default_factory=lambda: _now())

    @property
    def model(self) -> str:
        """The LUT model of :attr:`settings`."""
        return self.settings.model

    @property
    def degree(self) -> int:
        """The polynomial degree of :attr:`settings`."""
        return self.settings.degree

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


def new_session(dataset, settings: FitSettings | None = None, *, out=None,
                options: DecodeOptions = DecodeOptions(), positions=None, validate: bool = True,
                full_check: bool = False, **fit) -> Session:
    """Start a session on a dataset folder, validating it first.

    Parameters
    ----------
    dataset : path
        A ``ptp-dataset/1`` or ``/2`` folder.
    settings : FitSettings, optional
        How to fit (default: ``ptp calibrate``'s defaults).
    **fit
        Instead of ``settings``: some of its fields (``model="poly", degree=2``), the rest default.
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
        Bad settings (model, degree, stage sigma), or ``settings`` and ``fit`` keywords both given.
    """
    from ptpcore.io.dataset import DatasetSource

    settings = _settings_of(settings, fit)
    source = DatasetSource(dataset)
    if positions is not None:
        positions = tuple(int(p) for p in positions)
        bad = [p for p in positions if not 0 <= p < source.rig.stage.n_positions]
        if bad:
            raise ValueError(f"positions {bad} do not exist (the rig has {source.rig.stage.n_positions})")
    n_cal = source.rig.stage.n_positions if positions is None else len(positions)
    check_positions_for_model(settings.model, settings.degree, n_cal, str(source.folder / "rig.toml"))
    if validate:
        source.validate(full=full_check)
    return Session(rig=source.rig, dataset=str(Path(dataset).resolve()), settings=settings,
                   options=options, positions=positions, out=None if out is None else str(out),
                   sim_settings=_sim_settings_of(source.folder))


def _settings_of(settings: FitSettings | None, fit: dict) -> FitSettings:
    """``settings``, or a record made of the ``fit`` keywords (never both)."""
    if settings is not None and fit:
        raise ValueError(f"give the fit settings as one FitSettings or as keywords, not both ({', '.join(fit)})")
    if settings is None:
        return FitSettings.from_mapping(fit, "new_session") if fit else FitSettings()
    if not isinstance(settings, FitSettings):
        raise TypeError(f"settings must be a FitSettings, got {type(settings).__name__}")
    return settings


def _sim_settings_of(folder: Path) -> str | None:
    """The simulator settings JSON of a simulated dataset (``truth.h5``), if any."""
    truth = folder / "truth.h5"
    if not truth.is_file():
        return None
    try:
        with h5py.File(truth, "r") as f:
            return str_attr(f.attrs.get("settings"))
    except OSError:
        return None


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
    if not isinstance(session.settings, FitSettings):
        raise TypeError(f"session settings must be a FitSettings, got {type(session.settings).__name__}")
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
        c.attrs.update({"dataset": session.dataset or "", "out": session.out or "",
                        FIT_SETTINGS_KEY: session.settings.to_json(),
                        DECODE_OPTIONS_KEY: decode_options_json(session.options),
                        # also one by one, for readers that do not parse JSON (and files before the records)
                        "model": session.model, "degree": int(session.degree),
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
            write_lut_attrs(g)
            write_lut_group(g, session.lut)
        if session.comparison is not None:
            text = (session.comparison if isinstance(session.comparison, str)
                    else json.dumps(session.comparison, default=_json_default))
            f.create_group("comparison").attrs["json"] = text

    s = session.samples
    size = 0 if s is None else arrays_nbytes(s.x, s.y, s.x_ref, s.y_ref, s.reasons, s.modulation, s.background)
    if session.lut is not None:
        size += arrays_nbytes(session.lut.x, session.lut.y)
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
    fmt = str_attr(f.attrs.get("format"))
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
        s = str_attr(val)
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
                same = got is not None and [str_attr(v) or str(v) for v in np.atleast_1d(got)] == val
            else:
                same = got is not None and np.array_equal(np.asarray(got), np.asarray(val))
            if not same:
                raise FileFormatError(f"{where}: attribute {key!r} of /fringes ({got!r}) disagrees with /rig")

    settings = _read_fit_settings(f, where)
    options = _read_decode_options(f, where)
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
        lut = read_lut_group(f["lut"], where)
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

    stage = str_attr(f.attrs.get("stage"))
    session = Session(rig=rig, dataset=dataset, settings=settings, options=options, positions=positions, out=out,
                      sim_settings=sim, samples=samples, lut=lut, comparison=comparison,
                      created=str_attr(f.attrs.get("created")) or _now())
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


def _read_fit_settings(f, where: str) -> FitSettings:
    """``/calibration`` ``fit_settings``; in files written before the record, its fields one attribute each
    (``robust`` absent in files before the robust fit: off; ``model`` absent: poly)."""
    if "calibration" in f and FIT_SETTINGS_KEY in f["calibration"].attrs:
        text = _attr(f, "calibration", FIT_SETTINGS_KEY, where, str)
        try:
            settings = FitSettings.from_json(text, f"{where}: attribute {FIT_SETTINGS_KEY!r} of /calibration")
        except ValueError as exc:
            raise FileFormatError(str(exc)) from None
        for key in ("model", "degree"):  # the copies for readers without JSON must agree with the record
            copy = _attr(f, "calibration", key, where, str if key == "model" else int, getattr(settings, key))
            if copy != getattr(settings, key):
                raise FileFormatError(f"{where}: attribute {key!r} of /calibration ({copy!r}) disagrees with its"
                                      f" {FIT_SETTINGS_KEY!r} ({getattr(settings, key)!r})")
        return settings
    legacy = {"model": ("poly", str), "degree": (3, int), "stage_sigma_um": (0.0, float), "level_bias": (1, int),
              "footprint": (1, int), "refine_stage": (0, int), "robust": (0, int)}
    values = {key: _attr(f, "calibration", key, where, kind, default) for key, (default, kind) in legacy.items()}
    for key in ("level_bias", "footprint", "refine_stage", "robust"):
        if values[key] not in (0, 1):
            raise FileFormatError(f"{where}: /calibration {key} {values[key]} (0 or 1) out of range")
    try:
        return FitSettings.from_mapping(values, f"{where}: /calibration")
    except ValueError as exc:
        raise FileFormatError(str(exc)) from None


def _read_decode_options(f, where: str) -> DecodeOptions:
    """``/calibration`` ``decode_options``; in older files ``min_modulation`` and ``border_margin_px``."""
    if "calibration" in f and DECODE_OPTIONS_KEY in f["calibration"].attrs:
        text = _attr(f, "calibration", DECODE_OPTIONS_KEY, where, str)
        try:
            return decode_options_from_json(text, f"{where}: attribute {DECODE_OPTIONS_KEY!r} of /calibration")
        except ValueError as exc:
            raise FileFormatError(str(exc)) from None
    min_mod = _attr(f, "calibration", "min_modulation", where, float, DecodeOptions.min_modulation)
    border = _attr(f, "calibration", "border_margin_px", where, int, DecodeOptions.border_margin_px)
    if not 0 <= min_mod < 1 or border < 0:
        raise FileFormatError(f"{where}: /calibration min_modulation {min_mod} or border_margin_px {border}"
                              " out of range")
    return DecodeOptions(min_mod, border)


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

