"""Reading a fringe design: ``[fringes]`` of ``rig.toml`` (with ``[fringes.x]``/``[fringes.y]``)
and the fringe keys of ``[projector]``, every value checked, every error naming the key.

Part of :mod:`ptpcore.rig.reading`; :func:`check_heterodyne_span` also checks a heterodyne
design built in code (:func:`ptpcore.decode.patterns.heterodyne_rig`).
"""

from __future__ import annotations

import math
from dataclasses import replace

from ptpcore.errors import ConfigError

from .model import (DATASET_FORMAT, DATASET_FORMAT_2, DirectionFringes, FringeDesign, Rig, format_period,
                    heterodyne_beats)
from .toml_fields import Section, convert, short_repr

__all__ = ["MAX_GRAY_BITS", "MAX_PERIOD_PX", "MAX_STEPS", "read_fringes", "check_heterodyne_span"]

MAX_GRAY_BITS = 24
MAX_PERIOD_PX = 10_000_000
MAX_STEPS = 1000


def read_fringes(doc: dict, source: str, v2: bool, name: str = "fringes") -> FringeDesign:
    """``[fringes]`` (or ``[projector]``'s fringe keys, ``name``): the design, checked; errors name ``name.key``."""
    s = Section(doc, name, source)
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
                              f" got {short_repr(unwrap)}")
        extra["unwrap"] = unwrap
        extra["gray_bits"] = _check_bits(s.get("gray_bits", "int", 0), f"{source}: key '{name}.gray_bits'")
        inv = s.table.get("gray_inverse", False)
        s.used.add("gray_inverse")
        if not isinstance(inv, bool):
            raise ConfigError(f"{source}: key '{name}.gray_inverse' must be true or false, got {short_repr(inv)}")
        extra["gray_inverse"] = inv
        for d in ("x", "y"):
            if d not in s.table:
                continue
            s.used.add(d)
            sub = Section(s.table, d, source)
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
                          f" got {short_repr(directions)}")
    if extra.get("unwrap") == "heterodyne":
        order = sorted(range(len(periods)), key=lambda j: -float(periods[j]))
        periods, steps = _heterodyne_order(periods, steps, f"{source}: key '{name}.periods_px'")
        # a [fringes.x/y] steps list without its own periods follows the shared periods' order
        per_direction = [(d, o if o.periods_px is not None or o.steps is None else
                          replace(o, steps=tuple(o.steps[j] for j in order))) for d, o in per_direction]
    else:
        _check_periods(periods, f"{source}: key '{name}.periods_px'")
    if len(carrier) != 2:
        raise ConfigError(f"{source}: key '{name}.carrier_px_per_mm' must be [x, y], got {short_repr(carrier)}")
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


def _period_list(raw, where: str, v2: bool) -> tuple:
    """``periods_px``: integers in /1; numbers in /2 (integral ones kept as int)."""
    if not v2:
        for i, r in enumerate(raw if isinstance(raw, list) else []):
            if isinstance(r, float) and math.isfinite(r):
                fix = f"write {int(r)}" if r.is_integer() else f"a fractional one needs format = \"{DATASET_FORMAT_2}\""
                raise ConfigError(f"{where}[{i}] is {r!r}: a {DATASET_FORMAT} period is an integer ({fix})")
        return tuple(convert(raw, "list[int]", where))
    vals = convert(raw, "list[float]", where)
    return tuple(int(v) if float(v).is_integer() and not isinstance(r, float) else float(v)
                 for v, r in zip(vals, raw))


def _check_periods(periods, where: str) -> None:
    if not periods or any(not 2 <= p <= MAX_PERIOD_PX for p in periods):
        raise ConfigError(f"{where} must list periods of 2 to {MAX_PERIOD_PX} px, got {short_repr(list(periods))}")
    if any(b >= a for a, b in zip(periods, periods[1:])):
        raise ConfigError(f"{where} must decrease strictly (coarse to fine), got {short_repr(list(periods))}")


def _heterodyne_order(periods, steps, where: str) -> tuple[tuple, tuple]:
    """Heterodyne periods (any order, checked: :func:`heterodyne_beats`) and their steps, sorted
    longest first like every period list of the engine (so ``{period_index}`` 0 is the longest)."""
    if not periods or any(not 2 <= p <= MAX_PERIOD_PX for p in periods):
        raise ConfigError(f"{where} must list periods of 2 to {MAX_PERIOD_PX} px, got {short_repr(list(periods))}")
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
        steps = convert(raw, "list[int]", where)
    else:
        steps = [convert(raw, "int", where)] * n_periods
    if len(steps) != n_periods:
        raise ConfigError(f"{where} has {len(steps)} entries for {n_periods} periods")
    if any(not 3 <= n <= MAX_STEPS for n in steps):
        raise ConfigError(f"{where} must be 3 to {MAX_STEPS} per period, got {short_repr(steps)}")
    return tuple(steps)


def _check_sign(v: int, where: str) -> int:
    if v not in (1, -1):
        raise ConfigError(f"{where} must be 1 or -1, got {short_repr(v)}")
    return v


def _check_bits(v: int, where: str) -> int:
    if not 0 <= v <= MAX_GRAY_BITS:
        raise ConfigError(f"{where} must be 0 to {MAX_GRAY_BITS}, got {v}")
    return v
