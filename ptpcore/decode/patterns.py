"""Fringe patterns shown on the LCD (docs/method.md section 3) and the design check.

A pattern varies along one LCD axis only, so the engine works with 1-D
profiles (one value per LCD column for direction ``x``, per row for ``y``);
:func:`fringe_image` expands a profile to the full LCD image when a screen or
a preview needs it.

The displayed levels compensate the display's response: a measured one
(``[display]``, :func:`display_inverse`, measured by ``ptp capture``) when the
rig has it, else ``[fringes] gamma``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ptpcore.errors import ConfigError
from ptpcore.rig.rigfile import (Display, DirectionFringes, FringeDesign, Lcd, Rig, format_period,
                                 heterodyne_beats)

__all__ = [
    "fringe_values",
    "fringe_profile",
    "fringe_image",
    "display_response",
    "display_inverse",
    "DesignItem",
    "DesignReport",
    "design_check",
    "blind_origin_shifts",
    "equivalent_conventions",
    "wrap_origin",
    "phase_noise_rad",
    "gray_values",
    "gray_profile",
    "reference_profile",
    "gray_bits_needed",
    "gray_code_rig",
    "heterodyne_rig",
    "GRAY_TEMPLATE",
    "WHITE_TEMPLATE",
    "BLACK_TEMPLATE",
]

GRAY_TEMPLATE = "z{pos:03d}/{dir}_G{bit:02d}_{inverse}.png"
WHITE_TEMPLATE = "z{pos:03d}/white.png"
BLACK_TEMPLATE = "z{pos:03d}/black.png"


def fringe_values(coord, design: FringeDesign, direction: str, period: float, step: int,
                  n_steps: int, z_mm: float) -> np.ndarray:
    """Continuous (unrounded, uncompensated) pattern value at LCD coordinates.

    Parameters
    ----------
    coord : array_like
        LCD coordinate along the pattern's axis (``u`` for ``x``, ``v`` for ``y``), LCD px.
    design : FringeDesign
    direction : {"x", "y"}
    period : int
        Fringe period T, LCD px.
    step, n_steps : int
        Phase step n of N.
    z_mm : float
        Stage reading of the position (sets the carrier displacement ``s``).

    Returns
    -------
    ndarray, same shape as ``coord``
        ``offset + amplitude * cos(2*pi*(coord + s)/T + phase_origin + shift_sign*2*pi*n/N)``,
        grey levels (the direction's ``phase_origin_rad`` and ``shift_sign``).
    """
    s = design.carrier(direction) * z_mm
    coord = np.asarray(coord, dtype=float)
    return design.offset + design.amplitude * np.cos(
        2.0 * np.pi * (coord + s) / period + design.origin(direction)
        + design.sign(direction) * (2.0 * np.pi * step / n_steps)
    )


def display_response(display: Display, levels) -> np.ndarray:
    """The measured relative luminance at ``levels`` (0..255): monotone cubic (PCHIP) through the
    ``[display]`` points, normalised to 0 at the lowest and 1 at the highest measured level."""
    from scipy.interpolate import PchipInterpolator

    lv = np.asarray(display.levels, dtype=float)
    lum = np.asarray(display.luminance, dtype=float)
    rel = (lum - lum[0]) / (lum[-1] - lum[0])
    return PchipInterpolator(lv, rel, extrapolate=False)(np.clip(np.asarray(levels, dtype=float), lv[0], lv[-1]))


def display_inverse(display: Display, g) -> np.ndarray:
    """Continuous levels whose measured luminance is linear in ``g`` (0..255 -> the measured range).

    Parameters
    ----------
    display : Display
        ``[display]`` levels (strictly increasing) and luminance (increasing).
    g : array_like
        Wanted values on the linear scale, grey levels 0..255.

    Returns
    -------
    ndarray, shape of ``g``: levels in ``[levels[0], levels[-1]]`` (unrounded).
    """
    lv = np.asarray(display.levels, dtype=float)
    fine = np.linspace(lv[0], lv[-1], 4096)
    rel = np.maximum.accumulate(display_response(display, fine))  # monotone: np.interp needs it
    want = np.clip(np.asarray(g, dtype=float) / 255.0, 0.0, 1.0)
    return np.interp(want, rel, fine)


def fringe_profile(lcd: Lcd, design: FringeDesign, direction: str, period: int, step: int,
                   n_steps: int, z_mm: float, display: Display | None = None) -> np.ndarray:
    """The displayed integer levels along the pattern's axis.

    Parameters
    ----------
    display : Display, optional
        A measured response (``rig.display``): the levels go through its inverse
        (:func:`display_inverse`) and ``design.gamma`` is ignored.

    Returns
    -------
    (lcd.width,) or (lcd.height,) uint8
        Levels after the pre-compensation (``255*(g/255)**(1/gamma)``, or the
        measured response's inverse) and rounding.
    """
    n = lcd.width if direction == "x" else lcd.height
    g = fringe_values(np.arange(n), design, direction, period, step, n_steps, z_mm)
    g = np.clip(g, 0.0, 255.0)
    if display is not None and len(display.levels) >= 2:
        g = display_inverse(display, g)
    elif design.gamma != 1.0:
        g = 255.0 * (g / 255.0) ** (1.0 / design.gamma)
    return np.clip(np.rint(g), 0, 255).astype(np.uint8)


def fringe_image(lcd: Lcd, design: FringeDesign, direction: str, period: int, step: int,
                 n_steps: int, z_mm: float, display: Display | None = None) -> np.ndarray:
    """The full LCD image ``(lcd.height, lcd.width)`` uint8 for one pattern (``display``: :func:`fringe_profile`)."""
    prof = fringe_profile(lcd, design, direction, period, step, n_steps, z_mm, display)
    if direction == "x":
        return np.broadcast_to(prof[None, :], (lcd.height, lcd.width)).copy()
    return np.broadcast_to(prof[:, None], (lcd.height, lcd.width)).copy()


def _precompensate(g: np.ndarray, design: FringeDesign) -> np.ndarray:
    """Grey levels through the design's gamma pre-compensation, rounded to displayed uint8 levels."""
    g = np.clip(g, 0.0, 255.0)
    if design.gamma != 1.0:
        g = 255.0 * (g / 255.0) ** (1.0 / design.gamma)
    return np.clip(np.rint(g), 0, 255).astype(np.uint8)


def gray_values(coord, design: FringeDesign, direction: str, bit: int, inverse: bool,
                z_mm: float) -> np.ndarray:
    """Continuous (uncompensated) value of one Gray-code pattern at LCD coordinates.

    Bit ``bit`` (0 = most significant, of ``design.bits(direction)``) of the
    binary-reflected Gray code of the cycle index ``m = floor((coord + s) / T_0)``
    of the coarsest period ``T_0`` (``s``: the carrier displacement, so the code
    moves with the fringes); cycles below 0 count as 0 and beyond the code's
    range as its last. A set bit shows the fringes' brightest level
    ``offset + amplitude``, a clear bit their darkest ``offset - amplitude``
    (so a Gray-code frame clips the camera only where the fringes do); the
    inverse frame swaps them.

    Parameters
    ----------
    coord : array_like
        LCD coordinate along the pattern's axis (``u`` for ``x``, ``v`` for ``y``), LCD px.
    design : FringeDesign
    direction : {"x", "y"}
    bit : int
    inverse : bool
    z_mm : float
        Stage reading (sets the carrier displacement).

    Returns
    -------
    ndarray, same shape as ``coord``
        Grey levels before gamma pre-compensation.
    """
    n_bits = design.bits(direction)
    if not 0 <= bit < n_bits:
        raise ValueError(f"Gray-code bit {bit} does not exist (direction {direction} has {n_bits} bits)")
    t0 = float(design.periods(direction)[0])
    s = design.carrier(direction) * z_mm
    m = np.floor((np.asarray(coord, dtype=float) + s) / t0)
    m = np.clip(m, 0, (1 << n_bits) - 1).astype(np.int64)
    g = m ^ (m >> 1)
    on = ((g >> (n_bits - 1 - bit)) & 1).astype(bool) != bool(inverse)
    return np.where(on, design.offset + design.amplitude, design.offset - design.amplitude)


def gray_profile(lcd: Lcd, design: FringeDesign, direction: str, bit: int, inverse: bool,
                 z_mm: float) -> np.ndarray:
    """The displayed levels of one Gray-code pattern along its axis.

    Returns
    -------
    (lcd.width,) or (lcd.height,) uint8
        :func:`gray_values` after gamma pre-compensation, like :func:`fringe_profile`.
    """
    n = lcd.width if direction == "x" else lcd.height
    return _precompensate(gray_values(np.arange(n), design, direction, bit, inverse, z_mm), design)


def reference_profile(lcd: Lcd, design: FringeDesign, which: str) -> np.ndarray:
    """The displayed levels (along ``u``) of the ``"white"`` or ``"black"`` reference frame.

    White is the fringes' brightest level ``offset + amplitude``, black their
    darkest ``offset - amplitude`` (after gamma pre-compensation): where these
    clip the camera, the fringes do too.

    Returns
    -------
    (lcd.width,) uint8
    """
    if which not in ("white", "black"):
        raise ValueError(f"reference frame must be 'white' or 'black', got {which!r}")
    level = design.offset + (design.amplitude if which == "white" else -design.amplitude)
    return _precompensate(np.full(lcd.width, level, float), design)


def gray_bits_needed(rig: Rig, direction: str, coarsest_px: float | None = None) -> int:
    """Fewest Gray-code bits whose cycles of the coarsest period cover ``u + s`` over the LCD
    and every position's carrier shift (the design check's unambiguous range)."""
    f = rig.fringes
    t0 = float(coarsest_px if coarsest_px is not None else f.periods(direction)[0])
    extent = rig.lcd.width if direction == "x" else rig.lcd.height
    shifts = f.carrier(direction) * np.asarray(rig.stage.z_mm, float)
    span_hi = extent - 0.5 + max(0.0, float(shifts.max()))
    return max(1, int(math.ceil(math.log2(max(span_hi, 1.0) / t0 + 1e-9))))


def gray_code_rig(rig: Rig, levels: int = 2, *, inverse: bool = False, references: bool = False) -> Rig:
    """``rig`` with Gray-code unwrapping (``unwrap = "gray"``, ptp-dataset/2) instead of its coarse periods.

    Keeps the finest ``levels`` periods and their steps (per direction); each
    direction gets the fewest Gray-code bits covering the LCD and the carrier
    (a per-direction ``gray_bits`` where they differ); the templates are
    FORMATS.md's examples with the rig's image suffix.

    Parameters
    ----------
    rig : Rig
    levels : int
        Phase-shifted periods kept (1 = the finest only).
    inverse : bool
        Each Gray-code frame followed by its inverse.
    references : bool
        All-white and all-black frames at every position.
    """
    f = rig.fringes
    if levels < 1:
        raise ValueError(f"levels must be at least 1, got {levels}")
    per = {}
    for d in f.directions:
        per[d] = (tuple(f.periods(d)[-levels:]), tuple(f.steps_of(d)[-levels:]))
    base = per[f.directions[0]]
    probe = replace(rig, fringes=replace(f, periods_px=base[0], steps=base[1], per_direction=()))
    bits = {d: gray_bits_needed(probe, d, per[d][0][0]) for d in f.directions}
    first = f.directions[0]
    kept = dict(f.per_direction)  # origin and sign of a direction stay as they were
    overrides = []
    for d in f.directions:
        o = DirectionFringes(per[d][0] if per[d][0] != base[0] else None,
                             per[d][1] if per[d][1] != base[1] else None,
                             kept[d].phase_origin_rad if d in kept else None,
                             kept[d].shift_sign if d in kept else None,
                             bits[d] if bits[d] != bits[first] else None)
        if o != DirectionFringes():
            overrides.append((d, o))
    overrides = tuple(overrides)
    fringes = replace(f, periods_px=base[0], steps=base[1], unwrap="gray", gray_bits=bits[first],
                      gray_inverse=bool(inverse), per_direction=overrides)
    suffix = rig.template[rig.template.rfind("."):] if "." in rig.template else ".png"
    out = replace(rig, fringes=fringes, gray_template=GRAY_TEMPLATE.replace(".png", suffix))
    if references:
        out = replace(out, white_template=WHITE_TEMPLATE.replace(".png", suffix),
                      black_template=BLACK_TEMPLATE.replace(".png", suffix))
    return out


def heterodyne_rig(rig: Rig, periods, steps=None) -> Rig:
    """``rig`` unwrapping by heterodyne beats (``unwrap = "heterodyne"``, ptp-dataset/2) of ``periods``.

    Parameters
    ----------
    rig : Rig
    periods : sequence of 2 or 3 float
        LCD px, any order (sorted longest first, as the rig file's reader does); both directions.
    steps : int or sequence of int, optional
        N per period (in the order of ``periods``); default the rig's finest level's N.

    Raises
    ------
    ConfigError
        Not two or three different periods, equal beats, or an absolute beat that does not cover
        the LCD plus the carrier (the message names the periods).
    """
    from ptpcore.rig.rigfile import check_heterodyne_span

    f = rig.fringes
    ps = [float(t) for t in periods]
    if steps is None:
        steps = [f.steps_of(f.directions[0])[-1]] * len(ps)
    elif isinstance(steps, int):
        steps = [steps] * len(ps)
    try:
        heterodyne_beats(ps)
    except ValueError as exc:
        raise ConfigError(f"--heterodyne: {exc}") from None
    order = sorted(range(len(ps)), key=lambda j: -ps[j])
    kept = tuple((d, replace(o, periods_px=None, steps=None, gray_bits=None)) for d, o in f.per_direction)
    kept = tuple((d, o) for d, o in kept if o != DirectionFringes())
    fringes = replace(f, periods_px=tuple(format_period(ps[j]) for j in order),
                      steps=tuple(int(steps[j]) for j in order), unwrap="heterodyne", gray_bits=0,
                      gray_inverse=False, per_direction=kept)
    out = replace(rig, fringes=fringes, gray_template=None, white_template=None, black_template=None)
    check_heterodyne_span(out, "--heterodyne")
    return out


def phase_noise_rad(noise_dn, modulation_dn, n_steps: int):
    """Phase noise of N-step retrieval: ``sqrt(2/N) * sigma / B`` (docs/method.md section 4)."""
    return np.sqrt(2.0 / n_steps) * np.asarray(noise_dn, dtype=float) / np.asarray(modulation_dn, dtype=float)


@dataclass(frozen=True)
class DesignItem:
    """One verdict of the design check."""

    name: str
    ok: bool
    value: float
    requirement: str
    message: str


@dataclass(frozen=True)
class DesignReport:
    """Result of :func:`design_check`.

    Attributes
    ----------
    items : list of DesignItem
    noise_floor_um : (K,) float64
        Predicted 1-sigma coordinate noise per position (µm), finest period,
        worse of the two directions.
    """

    items: tuple[DesignItem, ...]
    noise_floor_um: np.ndarray

    @property
    def ok(self) -> bool:
        return all(item.ok for item in self.items)

    def failures(self) -> list[DesignItem]:
        return [item for item in self.items if not item.ok]


def blind_origin_shifts(periods, tol: float = 1e-6) -> tuple[float, ...] | None:
    """Origin errors that hierarchical unwrapping cannot see (docs/method.md section 4).

    A wrong origin adds the same ``e`` to the phase of every level; level ``j``
    then disagrees with the one above by ``(r_j - 1) * e (mod 2 pi)``,
    ``r_j = T_{j-1} / T_j``. Where the coarse phase wraps (``e`` pushed it past
    ``2 pi``) the effective error is ``e - 2 pi``: both are listed, so a
    fractional ratio (which tells ``e`` from ``e - 2 pi``) is handled exactly.

    Parameters
    ----------
    periods : sequence of float
        Periods coarse to fine, LCD px.
    tol : float
        Tolerance on ``(r_j - 1) e / 2 pi`` being an integer.

    Returns
    -------
    tuple of float, radians in (-2 pi, 2 pi), sorted, 0 included; or None
        None for a single period (no unwrapping: every origin is unseen by it).
    """
    ps = [float(t) for t in periods]
    if len(ps) < 2:
        return None
    ratios = [a / b for a, b in zip(ps, ps[1:])]
    first = ratios[0] - 1.0
    limit = int(math.floor(first - tol))  # |m| < r_1 - 1 keeps |e| < 2 pi
    out = []
    for m in range(-limit, limit + 1):
        e = 2.0 * math.pi * m / first
        if all(abs(q - round(q)) <= tol for q in ((r - 1.0) * e / (2.0 * math.pi) for r in ratios)):
            out.append(e)
    return tuple(sorted(out))


def equivalent_conventions(periods, sign: int, origin: float) -> list[tuple[int, float]]:
    """Every ``(shift_sign, phase_origin_rad)`` whose unwrapping is as consistent as ``(sign, origin)``.

    If the patterns were shown with ``(sign, origin)``, decoding with the same
    sign and origin ``origin - e`` shifts every phase by ``e``; decoding with the
    other sign and origin ``-origin - e`` negates every phase and adds ``e`` (a
    mirrored map). Both unwrap consistently exactly for ``e`` in
    :func:`blind_origin_shifts`. What is left to tell them apart is whether the
    coordinates stay on the LCD (the data's part: :func:`ptpcore.run.diagnose.convention_check`).

    Returns
    -------
    list of (int, float)
        Sign and origin (radians in (-pi, pi]), ``(sign, origin)`` first, no
        duplicates. Empty for a single period (any origin fits).
    """
    shifts = blind_origin_shifts(periods)
    if shifts is None:
        return []
    out: list[tuple[int, float]] = []
    for s, base in ((sign, origin), (-sign, -origin)):
        for e in sorted(shifts, key=abs):
            o = wrap_origin(base - e)
            if not any(s == s2 and abs(math.remainder(o - o2, 2 * math.pi)) < 1e-9 for s2, o2 in out):
                out.append((s, o))
    return out


def wrap_origin(rad: float) -> float:
    """An origin in (-pi, pi] (pi stays pi)."""
    r = math.remainder(float(rad), 2 * math.pi)
    return math.pi if abs(r + math.pi) < 1e-12 else r


def _hidden_width(periods, extent: float) -> list[tuple[int, float, float]]:
    """For each convention equivalent to the plain one ``(1, 0)``: ``(sign, origin, width)``, the
    widest part of the LCD (px, carrier left out) a camera may see without its coordinates
    leaving the LCD under it (0: never hidden)."""
    t0 = float(periods[0])
    out = []
    for s, o in equivalent_conventions(periods, 1, 0.0)[1:]:
        if s == 1:
            # Shift by D = T0 e / 2pi (or D - T0 where the coarse phase wraps).
            d = (-o % (2 * math.pi)) * t0 / (2 * math.pi)
            width = extent - min(d, t0 - d)
        else:
            # Mirror u' = C - u, C = T0 c / 2pi or that plus T0.
            c = (-o % (2 * math.pi)) * t0 / (2 * math.pi)
            width = max(min(cc, 2 * extent - cc) for cc in (c, c + t0))
        out.append((s, o, max(0.0, float(width))))
    return out


def _convention_item(rig: Rig, d: str) -> DesignItem | None:
    """The design check's verdict on which wrong conventions the data of direction ``d`` cannot reveal."""
    f = rig.fringes
    ps = f.periods(d)
    extent = float(rig.lcd.width if d == "x" else rig.lcd.height)
    if len(ps) < 2:
        return DesignItem(
            f"convention check {d}", True, 0.0, "a wrong phase_origin_rad or shift_sign shows in the data",
            f"direction {d} has one period: no unwrapping checks phase_origin_rad or shift_sign; only"
            " coordinates off the LCD can; check them against the pattern generator")
    hidden = [(s, o, w) for s, o, w in _hidden_width(ps, extent) if w > 0]
    if not hidden:
        return None
    shifts = blind_origin_shifts(ps)
    degrees = sorted({round(math.degrees(e) % 360.0, 4) % 360.0 for e in shifts} - {0.0})
    what = []
    if degrees:
        what.append("a phase_origin_rad wrong by " + ", ".join(f"{x:.4g}" for x in degrees) + " degrees")
    if any(s == -1 for s, _o, _w in hidden):
        what.append("a wrong shift_sign (with the origin negated)")
    widest = max(w for *_x, w in hidden)
    return DesignItem(
        f"convention check {d}", True, widest,
        "a wrong phase_origin_rad or shift_sign shows in the data",
        f"direction {d}: {' and '.join(what)} unwrap as consistently as the right ones (period ratios"
        f" {', '.join(f'{a / b:.4g}' for a, b in zip(ps, ps[1:]))}); only coordinates off the LCD tell them,"
        f" which a camera seeing up to {widest:.0f} of the LCD's {extent:.0f} px may not. A level whose ratio"
        " to the coarser one is 2 reveals every wrong origin; check the settings against the pattern generator")


def _heterodyne_range_item(f: FringeDesign, d: str, span_lo: float, span_hi: float) -> DesignItem:
    """The beats of a heterodyne design and whether the absolute one covers ``u + s``."""
    beats = heterodyne_beats(f.periods(d))
    ts = ", ".join(f"{format_period(t)}" for t in beats["periods"])
    listed = [f"T12 = {beats['steps'][-1][1]:.1f} px"]
    if len(beats["periods"]) == 3:
        listed += [f"T23 = {beats['t23']:.1f} px", f"T123 = {beats['absolute']:.1f} px"]
    cover = beats["absolute"]
    ok = span_lo >= -0.5 and span_hi - span_lo < cover
    return DesignItem(
        f"unambiguous range {d}", bool(ok), float(cover),
        f"absolute beat > span of u+s = [{span_lo:.1f}, {span_hi:.1f}] px",
        (f"heterodyne periods {ts} px: beats {', '.join(listed)}; {cover:.1f} px covers the LCD plus carrier"
         if ok else
         f"heterodyne periods {ts} px: beats {', '.join(listed)}; {cover:.1f} px does not cover u+s in"
         f" [{span_lo:.1f}, {span_hi:.1f}] px: choose periods closer together"))


def _heterodyne_margin_items(f: FringeDesign, d: str, noise_dn, modulation_dn: float,
                             margin_sigmas: float) -> list[DesignItem]:
    """The noise margin of every cascade step: a beat multiplies its phase noise by its ratio to
    the period it unwraps (``T123 / T12``, ``T12 / T1``)."""
    beats = heterodyne_beats(f.periods(d))
    ts = beats["periods"]
    by_period = dict(zip((float(t) for t in f.periods(d)), f.steps_of(d)))
    s = [float(phase_noise_rad(noise_dn, modulation_dn, by_period[t])) for t in ts]  # T1, T2 (, T3)
    s12 = math.hypot(s[0], s[1])
    beat_noise = {"T12": s12}
    if len(ts) == 3:
        beat_noise["T123"] = math.sqrt(s[0] ** 2 + 4 * s[1] ** 2 + s[2] ** 2)  # phi1 - 2 phi2 + phi3
    finer_noise = {ts[0]: s[0], beats["steps"][-1][1]: s12}
    items = []
    for name, t_beat, t_target in beats["steps"]:
        ratio = t_beat / t_target
        sigma = math.hypot(beat_noise[name] * ratio, finer_noise[t_target])
        margin = (np.pi / 2) / sigma if sigma > 0 else np.inf
        ok = margin >= margin_sigmas
        target = "T1" if t_target == ts[0] else "T12"
        items.append(DesignItem(
            f"unwrapping {name} -> {target}" + (f" ({d})" if f.per_direction else ""), bool(ok), float(margin),
            f"margin >= {margin_sigmas:g} sigma (quarter-period tolerance / phase noise)",
            f"beat {t_beat:.1f} px unwraps {t_target:.1f} px: its phase noise x {ratio:.1f}, margin {margin:.1f} sigma"
            + ("" if ok else " is too small: more steps, or periods further apart (a shorter beat)")))
    return items


def design_check(rig: Rig, *, modulation_dn=None, noise_dn: float | None = None,
                 margin_sigmas: float = 6.0, harmonic_dn: float | None = None) -> DesignReport:
    """Check a fringe design against the rig and the expected signal.

    Parameters
    ----------
    rig : Rig
    modulation_dn : float or (K,) array_like, optional
        Expected fringe modulation B in camera grey levels at each position.
        Default: half the camera's range times ``amplitude/127.5``.
    noise_dn : float, optional
        Expected noise per sample (grey levels). Default: 1 % of full scale.
    margin_sigmas : float
        How many sigmas of phase noise each unwrapping step must tolerate.
    harmonic_dn : float, optional
        Measured amplitude of the display's harmonics (grey levels): a warning
        when it exceeds ``noise_dn``.

    Returns
    -------
    DesignReport
        Verdicts: the coarsest period covers the LCD plus the carrier span;
        each unwrapping step has ``margin_sigmas`` of margin; the noise floor
        per position.
    """
    f = rig.fringes
    k = rig.stage.n_positions
    full = rig.camera.max_level
    if modulation_dn is None:
        modulation_dn = 0.5 * full * f.amplitude / 127.5
    mod = np.broadcast_to(np.asarray(modulation_dn, dtype=float), (k,))
    if noise_dn is None:
        noise_dn = 0.01 * full
    items = []
    z = np.asarray(rig.stage.z_mm)
    for d in f.directions:
        extent = rig.lcd.width if d == "x" else rig.lcd.height
        shifts = f.carrier(d) * z
        span_lo = min(0.0, shifts.min()) - 0.5
        span_hi = extent - 0.5 + max(0.0, shifts.max())
        span = span_hi - span_lo
        t0 = f.periods(d)[0]
        if f.unwrap == "heterodyne":
            items.append(_heterodyne_range_item(f, d, span_lo, span_hi))
        elif f.unwrap == "gray":
            cover = t0 * (1 << f.bits(d))
            ok = span_lo >= -0.5 and span_hi < cover
            items.append(DesignItem(
                f"unambiguous range {d}", bool(ok), float(cover),
                f"Gray code ({f.bits(d)} bits of {format_period(t0)} px cycles) > span of u+s"
                f" = [{span_lo:.1f}, {span_hi:.1f}] px",
                (f"{f.bits(d)} Gray-code bits cover {cover:g} px: the LCD plus carrier" if ok else
                 f"{f.bits(d)} Gray-code bits cover only {cover:g} px of u+s in [{span_lo:.1f}, {span_hi:.1f}] px:"
                 " add a bit"),
            ))
        else:
            ok = span_lo >= -0.5 and span_hi < t0
            items.append(DesignItem(
                f"unambiguous range {d}", bool(ok), float(t0),
                f"coarsest period > span of u+s = [{span_lo:.1f}, {span_hi:.1f}] px ({span:.1f} px)",
                (f"period {format_period(t0)} px covers the LCD plus carrier" if ok else
                 f"coarsest period {format_period(t0)} px does not cover u+s in [{span_lo:.1f}, {span_hi:.1f}]"
                 " px: unwrapping would be ambiguous; use a longer coarse period or a smaller carrier"
                 if span_lo >= -0.5 else
                 f"negative carrier shifts u+s below 0 (to {span_lo:.1f} px): the coarse phase wraps"),
            ))
    worst_mod = float(mod.min())
    dirs = f.directions if f.per_direction else f.directions[:1]
    for d in dirs:
        ps, ns = f.periods(d), f.steps_of(d)
        if f.unwrap == "heterodyne":
            items.extend(_heterodyne_margin_items(f, d, noise_dn, worst_mod, margin_sigmas))
            continue
        for j in range(1, len(ps)):
            ratio = ps[j - 1] / ps[j]
            s_prev = phase_noise_rad(noise_dn, worst_mod, ns[j - 1]) * ratio
            s_this = phase_noise_rad(noise_dn, worst_mod, ns[j])
            sigma = float(math.hypot(s_prev, s_this))
            margin = (np.pi / 2) / sigma if sigma > 0 else np.inf
            ok = margin >= margin_sigmas
            label = f"unwrapping {format_period(ps[j - 1])} -> {format_period(ps[j])}"
            items.append(DesignItem(
                label + (f" ({d})" if f.per_direction else ""), bool(ok), float(margin),
                f"margin >= {margin_sigmas:g} sigma (quarter-period tolerance / phase noise)",
                f"ratio {ratio:.2f}: margin {margin:.1f} sigma" + ("" if ok else
                  " is too small: add an intermediate period or more steps"),
            ))
    for d in (f.directions if f.unwrap == "periods" else ()):
        item = _convention_item(rig, d)
        if item is not None:
            items.append(item)
    if harmonic_dn is not None and noise_dn is not None and harmonic_dn > noise_dn:
        items.append(DesignItem(
            "display harmonics", False, float(harmonic_dn),
            "display harmonics below the noise",
            f"the fringes carry harmonics of {harmonic_dn:.2g} DN, above the noise ({noise_dn:.2g} DN): the"
            " display's response differs from the gamma pre-compensation; use more steps (they then cancel"
            " in the phase) or a matching pre-compensation ([display] levels and luminance)",
        ))
    pitch = max(rig.lcd.pitch_mm)
    d_fine = f.directions[0]
    sigma_u = phase_noise_rad(noise_dn, mod, f.steps_of(d_fine)[-1]) * f.periods(d_fine)[-1] / (2 * np.pi)
    floor_um = sigma_u * pitch * 1000.0
    items.append(DesignItem(
        "noise floor", True, float(floor_um.max()),
        "predicted 1-sigma coordinate noise, finest period",
        f"{floor_um.min():.2f} to {floor_um.max():.2f} µm per position",
    ))
    return DesignReport(tuple(items), floor_um)
