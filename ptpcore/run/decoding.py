"""``ptp decode``: a dataset's LCD coordinates, for rig bring-up and other tools.

One or more positions, one or both directions; no heights are needed and the
z readings are never judged. Each position is decoded with the calibration's
own decoder (:func:`ptpcore.run.pipeline.decode_position`); the reasons are
classified per direction (the ``ptp-decoded/1`` file keeps them apart).
Never silent (:mod:`ptpcore.run.diagnose`): positions keeping too few pixels
are reported with their dominant reason, a wrong phase convention is named,
and a decode that keeps no pixel fails.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ptpcore.decode.phase import REASON_KEYS, DecodeOptions, finish_position
from ptpcore.errors import DatasetError
from ptpcore.io.decodedfile import Decoded
from ptpcore.rig.rigfile import rig_to_toml
from ptpcore.run.diagnose import MIN_VALID_FRACTION, convention_check, dominant_reason, position_report

__all__ = ["DecodeRun", "decode_dataset", "direction_reasons"]


@dataclass
class DecodeRun:
    """A decode's maps and what it had to say."""

    decoded: Decoded
    warnings: list = field(default_factory=list)
    noise_sources: dict = field(default_factory=dict)
    valid_fraction: dict = field(default_factory=dict)  # (k, d) -> fraction


def _harmonics_warning(rig, pos) -> str | None:
    """The design check's display-harmonics verdict on the harmonics measured at ``pos``
    (:func:`ptpcore.decode.harmonics.measured_harmonics`), or None when they are below the noise."""
    from ptpcore.decode.harmonics import measured_harmonics
    from ptpcore.decode.patterns import design_check

    m = measured_harmonics(pos.info.get("noise_samples") or {})
    if m is None:
        return None
    report = design_check(rig, modulation_dn=m.modulation_dn, noise_dn=m.noise_dn, harmonic_dn=m.harmonic_dn)
    bad = [i.message for i in report.items if i.name == "display harmonics" and not i.ok]
    return bad[0] if bad else None


def direction_reasons(rig, pos, options: DecodeOptions = DecodeOptions()) -> dict:
    """The invalid-pixel reasons of each direction of a decoded position, apart.

    A position's own ``reasons`` combine both directions (a sample needs both);
    here each direction is classified alone, as ``ptp decode`` writes them.

    Parameters
    ----------
    rig : Rig
    pos : DecodedPosition
        From :func:`ptpcore.run.pipeline.decode_position`.
    options : DecodeOptions
        Thresholds (the rig's ``[decode]`` ones where these are the defaults).

    Returns
    -------
    dict
        ``{direction: (H, W) uint8}``: :class:`ptpcore.decode.phase.Reason` bits, 0 where valid.
    """
    from ptpcore.run.pipeline import flag_more_reasons

    options = options.for_rig(rig)
    out = {}
    for d, dec in pos.directions.items():
        r = finish_position(rig, pos.index, {d: dec}, options).reasons
        flag_more_reasons(rig, pos, options, r, directions=[d])
        out[d] = r
    return out


def decode_dataset(source, positions=None, *, options: DecodeOptions = DecodeOptions(),
                   min_fraction: float = MIN_VALID_FRACTION, check_conventions: bool = True,
                   progress: Callable[[float, str], None] | None = None) -> DecodeRun:
    """Decode some positions of a dataset into ``ptp-decoded/1`` arrays.

    Raises
    ------
    DatasetError
        A wrong phase convention recognised from the data (naming the setting
        that fixes it), or no pixel valid in any position and direction.
    ValueError
        A position that does not exist.
    """
    from ptpcore.run.pipeline import decode_position

    rig = source.rig
    f = rig.fringes
    k_total = rig.stage.n_positions
    todo = list(range(k_total)) if positions is None else [int(k) for k in positions]
    bad = [k for k in todo if not 0 <= k < k_total]
    if bad:
        raise ValueError(f"positions {bad} do not exist (the dataset has {k_total}: 0 to {k_total - 1})")
    if not todo:
        raise ValueError("no position to decode")
    options = options.for_rig(rig)
    h, w = rig.camera.shape
    kk = len(todo)
    u = np.full((kk, h, w), np.nan, np.float32)
    v = np.full((kk, h, w), np.nan, np.float32)
    mod = np.zeros((kk, 2, h, w), np.float32)
    bg = np.zeros((kk, 2, h, w), np.float32)
    reasons = np.zeros((kk, 2, h, w), np.uint16)
    run = DecodeRun(None)
    checked = False
    for i, k in enumerate(todo):
        if progress:
            progress(i / kk, f"decoding position {k + 1}/{k_total}")
        pos = decode_position(source, k, options)
        per_direction = direction_reasons(rig, pos, options)
        for d in f.directions:
            di = "xy".index(d)
            dec = pos.directions[d]
            r = per_direction[d]
            reasons[i, di] = r
            fine = dec.wrapped[-1]
            mod[i, di] = fine.modulation
            if fine.background is not None:
                bg[i, di] = fine.background
            coord = np.where(r == 0, dec.coord, np.nan).astype(np.float32)
            (u if d == "x" else v)[i] = coord
            run.valid_fraction[(k, d)] = float(np.mean(r == 0))
            line = position_report(f"position {k} (z = {rig.stage.z_mm[k]:g} mm), direction {d},", r, min_fraction)
            if line:
                run.warnings.append(line)
            run.noise_sources[(k, d)] = pos.info.get("noise_source", {}).get(d)
        if check_conventions and (not checked or any(run.valid_fraction[(k, d)] < min_fraction
                                                     for d in f.directions)):
            if not checked:
                harmonics = _harmonics_warning(rig, pos)
                if harmonics:
                    run.warnings.append(f"position {k} (z = {rig.stage.z_mm[k]:g} mm): {harmonics}")
            checked = True
            findings = convention_check(rig, pos, options)
            if findings:
                raise DatasetError("; ".join(fd.message(str(getattr(source, "folder", "dataset")) + "/rig.toml")
                                             for fd in findings))
    present = ["xy".index(d) for d in f.directions]
    if not np.any(reasons[:, present] == 0):
        name, frac = dominant_reason(reasons[:, present])
        raise DatasetError(f"no pixel is valid in any decoded position and direction; dominant reason: {name}"
                           f" ({100 * frac:.1f} % of pixels)")
    for line in run.warnings:
        warnings.warn(line, stacklevel=2)
    toml = rig_to_toml(rig)
    folder = getattr(source, "folder", None)
    if folder is not None and (folder / "rig.toml").is_file():
        toml = (folder / "rig.toml").read_text(encoding="utf-8")
    run.decoded = Decoded(np.asarray(todo, np.int32), np.asarray([rig.stage.z_mm[k] for k in todo], float),
                          u, v, mod, bg, reasons, {name: bit for bit, name in REASON_KEYS.items()}, toml)
    if progress:
        progress(1.0, "decoding done")
    return run
