"""The rig: camera, LCD, stage, fringe design and image layout.

These dataclasses are the in-memory form of a ``ptp-dataset/1`` or ``/2``
``rig.toml`` (FORMATS.md). All validation happens here, at load time: once a
:class:`Rig` exists, the numerics downstream can trust it. A rig that uses no
``/2`` key is written as ``/1``, so older readers keep reading it.
"""

from __future__ import annotations

import math
import re
import string
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import tomli_w

from ptpcore.atomic import write_text_atomic
from ptpcore.errors import ConfigError

__all__ = [
    "DATASET_FORMAT",
    "DATASET_FORMAT_2",
    "Camera",
    "Lcd",
    "Stage",
    "Display",
    "DirectionFringes",
    "FringeDesign",
    "DecodeSettings",
    "FrameEntry",
    "Rig",
    "Projector",
    "HeightSweep",
    "ScanSpec",
    "SCAN_FORMAT",
    "projector_rig",
    "load_scan",
    "scan_to_toml",
    "format_period",
    "load_rig",
    "rig_from_toml",
    "rig_to_toml",
    "save_rig",
    "validate_template",
    "heterodyne_beats",
    "check_heterodyne_span",
]

DATASET_FORMAT = "ptp-dataset/1"
DATASET_FORMAT_2 = "ptp-dataset/2"
TEMPLATE_FIELDS = ("pos", "dir", "period", "step", "steps", "period_index")
GRAY_TEMPLATE_FIELDS = ("pos", "dir", "bit", "inverse")
REFERENCE_TEMPLATE_FIELDS = ("pos",)
MAX_GRAY_BITS = 24
DEFAULT_TEMPLATE = "z{pos:03d}/{dir}_T{period}_n{step:02d}.png"
MAX_POSITIONS = 10_000
MAX_PERIOD_PX = 10_000_000
MAX_STEPS = 1000
# A plain format spec: [[fill]align][sign][#][0][width][,_][.precision][type], widths <= 3 digits.
_SPEC = re.compile(r"(?:[^{}]?[<>=^])?[+\- ]?#?0?(?:\d{1,3})?[,_]?(?:\.\d{1,3})?[bdoxXs]?")


@dataclass(frozen=True)
class Camera:
    """The camera's sensor: ``width`` x ``height`` pixels, ``bit_depth`` bits per sample."""

    width: int = 640
    height: int = 480
    bit_depth: int = 8
    bit_shift: int = 0  # ptp-dataset/2: samples stored MSB-aligned; value >> bit_shift = counts

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``: the shape of every image and per-pixel map."""
        return (self.height, self.width)

    @property
    def max_level(self) -> int:
        """Largest grey level the sensor can report."""
        return (1 << self.bit_depth) - 1


@dataclass(frozen=True)
class Lcd:
    """The LCD: ``width`` x ``height`` pixels with pitch ``(x, y)`` in mm."""

    width: int = 3840
    height: int = 2160
    pitch_mm: tuple[float, float] = (0.05, 0.05)
    # ptp-dataset/2 (kept here for the corrections that use them):
    cover_glass_mm: float | None = None  # None: the key is absent (a bare panel assumed); 0: no glass, declared
    cover_glass_index: float = 1.52
    cover_glass_mm_sigma: float = 0.0
    cover_glass_index_sigma: float = 0.0
    flatness_u_px: tuple[float, ...] = ()
    flatness_v_px: tuple[float, ...] = ()
    flatness_um: tuple[tuple[float, ...], ...] = ()  # [v][u], um


@dataclass(frozen=True)
class Stage:
    """Stage readings ``z_mm`` (capture order) and travel direction ``(a, b, 1)``."""

    z_mm: tuple[float, ...] = tuple(float(4 * k) for k in range(11))
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    repeat_z_mm: tuple[float, ...] = ()  # ptp-dataset/2: readings captured again after the sweep

    @property
    def n_positions(self) -> int:
        return len(self.z_mm)


@dataclass(frozen=True)
class Display:
    """ptp-dataset/2 ``[display]``: measured relative luminance at some levels (monotonic)."""

    levels: tuple[float, ...] = ()
    luminance: tuple[float, ...] = ()


@dataclass(frozen=True)
class DirectionFringes:
    """ptp-dataset/2 ``[fringes.x]`` / ``[fringes.y]``: what differs for one direction (None: as ``[fringes]``)."""

    periods_px: tuple[float, ...] | None = None
    steps: tuple[int, ...] | None = None
    phase_origin_rad: float | None = None
    shift_sign: int | None = None
    gray_bits: int | None = None


@dataclass(frozen=True)
class FringeDesign:
    """What the LCD shows at every position (METHOD.md section 3).

    ``periods_px`` run coarse to fine (fractional in ``ptp-dataset/2``);
    ``steps[j]`` is N for ``periods_px[j]``. ``per_direction`` holds the
    overrides of ``[fringes.x]``/``[fringes.y]``: use :meth:`periods`,
    :meth:`steps_of`, :meth:`origin`, :meth:`sign` and :meth:`bits` for the
    values of one direction.
    """

    directions: tuple[str, ...] = ("x", "y")
    periods_px: tuple[float, ...] = (4096, 512, 64, 16)
    steps: tuple[int, ...] = (4, 4, 4, 8)
    offset: float = 127.5
    amplitude: float = 100.0
    carrier_px_per_mm: tuple[float, float] = (0.0, 0.0)
    gamma: float = 1.0
    phase_origin_rad: float = 0.0
    shift_sign: int = 1
    unwrap: str = "periods"
    gray_bits: int = 0
    gray_inverse: bool = False
    per_direction: tuple[tuple[str, DirectionFringes], ...] = ()

    def carrier(self, direction: str) -> float:
        """Carrier displacement (LCD px per mm of z) for ``direction``."""
        return self.carrier_px_per_mm[0 if direction == "x" else 1]

    def _override(self, direction: str, name: str):
        for d, o in self.per_direction:
            if d == direction and getattr(o, name) is not None:
                return getattr(o, name)
        return getattr(self, name)

    def periods(self, direction: str) -> tuple[float, ...]:
        """Periods (LCD px, coarse to fine) of ``direction``."""
        return self._override(direction, "periods_px")

    def steps_of(self, direction: str) -> tuple[int, ...]:
        """Steps N of every period of ``direction``."""
        return self._override(direction, "steps")

    def origin(self, direction: str) -> float:
        """``phase_origin_rad`` of ``direction``."""
        return float(self._override(direction, "phase_origin_rad"))

    def sign(self, direction: str) -> int:
        """``shift_sign`` of ``direction``."""
        return int(self._override(direction, "shift_sign"))

    def bits(self, direction: str) -> int:
        """Gray-code bits of ``direction`` (0 unless ``unwrap = "gray"``)."""
        return int(self._override(direction, "gray_bits")) if self.unwrap == "gray" else 0

    @property
    def is_plain(self) -> bool:
        """True for a ``ptp-dataset/1`` design: integer periods and steps shared by both
        directions, phase origin 0, shift sign +1, unwrapping by periods (the fast paths)."""
        return (not self.per_direction and self.phase_origin_rad == 0.0 and self.shift_sign == 1
                and self.unwrap == "periods" and all(float(t).is_integer() for t in self.periods_px))

    def frames(self):
        """Yield ``(direction, level, period, step, n_steps)`` of the phase-shifted frames in capture order."""
        for d in self.directions:
            for j, (t, n) in enumerate(zip(self.periods(d), self.steps_of(d))):
                for s in range(n):
                    yield d, j, t, s, n

    def gray_frames(self):
        """Yield ``(direction, bit, inverse)`` of the Gray-code frames (none unless ``unwrap = "gray"``)."""
        for d in self.directions:
            for b in range(self.bits(d)):
                yield d, b, False
                if self.gray_inverse:
                    yield d, b, True

    @property
    def frames_per_position(self) -> int:
        return sum(sum(self.steps_of(d)) for d in self.directions) + sum(1 for _ in self.gray_frames())


@dataclass(frozen=True)
class DecodeSettings:
    """ptp-dataset/2 ``[decode]`` thresholds; None: the engine's default."""

    min_modulation: float | None = None
    border_margin_px: int | None = None
    unwrap_tolerance: float | None = None


