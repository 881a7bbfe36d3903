"""Rigs drawn per seed, and rigs with lens models Brown cannot describe (issue 30).

A Monte Carlo that varies only the noise seed of one preset tests an estimator
on one lens, one pose and one set of stage errors. :func:`draw_rig` draws a
new rig around a base preset from a seed: its lens (focal length, principal
point, Brown coefficients, the smooth field's amplitude, the pupil shift and
the terms of :mod:`ptpcore.simulate.lens_models`), its pose, its cover glass
(thickness and index, when the preset has one) and its stage (height errors,
carriage run-out and tilt, travel skew, panel bow). The simulator's seed then
draws the field's modes and the noise, so a drawn rig is ``(rig, settings,
seed)``.

:data:`LENS_MODELS` are three rigs on the ``realistic`` preset whose lens
leaves the simulator's Brown-plus-smooth-field family: an equidistant
(fisheye-like) lens at a shorter focal length and closer to the LCD, a lens
with thin-prism terms, and a lens with a short-scale distortion field.

Everything is seeded: ``draw_rig(base, name, seed)`` is the same rig on every
machine (numpy's ``default_rng`` streams are stable for ``uniform`` and
``normal``).
"""

from __future__ import annotations

import zlib
from dataclasses import replace

import numpy as np

from ptpcore.errors import ConfigError
from ptpcore.rig.rigfile import Rig
from ptpcore.simulate.virtual_rig import SimSettings, preset

__all__ = ["LENS_MODELS", "lens_model_rig", "base_rig", "draw_rig"]

LENS_MODELS = ("fisheye", "prism", "ripple")
"""Rigs with a lens beyond Brown plus a smooth field (see :func:`lens_model_rig`)."""


def lens_model_rig(name: str) -> tuple[Rig, SimSettings]:
    """The ``realistic`` preset with a lens model of :mod:`ptpcore.simulate.lens_models`.

    ``fisheye``
        Equidistant projection (``r = f theta``) at f = 520 px (640 px wide,
        45 degrees off axis in the corners), mild Brown on top, 120 mm from
        the middle of the sweep (the LCD fills the image at the near end and
        about 70 % of it at the far end).
    ``prism``
        The realistic lens plus thin-prism terms ``s1..s4 = 2e-3, -1e-3,
        -1.5e-3, 8e-4`` (about 0.4 px in the corners).
    ``ripple``
        The realistic lens plus a short-scale field: 0.05 px RMS per axis at
        a 32 px wavelength (the smooth field varies over the whole image).
    """
    rig, s = preset("realistic")
    lens = s.lens
    if name == "fisheye":
        lens = replace(lens, focal_px=520.0, projection="equidistant", dist=(-0.02, 0.004, 3e-4, -2e-4, 0.0))
        s = replace(s, distance_mm=120.0)
    elif name == "prism":
        lens = replace(lens, prism=(2e-3, -1e-3, -1.5e-3, 8e-4))
    elif name == "ripple":
        lens = replace(lens, ripple_px=0.05, ripple_wavelength_px=32.0)
    else:
        raise ConfigError(f"unknown lens model '{name}' (choose from {', '.join(LENS_MODELS)})")
    return rig, replace(s, name=name, lens=lens)


def base_rig(name: str) -> tuple[Rig, SimSettings]:
    """A preset (:data:`ptpcore.simulate.PRESETS`) or a lens-model rig (:data:`LENS_MODELS`) by name."""
    return lens_model_rig(name) if name in LENS_MODELS else preset(name)


def _factor(rng: np.random.Generator, spread: float) -> float:
    """A factor uniform in ``[1 - spread, 1 + spread]``."""
    return float(rng.uniform(1.0 - spread, 1.0 + spread))


