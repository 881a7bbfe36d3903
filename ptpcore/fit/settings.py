"""The fit's settings: one frozen record, passed whole from every front end to the fit.

``ptp calibrate``'s flags, the wizard's Calibrate controls, a session file's ``/calibration``
and a LUT's ``/provenance`` ``fit_settings`` all hold one :class:`FitSettings`. Each field
carries the facts a front end needs to offer it (its command-line flag and help, the words
of a wizard control), so a new option is added here, where it is used, and in the wizard's
control: :func:`fit_arguments` makes the flags and :func:`FitSettings.from_flags` reads them.

The record in a file is JSON (:meth:`FitSettings.to_json`): a file written before a field
existed reads that field's default (:meth:`FitSettings.from_mapping`), a key this version
does not know is refused with its name.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Mapping

__all__ = ["FitSettings", "FIT_SETTINGS_KEY", "fit_arguments"]

FIT_SETTINGS_KEY = "fit_settings"
"""The name of the record: a LUT's ``/provenance`` attribute and a session's ``/calibration`` attribute."""

MODELS = ("auto", "poly", "pchip", "linear", "smooth")
"""Every LUT model (the same tuple as :data:`ptpcore.fit.models.LUT_MODELS`)."""


def _option(default, flag: str, help: str, **cli) -> Any:
    """A field with its command-line flag (``--no-x`` flags invert a default-on switch) and help."""
    return field(default=default, metadata={"flag": flag, "help": help, **cli})


@dataclass(frozen=True)
class FitSettings:
    """How a LUT is fitted to decoded samples (``ptp calibrate``'s defaults when made with no arguments).

    Attributes
    ----------
    model : {"auto", "poly", "pchip", "linear", "smooth"}
        ``auto``: the most accurate of poly degrees 1-3 and smooth at held-out positions.
    degree : int
        Polynomial degree 1-5 (``poly``, ``smooth``; ``auto`` chooses its own).
    stage_sigma_um : float
        1-sigma error of the stage readings (µm): part of the predicted sigma maps.
    level_bias : bool
        ``smooth``: remove the bias of the LCD's integer levels (:mod:`ptpcore.decode.display`).
    footprint : bool
        ``smooth``: remove each pixel's footprint bias (:func:`ptpcore.fit.smooth.footprint_bias`).
    refine_stage : bool
        Estimate every position's stage pose and correct the samples first (:mod:`ptpcore.fit.stage_pose`).
    robust : bool
        Leave out samples far outside their pixel's curve (:mod:`ptpcore.fit.robust`).
    """

    model: str = _option("auto", "--model", "auto: the most accurate of poly degrees 1-3 and smooth at held-out"
                         " positions (the summary shows the table); poly: per-pixel polynomial; pchip, linear:"
                         " interpolated tables; smooth: per-pixel polynomial regularised across neighbouring"
                         " pixels (default auto)", choices=MODELS)
    degree: int = _option(3, "--degree", "polynomial degree 1-5 (poly and smooth, default 3; auto chooses its"
                          " own)", choices=range(1, 6), metavar="D")
    stage_sigma_um: float = _option(0.0, "--stage-sigma-um", "1-sigma error of the stage readings in µm (its"
                                    " specification); part of the LUT's predicted sigma maps (default 0)",
                                    metavar="S")
    level_bias: bool = _option(True, "--no-level-bias", "smooth: keep the bias of the LCD's integer levels (for a"
                               " display that dithers)")
    footprint: bool = _option(True, "--no-footprint", "smooth: keep each pixel's footprint bias (where the lens"
                              " bends, a pixel decodes its footprint's average fringe, off its centre ray; the"
                              " footprint's size is read from the fringe contrast: turn off when ambient light or"
                              " a camera black level lower the contrast)")
    refine_stage: bool = _option(False, "--refine-stage", "estimate every position's stage pose errors (dx, dy,"
                                 " dz; pitch, yaw, roll) from the straightness of the rays, up to a common offset,"
                                 " scale and linear trend, and correct the samples before fitting (docs/method.md"
                                 " section 8)")
    robust: bool = _option(True, "--no-robust", "keep every sample (default: samples beyond 5 predicted sigmas of"
                           " their pixel's curve are left out and counted, a position rejected at most pixels is"
                           " named suspect and left out)")

    def __post_init__(self) -> None:
        for f in fields(self):
            reason = _problem(f, getattr(self, f.name))
            if reason:
                raise ValueError(f"fit settings: {f.name} {reason}, got {getattr(self, f.name)!r}")

    # ---- records -------------------------------------------------------------------------
    def to_json(self) -> str:
        """The record as JSON text (keys in field order)."""
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str, where: str = "fit settings") -> "FitSettings":
        """The record :meth:`to_json` wrote; ``where`` names the file and attribute in errors."""
        try:
            data = json.loads(text)
        except ValueError:
            raise ValueError(f"{where}: not valid JSON") from None
        if not isinstance(data, dict):
            raise ValueError(f"{where}: expected a JSON object of fit settings, got {type(data).__name__}")
        return cls.from_mapping(data, where)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], where: str = "fit settings") -> "FitSettings":
        """Settings from a mapping of field names; a missing field takes its default (files written before
        it), an unknown one is refused by name."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"{where}: unknown fit setting {unknown[0]!r} (known: {', '.join(sorted(names))});"
                             " written by a newer version?")
        values = {}
        for f in fields(cls):
            if f.name not in data:
                continue
            val = data[f.name]
            if f.type in ("bool", bool) and isinstance(val, int) and val in (0, 1):
                val = bool(val)  # HDF5 attributes of older files hold 0 / 1
            elif f.type in ("float", float) and isinstance(val, int) and not isinstance(val, bool):
                val = float(val)
            values[f.name] = val
        try:
            return cls(**values)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None

    # ---- front ends ------------------------------------------------------------------------
    @classmethod
    def from_flags(cls, args) -> "FitSettings":
        """Settings from parsed command-line flags made by :func:`fit_arguments` (a bad value: one line
        naming its flag)."""
        values = {}
        for f in fields(cls):
            got = getattr(args, f.name)
            values[f.name] = (not got) if f.metadata["flag"].startswith("--no-") else got
            reason = _problem(f, values[f.name])
            if reason:
                raise ValueError(f"{f.metadata['flag']} {got}: {reason}")
        return cls(**values)

    def with_changes(self, **changes) -> "FitSettings":
        """A copy with some fields changed (checked like a new record)."""
        return replace(self, **changes)

    @property
    def stage_sigma_mm(self) -> float:
        """:attr:`stage_sigma_um` in mm."""
        return self.stage_sigma_um * 1e-3