@dataclass(frozen=True)
class FrameEntry:
    """One ``[[images.frames]]`` entry: a phase step, a Gray-code bit or a reference frame."""

    file: str
    pos: int = 0
    dir: str | None = None
    period_index: int | None = None
    step: int | None = None
    gray_bit: int | None = None
    inverse: bool = False
    reference: str | None = None

    @property
    def key(self) -> tuple:
        if self.reference is not None:
            return (self.pos, "ref", self.reference)
        if self.gray_bit is not None:
            return (self.pos, "gray", self.dir, self.gray_bit, self.inverse)
        return (self.pos, "phase", self.dir, self.period_index, self.step)


@dataclass(frozen=True)
class Projector:
    """ptp-dataset/2 ``[projector]``: the scanner's own fringe source, fixed to the camera (METHOD.md section 9).

    ``width`` x ``height`` projector pixels: the range of the decoded projector coordinate ``u_p``
    (and ``v_p``). ``fringes`` is its pattern design, as ``[fringes]`` but without a carrier.
    """

    width: int = 1280
    height: int = 800
    fringes: FringeDesign = field(default_factory=lambda: FringeDesign(("x",), (1280.0, 160.0, 20.0), (4, 4, 8)))

    @property
    def design_attrs(self) -> dict:
        """The pattern design a scanner needs to decode ``u_p`` as the calibration did
        (the ``/height`` attributes of ``ptp-lut/1``; direction ``x``)."""
        f = self.fringes
        return {"width": int(self.width), "height": int(self.height),
                "periods_px": [float(t) for t in f.periods("x")], "steps": [int(n) for n in f.steps_of("x")],
                "phase_origin_rad": float(f.origin("x")), "shift_sign": int(f.sign("x")), "unwrap": f.unwrap,
                "offset": float(f.offset), "amplitude": float(f.amplitude), "gamma": float(f.gamma)}


@dataclass(frozen=True)
class HeightSweep:
    """ptp-dataset/2 ``[height]``: the matte plate's heights (same datum as ``[stage] z_mm``) and its frames."""

    z_mm: tuple[float, ...] = ()
    template: str = "h{pos:03d}/{dir}_T{period}_n{step:02d}.png"


def format_period(period) -> int | float:
    """A period as ``{period}`` shows it: its shortest decimal form (``67.5``; ``120`` for ``120.0``)."""
    p = float(period)
    return int(p) if p.is_integer() else p


@dataclass(frozen=True)
class Rig:
    """Everything ``rig.toml`` describes."""

    camera: Camera = field(default_factory=Camera)
    lcd: Lcd = field(default_factory=Lcd)
    stage: Stage = field(default_factory=Stage)
    fringes: FringeDesign = field(default_factory=FringeDesign)
    template: str = DEFAULT_TEMPLATE
    display: Display | None = None
    decode: DecodeSettings = field(default_factory=DecodeSettings)
    gray_template: str | None = None
    white_template: str | None = None
    black_template: str | None = None
    frame_list: tuple[FrameEntry, ...] = ()
    projector: Projector | None = None  # ptp-dataset/2 [projector] (METHOD.md section 9)
    height: HeightSweep | None = None   # ptp-dataset/2 [height]: the plate's sweep

    def height_rig(self) -> "Rig":
        """The height sweep as a rig the decoder reads: the projector in the LCD's place (its
        pixels, pitch 1), the plate's heights as the stage's, no carrier, the ``[height]`` template.

        Raises
        ------
        ConfigError
            The dataset has no ``[projector]`` and ``[height]``.
        """
        if self.projector is None or self.height is None:
            raise ConfigError("the dataset has no height sweep ([projector] and [height], FORMATS.md)")
        return projector_rig(self.camera, self.projector, self.height.z_mm, self.height.template, self.decode)

    def image_name(self, pos: int, direction: str, period, step: int, steps: int,
                   period_index: int | None = None) -> str:
        """Relative path of one phase-shifted image (``[[images.frames]]`` or ``template``)."""
        if period_index is None:
            ps = self.fringes.periods(direction)
            period_index = next((j for j, t in enumerate(ps) if float(t) == float(period)), 0)
        if self.frame_list:
            return self._listed((pos, "phase", direction, period_index, step))
        return self.template.format(pos=pos, dir=direction, period=format_period(period), step=step,
                                    steps=steps, period_index=period_index)

    def gray_name(self, pos: int, direction: str, bit: int, inverse: bool) -> str:
        """Relative path of one Gray-code image."""
        if self.frame_list:
            return self._listed((pos, "gray", direction, bit, bool(inverse)))
        return (self.gray_template or "").format(pos=pos, dir=direction, bit=bit, inverse=int(bool(inverse)))

    def reference_name(self, pos: int, which: str) -> str | None:
        """Relative path of the all-white or all-black frame of ``pos``, or None without one."""
        if self.frame_list:
            for e in self.frame_list:
                if e.key == (pos, "ref", which):
                    return e.file
            return None
        t = self.white_template if which == "white" else self.black_template
        return None if t is None else t.format(pos=pos)

    @property
    def has_references(self) -> bool:
        """Whether the dataset has white and black reference frames."""
        if self.frame_list:
            return any(e.reference == "white" for e in self.frame_list) and \
                any(e.reference == "black" for e in self.frame_list)
        return self.white_template is not None and self.black_template is not None

    def _listed(self, key: tuple) -> str:
        for e in self.frame_list:
            if e.key == key:
                return e.file
        raise KeyError(f"no [[images.frames]] entry for {key}")

    def with_z(self, z_mm) -> "Rig":
        """A copy with other stage positions."""
        return replace(self, stage=replace(self.stage, z_mm=tuple(float(z) for z in z_mm)))


# --------------------------------------------------------------------------
# Loading with validation. Each helper names the key ("section.key") it reads.

class _Section:
    """Reads typed values out of one TOML table and rejects unknown keys."""

    def __init__(self, doc: dict, name: str, source: str, required: bool = True):
        self.source = source
        self.name = name
        if name not in doc:
            if required:
                raise ConfigError(f"{source}: missing section [{name}]")
            self.table = {}
        else:
            self.table = doc[name]
            if not isinstance(self.table, dict):
                raise ConfigError(f"{source}: '{name}' must be a table [{name}], got {_tname(self.table)}")
        self.used: set[str] = set()

    def _key(self, key: str) -> str:
        return f"{self.name}.{key}"

    def get(self, key: str, kind: str, default: Any = ...):
        self.used.add(key)
        if key not in self.table:
            if default is ...:
                raise ConfigError(f"{self.source}: missing key '{self._key(key)}' (expected {kind})")
            return default
        return _convert(self.table[key], kind, f"{self.source}: key '{self._key(key)}'")

    def finish(self) -> None:
        unknown = sorted(set(self.table) - self.used)
        if unknown:
            raise ConfigError(
                f"{self.source}: unknown key {_short_repr(self._key(unknown[0]))}"
                f" (allowed: {', '.join(sorted(self.used))})"
            )


def _tname(v: Any) -> str:
    return {dict: "a table", list: "a list", str: "a string", bool: "a boolean",
            int: "an integer", float: "a float"}.get(type(v), type(v).__name__)