def draw_rig(base: tuple[Rig, SimSettings], name: str, seed: int) -> tuple[Rig, SimSettings]:
    """A new rig drawn around ``base`` from ``seed`` (the module docstring says what varies).

    Every size is the base's times a factor (uniform within +-30 %, the focal
    length +-5 %), every signed small term (tangential and prism coefficients)
    also gets a random sign, the pose a normal perturbation (0.5 degrees per
    axis, 1 mm sideways, +-5 % distance) and the travel skew 1 mrad per
    axis (declared in ``rig.toml`` as the base declares it: the rig says its
    true travel direction). A cover glass is drawn only where the base has
    one (0.7 .. 1.5 mm, index 1.48 .. 1.56, declared as the base declares
    it). The camera, the LCD's photometry, the fringes and the stage readings
    stay the base's.

    Parameters
    ----------
    base : (Rig, SimSettings)
        E.g. :func:`base_rig`, possibly scaled (:func:`ptpcore.simulate.scaled_preset`).
    name : str
        The base's name: with ``seed``, it selects the stream (two bases never share draws).
    seed : int

    Returns
    -------
    (Rig, SimSettings)
        ``settings.name`` is ``"{name}#{seed}"``; simulate it with the same ``seed``.
    """
    rig, s = base
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
    lens = s.lens
    sign = lambda: float(rng.choice([-1.0, 1.0]))  # noqa: E731
    k1, k2, p1, p2, k3 = (tuple(lens.dist) + (0.0,) * 5)[:5]
    dist = (k1 * _factor(rng, 0.3), k2 * _factor(rng, 0.3), p1 * _factor(rng, 0.5) * sign(),
            p2 * _factor(rng, 0.5) * sign(), k3 * _factor(rng, 0.3))
    scale_px = rig.camera.width / 640.0
    lens = replace(
        lens, focal_px=lens.focal_px * _factor(rng, 0.05), dist=dist,
        principal_offset_px=tuple(float(p + rng.normal(0.0, 4.0 * scale_px)) for p in lens.principal_offset_px),
        field_amplitude_px=lens.field_amplitude_px * _factor(rng, 0.5),
        pupil_shift_mm=lens.pupil_shift_mm * _factor(rng, 0.5),
        prism=tuple(float(v) * _factor(rng, 0.5) * sign() for v in lens.prism),
        ripple_px=lens.ripple_px * _factor(rng, 0.3),
        ripple_wavelength_px=lens.ripple_wavelength_px * _factor(rng, 0.2))
    skew = tuple(float(v + rng.normal(0.0, 1e-3)) for v in s.skew)
    s = replace(
        s, name=f"{name}#{int(seed)}", lens=lens,
        tilt_deg=tuple(float(v + rng.normal(0.0, 0.5)) for v in s.tilt_deg),
        offset_mm=tuple(float(v + rng.normal(0.0, 1.0)) for v in s.offset_mm),
        distance_mm=s.distance_mm * _factor(rng, 0.05),
        stage_error_um=s.stage_error_um * _factor(rng, 0.5), skew=skew,
        tilt_urad=s.tilt_urad * _factor(rng, 0.5), roll_urad=s.roll_urad * _factor(rng, 0.5),
        runout_um=s.runout_um * _factor(rng, 0.5), bow_um=s.bow_um * _factor(rng, 0.5))
    declared_skew = tuple(rig.stage.direction[:2]) == tuple(base[1].skew)
    stage = replace(rig.stage, direction=(skew[0], skew[1], 1.0)) if declared_skew else rig.stage
    rig = replace(rig, stage=stage)
    if s.cover_glass_mm > 0:
        t, n = float(rng.uniform(0.7, 1.5)), float(rng.uniform(1.48, 1.56))
        s = replace(s, cover_glass_mm=t, cover_glass_index=n)
        if rig.lcd.cover_glass_mm:  # declared in rig.toml: declare the drawn one
            rig = replace(rig, lcd=replace(rig.lcd, cover_glass_mm=t, cover_glass_index=n))
    return rig, s
