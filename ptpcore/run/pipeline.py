"""The streaming decode: frames -> LCD coordinates -> samples, one position at a time.

It streams: one position is decoded at a time from a
:class:`~ptpcore.io.dataset.FrameSource`, its world coordinates are stored in a
:class:`~ptpcore.io.SampleStack`, and its frames are dropped. This module only orders the
stages; each lives in its room (``docs/performance.md`` has the numbers):

- the read-ahead (:mod:`ptpcore.io.readahead`): from a dataset folder, a reader thread reads
  the next sets (the N frames of one period and direction) while the current one is decoded;
- the per-position recipe (:mod:`ptpcore.decode.position`): wrapped phases in cache-sized row
  tiles on every core, unwrapping, pixel classification, the noise samples;
- sample storage (:mod:`ptpcore.io.sample_store`): the world coordinates over the same row
  tiles, written straight into the sample stack, which lives in a temporary file
  (:class:`ptpcore.store.SpillStore`) when it is big, so memory stays flat however many
  positions there are;
- between positions the C allocator's free pages go back to the system
  (:func:`ptpcore.store.release_free_memory`), so the resident size does not creep up
  position by position.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from ptpcore.io.readahead import DatasetReader, check_alignment, is_dataset, source_sets, tapped_sets
from ptpcore.io.sample_store import SampleWriter, world_xy
from ptpcore.io.samples import SampleStack
from ptpcore.rig.naming import position_label
from ptpcore.decode.noise import NoiseAccumulator, NoiseModel
from ptpcore.decode.phase import DecodedPosition, DecodeOptions
from ptpcore.decode.position import decode_sets, neighbourhood_noise_dn
from ptpcore.progress import Progress
from ptpcore.store import release_free_memory
from ptpcore.rig import Rig

__all__ = ["decode_position", "decode_positions", "world_xy", "collect_samples", "SPILL_BYTES"]

SPILL_BYTES = 256 << 20
"""``collect_samples(spill=None)`` moves the sample stack to a temporary file above this size."""


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
    if is_dataset(source):
        reader = DatasetReader(source, [k])
        try:
            return decode_sets(rig, k, reader.sets_of(k), options, True, source=source)
        finally:
            reader.close()
    return decode_sets(rig, k, source_sets(source, k), options, True, source=source)


def decode_positions(source, positions, options: DecodeOptions = DecodeOptions(), *, spatial: bool = True,
                     per_direction: bool = False):
    """Decode positions one after the other, as ``ptp decode`` needs them: a generator.

    One reader for all of them (a dataset folder's is read ahead across positions), and
    every position decoded into the same maps: the background of the finest level only
    (what the samples and a ``ptp-decoded/1`` file keep; :func:`decode_position` has every
    level's). Each yielded position is valid until the next is asked for.

    Parameters
    ----------
    source : FrameSource
    positions : sequence of int
    options : DecodeOptions
    spatial : bool
        False: no spatial-consistency flags in the positions' ``reasons`` (a caller that
        classifies each direction alone, as ``ptp decode`` does, runs its own check).
    per_direction : bool
        Each direction also classified alone, in the same pass (``info["direction_reasons"]``,
        :func:`ptpcore.decode.position.decode_sets`); ``reasons`` is then their OR.

    Yields
    ------
    DecodedPosition
    """
    rig: Rig = source.rig
    if not spatial:
        options = replace(options, spatial_k=None)
    todo = list(positions)
    reader = DatasetReader(source, todo) if is_dataset(source) and todo else None
    buffers: dict = {}
    try:
        for k in todo:
            sets = reader.sets_of(k) if reader else source_sets(source, k)
            yield decode_sets(rig, k, sets, options, False, buffers, source, per_direction)
    finally:
        if reader:
            reader.close()


def collect_samples(source, *, options: DecodeOptions = DecodeOptions(), positions=None,
                    progress: Progress | None = None, on_position=None, spill: bool | None = None,
                    spill_dir=None, on_frame=None, full_positions=None) -> SampleStack:
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
        ``on_position(decoded)`` after each position (e.g. a GUI preview); the
        decoded position then carries background and noise maps of every
        level (otherwise only of the finest, which is all the samples need),
        in arrays of its own. Call it on the calling thread; it must not keep
        the maps of a position outside ``full_positions`` (they are reused).
    full_positions : collection of int, optional
        With ``on_position``: only these positions' maps are complete and their
        own (default: every position's). A big sensor's GUI that shows one
        position's phase maps needs one set, not one per position (617 MB at 5 MP).
    on_frame : callable, optional
        ``on_frame(k, (d, j, period, n, N), image (H, W))`` for every frame of
        position ``k`` once its set (the N phase steps of one period) is read
        (e.g. a live preview); may raise to cancel. The image is the reader's
        buffer: copy what is kept.
    spill : bool, optional
        Keep the ``(K, H, W)`` arrays in a temporary file (``numpy.memmap``)
        instead of memory. Default: when they would exceed :data:`SPILL_BYTES`.
    spill_dir : path, optional
        Folder of that file (default: the system's temporary folder).

    Returns
    -------
    SampleStack
    """
    rig: Rig = source.rig
    if set(rig.fringes.directions) != {"x", "y"}:
        raise ValueError("calibration needs fringes in both directions x and y")
    k_total = rig.stage.n_positions
    todo = list(range(k_total)) if positions is None else list(positions)
    check_alignment(source, todo)
    shape = rig.camera.shape
    if spill is None:
        spill = k_total * shape[0] * shape[1] * 17 > SPILL_BYTES
    sink = SampleWriter(rig, spill, spill_dir)
    # Spilled (a big sensor): the noise model's binning gets a thread of its own.
    writer = ThreadPoolExecutor(1, thread_name_prefix="ptp-noise") if sink.spilled else None
    noise = NoiseAccumulator(rig.camera.max_level)
    fallback: list = []
    reader = DatasetReader(source, todo) if is_dataset(source) else None
    buffers: dict = {}
    noise_jobs: list = []
    try:
        for i, k in enumerate(todo):
            if progress:
                progress(i / len(todo), f"decoding {position_label(k, rig.stage.z_mm[k])} ({i + 1} of {len(todo)})")
            sets = reader.sets_of(k) if reader else source_sets(source, k)
            if on_frame is not None:
                sets = tapped_sets(sets, rig, k, on_frame)
            # Without a listener the position's maps are scratch: reuse them.
            full = on_position is not None and (full_positions is None or k in full_positions)
            pos = decode_sets(rig, k, sets, options, full, None if full else buffers, source)
            sink.put(pos, k)
            for d, part in pos.info.get("noise_samples", {}).items():
                valid = pos.reasons[part["rows"]][:, part["cols"]].ravel() == 0
                args = (part["background"], part["var"], valid & np.isfinite(part["var"]), part["dof"])
                if writer is None:
                    noise.add(*args)
                else:  # on its own thread (in order), off the decoding's path
                    noise_jobs.append(writer.submit(noise.add, *args))
            fallback.extend(neighbourhood_noise_dn(rig, pos))
            for d, (t, n) in pos.info.get("noise_levels", {}).items():
                if float(t) != float(rig.fringes.periods(d)[-1]):
                    noise.source = f"residual of period {float(t):g} px (N = {n})"
            if on_position:
                on_position(pos)
            release_free_memory()  # the position's transients: keep the heap from growing position by position
    finally:
        if reader:
            reader.close()
        if writer is not None:
            writer.shutdown(wait=True)
    for w in noise_jobs:
        w.result()  # raise a failure here
    samples = sink.finish()
    samples.noise = noise.model()
    if samples.noise is None and fallback:
        samples.noise = NoiseModel(float(np.median(fallback)) ** 2, 0.0, "neighbourhood")
    if progress:
        progress(1.0, "decoding done")
    return samples
