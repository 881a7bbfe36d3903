"""Image-name templates (``[images] template`` and its kin): user text checked before it names a file.

Only the documented fields with plain format specs; no attribute or index access, no conversion,
no path leaving the dataset folder (FORMATS.md, ``ptp-dataset/1`` and ``/2``).
"""

from __future__ import annotations

import re
import string
from pathlib import Path

from ptpcore.errors import ConfigError

from .model import FringeDesign, Stage
from .toml_fields import short_repr

__all__ = ["TEMPLATE_FIELDS", "GRAY_TEMPLATE_FIELDS", "REFERENCE_TEMPLATE_FIELDS", "validate_template",
           "needed_fields"]

TEMPLATE_FIELDS = ("pos", "dir", "period", "step", "steps", "period_index")
GRAY_TEMPLATE_FIELDS = ("pos", "dir", "bit", "inverse")
REFERENCE_TEMPLATE_FIELDS = ("pos",)
# A plain format spec: [[fill]align][sign][#][0][width][,_][.precision][type], widths <= 3 digits.
_SPEC = re.compile(r"(?:[^{}]?[<>=^])?[+\- ]?#?0?(?:\d{1,3})?[,_]?(?:\.\d{1,3})?[bdoxXs]?")


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
        raise ConfigError(f"{where} must not contain control characters (got {short_repr(template)})")
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


def needed_fields(needed: tuple[str, ...], fringes: FringeDesign, stage: Stage) -> tuple[str, ...]:
    """A template's required fields, less ``dir`` with one direction and ``pos`` with one position
    (repeats included): the names are unique without them (FORMATS.md, ptp-dataset/2)."""
    drop = set()
    if len(fringes.directions) == 1:
        drop.add("dir")
    if stage.n_positions + len(stage.repeat_z_mm) == 1:
        drop.add("pos")
    return tuple(n for n in needed if n not in drop)
