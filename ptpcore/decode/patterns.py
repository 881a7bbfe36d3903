"""Fringe patterns shown on the LCD (METHOD.md section 3) and the design check.

A pattern varies along one LCD axis only, so the engine works with 1-D
profiles (one value per LCD column for direction ``x``, per row for ``y``);
:func:`fringe_image` expands a profile to the full LCD image when a screen or
a preview needs it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ptpcore.rig.rigfile import FringeDesign, Lcd, Rig

__all__ = [
    "fringe_values",
    "fringe_profile",
    "fringe_image",
    "DesignItem",
    "DesignReport",
    "design_check",
    "phase_noise_rad",
]


def fringe_values(coord, design: FringeDesign, direction: str, period: int, step: int,
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
        ``offset + amplitude * cos(2*pi*(coord + s)/T + 2*pi*n/N)``, grey levels.
    """
    s = design.carrier(direction) * z_mm
    coord = np.asarray(coord, dtype=float)
    return design.offset + design.amplitude * np.cos(
        2.0 * np.pi * (coord + s) / period + 2.0 * np.pi * step / n_steps
    )


def fringe_profile(lcd: Lcd, design: FringeDesign, direction: str, period: int, step: int,
                   n_steps: int, z_mm: float) -> np.ndarray:
    """The displayed integer levels along the pattern's axis.

    Returns
    -------
    (lcd.width,) or (lcd.height,) uint8
        Levels after gamma pre-compensation ``255*(g/255)**(1/gamma)`` and rounding.
    """
    n = lcd.width if direction == "x" else lcd.height
    g = fringe_values(np.arange(n), design, direction, period, step, n_steps, z_mm)
    g = np.clip(g, 0.0, 255.0)
    if design.gamma != 1.0:
        g = 255.0 * (g / 255.0) ** (1.0 / design.gamma)
    return np.clip(np.rint(g), 0, 255).astype(np.uint8)


def fringe_image(lcd: Lcd, design: FringeDesign, direction: str, period: int, step: int,
                 n_steps: int, z_mm: float) -> np.ndarray:
    """The full LCD image ``(lcd.height, lcd.width)`` uint8 for one pattern."""
    prof = fringe_profile(lcd, design, direction, period, step, n_steps, z_mm)
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


def design_check(rig: Rig, *, modulation_dn=None, noise_dn: float | None = None,
                 margin_sigmas: float = 6.0) -> DesignReport:
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
        ok = span_lo >= -0.5 and span_hi < f.periods_px[0]
        items.append(DesignItem(
            f"unambiguous range {d}", bool(ok), float(f.periods_px[0]),
            f"coarsest period > span of u+s = [{span_lo:.1f}, {span_hi:.1f}] px ({span:.1f} px)",
            (f"period {f.periods_px[0]} px covers the LCD plus carrier" if ok else
             f"coarsest period {f.periods_px[0]} px does not cover u+s in [{span_lo:.1f}, {span_hi:.1f}]"
             " px: unwrapping would be ambiguous; use a longer coarse period or a smaller carrier"
             if span_lo >= -0.5 else
             f"negative carrier shifts u+s below 0 (to {span_lo:.1f} px): the coarse phase wraps"),
        ))
    worst_mod = float(mod.min())
    for j in range(1, len(f.periods_px)):
        ratio = f.periods_px[j - 1] / f.periods_px[j]
        s_prev = phase_noise_rad(noise_dn, worst_mod, f.steps[j - 1]) * ratio
        s_this = phase_noise_rad(noise_dn, worst_mod, f.steps[j])
        sigma = float(math.hypot(s_prev, s_this))
        margin = (np.pi / 2) / sigma if sigma > 0 else np.inf
        ok = margin >= margin_sigmas
        items.append(DesignItem(
            f"unwrapping {f.periods_px[j - 1]} -> {f.periods_px[j]}", bool(ok), float(margin),
            f"margin >= {margin_sigmas:g} sigma (quarter-period tolerance / phase noise)",
            f"ratio {ratio:.2f}: margin {margin:.1f} sigma" + ("" if ok else
              " is too small: add an intermediate period or more steps"),
        ))
    pitch = max(rig.lcd.pitch_mm)
    sigma_u = phase_noise_rad(noise_dn, mod, f.steps[-1]) * f.periods_px[-1] / (2 * np.pi)
    floor_um = sigma_u * pitch * 1000.0
    items.append(DesignItem(
        "noise floor", True, float(floor_um.max()),
        "predicted 1-sigma coordinate noise, finest period",
        f"{floor_um.min():.2f} to {floor_um.max():.2f} µm per position",
    ))
    return DesignReport(tuple(items), floor_um)
