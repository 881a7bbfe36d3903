"""The rig: camera, LCD, stage, fringe design and image layout.

These dataclasses are the in-memory form of a ``ptp-dataset/1`` ``rig.toml``
(FORMATS.md). All validation happens here, at load time: once a :class:`Rig`
exists, the numerics downstream can trust it.
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
    "Camera",
    "Lcd",
    "Stage",
    "FringeDesign",
    "Rig",
    "load_rig",
    "rig_from_toml",
    "rig_to_toml",
    "save_rig",
    "validate_template",
]

DATASET_FORMAT = "ptp-dataset/1"
TEMPLATE_FIELDS = ("pos", "dir", "period", "step", "steps")
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


@dataclass(frozen=True)
class Stage:
    """Stage readings ``z_mm`` (capture order) and travel direction ``(a, b, 1)``."""

    z_mm: tuple[float, ...] = tuple(float(4 * k) for k in range(11))
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)

    @property
    def n_positions(self) -> int:
        return len(self.z_mm)


@dataclass(frozen=True)
class FringeDesign:
    """What the LCD shows at every position (METHOD.md section 3).

    ``periods_px`` run coarse to fine; ``steps[j]`` is N for ``periods_px[j]``.
    """

    directions: tuple[str, ...] = ("x", "y")
    periods_px: tuple[int, ...] = (4096, 512, 64, 16)
    steps: tuple[int, ...] = (4, 4, 4, 8)
    offset: float = 127.5
    amplitude: float = 100.0
    carrier_px_per_mm: tuple[float, float] = (0.0, 0.0)
    gamma: float = 1.0

    def carrier(self, direction: str) -> float:
        """Carrier displacement (LCD px per mm of z) for ``direction``."""
        return self.carrier_px_per_mm[0 if direction == "x" else 1]

    def frames(self):
        """Yield ``(direction, level, period, step, n_steps)`` in capture order."""
        for d in self.directions:
            for j, (t, n) in enumerate(zip(self.periods_px, self.steps)):
                for s in range(n):
                    yield d, j, t, s, n

    @property
    def frames_per_position(self) -> int:
        return len(self.directions) * sum(self.steps)


@dataclass(frozen=True)
class Rig:
    """Everything ``rig.toml`` describes."""

    camera: Camera = field(default_factory=Camera)
    lcd: Lcd = field(default_factory=Lcd)
    stage: Stage = field(default_factory=Stage)
    fringes: FringeDesign = field(default_factory=FringeDesign)
    template: str = DEFAULT_TEMPLATE

    def image_name(self, pos: int, direction: str, period: int, step: int, steps: int) -> str:
        """Relative path of one image, from ``template``."""
        return self.template.format(pos=pos, dir=direction, period=period, step=step, steps=steps)

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


def validate_template(template: str, source: str = "rig.toml") -> str:
    """Check ``images.template``: only documented fields with plain format specs.

    Attribute or index access (``{pos.__class__}``, ``{dir[0]}``), conversions
    (``!r``), nested fields and unknown names are refused: the template is user
    text and must never reach into Python objects.
    """
    where = f"{source}: key 'images.template'"
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
        if name not in TEMPLATE_FIELDS:
            raise ConfigError(
                f"{where}: field '{{{name}}}' is not allowed (only {', '.join(TEMPLATE_FIELDS)};"
                " no attribute or index access)"
            )
        if conversion:
            raise ConfigError(f"{where}: conversion '!{conversion}' in '{{{name}}}' is not allowed")
        if spec and ("{" in spec or not _SPEC.fullmatch(spec)):
            raise ConfigError(f"{where}: format spec '{spec}' of '{{{name}}}' is not a plain format spec")
        seen.add(name)
    for needed in ("pos", "dir", "period", "step"):
        if needed not in seen:
            raise ConfigError(f"{where} must contain '{{{needed}}}' so every image has its own name")
    try:
        template.format(pos=0, dir="x", period=16, step=0, steps=4)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if template.startswith(("/", "\\")) or ".." in Path(template).parts:
        raise ConfigError(f"{where} must be a relative path inside the dataset folder")
    return template


def rig_from_toml(text: str, source: str = "rig.toml") -> Rig:
    """Parse and validate the text of a ``rig.toml``.

    Raises
    ------
    ConfigError
        Naming the key and what was expected.
    """
    doc = _toml_document(text, source, DATASET_FORMAT, {"format", "camera", "lcd", "stage", "fringes", "images"})

    s = _Section(doc, "camera", source)
    camera = Camera(s.get("width", "int"), s.get("height", "int"), s.get("bit_depth", "int", 8))
    s.finish()
    for key, v in (("width", camera.width), ("height", camera.height)):
        if not 1 <= v <= 100_000:
            raise ConfigError(f"{source}: key 'camera.{key}' must be between 1 and 100000, got {v}")
    if not 8 <= camera.bit_depth <= 16:
        raise ConfigError(f"{source}: key 'camera.bit_depth' must be 8 to 16, got {camera.bit_depth}")

    s = _Section(doc, "lcd", source)
    lcd_w, lcd_h = s.get("width", "int"), s.get("height", "int")
    pitch = s.get("pitch_mm", "list[float]")
    s.finish()
    if len(pitch) != 2 or min(pitch) <= 0:
        raise ConfigError(f"{source}: key 'lcd.pitch_mm' must be two positive numbers [x, y],"
                          f" got {_short_repr(pitch)}")
    for key, v in (("width", lcd_w), ("height", lcd_h)):
        if not 1 <= v <= 1_000_000:
            raise ConfigError(f"{source}: key 'lcd.{key}' must be between 1 and 1000000, got {_short_repr(v)}")
    lcd = Lcd(lcd_w, lcd_h, (pitch[0], pitch[1]))

    s = _Section(doc, "stage", source)
    z = s.get("z_mm", "list[float]")
    direction = s.get("direction", "list[float]", [0.0, 0.0, 1.0])
    s.finish()
    if len(z) < 2:
        raise ConfigError(f"{source}: key 'stage.z_mm' needs at least 2 positions, got {len(z)}")
    if len(z) > MAX_POSITIONS:
        raise ConfigError(f"{source}: key 'stage.z_mm' lists {len(z)} positions, at most {MAX_POSITIONS}")
    dz = [b - a for a, b in zip(z, z[1:])]
    if not (all(d > 0 for d in dz) or all(d < 0 for d in dz)):
        i = next(i for i, d in enumerate(dz) if d == 0 or (d > 0) != (dz[0] > 0))
        what = "a duplicate position" if dz[i] == 0 else "a change of direction"
        raise ConfigError(
            f"{source}: key 'stage.z_mm' must be strictly monotonic; {what} at index {i + 1}"
            f" ({z[i]} -> {z[i + 1]})"
        )
    if len(direction) != 3 or direction[2] != 1.0:
        raise ConfigError(f"{source}: key 'stage.direction' must be [a, b, 1.0], got {_short_repr(direction)}")
    stage = Stage(tuple(z), (direction[0], direction[1], 1.0))

    s = _Section(doc, "fringes", source)
    directions = s.get("directions", "list[str]", ["x", "y"])
    periods = s.get("periods_px", "list[int]")
    steps_raw = s.table.get("steps", 4)
    s.used.add("steps")
    if isinstance(steps_raw, list):
        steps = _convert(steps_raw, "list[int]", f"{source}: key 'fringes.steps'")
    else:
        steps = [_convert(steps_raw, "int", f"{source}: key 'fringes.steps'")] * len(periods)
    offset = s.get("offset", "float", 127.5)
    amplitude = s.get("amplitude", "float", 100.0)
    carrier = s.get("carrier_px_per_mm", "list[float]", [0.0, 0.0])
    gamma = s.get("gamma", "float", 1.0)
    s.finish()
    if not directions or len(set(directions)) != len(directions) or any(d not in ("x", "y") for d in directions):
        raise ConfigError(f"{source}: key 'fringes.directions' must list 'x' and/or 'y' once each,"
                          f" got {_short_repr(directions)}")
    if not periods or any(not 2 <= p <= MAX_PERIOD_PX for p in periods):
        raise ConfigError(f"{source}: key 'fringes.periods_px' must list periods of 2 to {MAX_PERIOD_PX} px,"
                          f" got {_short_repr(periods)}")
    if any(b >= a for a, b in zip(periods, periods[1:])):
        raise ConfigError(f"{source}: key 'fringes.periods_px' must decrease strictly (coarse to fine),"
                          f" got {_short_repr(periods)}")
    if len(steps) != len(periods):
        raise ConfigError(
            f"{source}: key 'fringes.steps' has {len(steps)} entries for {len(periods)} periods"
        )
    if any(not 3 <= n <= MAX_STEPS for n in steps):
        raise ConfigError(f"{source}: key 'fringes.steps' must be 3 to {MAX_STEPS} per period,"
                          f" got {_short_repr(steps)}")
    if len(carrier) != 2:
        raise ConfigError(f"{source}: key 'fringes.carrier_px_per_mm' must be [x, y], got {_short_repr(carrier)}")
    if amplitude <= 0 or offset - amplitude < -0.5 or offset + amplitude > 255.5:
        raise ConfigError(
            f"{source}: keys 'fringes.offset' ± 'fringes.amplitude' must stay within 0..255"
            f" with amplitude > 0, got {offset} ± {amplitude}"
        )
    if gamma <= 0:
        raise ConfigError(f"{source}: key 'fringes.gamma' must be positive, got {gamma}")
    fringes = FringeDesign(tuple(directions), tuple(periods), tuple(steps), offset, amplitude,
                           (carrier[0], carrier[1]), gamma)

    s = _Section(doc, "images", source, required=False)
    template = s.get("template", "str", DEFAULT_TEMPLATE)
    s.finish()
    validate_template(template, source)
    return Rig(camera, lcd, stage, fringes, template)


def load_rig(path: str | Path) -> Rig:
    """Read and validate a ``rig.toml`` file (or the one inside a dataset folder)."""
    path = Path(path)
    if path.is_dir():
        path = path / "rig.toml"
    return rig_from_toml(_read_text(path), str(path))


def _read_text(path: Path) -> str:
    """A UTF-8 configuration file's text; a missing or unreadable file is a ConfigError naming it."""
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None


