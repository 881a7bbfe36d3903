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

import contextlib

import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ptpcore.decode.phase import REASON_KEYS, REASON_NAMES, DecodeOptions, finish_position
from ptpcore.errors import DatasetError
from ptpcore.io.decodedfile import Decoded
from ptpcore.store import release_free_memory
from ptpcore.rig.naming import position_label
from ptpcore.rig.rigfile import rig_to_toml
from ptpcore.run.diagnose import MIN_VALID_FRACTION, convention_check, position_report

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
        A position decoded with ``per_direction`` (:func:`ptpcore.run.pipeline.decode_positions`)
        brings each direction's classification along: it is completed (in a copy), not made again.
    """
    from ptpcore.decode.position import flag_more_reasons

    options = options.for_rig(rig)
    done = pos.info.get("direction_reasons", {})
    out = {}
    for d, dec in pos.directions.items():
        r = done.get(d)
        r = finish_position(rig, pos.index, {d: dec}, options).reasons if r is None else r.copy()
        flag_more_reasons(rig, pos, options, r, directions=[d])
        out[d] = r
    return out


def decode_dataset(source, positions=None, *, options: DecodeOptions = DecodeOptions(),
                   min_fraction: float = MIN_VALID_FRACTION, check_conventions: bool = True,
                   progress: Callable[[float, str], None] | None = None, out=None,
                   compression: str = "none") -> DecodeRun:
    """Decode some positions of a dataset into ``ptp-decoded/1`` arrays.

    Parameters
    ----------
    out : path, optional
        Write the ``ptp-decoded/1`` file there position by position (atomically:
        nothing is left on an error), each position written on a thread of its own while the
        next one decodes (:class:`ptpcore.io.decodedfile.BackgroundWriter`: two positions' maps in
        memory at most); ``DecodeRun.decoded`` is then None. Without it the arrays of every
        position come back in memory.
    compression : str
        The file's filters: ``"none"`` or ``"gzip"`` (shuffle + deflate level 1: about a third of
        the size, 2.35 CPU-s more per 5 MP position, twice its reading;
        :data:`ptpcore.io.decodedfile.COMPRESSIONS`).

    Raises
    ------
    DatasetError
        A wrong phase convention recognised from the data (naming the setting
        that fixes it), or no pixel valid in any position and direction.
    ValueError
        A position that does not exist.
    """
    from ptpcore.io.decodedfile import BackgroundWriter, decoded_writer

    rig = source.rig
    k_total = rig.stage.n_positions
    todo = list(range(k_total)) if positions is None else [int(k) for k in positions]
    bad = [k for k in todo if not 0 <= k < k_total]
    if bad:
        raise ValueError(f"positions {bad} do not exist (the dataset has {k_total}: 0 to {k_total - 1})")
    if not todo:
        raise ValueError("no position to decode")
    z = np.asarray([rig.stage.z_mm[k] for k in todo], float)
    toml = _rig_text(source)
    bits = {name: bit for bit, name in REASON_KEYS.items()}
    if out is None:
        sink = _MemorySink(todo, z, rig.camera.shape, bits, toml)
        run = _decode_into(source, todo, options.for_rig(rig), min_fraction, check_conventions, progress, sink)
        run.decoded = sink.decoded
        return run
    with decoded_writer(out, todo, z, rig.camera.shape, bits, toml, compression) as file_sink:
        sink = BackgroundWriter(file_sink)
        try:
            run = _decode_into(source, todo, options.for_rig(rig), min_fraction, check_conventions, progress, sink)
        except BaseException:
            sink.close(quiet=True)  # the writing thread ends before the file is dropped
            raise
        sink.close()
        return run


def _rig_text(source) -> str:
    """The dataset's own ``rig.toml`` text (kept as written), or the rig written anew."""
    folder = getattr(source, "folder", None)
    if folder is not None and (folder / "rig.toml").is_file():
        return (folder / "rig.toml").read_text(encoding="utf-8")
    return rig_to_toml(source.rig)


class _MemorySink:
    """Every decoded position's maps in memory (:func:`decode_dataset` without ``out``)."""

    def __init__(self, todo, z, shape, bits: dict, toml: str):
        kk, (h, w) = len(todo), shape
        self.decoded = Decoded(np.asarray(todo, np.int32), z, np.full((kk, h, w), np.nan, np.float32),
                               np.full((kk, h, w), np.nan, np.float32), np.zeros((kk, 2, h, w), np.float32),
                               np.zeros((kk, 2, h, w), np.float32), np.zeros((kk, 2, h, w), np.uint16), bits, toml)

    def write(self, i: int, u, v, modulation, background, reasons) -> None:
        d = self.decoded
        d.u[i], d.v[i], d.modulation[i], d.background[i], d.reasons[i] = u, v, modulation, background, reasons