def _problem(f, value) -> str | None:
    """Why ``value`` cannot be field ``f`` of :class:`FitSettings` (None: it can)."""
    kind = f.type if isinstance(f.type, str) else f.type.__name__
    if kind == "bool":
        return None if isinstance(value, bool) else "must be true or false"
    if f.name == "model":
        return None if value in MODELS else f"must be one of {', '.join(MODELS)}"
    if f.name == "degree":
        ok = isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 5
        return None if ok else "must be an integer 1 to 5"
    if f.name == "stage_sigma_um":
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0
        return None if ok else "(the stage sigma) must be a finite number >= 0 µm"
    return None


def fit_arguments(parser, defaults: FitSettings | None = None, helps: dict | None = None) -> None:
    """Add a flag for every field of :class:`FitSettings` to an argparse ``parser``.

    A ``bool`` field whose flag starts with ``--no-`` is a default-on switch; other ``bool`` fields
    are default-off switches; other fields take a value of the field's type. The parsed names are
    the field names (:meth:`FitSettings.from_flags` reads them back). ``defaults``: another command's
    defaults for the valued fields (``ptp demo``'s poly); ``helps``: field name -> help text in place of
    the field's own (a changed default says so there).
    """
    defaults = defaults or FitSettings()
    helps = helps or {}
    for f in fields(FitSettings):
        meta = dict(f.metadata)
        flag, text = meta.pop("flag"), helps.get(f.name, meta.pop("help"))
        meta.pop("help", None)
        if f.type in ("bool", bool):
            parser.add_argument(flag, dest=f.name, action="store_true", help=text)
            continue
        kind = {"int": int, "float": float, "str": str}.get(f.type, f.type) if isinstance(f.type, str) else f.type
        parser.add_argument(flag, dest=f.name, type=kind, default=getattr(defaults, f.name),
                            choices=list(meta.pop("choices")) if "choices" in meta and kind is str
                            else meta.pop("choices", None), help=text, **meta)
