"""The decode's options as a record in files: a session's ``/calibration`` and a LUT's ``/provenance``.

:class:`~ptpcore.decode.phase.DecodeOptions` is the one object every front end passes to the
decode; this module writes it as JSON and reads it back (a field missing from an older record
takes its default; an unknown one is refused by name).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, fields

from ptpcore.decode.phase import DecodeOptions

__all__ = ["DECODE_OPTIONS_KEY", "decode_options_json", "decode_options_from_json"]

DECODE_OPTIONS_KEY = "decode_options"
"""The record's name: a session's ``/calibration`` attribute and a LUT's ``/provenance`` attribute."""


def decode_options_json(options: DecodeOptions) -> str:
    """``options`` as JSON text (``spatial_k`` null when the spatial check is off)."""
    return json.dumps(asdict(options))


def decode_options_from_json(text: str, where: str = "decode options") -> DecodeOptions:
    """The record :func:`decode_options_json` wrote; ``where`` names the file and attribute in errors.

    Raises
    ------
    ValueError
        Not JSON, an unknown key, or a value out of range (one line naming it).
    """
    try:
        data = json.loads(text)
    except ValueError:
        raise ValueError(f"{where}: not valid JSON") from None
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected a JSON object of decode options")
    names = {f.name for f in fields(DecodeOptions)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{where}: unknown decode option {unknown[0]!r} (known: {', '.join(sorted(names))})")
    opts = DecodeOptions(**data)
    _check(opts, where)
    return opts


def _check(opts: DecodeOptions, where: str) -> None:
    """Every value in its range, else one line naming it."""
    def number(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    if not (number(opts.min_modulation) and 0 <= opts.min_modulation < 1):
        raise ValueError(f"{where}: min_modulation {opts.min_modulation!r} must be in [0, 1)")
    if isinstance(opts.border_margin_px, bool) or not isinstance(opts.border_margin_px, int) \
            or opts.border_margin_px < 0:
        raise ValueError(f"{where}: border_margin_px {opts.border_margin_px!r} must be an integer >= 0")
    if not (number(opts.unwrap_tolerance) and 0 < opts.unwrap_tolerance <= 0.5):
        raise ValueError(f"{where}: unwrap_tolerance {opts.unwrap_tolerance!r} must be in (0, 0.5]")
    if opts.spatial_k is not None and not (number(opts.spatial_k) and opts.spatial_k > 0):
        raise ValueError(f"{where}: spatial_k {opts.spatial_k!r} must be a number > 0 or null")