class _ReasonTally:
    """How many pixels carry each reason bit, over every decoded position and direction."""

    def __init__(self):
        self.counts: dict = {}
        self.n = 0
        self.any_valid = False

    def add(self, reasons: np.ndarray) -> None:
        self.any_valid |= bool(np.any(reasons == 0))
        self.n += reasons.size
        for bit in REASON_NAMES:
            self.counts[bit] = self.counts.get(bit, 0) + int(np.count_nonzero(reasons & bit))

    def dominant(self) -> tuple[str, float]:
        """As :func:`ptpcore.run.diagnose.dominant_reason` over everything added."""
        best, frac = "none", 0.0
        for bit, name in REASON_NAMES.items():
            c = self.counts.get(bit, 0) / max(self.n, 1)
            if c > frac:
                best, frac = name, c
        return best, frac


def _position_maps(rig, pos, per_direction: dict, run: DecodeRun, min_fraction: float):
    """One position's ``ptp-decoded/1`` maps (u, v (H, W); modulation, background, reasons (2, H, W))."""
    h, w = rig.camera.shape
    u, v = np.full((h, w), np.nan, np.float32), np.full((h, w), np.nan, np.float32)
    mod, bg = np.zeros((2, h, w), np.float32), np.zeros((2, h, w), np.float32)
    reasons = np.zeros((2, h, w), np.uint16)
    k = pos.index
    for d in rig.fringes.directions:
        di = "xy".index(d)
        dec, r = pos.directions[d], per_direction[d]
        reasons[di] = r
        fine = dec.wrapped[-1]
        mod[di] = fine.modulation
        if fine.background is not None:
            bg[di] = fine.background
        (u if d == "x" else v)[...] = np.where(r == 0, dec.coord, np.nan)
        run.valid_fraction[(k, d)] = float(np.mean(r == 0))
        line = position_report(f"position {k} (z = {rig.stage.z_mm[k]:g} mm), direction {d},", r, min_fraction)
        if line:
            run.warnings.append(line)
        run.noise_sources[(k, d)] = pos.info.get("noise_source", {}).get(d)
    return u, v, mod, bg, reasons


def _decode_into(source, todo, options, min_fraction, check_conventions, progress, sink) -> DecodeRun:
    """Decode ``todo`` position by position into ``sink`` (``sink.write(i, u, v, mod, bg, reasons)``)."""
    from ptpcore.run.pipeline import decode_positions

    rig = source.rig
    run, tally, checked = DecodeRun(None), _ReasonTally(), False
    present = ["xy".index(d) for d in rig.fringes.directions]
    # direction_reasons runs the spatial check of each direction alone: the decoder's own check (both
    # directions' flags together; only the positions' combined reasons, not written here) would be lost work.
    with contextlib.closing(decode_positions(source, todo, options, spatial=False, per_direction=True)) as decoded:
        for i, k in enumerate(todo):
            if progress:
                progress(i / len(todo), f"decoding {position_label(k, rig.stage.z_mm[k])} ({i + 1} of {len(todo)})")
            pos = next(decoded)
            maps = _position_maps(rig, pos, direction_reasons(rig, pos, options), run, min_fraction)
            tally.add(maps[4][present])
            if check_conventions and (not checked or any(run.valid_fraction[(k, d)] < min_fraction
                                                         for d in rig.fringes.directions)):
                if not checked:
                    harmonics = _harmonics_warning(rig, pos)
                    if harmonics:
                        run.warnings.append(f"position {k} (z = {rig.stage.z_mm[k]:g} mm): {harmonics}")
                checked = True
                where = str(getattr(source, "folder", "dataset")) + "/rig.toml"
                findings = convention_check(rig, pos, options)
                if any(fd.fatal for fd in findings):
                    raise DatasetError("; ".join(fd.message(where) for fd in findings if fd.fatal))
                run.warnings.extend(fd.message(where) for fd in findings)
            del pos
            sink.write(i, *maps)
            del maps
            release_free_memory()  # the position's transients (see ptpcore.parallel)
    if not tally.any_valid:
        name, frac = tally.dominant()
        raise DatasetError(f"no pixel is valid in any decoded position and direction; dominant reason: {name}"
                           f" ({100 * frac:.1f} % of pixels)")
    for line in run.warnings:
        warnings.warn(line, stacklevel=3)
    if progress:
        progress(1.0, "decoding done")
    return run
