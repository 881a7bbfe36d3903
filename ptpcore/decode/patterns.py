"""Fringe patterns shown on the LCD (METHOD.md section 3) and the design check.

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
from dataclasses import dataclass

import numpy as np

from ptpcore.rig.rigfile import Display, FringeDesign, Lcd, Rig, format_period

__all__ = [
    "fringe_values",
    "fringe_profile",
    "fringe_image",
    "display_response",
    "display_inverse",
    "DesignItem",
    "DesignReport",
    "design_check",
    "convention_detectable",
    "phase_noise_rad",
]


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


def phase_noise_rad(noise_dn, modulation_dn, n_steps: int):
    """Phase noise of N-step retrieval: ``sqrt(2/N) * sigma / B`` (METHOD.md section 4)."""
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


def convention_detectable(rig: Rig, direction: str) -> dict:
    """Whether a wrong ``phase_origin`` (by pi) and a wrong ``shift_sign`` show in decoded data
    (METHOD.md section 4): as unwrapping disagreement when a period ratio is not an odd
    integer (origin) or not an integer (sign), or as coordinates off the LCD when the
    coarsest period exceeds it."""
    f = rig.fringes
    ps = [float(t) for t in f.periods(direction)]
    ratios = [a / b for a, b in zip(ps, ps[1:])]
    extent = rig.lcd.width if direction == "x" else rig.lcd.height
    exceeds = ps[0] > extent + 1.0

    def is_int(r):
        return abs(r - round(r)) < 1e-9

    origin = exceeds or any(not (is_int(r) and round(r) % 2 == 1) for r in ratios)
    sign = exceeds or any(not is_int(r) for r in ratios)
    return {"phase_origin_rad": origin, "shift_sign": sign}


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
        if f.unwrap == "gray":
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
        tells = convention_detectable(rig, d)
        if not all(tells.values()):
            blind = [k for k, v in tells.items() if not v]
            items.append(DesignItem(
                f"convention check {d}", True, 0.0,
                "a wrong phase_origin_rad or shift_sign shows in the data",
                f"this design cannot tell a wrong {' or '.join(blind)} from the data (direction {d}):"
                " consecutive period ratios are odd integers (origin) or integers (sign) and the coarsest"
                " period does not exceed the LCD; check those settings against the pattern generator",
            ))
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