def _toml_document(text: str, source: str, expected_format: str, known: set[str]) -> dict:
    """Parse a versioned TOML file: valid TOML, ``format = expected_format``, no unknown top-level key."""
    try:
        doc = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, ValueError) as exc:  # ValueError: e.g. an integer too long to read
        raise ConfigError(f"{source}: not valid TOML ({exc})") from None
    fmt = doc.get("format")
    if fmt != expected_format:
        if fmt is None:
            raise ConfigError(f"{source}: missing key 'format' (expected \"{expected_format}\")")
        raise ConfigError(f"{source}: key 'format' is {_short_repr(fmt)}, expected \"{expected_format}\"")
    for key in doc:
        if key not in known:
            raise ConfigError(f"{source}: unknown key {_short_repr(key)} (allowed: {', '.join(sorted(known))})")
    return doc


def rig_to_toml(rig: Rig) -> str:
    """The ``rig.toml`` text of ``rig`` (round-trips through :func:`rig_from_toml`)."""
    f = rig.fringes
    doc = {
        "format": DATASET_FORMAT,
        "camera": {"width": rig.camera.width, "height": rig.camera.height, "bit_depth": rig.camera.bit_depth},
        "lcd": {"width": rig.lcd.width, "height": rig.lcd.height, "pitch_mm": list(rig.lcd.pitch_mm)},
        "stage": {"z_mm": [float(z) for z in rig.stage.z_mm], "direction": list(rig.stage.direction)},
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
    return tomli_w.dumps(doc)


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write ``rig.toml`` atomically."""
    write_text_atomic(path, rig_to_toml(rig))
