"""Typed values out of a versioned TOML file, each error naming the file and the key.

The reading helpers of ``rig.toml`` and ``scan.toml`` (:mod:`ptpcore.rig.reading`), shared with
the capture configuration: :func:`read_text` a file, :func:`toml_document` its top level (format,
known keys), :class:`Section` one table (typed keys, unknown keys refused).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

from ptpcore.errors import ConfigError

__all__ = ["Section", "tname", "short_repr", "convert", "read_text", "toml_document"]


class Section:
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
                raise ConfigError(f"{source}: '{name}' must be a table [{name}], got {tname(self.table)}")
        self.used: set[str] = set()

    def _key(self, key: str) -> str:
        return f"{self.name}.{key}"

    def get(self, key: str, kind: str, default: Any = ...):
        self.used.add(key)
        if key not in self.table:
            if default is ...:
                raise ConfigError(f"{self.source}: missing key '{self._key(key)}' (expected {kind})")
            return default
        return convert(self.table[key], kind, f"{self.source}: key '{self._key(key)}'")

    def finish(self) -> None:
        unknown = sorted(set(self.table) - self.used)
        if unknown:
            raise ConfigError(
                f"{self.source}: unknown key {short_repr(self._key(unknown[0]))}"
                f" (allowed: {', '.join(sorted(self.used))})"
            )


def tname(v: Any) -> str:
    return {dict: "a table", list: "a list", str: "a string", bool: "a boolean",
            int: "an integer", float: "a float"}.get(type(v), type(v).__name__)


def short_repr(v: Any, limit: int = 60) -> str:
    """``repr`` cut to ``limit`` characters (and safe for integers too long to print)."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 10**limit:
        return f"{'-' if v < 0 else ''}<integer of about {int(abs(v).bit_length() * 0.30103)} digits>"
    try:
        text = repr(v)
    except ValueError:
        text = f"<{type(v).__name__}>"
    return text if len(text) <= limit else text[:limit - 3] + "..."


def convert(value: Any, kind: str, where: str):
    def bad(expected: str):
        return ConfigError(f"{where} must be {expected}, got {tname(value)} {short_repr(value)}")

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
            out.append(convert(item, inner, f"{where}[{i}]"))
        return out
    raise AssertionError(kind)


def read_text(path: Path) -> str:
    """A UTF-8 configuration file's text; a missing or unreadable file is a ConfigError naming it.

    A leading byte-order mark (as Windows Notepad writes) is dropped.
    """
    try:
        return path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None


def toml_document(text: str, source: str, expected_format, known: set[str]) -> dict:
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
        raise ConfigError(f"{source}: key 'format' is {short_repr(fmt)}, expected {want}")
    for key in doc:
        if key not in known:
            raise ConfigError(f"{source}: unknown key {short_repr(key)} (allowed: {', '.join(sorted(known))})")
    return doc
