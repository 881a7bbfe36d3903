"""What the LCD's integer levels do to the decoded coordinates.

The patterns are shown as 8-bit levels (``patterns.fringe_profile``), not as
the continuous sinusoid of docs/method.md section 3. Rounding a level moves it by up
to half a grey level, and the N-step phase of the rounded levels differs from
the ideal one by a deterministic error ``eps(j)`` for every LCD pixel ``j``:
about 0.01 LCD px RMS for ``amplitude = 100`` and 8 steps. A camera pixel
averages ``eps`` over its footprint (several LCD pixels), so what is left
is mostly ``eps``'s mean, which does *not* average out: with the presets'
designs it is -0.0015 LCD px (-0.08 um at a 50 um pitch), the same sign at
every pixel of a position and different between positions (it depends on the
carrier shift ``s``, hence on z). Far below the phase noise of one sample,
it is what limits a LUT that averages many pixels (the ``smooth`` kind).

The bias is known from the design: the levels are the engine's own. ``eps``
would be periodic in ``j`` with the (integer) period, but rounding breaks the
ties of ``offset = 127.5`` differently from period to period, so the expected
bias of a pixel whose footprint's phase is unknown is the mean of ``eps`` over
one period around its coordinate: :func:`level_bias_at` (from the table of
:func:`level_bias_table`). The smooth LUT subtracts it from every sample
before fitting (``fit_smooth_lut(level_bias=True)``); the plain LUT and 3DSTC,
noise-limited far above it, keep the decoded coordinates as they are.

The display is assumed to emit ``(level / 255) ** gamma`` with the gamma the
patterns were pre-compensated for (``[fringes] gamma``). A display that
dithers (FRC) shows levels between the integers and has no such bias: switch
the correction off there (``ptp calibrate --no-level-bias``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ptpcore.decode.patterns import fringe_profile
from ptpcore.rig.rigfile import FringeDesign, Lcd

__all__ = ["level_bias_px", "level_bias_table", "level_bias_at", "level_phase_errors_px"]


def level_phase_errors_px(design: FringeDesign, lcd: Lcd, direction: str, z_mm: float) -> np.ndarray:
    """Decoded-coordinate error of every LCD pixel, from the displayed (rounded) levels.

    Parameters
    ----------
    design : FringeDesign
    lcd : Lcd
    direction : {"x", "y"}
    z_mm : float
        Stage reading (sets the carrier shift ``s``).

    Returns
    -------
    (n,) float64
        ``eps(j)`` for every LCD pixel ``j`` along the pattern's axis (LCD px):
        the N-step coordinate of the displayed luminances of the finest
        period (the one the coordinates come from) minus the ideal ``j``.
    """
    j_fin = len(design.periods_px) - 1
    period, n_steps = int(design.periods_px[j_fin]), int(design.steps[j_fin])
    n = lcd.width if direction == "x" else lcd.height
    levels = np.stack([fringe_profile(lcd, design, direction, period, s, n_steps, z_mm)
                       for s in range(n_steps)]).astype(float)
    lum = (levels / 255.0) ** design.gamma
    # sum_n L_n exp(-i 2 pi n / N) = (N B / 2) exp(i phi) for L_n = A + B cos(phi + 2 pi n / N).
    delta = 2.0 * np.pi * np.arange(n_steps) / n_steps
    phasor = (lum * np.exp(-1j * delta)[:, None]).sum(axis=0)
    ideal = 2.0 * np.pi * (np.arange(n) + design.carrier(direction) * z_mm) / period
    return np.angle(phasor * np.exp(-1j * ideal)) * period / (2.0 * np.pi)


@lru_cache(maxsize=256)
def _table(design: FringeDesign, lcd: Lcd, direction: str, z_mm: float) -> tuple[np.ndarray, np.ndarray]:
    period = int(design.periods_px[-1])
    n = lcd.width if direction == "x" else lcd.height
    eps = level_phase_errors_px(design, lcd, direction, z_mm)
    # Antiderivative of the piecewise-constant eps at the pixel edges; near the
    # LCD's ends the window is the nearest whole period inside it.
    edges = np.arange(n + 1) - 0.5
    anti = np.concatenate([[0.0], np.cumsum(eps)])
    lo = np.clip(edges - period / 2.0, -0.5, max(n - 0.5 - period, -0.5))
    hi = np.minimum(lo + period, n - 0.5)
    bias = (np.interp(hi, edges, anti) - np.interp(lo, edges, anti)) / (hi - lo)
    edges.setflags(write=False)
    bias.setflags(write=False)
    return edges, bias


def level_bias_px(design: FringeDesign, lcd: Lcd, direction: str, z_mm: float) -> float:
    """Mean decoded-coordinate error (LCD px) of the displayed levels over the whole LCD at one position."""
    return float(level_phase_errors_px(design, lcd, direction, z_mm).mean())


def level_bias_table(design: FringeDesign, lcd: Lcd, direction: str, z_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The decoded-coordinate bias of the displayed levels, averaged over one period around each coordinate.

    ``eps(j)`` of :func:`level_phase_errors_px` is periodic only up to how the
    rounding breaks ties (``offset = 127.5`` puts levels exactly on .5 and the
    floating-point cosine decides), so its mean differs from period to period
    by up to 0.001 LCD px: the table follows it. A camera pixel whose
    footprint covers several LCD pixels sees ``eps`` averaged over its
    footprint; averaged over a period around the pixel's coordinate is the
    expectation when the footprint's phase within the period is unknown.

    Returns
    -------
    coords : (n + 1,) float64
        LCD coordinates ``-0.5 .. n - 0.5`` (LCD px) where the table is given.
    bias : (n + 1,) float64
        Mean of ``eps`` over ``[c - T/2, c + T/2]`` (LCD px), ``eps`` taken
        piecewise constant on each LCD pixel (``[j - 0.5, j + 0.5)``).
    """
    return _table(design, lcd, str(direction), float(z_mm))


def level_bias_at(design: FringeDesign, lcd: Lcd, direction: str, z_mm: float, coord) -> np.ndarray:
    """The bias of :func:`level_bias_table` at decoded coordinates ``coord`` (LCD px, any shape).

    Subtract it from the decoded coordinate. NaN stays NaN.
    """
    edges, bias = level_bias_table(design, lcd, direction, z_mm)
    return np.interp(coord, edges, bias)
