"""The calibration pipeline: frames -> LCD coordinates -> samples -> LUT.

It streams: one position is decoded at a time from a
:class:`~ptpcore.dataset.FrameSource`, its world coordinates are stored in a
:class:`~ptpcore.lut.SampleStack`, and its frames are dropped.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .lut import Lut, SampleStack, fit_lut
from .phase import (DecodedPosition, DecodeOptions, PhaseAccumulator, decode_direction,
                    finish_position)
from .rig import Rig, rig_to_toml

__all__ = ["decode_position", "world_xy", "collect_samples", "calibrate"]

Progress = Callable[[float, str], None]


def decode_position(source, k: int, options: DecodeOptions = DecodeOptions()) -> DecodedPosition:
    """Decode every direction and period of position ``k``.

    Parameters
    ----------
    source : FrameSource
    k : int
    options : DecodeOptions

    Returns
    -------
    DecodedPosition
        With the wrapped phase, modulation and background of every level.
    """
    rig: Rig = source.rig
    f = rig.fringes
    shape = rig.camera.shape
    accs: dict[tuple[str, int], PhaseAccumulator] = {}
    for (d, j, _t, n, big_n), img in source.frames(k):
        acc = accs.get((d, j))
        if acc is None:
            acc = accs[(d, j)] = PhaseAccumulator(shape, big_n, rig.camera.max_level)
        acc.add(img, n)
    decoded = {}
    z = rig.stage.z_mm[k]
    for d in f.directions:
        wrapped = [accs[(d, j)].result() for j in range(len(f.periods_px))]
        decoded[d] = decode_direction(wrapped, f.periods_px, f.carrier(d) * z)
    return finish_position(rig, k, decoded, options)


def world_xy(rig: Rig, pos: DecodedPosition) -> tuple[np.ndarray, np.ndarray]:
    """World X, Y (mm) of a decoded position: ``X = u*pitch_x + a*z`` (METHOD.md section 2)."""
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    x = pos.u * px + a * pos.z_mm if pos.u is not None else None
    y = pos.v * py + b * pos.z_mm if pos.v is not None else None
    return x, y


def collect_samples(source, *, options: DecodeOptions = DecodeOptions(), positions=None,
                    progress: Progress | None = None, on_position=None) -> SampleStack:
    """Decode every position and gather each pixel's samples.

    Parameters
    ----------
    source : FrameSource
        Must show both directions.
    options : DecodeOptions
    positions : sequence of int, optional
        Decode only these positions (others stay invalid).
    progress : callable, optional
        ``progress(fraction, message)``; may raise to cancel.
    on_position : callable, optional
        ``on_position(decoded)`` after each position (e.g. a GUI preview).

    Returns
    -------
    SampleStack
    """
    rig: Rig = source.rig
    if set(rig.fringes.directions) != {"x", "y"}:
        raise ValueError("calibration needs fringes in both directions x and y")
    k_total = rig.stage.n_positions
    todo = list(range(k_total)) if positions is None else list(positions)
    samples = SampleStack.empty(rig.stage.z_mm, rig.camera.shape)
    for i, k in enumerate(todo):
        if progress:
            progress(i / len(todo), f"decoding position {k + 1}/{k_total} (z = {rig.stage.z_mm[k]:g} mm)")
        pos = decode_position(source, k, options)
        x, y = world_xy(rig, pos)
        fine_x = pos.directions["x"].wrapped[-1]
        fine_y = pos.directions["y"].wrapped[-1]
        samples.set_position(k, x, y, pos.reasons,
                             np.minimum(fine_x.modulation, fine_y.modulation),
                             0.5 * (fine_x.background + fine_y.background))
        if on_position:
            on_position(pos)
    if progress:
        progress(1.0, "decoding done")
    return samples


def calibrate(source, *, model: str = "poly", degree: int = 3, options: DecodeOptions = DecodeOptions(),
              positions=None, progress: Progress | None = None) -> tuple[Lut, SampleStack]:
    """Images to LUT in one call.

    Parameters
    ----------
    source : FrameSource
    model, degree : see :func:`ptpcore.lut.fit_lut`
    options : DecodeOptions
    positions : sequence of int, optional
        Positions to calibrate on (default all).
    progress : callable, optional

    Returns
    -------
    lut : Lut
    samples : SampleStack
    """
    def sub(lo, hi):
        if progress is None:
            return None
        return lambda f, msg: progress(lo + (hi - lo) * f, msg)

    samples = collect_samples(source, options=options, positions=positions, progress=sub(0.0, 0.9))
    lut = fit_lut(samples, model, degree, positions=positions, rig_toml=rig_to_toml(source.rig),
                  progress=sub(0.9, 1.0))
    return lut, samples
