"""The trust harness's rigs, and the product run on them as a user runs it (issue 30).

Each draw is a new rig (:func:`ptpcore.simulate.draw_rig`: lens, field, glass, stage errors and pose
drawn from the seed) of one of :data:`RIG_TYPES` at :data:`WIDTH` px; :func:`simulate` renders its
dataset folder as ``ptp simulate`` does and :func:`calibrate` writes the LUTs ``ptp calibrate`` writes.
Every research tool draws its rigs here, so a rig named ``KIND#SEED`` is the same rig in all of them.
"""

from __future__ import annotations

import os
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np

from research.scoring import fit_weights

RIG_TYPES = ("mild", "realistic", "rough", "real", "symmetric", "fisheye", "prism", "ripple")
"""Every noisy preset, an x/y-symmetric rig with a declared cover glass, and the lens models the
Brown-plus-field generator cannot produce (:data:`ptpcore.simulate.LENS_MODELS`)."""
GLASS_MM, GLASS_INDEX = 1.1, 1.52
WIDTH = int(os.environ.get("PTP_TRUST_WIDTH", 640))
"""Sensor width of every draw (``PTP_TRUST_WIDTH``: another width, for a quick check of the harness only;
:mod:`research.trust_mc`'s worker processes read it)."""


def symmetric_rig():
    """The realistic preset made x/y-symmetric (no tilt, offset, skew, principal-point offset,
    tangential distortion; equal carriers) with a declared 1.1 mm cover glass."""
    from ptpcore.simulate import preset

    rig, s = preset("realistic")
    lens = replace(s.lens, principal_offset_px=(0.0, 0.0), dist=(s.lens.dist[0], s.lens.dist[1], 0.0, 0.0,
                                                                  s.lens.dist[4]))
    rig = replace(rig, stage=replace(rig.stage, direction=(0.0, 0.0, 1.0)),
                  fringes=replace(rig.fringes, carrier_px_per_mm=(1.5, 1.5)),
                  lcd=replace(rig.lcd, cover_glass_mm=GLASS_MM, cover_glass_index=GLASS_INDEX))
    s = replace(s, name="symmetric", lens=lens, tilt_deg=(0.0, 0.0, 0.0), offset_mm=(0.0, 0.0),
                skew=(0.0, 0.0), cover_glass_mm=GLASS_MM, cover_glass_index=GLASS_INDEX)
    return rig, s


def drawn_rig(kind: str, seed: int, glass: bool = False):
    """The rig of draw ``seed`` of ``kind`` (a :data:`RIG_TYPES` name); ``glass``: with a declared
    1.1 mm cover glass added (the drift checks)."""
    from ptpcore.simulate import base_rig, draw_rig, scale_rig

    base = symmetric_rig() if kind == "symmetric" else base_rig(kind)
    if WIDTH != base[0].camera.width:
        base = scale_rig(*base, WIDTH)
    rig, s = draw_rig(base, kind, seed)
    if glass:
        rig = replace(rig, lcd=replace(rig.lcd, cover_glass_mm=GLASS_MM, cover_glass_index=GLASS_INDEX))
        s = replace(s, cover_glass_mm=GLASS_MM, cover_glass_index=GLASS_INDEX)
    return rig, s


def simulator_seed(kind: str, seed: int) -> int:
    """The simulator's seed of draw ``seed`` of ``kind``: its own stream per rig type.

    The simulator's seed draws the distortion field's modes and the stage's height errors; with the
    draw's seed alone, draw 1 of every rig type had the same normal deviates (stage errors 1.35x their
    declared sigma on all eight), so the rig types' rows were not independent.
    """
    return zlib.crc32(f"{kind}#{int(seed)}".encode())


def simulate(folder: Path, rig, settings, seed: int, noise_seed: int) -> Path:
    """Render a dataset folder (what ``ptp simulate`` writes) of a drawn rig."""
    from ptpcore.simulate import simulate_dataset

    return simulate_dataset(folder, rig, settings, seed=seed, noise_seed=noise_seed)


def calibrate(folder: Path, models, stage_sigma_um: float, record: dict | None = None) -> dict:
    """``ptp calibrate FOLDER --model M --degree D --stage-sigma-um S`` for each ``(name, M, D)``
    or ``(name, M, D, rig)``, decoding once; ``rig`` replaces the folder's rig.toml for that fit
    (the undeclared glass: the decoded samples do not depend on it). With ``record``, its
    ``"position_sigma_um"`` gets each position's median predicted sample sigma (um; the weights of
    each pixel's fit in z, for :func:`research.stage_luck.drawn_stage_luck`).

    Returns ``{name: path of the written LUT}`` (``FOLDER/NAME.lut.h5``).
    """
    from ptpcore.io.lutfile import save_lut
    from ptpcore.run import new_session, run_session

    session = new_session(folder, model="auto", stage_sigma_um=stage_sigma_um)
    run_session(session, stop_after="samples", validate=False)
    if record is not None:
        w = fit_weights(session.samples, session.rig)
        record["position_sigma_um"] = [float(1e3 / np.sqrt(np.median(wk[wk > 0]))) for wk in w]
        del w
    out = {}
    for name, model, degree, *other in models:
        s = replace(session, settings=session.settings.with_changes(model=model, degree=degree), lut=None,
                    rig=other[0] if other else session.rig)
        run_session(s, validate=False)
        path = folder / f"{name}.lut.h5"
        save_lut(s.lut, path)
        out[name] = path
    return out


def sweep_folder(out: Path, kind: str, seed: int, noiseless: bool) -> Path:
    """Sweep A of draw ``KIND#SEED`` rendered (once) under ``out``: ``KIND-SEED-a`` (the folder
    :mod:`research.trust_split` also renders), or ``KIND-SEED-noiseless`` (no image noise, no stage
    errors)."""
    rig, settings = drawn_rig(kind, seed)
    sim = simulator_seed(kind, seed)
    folder = out / f"{kind}-{seed}-{'noiseless' if noiseless else 'a'}"
    if not (folder / "rig.toml").exists():
        if noiseless:
            settings = replace(settings, noise=False, stage_error_um=0.0)
        simulate(folder, rig, settings, sim, sim)
    return folder