def _short_repr(v: Any, limit: int = 60) -> str:
    """``repr`` cut to ``limit`` characters (and safe for integers too long to print)."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 10**limit:
        return f"{'-' if v < 0 else ''}<integer of about {int(abs(v).bit_length() * 0.30103)} digits>"
    try:
        text = repr(v)
    except ValueError:
        text = f"<{type(v).__name__}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _convert(value: Any, kind: str, where: str):
    def bad(expected: str):
        return ConfigError(f"{where} must be {expected}, got {_tname(value)} {_short_repr(value)}")

    def number(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise bad("a number")
        try:
            f = float(v)
        except OverflowError:
            raise bad("a finite number") from None
        if not math.isfinite(f):
            raise bad("a finite number")
        return f

    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        return int(value)
    if kind == "float":
        return number(value)
    if kind == "str":
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if kind.startswith("list[") and kind.endswith("]"):
        inner = kind[5:-1]
        if not isinstance(value, list):
            raise bad(f"a list of {inner}s")
        out = []
        for i, item in enumerate(value):
            out.append(_convert(item, inner, f"{where}[{i}]"))
        return out
    raise AssertionError(kind)


def validate_template(template: str, source: str = "rig.toml", *, key: str = "images.template",
                      fields: tuple[str, ...] = TEMPLATE_FIELDS,
                      needed: tuple[str, ...] = ("pos", "dir", "period", "step")) -> str:
    """Check an image template: only documented fields with plain format specs.

    Attribute or index access (``{pos.__class__}``, ``{dir[0]}``), conversions
    (``!r``), nested fields and unknown names are refused: the template is user
    text and must never reach into Python objects. In ``needed``, ``"period"``
    is also satisfied by ``{period_index}``.
    """
    where = f"{source}: key '{key}'"
    if any(ord(c) < 32 or ord(c) == 127 for c in template):
        raise ConfigError(f"{where} must not contain control characters (got {_short_repr(template)})")
    try:
        parsed = list(string.Formatter().parse(template))
    except ValueError as exc:
        raise ConfigError(f"{where} is not a valid format string ({exc})") from None
    seen = set()
    for _literal, name, spec, conversion in parsed:
        if name is None:
            continue
        if name not in fields:
            raise ConfigError(
                f"{where}: field '{{{name}}}' is not allowed (only {', '.join(fields)};"
                " no attribute or index access)"
            )
        if conversion:
            raise ConfigError(f"{where}: conversion '!{conversion}' in '{{{name}}}' is not allowed")
        if spec and ("{" in spec or not _SPEC.fullmatch(spec)):
            raise ConfigError(f"{where}: format spec '{spec}' of '{{{name}}}' is not a plain format spec")
        seen.add(name)
    for need in needed:
        if need not in seen and not (need == "period" and "period_index" in seen):
            raise ConfigError(f"{where} must contain '{{{need}}}' so every image has its own name")
    try:
        template.format(pos=0, dir="x", period=16, step=0, steps=4, period_index=0, bit=0, inverse=0)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if template.startswith(("/", "\\")) or ".." in Path(template).parts:
        raise ConfigError(f"{where} must be a relative path inside the dataset folder")
    return template


def _period_list(raw, where: str, v2: bool) -> tuple:
    """``periods_px``: integers in /1; numbers in /2 (integral ones kept as int)."""
    if not v2:
        return tuple(_convert(raw, "list[int]", where))
    vals = _convert(raw, "list[float]", where)
    return tuple(int(v) if float(v).is_integer() and not isinstance(r, float) else float(v)
                 for v, r in zip(vals, raw))


def _check_periods(periods, where: str) -> None:
    if not periods or any(not 2 <= p <= MAX_PERIOD_PX for p in periods):
        raise ConfigError(f"{where} must list periods of 2 to {MAX_PERIOD_PX} px, got {_short_repr(list(periods))}")
    if any(b >= a for a, b in zip(periods, periods[1:])):
        raise ConfigError(f"{where} must decrease strictly (coarse to fine), got {_short_repr(list(periods))}")


def heterodyne_beats(periods) -> dict:
    """The beats of a heterodyne design (FORMATS.md ``unwrap = "heterodyne"``).

    Parameters
    ----------
    periods : sequence of 2 or 3 float
        LCD px, any order.

    Returns
    -------
    dict
        ``periods``: sorted ``T1 < T2 (< T3)``; ``steps``: the cascade as
        ``(name, beat period, period it unwraps)`` from the absolute beat down to
        ``T1``; ``absolute``: the beat whose phase is taken as absolute (``T12``
        for two periods, ``T123`` for three), LCD px.

    Raises
    ------
    ValueError
        Not 2 or 3 distinct periods, or (three) equal beats ``T12 = T23``.
    """
    ts = sorted(float(t) for t in periods)
    if len(ts) not in (2, 3) or len(set(ts)) != len(ts):
        raise ValueError(f"heterodyne unwrapping needs two or three different periods, got {list(periods)}")
    t12 = ts[0] * ts[1] / (ts[1] - ts[0])
    if len(ts) == 2:
        return {"periods": ts, "absolute": t12, "steps": [("T12", t12, ts[0])]}
    t23 = ts[1] * ts[2] / (ts[2] - ts[1])
    if abs(t23 - t12) <= 1e-9 * t12:
        raise ValueError(f"periods {', '.join(f'{t:g}' for t in ts)} px have equal beats T12 = T23 ="
                         f" {t12:g} px: their beat is infinite and unwraps nothing")
    t123 = t12 * t23 / abs(t23 - t12)
    return {"periods": ts, "absolute": t123, "t23": t23,
            "steps": [("T123", t123, t12), ("T12", t12, ts[0])]}


def _heterodyne_order(periods, steps, where: str) -> tuple[tuple, tuple]:
    """Heterodyne periods (any order, checked: :func:`heterodyne_beats`) and their steps, sorted
    longest first like every period list of the engine (so ``{period_index}`` 0 is the longest)."""
    if not periods or any(not 2 <= p <= MAX_PERIOD_PX for p in periods):
        raise ConfigError(f"{where} must list periods of 2 to {MAX_PERIOD_PX} px, got {_short_repr(list(periods))}")
    try:
        heterodyne_beats(periods)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc} (unwrap = \"heterodyne\")") from None
    order = sorted(range(len(periods)), key=lambda j: -float(periods[j]))
    return tuple(periods[j] for j in order), tuple(steps[j] for j in order)


def check_heterodyne_span(rig: "Rig", source: str) -> None:
    """Refuse a heterodyne design whose absolute beat does not exceed the span of ``u + s``."""
    f = rig.fringes
    z = list(rig.stage.z_mm) + list(rig.stage.repeat_z_mm)
    for d in f.directions:
        extent = rig.lcd.width if d == "x" else rig.lcd.height
        shifts = [f.carrier(d) * zz for zz in z]
        lo, hi = min(0.0, min(shifts)) - 0.5, extent - 0.5 + max(0.0, max(shifts))
        beats = heterodyne_beats(f.periods(d))
        if hi - lo >= beats["absolute"]:
            names = ", ".join(f"{format_period(t)}" for t in beats["periods"])
            key = "fringes.periods_px" if not any(dd == d and o.periods_px for dd, o in f.per_direction) \
                else f"fringes.{d}.periods_px"
            raise ConfigError(f"{source}: key '{key}': the heterodyne periods {names} px (direction {d}) beat at"
                              f" {beats['absolute']:.1f} px, which does not cover the span of u + s"
                              f" ({hi - lo:.1f} px: the LCD plus the carrier); choose periods closer together")


def _steps_list(raw, n_periods: int, where: str) -> tuple:
    if isinstance(raw, list):
        steps = _convert(raw, "list[int]", where)
    else:
        steps = [_convert(raw, "int", where)] * n_periods
    if len(steps) != n_periods:
        raise ConfigError(f"{where} has {len(steps)} entries for {n_periods} periods")
    if any(not 3 <= n <= MAX_STEPS for n in steps):
        raise ConfigError(f"{where} must be 3 to {MAX_STEPS} per period, got {_short_repr(steps)}")
    return tuple(steps)


def _check_sign(v: int, where: str) -> int:
    if v not in (1, -1):
        raise ConfigError(f"{where} must be 1 or -1, got {_short_repr(v)}")
    return v


def _check_bits(v: int, where: str) -> int:
    if not 0 <= v <= MAX_GRAY_BITS:
        raise ConfigError(f"{where} must be 0 to {MAX_GRAY_BITS}, got {v}")
    return v


def _nonneg(v: float, where: str) -> float:
    if v < 0:
        raise ConfigError(f"{where} must be >= 0, got {v}")
    return v


def _nonneg_or_none(v: float | None, where: str) -> float | None:
    """``v`` checked >= 0; None (an absent key) stays None."""
    return None if v is None else _nonneg(v, where)


def rig_from_toml(text: str, source: str = "rig.toml") -> Rig:
    """Parse and validate the text of a ``rig.toml`` (``ptp-dataset/1`` or ``/2``).

    Raises
    ------
    ConfigError
        Naming the key and what was expected.
    """
    known = {"format", "camera", "lcd", "stage", "fringes", "images"}
    doc = _toml_document(text, source, (DATASET_FORMAT, DATASET_FORMAT_2),
                         known | {"display", "decode", "projector", "height"})
    v2 = doc["format"] == DATASET_FORMAT_2
    if not v2:
        for key in ("display", "decode", "projector", "height"):
            if key in doc:
                raise ConfigError(f"{source}: unknown key {key!r} in a {DATASET_FORMAT} file"
                                  f" (it is a {DATASET_FORMAT_2} key; set format = \"{DATASET_FORMAT_2}\")")

    camera = _camera_section(doc, source, v2)
    lcd = _lcd_section(doc, source, v2)
    stage = _stage_section(doc, source, v2)
    fringes = _fringes(doc, source, v2)
    display = _display_section(doc, source, v2)
    decode = _decode_section(doc, source, v2)
    rig = _images_section(doc, source, v2, camera, lcd, stage, fringes, display, decode)
    if fringes.unwrap == "heterodyne":
        check_heterodyne_span(rig, source)
    if v2 and ("projector" in doc or "height" in doc):
        if "projector" not in doc or "height" not in doc:
            missing = "projector" if "projector" not in doc else "height"
            raise ConfigError(f"{source}: a height sweep needs both [projector] and [height]; [{missing}] is missing")
        rig = replace(rig, projector=_projector_section(doc, source), height=_height_section(doc, source))
        h_rig = rig.height_rig()
        validate_template(rig.height.template, source, key="height.template",
                          needed=_needed_fields(("pos", "dir", "period", "step"), h_rig.fringes, h_rig.stage))
    return rig


def _projector_section(doc: dict, source: str) -> Projector:
    """``[projector]`` (/2): the projector's size and its pattern design, as ``[fringes]`` without a carrier.

    Unwrapping by periods or heterodyne (a height sweep names no Gray-code frames); direction ``x``
    (what heights need) must be shown.
    """
    table = doc["projector"]
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: 'projector' must be a table [projector], got {_tname(table)}")
    size = {}
    for key in ("width", "height"):
        if key not in table:
            raise ConfigError(f"{source}: missing key 'projector.{key}' (expected int)")
        size[key] = _convert(table[key], "int", f"{source}: key 'projector.{key}'")
        if not 1 <= size[key] <= 100_000:
            raise ConfigError(f"{source}: key 'projector.{key}' must be between 1 and 100000, got {size[key]}")
    if "carrier_px_per_mm" in table:
        raise ConfigError(f"{source}: key 'projector.carrier_px_per_mm' is not allowed (the projector has no carrier)")
    rest = {k: v for k, v in table.items() if k not in ("width", "height")}
    rest.setdefault("directions", ["x"])
    f = _fringes({"projector": rest}, source, True, name="projector")
    if f.unwrap == "gray":
        raise ConfigError(f"{source}: key 'projector.unwrap' = \"gray\" is not supported (a height sweep names"
                          " no Gray-code frames); use \"periods\" or \"heterodyne\"")
    if "x" not in f.directions:
        raise ConfigError(f"{source}: key 'projector.directions' must include \"x\" (heights come from u_p),"
                          f" got {_short_repr(list(f.directions))}")
    for d in f.directions:
        extent = size["width"] if d == "x" else size["height"]
        if f.unwrap == "periods" and float(f.periods(d)[0]) < extent:
            raise ConfigError(f"{source}: key 'projector.periods_px': the coarsest period of direction {d}"
                              f" ({format_period(f.periods(d)[0])} px) must span the projector's {extent} px")
    return Projector(size["width"], size["height"], f)


def _height_section(doc: dict, source: str) -> HeightSweep:
    """``[height]`` (/2): the plate's heights (at least 3, strictly monotonic) and its frames' template."""
    s = _Section(doc, "height", source)
    z = s.get("z_mm", "list[float]")
    template = s.get("template", "str", HeightSweep().template)
    s.finish()
    if len(z) < 3:
        raise ConfigError(f"{source}: key 'height.z_mm' needs at least 3 heights, got {len(z)}")
    if len(z) > MAX_POSITIONS:
        raise ConfigError(f"{source}: key 'height.z_mm' lists {len(z)} heights, at most {MAX_POSITIONS}")
    dz = [b - a for a, b in zip(z, z[1:])]
    if not (all(d > 0 for d in dz) or all(d < 0 for d in dz)):
        i = next(i for i, d in enumerate(dz) if d == 0 or (d > 0) != (dz[0] > 0))
        raise ConfigError(f"{source}: key 'height.z_mm' must be strictly monotonic; at index {i + 1}"
                          f" ({z[i]} -> {z[i + 1]})")
    return HeightSweep(tuple(float(v) for v in z), template)


def projector_rig(camera: Camera, projector: Projector, z_mm, template: str,
                  decode: DecodeSettings = DecodeSettings()) -> Rig:
    """A rig the decoder reads for frames of the scanner's projector (a height sweep or a scan).

    The projector stands in the LCD's place: its pixels (pitch 1, so world X of a decoded position
    is ``u_p`` itself), the heights ``z_mm`` as stage readings (one 0 for a scan), no carrier.
    """
    fringes = replace(projector.fringes, carrier_px_per_mm=(0.0, 0.0))
    return Rig(camera, Lcd(projector.width, projector.height, (1.0, 1.0)),
               Stage(tuple(float(v) for v in z_mm)), fringes, template, None, decode)


SCAN_FORMAT = "ptp-scan/1"


@dataclass(frozen=True)
class ScanSpec:
    """A scan to reconstruct (``scan.toml``, ``ptp-scan/1``): camera, projector design, frames' template.

    ``views``: how many views the folder holds (``{pos}`` in the template: counted from the files
    present, 0, 1, ... while a view's first frame exists; 1 without ``{pos}``).
    """

    camera: Camera
    projector: Projector
    template: str
    views: int = 1

    def rig(self) -> Rig:
        """The rig the decoder reads for this scan's frames (:func:`projector_rig`), one position per view."""
        return projector_rig(self.camera, self.projector, tuple(float(k) for k in range(self.views)), self.template)


def load_scan(folder) -> ScanSpec:
    """Read and validate a scan folder's ``scan.toml`` (FORMATS.md ``ptp-scan/1``).

    Raises
    ------
    ConfigError
        A missing or invalid ``scan.toml`` (naming the key), or a template naming no frame present.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"{folder}: scan folder not found")
    path = folder / "scan.toml"
    source = str(path)
    doc = _toml_document(_read_text(path), source, SCAN_FORMAT, {"format", "camera", "projector", "images"})
    camera = _camera_section(doc, source, True)
    if "projector" not in doc:
        raise ConfigError(f"{source}: missing section [projector]")
    projector = _projector_section(doc, source)
    s = _Section(doc, "images", source)
    template = s.get("template", "str")
    s.finish()
    needed = ("period", "step") + (("dir",) if len(projector.fringes.directions) > 1 else ())
    validate_template(template, source, needed=needed)
    spec = ScanSpec(camera, projector, template)
    if "{pos" not in template:
        return spec
    first = next(iter(spec.rig().fringes.frames()))
    d, j, t, n, big_n = first
    views = 0
    while (folder / template.format(pos=views, dir=d, period=format_period(t), step=n, steps=big_n,
                                    period_index=j)).is_file() and views < MAX_POSITIONS:
        views += 1
    if views == 0:
        raise ConfigError(f"{source}: key 'images.template' names no frame present (first:"
                          f" {template.format(pos=0, dir=d, period=format_period(t), step=n, steps=big_n, period_index=j)})")
    return replace(spec, views=views)


def scan_to_toml(spec: ScanSpec) -> str:
    """The ``scan.toml`` text of ``spec`` (round-trips through :func:`load_scan`)."""
    c = spec.camera
    camera = {"width": c.width, "height": c.height, "bit_depth": c.bit_depth}
    if c.bit_shift:
        camera["bit_shift"] = c.bit_shift
    return tomli_w.dumps({"format": SCAN_FORMAT, "camera": camera, "projector": _projector_table(spec.projector),
                          "images": {"template": spec.template}})


def _projector_table(p: Projector) -> dict:
    """``[projector]`` of ``rig.toml`` or ``scan.toml``: size and design (keys at their defaults left out)."""
    f = p.fringes
    t: dict = {"width": p.width, "height": p.height, "directions": list(f.directions),
               "periods_px": [float(v) for v in f.periods_px], "steps": list(f.steps),
               "offset": float(f.offset), "amplitude": float(f.amplitude), "gamma": float(f.gamma)}
    if f.phase_origin_rad != 0.0:
        t["phase_origin_rad"] = float(f.phase_origin_rad)
    if f.shift_sign != 1:
        t["shift_sign"] = int(f.shift_sign)
    if f.unwrap != "periods":
        t["unwrap"] = f.unwrap
    for dname, o in f.per_direction:
        sub = {}
        if o.periods_px is not None:
            sub["periods_px"] = [float(v) for v in o.periods_px]
        if o.steps is not None:
            sub["steps"] = list(o.steps)
        for key in ("phase_origin_rad", "shift_sign"):
            if getattr(o, key) is not None:
                sub[key] = getattr(o, key)
        if sub:
            t[dname] = sub
    return t


def _camera_section(doc: dict, source: str, v2: bool) -> Camera:
    """``[camera]``: size 1..100000 px, bit depth 8..16, bit_shift within the stored bits (/2)."""
    s = _Section(doc, "camera", source)
    camera = Camera(s.get("width", "int"), s.get("height", "int"), s.get("bit_depth", "int", 8),
                    s.get("bit_shift", "int", 0) if v2 else 0)
    s.finish()
    for key, v in (("width", camera.width), ("height", camera.height)):
        if not 1 <= v <= 100_000:
            raise ConfigError(f"{source}: key 'camera.{key}' must be between 1 and 100000, got {v}")
    if not 8 <= camera.bit_depth <= 16:
        raise ConfigError(f"{source}: key 'camera.bit_depth' must be 8 to 16, got {camera.bit_depth}")
    stored_bits = 8 if camera.bit_depth == 8 else 16
    if not 0 <= camera.bit_shift <= stored_bits - camera.bit_depth:
        raise ConfigError(f"{source}: key 'camera.bit_shift' must be 0 to {stored_bits - camera.bit_depth}"
                          f" for a {camera.bit_depth}-bit camera, got {camera.bit_shift}")
    return camera


def _lcd_section(doc: dict, source: str, v2: bool) -> Lcd:
    """``[lcd]``: size, pitch (mm), and for /2 the cover glass, its tolerances and the flatness grid."""
    s = _Section(doc, "lcd", source)
    lcd_w, lcd_h = s.get("width", "int"), s.get("height", "int")
    pitch = s.get("pitch_mm", "list[float]")
    extra = {}
    if v2:
        extra = dict(
            cover_glass_mm=_nonneg_or_none(s.get("cover_glass_mm", "float", None), f"{source}: key 'lcd.cover_glass_mm'"),
            cover_glass_index=s.get("cover_glass_index", "float", 1.52),
            cover_glass_mm_sigma=_nonneg(s.get("cover_glass_mm_sigma", "float", 0.0),
                                         f"{source}: key 'lcd.cover_glass_mm_sigma'"),
            cover_glass_index_sigma=_nonneg(s.get("cover_glass_index_sigma", "float", 0.0),
                                            f"{source}: key 'lcd.cover_glass_index_sigma'"),
            flatness_u_px=tuple(s.get("flatness_u_px", "list[float]", [])),
            flatness_v_px=tuple(s.get("flatness_v_px", "list[float]", [])),
        )
        rows = s.table.get("flatness_um", [])
        s.used.add("flatness_um")
        if not isinstance(rows, list):
            raise ConfigError(f"{source}: key 'lcd.flatness_um' must be a list of rows, got {_tname(rows)}")
        extra["flatness_um"] = tuple(tuple(_convert(r, "list[float]", f"{source}: key 'lcd.flatness_um[{i}]'"))
                                     for i, r in enumerate(rows))
    s.finish()
    if len(pitch) != 2 or min(pitch) <= 0:
        raise ConfigError(f"{source}: key 'lcd.pitch_mm' must be two positive numbers [x, y],"
                          f" got {_short_repr(pitch)}")
    for key, v in (("width", lcd_w), ("height", lcd_h)):
        if not 1 <= v <= 1_000_000:
            raise ConfigError(f"{source}: key 'lcd.{key}' must be between 1 and 1000000, got {_short_repr(v)}")
    if v2:
        if not 1.0 <= extra["cover_glass_index"] <= 3.0:
            raise ConfigError(f"{source}: key 'lcd.cover_glass_index' must be 1 to 3, got {extra['cover_glass_index']}")
        fu, fv, fz = extra["flatness_u_px"], extra["flatness_v_px"], extra["flatness_um"]
        if fu or fv or fz:
            for key, grid in (("flatness_u_px", fu), ("flatness_v_px", fv)):
                if len(grid) < 2 or any(b <= a for a, b in zip(grid, grid[1:])):
                    raise ConfigError(f"{source}: key 'lcd.{key}' must list at least 2 increasing LCD coordinates,"
                                      f" got {_short_repr(list(grid))}")
            if len(fz) != len(fv) or any(len(r) != len(fu) for r in fz):
                raise ConfigError(f"{source}: key 'lcd.flatness_um' must have {len(fv)} rows of {len(fu)} values"
                                  " ([v][u], one per flatness_v_px and flatness_u_px)")
    lcd = Lcd(lcd_w, lcd_h, (pitch[0], pitch[1]), **extra)
    return lcd


def _stage_section(doc: dict, source: str, v2: bool) -> Stage:
    """``[stage]``: readings strictly monotonic (mm), travel direction ``[a, b, 1]``, repeat readings (/2)."""
    s = _Section(doc, "stage", source)
    z = s.get("z_mm", "list[float]")
    direction = s.get("direction", "list[float]", [0.0, 0.0, 1.0])
    repeat = s.get("repeat_z_mm", "list[float]", []) if v2 else []
    s.finish()
    min_positions = 1 if v2 else 2
    if len(z) < min_positions:
        raise ConfigError(f"{source}: key 'stage.z_mm' needs at least {min_positions} position"
                          f"{'s' if min_positions > 1 else ''}, got {len(z)}")
    if len(z) + len(repeat) > MAX_POSITIONS:
        raise ConfigError(f"{source}: key 'stage.z_mm' lists {len(z)} positions, at most {MAX_POSITIONS}")
    dz = [b - a for a, b in zip(z, z[1:])]
    if dz and not (all(d > 0 for d in dz) or all(d < 0 for d in dz)):
        i = next(i for i, d in enumerate(dz) if d == 0 or (d > 0) != (dz[0] > 0))
        what = "a duplicate position" if dz[i] == 0 else "a change of direction"
        raise ConfigError(
            f"{source}: key 'stage.z_mm' must be strictly monotonic; {what} at index {i + 1}"
            f" ({z[i]} -> {z[i + 1]})"
        )
    if len(direction) != 3 or direction[2] != 1.0:
        raise ConfigError(f"{source}: key 'stage.direction' must be [a, b, 1.0], got {_short_repr(direction)}")
    stage = Stage(tuple(z), (direction[0], direction[1], 1.0), tuple(repeat))
    return stage


def _display_section(doc: dict, source: str, v2: bool):
    """``[display]`` (/2): a measured response, levels strictly increasing in 0..255 and luminance monotonic; or None."""
    display = None
    if v2 and "display" in doc:
        s = _Section(doc, "display", source)
        levels = s.get("levels", "list[float]")
        lum = s.get("luminance", "list[float]")
        s.finish()
        if len(levels) < 2 or len(levels) != len(lum):
            raise ConfigError(f"{source}: keys 'display.levels' and 'display.luminance' must have the same"
                              f" length (at least 2), got {len(levels)} and {len(lum)}")
        if any(b <= a for a, b in zip(levels, levels[1:])) or not 0 <= levels[0] or levels[-1] > 255:
            raise ConfigError(f"{source}: key 'display.levels' must increase strictly within 0..255,"
                              f" got {_short_repr(levels)}")
        if any(b < a for a, b in zip(lum, lum[1:])) or lum[-1] <= lum[0]:
            raise ConfigError(f"{source}: key 'display.luminance' must be monotonic (increasing),"
                              f" got {_short_repr(lum)}")
        display = Display(tuple(levels), tuple(lum))
    return display


def _decode_section(doc: dict, source: str, v2: bool) -> DecodeSettings:
    """``[decode]`` (/2): thresholds, each None where the engine's default applies."""
    decode = DecodeSettings()
    if v2 and "decode" in doc:
        s = _Section(doc, "decode", source)
        decode = DecodeSettings(s.get("min_modulation", "float", None), s.get("border_margin_px", "int", None),
                                s.get("unwrap_tolerance", "float", None))
        s.finish()
        if decode.min_modulation is not None and not 0 <= decode.min_modulation < 1:
            raise ConfigError(f"{source}: key 'decode.min_modulation' must be 0 to 1 (a fraction of full scale),"
                              f" got {decode.min_modulation}")
        if decode.border_margin_px is not None and not 0 <= decode.border_margin_px <= 1000:
            raise ConfigError(f"{source}: key 'decode.border_margin_px' must be 0 to 1000, got {decode.border_margin_px}")
        if decode.unwrap_tolerance is not None and not 0 < decode.unwrap_tolerance <= 0.5:
            raise ConfigError(f"{source}: key 'decode.unwrap_tolerance' must be above 0 and at most 0.5 (periods),"
                              f" got {decode.unwrap_tolerance}")
    return decode


def _needed_fields(needed: tuple[str, ...], fringes, stage: Stage) -> tuple[str, ...]:
    """A template's required fields, less ``dir`` with one direction and ``pos`` with one position
    (repeats included): the names are unique without them (FORMATS.md, ptp-dataset/2)."""
    drop = set()
    if len(fringes.directions) == 1:
        drop.add("dir")
    if stage.n_positions + len(stage.repeat_z_mm) == 1:
        drop.add("pos")
    return tuple(n for n in needed if n not in drop)


def _images_section(doc: dict, source: str, v2: bool, camera: Camera, lcd: Lcd, stage: Stage, fringes,
                    display, decode: DecodeSettings) -> Rig:
    """``[images]``: the templates (or, /2, the frames named one by one), checked against the design; the whole rig."""
    s = _Section(doc, "images", source, required=False)
    template = s.get("template", "str", DEFAULT_TEMPLATE)
    gray_t = white_t = black_t = None
    frames_raw = []
    if v2:
        gray_t = s.get("gray_template", "str", None)
        white_t = s.get("white_template", "str", None)
        black_t = s.get("black_template", "str", None)
        frames_raw = s.table.get("frames", [])
        s.used.add("frames")
    s.finish()
    rig = Rig(camera, lcd, stage, fringes, template, display, decode, gray_t, white_t, black_t)
    if v2 and frames_raw:
        return replace(rig, frame_list=_frame_list(frames_raw, rig, source))
    validate_template(template, source, needed=_needed_fields(("pos", "dir", "period", "step"), fringes, stage))
    for d in fringes.directions:
        for j, t in enumerate(fringes.periods(d)):
            try:
                template.format(pos=0, dir=d, period=format_period(t), step=0, steps=3, period_index=j)
            except (ValueError, TypeError) as exc:
                raise ConfigError(f"{source}: key 'images.template' cannot name period {format_period(t)} px"
                                  f" ({exc}); use {{period}} without an integer format spec, or {{period_index}}")\
                    from None
    if fringes.unwrap == "gray":
        if gray_t is None:
            raise ConfigError(f"{source}: key 'images.gray_template' is needed with fringes.unwrap = \"gray\""
                              " (or name the frames in [[images.frames]])")
        needed = _needed_fields(("pos", "dir", "bit") + (("inverse",) if fringes.gray_inverse else ()), fringes, stage)
        validate_template(gray_t, source, key="images.gray_template", fields=GRAY_TEMPLATE_FIELDS, needed=needed)
    elif gray_t is not None:
        raise ConfigError(f"{source}: key 'images.gray_template' is given but fringes.unwrap is not \"gray\"")
    if (white_t is None) != (black_t is None):
        raise ConfigError(f"{source}: keys 'images.white_template' and 'images.black_template' go together")
    for key, t in (("images.white_template", white_t), ("images.black_template", black_t)):
        if t is not None:
            validate_template(t, source, key=key, fields=REFERENCE_TEMPLATE_FIELDS,
                              needed=_needed_fields(("pos",), fringes, stage))
    return rig


def _fringes(doc: dict, source: str, v2: bool, name: str = "fringes") -> FringeDesign:
    """``[fringes]`` (or ``[projector]``'s fringe keys, ``name``): the design, checked; errors name ``name.key``."""
    s = _Section(doc, name, source)
    directions = s.get("directions", "list[str]", ["x", "y"])
    s.used.add("periods_px")
    if "periods_px" not in s.table:
        raise ConfigError(f"{source}: missing key '{name}.periods_px' (expected list[{'float' if v2 else 'int'}])")
    periods = _period_list(s.table["periods_px"], f"{source}: key '{name}.periods_px'", v2)
    s.used.add("steps")
    steps = _steps_list(s.table.get("steps", 4), len(periods), f"{source}: key '{name}.steps'")
    offset = s.get("offset", "float", 127.5)
    amplitude = s.get("amplitude", "float", 100.0)
    carrier = s.get("carrier_px_per_mm", "list[float]", [0.0, 0.0])
    gamma = s.get("gamma", "float", 1.0)
    extra: dict = {}
    per_direction = []
    if v2:
        extra["phase_origin_rad"] = s.get("phase_origin_rad", "float", 0.0)
        extra["shift_sign"] = _check_sign(s.get("shift_sign", "int", 1), f"{source}: key '{name}.shift_sign'")
        unwrap = s.get("unwrap", "str", "periods")
        if unwrap not in ("periods", "gray", "heterodyne"):
            raise ConfigError(f"{source}: key '{name}.unwrap' must be \"periods\", \"gray\" or \"heterodyne\","
                              f" got {_short_repr(unwrap)}")
        extra["unwrap"] = unwrap
        extra["gray_bits"] = _check_bits(s.get("gray_bits", "int", 0), f"{source}: key '{name}.gray_bits'")
        inv = s.table.get("gray_inverse", False)
        s.used.add("gray_inverse")
        if not isinstance(inv, bool):
            raise ConfigError(f"{source}: key '{name}.gray_inverse' must be true or false, got {_short_repr(inv)}")
        extra["gray_inverse"] = inv
        for d in ("x", "y"):
            if d not in s.table:
                continue
            s.used.add(d)
            sub = _Section(s.table, d, source)
            sub.name = f"{name}.{d}"
            o_periods = None
            if "periods_px" in sub.table:
                sub.used.add("periods_px")
                o_periods = _period_list(sub.table["periods_px"], f"{source}: key '{name}.{d}.periods_px'", True)
                if unwrap != "heterodyne":
                    _check_periods(o_periods, f"{source}: key '{name}.{d}.periods_px'")
            o_steps = None
            if "steps" in sub.table:
                sub.used.add("steps")
                o_steps = _steps_list(sub.table["steps"], len(o_periods or periods), f"{source}: key '{name}.{d}.steps'")
            elif o_periods is not None and len(o_periods) != len(steps):
                if isinstance(s.table.get("steps", 4), list):
                    raise ConfigError(f"{source}: key '{name}.{d}.periods_px' lists {len(o_periods)} periods;"
                                      f" give '{name}.{d}.steps' too ({name}.steps has {len(steps)})")
                o_steps = (steps[0],) * len(o_periods)
            origin = sub.get("phase_origin_rad", "float", None)
            sign = sub.get("shift_sign", "int", None)
            if sign is not None:
                _check_sign(sign, f"{source}: key '{name}.{d}.shift_sign'")
            bits = sub.get("gray_bits", "int", None)
            if bits is not None:
                _check_bits(bits, f"{source}: key '{name}.{d}.gray_bits'")
            sub.finish()
            if unwrap == "heterodyne" and o_periods is not None:
                o_periods, o_steps = _heterodyne_order(o_periods, o_steps or (steps[0],) * len(o_periods),
                                                       f"{source}: key '{name}.{d}.periods_px'")
            o = DirectionFringes(o_periods, o_steps, origin, sign, bits)
            if o != DirectionFringes():
                per_direction.append((d, o))
    s.finish()
    if not directions or len(set(directions)) != len(directions) or any(d not in ("x", "y") for d in directions):
        raise ConfigError(f"{source}: key '{name}.directions' must list 'x' and/or 'y' once each,"
                          f" got {_short_repr(directions)}")
    if extra.get("unwrap") == "heterodyne":
        order = sorted(range(len(periods)), key=lambda j: -float(periods[j]))
        periods, steps = _heterodyne_order(periods, steps, f"{source}: key '{name}.periods_px'")
        # a [fringes.x/y] steps list without its own periods follows the shared periods' order
        per_direction = [(d, o if o.periods_px is not None or o.steps is None else
                          replace(o, steps=tuple(o.steps[j] for j in order))) for d, o in per_direction]
    else:
        _check_periods(periods, f"{source}: key '{name}.periods_px'")
    if len(carrier) != 2:
        raise ConfigError(f"{source}: key '{name}.carrier_px_per_mm' must be [x, y], got {_short_repr(carrier)}")
    if amplitude <= 0 or offset - amplitude < -0.5 or offset + amplitude > 255.5:
        raise ConfigError(
            f"{source}: keys '{name}.offset' ± '{name}.amplitude' must stay within 0..255"
            f" with amplitude > 0, got {offset} ± {amplitude}"
        )
    if gamma <= 0:
        raise ConfigError(f"{source}: key '{name}.gamma' must be positive, got {gamma}")
    f = FringeDesign(tuple(directions), periods, steps, offset, amplitude, (carrier[0], carrier[1]), gamma,
                     **extra, per_direction=tuple(per_direction))
    if f.unwrap == "gray":
        for d in f.directions:
            if f.bits(d) < 1:
                raise ConfigError(f"{source}: key '{name}.gray_bits' must be at least 1 with unwrap = \"gray\""
                                  f" (direction {d})")
    return f


_FRAME_KEYS = {"pos", "dir", "period_index", "step", "gray_bit", "inverse", "reference", "file"}


def _frame_list(raw, rig: Rig, source: str) -> tuple[FrameEntry, ...]:
    """``[[images.frames]]``: every entry valid, every frame the design needs named exactly once."""
    if not isinstance(raw, list) or not all(isinstance(e, dict) for e in raw):
        raise ConfigError(f"{source}: key 'images.frames' must be an array of tables [[images.frames]]")
    f = rig.fringes
    k_total = rig.stage.n_positions
    out = []
    seen: dict = {}
    for i, e in enumerate(raw):
        where = f"{source}: [[images.frames]] entry {i + 1}"
        unknown = sorted(set(e) - _FRAME_KEYS)
        if unknown:
            raise ConfigError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(_FRAME_KEYS))})")

        def get(key, kind, default=...):
            if key not in e:
                if default is ...:
                    raise ConfigError(f"{where}: missing key {key!r}")
                return default
            if kind == "bool":
                if not isinstance(e[key], bool):
                    raise ConfigError(f"{where}: key {key!r} must be true or false, got {_short_repr(e[key])}")
                return e[key]
            return _convert(e[key], kind, f"{where}: key {key!r}")

        file = get("file", "str")
        try:
            validate_template(file, source, key=f"images.frames[{i}].file", fields=(), needed=())
        except ConfigError as exc:
            raise ConfigError(str(exc)) from None
        pos = get("pos", "int", 0)
        if not 0 <= pos < k_total:
            raise ConfigError(f"{where}: key 'pos' must be 0 to {k_total - 1}, got {pos}")
        ref = get("reference", "str", None)
        if ref is not None:
            if ref not in ("white", "black"):
                raise ConfigError(f"{where}: key 'reference' must be \"white\" or \"black\", got {_short_repr(ref)}")
            extra = sorted(set(e) & {"dir", "period_index", "step", "gray_bit", "inverse"})
            if extra:
                raise ConfigError(f"{where}: a reference frame takes no key {extra[0]!r}")
            entry = FrameEntry(file, pos, reference=ref)
        else:
            d = get("dir", "str", None)
            if d is None and len(f.directions) == 1:
                d = f.directions[0]
            if d not in f.directions:
                raise ConfigError(f"{where}: key 'dir' must be one of {list(f.directions)}, got {_short_repr(d)}")
            if "gray_bit" in e:
                if f.unwrap != "gray":
                    raise ConfigError(f"{where}: a Gray-code frame, but fringes.unwrap is not \"gray\"")
                bit = get("gray_bit", "int")
                if not 0 <= bit < f.bits(d):
                    raise ConfigError(f"{where}: key 'gray_bit' must be 0 to {f.bits(d) - 1}, got {bit}")
                inv = get("inverse", "bool", False)
                if inv and not f.gray_inverse:
                    raise ConfigError(f"{where}: an inverse Gray-code frame, but fringes.gray_inverse is false")
                if "period_index" in e or "step" in e:
                    raise ConfigError(f"{where}: a Gray-code frame takes no 'period_index' or 'step'")
                entry = FrameEntry(file, pos, d, gray_bit=bit, inverse=inv)
            else:
                j = get("period_index", "int")
                n_levels = len(f.periods(d))
                if not 0 <= j < n_levels:
                    raise ConfigError(f"{where}: key 'period_index' must be 0 to {n_levels - 1}, got {j}")
                n = f.steps_of(d)[j]
                step = get("step", "int")
                if not 0 <= step < n:
                    raise ConfigError(f"{where}: key 'step' must be 0 to {n - 1}, got {step}")
                if "inverse" in e:
                    raise ConfigError(f"{where}: key 'inverse' belongs to Gray-code frames")
                entry = FrameEntry(file, pos, d, period_index=j, step=step)
        if entry.key in seen:
            raise ConfigError(f"{where}: the same frame as entry {seen[entry.key] + 1}")
        seen[entry.key] = i
        out.append(entry)
    rig = replace(rig, frame_list=tuple(out))
    for k in range(k_total):
        for d, j, _t, s_, _n in f.frames():
            if (k, "phase", d, j, s_) not in seen:
                raise ConfigError(f"{source}: [[images.frames]] names no frame for pos = {k}, dir = {d!r},"
                                  f" period_index = {j}, step = {s_}")
        for d, b, inv in f.gray_frames():
            if (k, "gray", d, b, inv) not in seen:
                raise ConfigError(f"{source}: [[images.frames]] names no Gray-code frame for pos = {k},"
                                  f" dir = {d!r}, gray_bit = {b}" + (", inverse = true" if inv else ""))
        refs = {r for r in ("white", "black") if (k, "ref", r) in seen}
        if len(refs) == 1:
            raise ConfigError(f"{source}: [[images.frames]] has a {next(iter(refs))} reference frame for"
                              f" pos = {k} but not its {'black' if 'white' in refs else 'white'} one")
    return tuple(out)


def load_rig(path: str | Path) -> Rig:
    """Read and validate a ``rig.toml`` file (or the one inside a dataset folder)."""
    path = Path(path)
    if path.is_dir():
        path = path / "rig.toml"
    return rig_from_toml(_read_text(path), str(path))


def _read_text(path: Path) -> str:
    """A UTF-8 configuration file's text; a missing or unreadable file is a ConfigError naming it.

    A leading byte-order mark (as Windows Notepad writes) is dropped.
    """
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None


def _toml_document(text: str, source: str, expected_format, known: set[str]) -> dict:
    """Parse a versioned TOML file: valid TOML, ``format = expected_format`` (or one of a tuple of
    them), no unknown top-level key."""
    try:
        doc = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, ValueError) as exc:  # ValueError: e.g. an integer too long to read
        raise ConfigError(f"{source}: not valid TOML ({exc})") from None
    fmt = doc.get("format")
    allowed = (expected_format,) if isinstance(expected_format, str) else tuple(expected_format)
    if fmt not in allowed:
        want = " or ".join(f'"{a}"' for a in allowed)
        if fmt is None:
            raise ConfigError(f"{source}: missing key 'format' (expected {want})")
        raise ConfigError(f"{source}: key 'format' is {_short_repr(fmt)}, expected {want}")
    for key in doc:
        if key not in known:
            raise ConfigError(f"{source}: unknown key {_short_repr(key)} (allowed: {', '.join(sorted(known))})")
    return doc


def rig_to_toml(rig: Rig) -> str:
    """The ``rig.toml`` text of ``rig`` (round-trips through :func:`rig_from_toml`).

    ``ptp-dataset/1`` unless the rig uses a ``/2`` key (only those that differ
    from their defaults are written).
    """
    f = rig.fringes
    v2: dict = {}  # section -> {key: value} of the /2 keys in use

    def put(section: str, key: str, value) -> None:
        v2.setdefault(section, {})[key] = value

    c, lcd, st = rig.camera, rig.lcd, rig.stage
    if c.bit_shift:
        put("camera", "bit_shift", c.bit_shift)
    d = Lcd()
    if lcd.cover_glass_mm is not None:  # 0 too: "no glass" declared is not a bare panel assumed
        put("lcd", "cover_glass_mm", float(lcd.cover_glass_mm))
    for key in ("cover_glass_index", "cover_glass_mm_sigma", "cover_glass_index_sigma"):
        if getattr(lcd, key) != getattr(d, key):
            put("lcd", key, float(getattr(lcd, key)))
    if lcd.flatness_um:
        put("lcd", "flatness_u_px", [float(x) for x in lcd.flatness_u_px])
        put("lcd", "flatness_v_px", [float(x) for x in lcd.flatness_v_px])
        put("lcd", "flatness_um", [[float(x) for x in r] for r in lcd.flatness_um])
    if st.repeat_z_mm:
        put("stage", "repeat_z_mm", [float(z) for z in st.repeat_z_mm])
    if any(isinstance(t, float) for t in f.periods_px):
        put("fringes", "periods_px", [format_period(t) if isinstance(t, int) else float(t) for t in f.periods_px])
    if f.phase_origin_rad != 0.0:
        put("fringes", "phase_origin_rad", float(f.phase_origin_rad))
    if f.shift_sign != 1:
        put("fringes", "shift_sign", int(f.shift_sign))
    if f.unwrap != "periods":
        put("fringes", "unwrap", f.unwrap)
    if f.gray_bits:
        put("fringes", "gray_bits", int(f.gray_bits))
    if f.gray_inverse:
        put("fringes", "gray_inverse", True)
    for dname, o in f.per_direction:
        sub = {}
        if o.periods_px is not None:
            sub["periods_px"] = [t if isinstance(t, int) else float(t) for t in o.periods_px]
        if o.steps is not None:
            sub["steps"] = list(o.steps)
        for key in ("phase_origin_rad", "shift_sign", "gray_bits"):
            if getattr(o, key) is not None:
                sub[key] = getattr(o, key)
        if sub:
            put("fringes", dname, sub)
    if rig.display is not None:
        v2["display"] = {"levels": [float(x) for x in rig.display.levels],
                         "luminance": [float(x) for x in rig.display.luminance]}
    dec = {k: v for k, v in (("min_modulation", rig.decode.min_modulation),
                             ("border_margin_px", rig.decode.border_margin_px),
                             ("unwrap_tolerance", rig.decode.unwrap_tolerance)) if v is not None}
    if dec:
        v2["decode"] = dec
    for key in ("gray_template", "white_template", "black_template"):
        if getattr(rig, key) is not None:
            put("images", key, getattr(rig, key))
    if rig.frame_list:
        frames = []
        for e in rig.frame_list:
            t = {"pos": e.pos}
            if e.reference is not None:
                t["reference"] = e.reference
            elif e.gray_bit is not None:
                t.update({"dir": e.dir, "gray_bit": e.gray_bit, "inverse": e.inverse})
            else:
                t.update({"dir": e.dir, "period_index": e.period_index, "step": e.step})
            t["file"] = e.file
            frames.append(t)
        put("images", "frames", frames)
    if st.n_positions < 2:
        v2.setdefault("stage", {})
    if rig.projector is not None and rig.height is not None:
        v2["projector"] = _projector_table(rig.projector)
        v2["height"] = {"z_mm": [float(z) for z in rig.height.z_mm], "template": rig.height.template}

    doc = {
        "format": DATASET_FORMAT_2 if v2 else DATASET_FORMAT,
        "camera": {"width": c.width, "height": c.height, "bit_depth": c.bit_depth},
        "lcd": {"width": lcd.width, "height": lcd.height, "pitch_mm": list(lcd.pitch_mm)},
        "stage": {"z_mm": [float(z) for z in st.z_mm], "direction": list(st.direction)},
        "fringes": {
            "directions": list(f.directions),
            "periods_px": list(f.periods_px),
            "steps": list(f.steps),
            "offset": f.offset,
            "amplitude": f.amplitude,
            "carrier_px_per_mm": list(f.carrier_px_per_mm),
            "gamma": f.gamma,
        },
        "images": {"template": rig.template},
    }
    for section, keys in v2.items():
        doc.setdefault(section, {}).update(keys)
    # Sub-tables after plain keys (TOML needs [fringes.y] after the keys of [fringes]).
    fr = doc["fringes"]
    doc["fringes"] = {k: v for k, v in fr.items() if not isinstance(v, dict)} | \
        {k: v for k, v in fr.items() if isinstance(v, dict)}
    return tomli_w.dumps(doc)


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write ``rig.toml`` atomically."""
    write_text_atomic(path, rig_to_toml(rig))
