"""The calibration pipeline: frames -> LCD coordinates -> samples -> LUT.

It streams: one position is decoded at a time from a
:class:`~ptpcore.io.dataset.FrameSource`, its world coordinates are stored in a
:class:`~ptpcore.io.SampleStack`, and its frames are dropped.

How it is fast on big sensors (``docs/performance.md`` has the numbers):

- The frames of one period and direction (a *set*) are gathered in a
  preallocated ``(N, H, W)`` buffer and reduced in cache-sized row tiles on
  every core (:func:`ptpcore.decode.phase.wrapped_phase`); the background and noise
  residuals are computed only at the finest period, where they are used.
- From a dataset folder, a reader thread reads the next sets while the
  current one is decoded: plain TIFFs are mapped (:func:`ptpcore.io.fastio.map_frame`,
  with the numba kernels); compressed TIFFs (LZW, deflate) and PNGs are decoded
  straight into the buffers on every core (:func:`ptpcore.io.read_into`:
  imagecodecs, the GIL released).
- Between positions the C allocator's free pages go back to the system
  (:func:`ptpcore.store.release_free_memory`), so the resident size does
  not creep up position by position.
- Unwrapping, pixel classification and the world coordinates run over the
  same row tiles, written straight into the sample stack.
- Big sample stacks live in a temporary file (:class:`ptpcore.store.SpillStore`),
  so memory stays flat however many positions there are; each row tile writes
  its rows of the position there as soon as it has stored them.
"""

from __future__ import annotations

import queue
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import Callable

import numpy as np

from ptpcore.io.lutfile import Lut
from ptpcore.fit.perpixel import fit_lut
from ptpcore.io.samples import SampleStack
from ptpcore.rig.naming import position_label
from ptpcore.decode.harmonics import harmonic_noise_samples
from ptpcore.decode.noise import NoiseAccumulator, NoiseModel
from ptpcore.decode.phase import (DecodedPosition, DecodeOptions, Reason, WrappedPhase, apply_convention,
    black_clipped, decode_and_finish, decode_direction, finish_position, fused_kernels, wrapped_phase)
from ptpcore.parallel import KERNEL_TILE_PIXELS, TILE_PIXELS, run_tiles, tile_workers
from ptpcore.store import release_free_memory
from ptpcore.rig.rigfile import Rig, rig_to_toml

__all__ = ["decode_position", "world_xy", "collect_samples", "calibrate", "SPILL_BYTES", "repeat_drift"]

Progress = Callable[[float, str], None]

SPILL_BYTES = 256 << 20
"""``collect_samples(spill=None)`` moves the sample stack to a temporary file above this size."""

NOISE_PIXELS = 1 << 18
"""At most about this many pixels per position and direction feed the noise model
(a regular sub-grid: every pixel up to 0.26 MP, every 4th row and column at 5 MP)."""


def _set_order(rig: Rig) -> list[tuple[str, int, int, int]]:
    """``(direction, level, period, N)`` of every set, in capture order."""
    f = rig.fringes
    return [(d, j, t, n) for d in f.directions for j, (t, n) in enumerate(zip(f.periods(d), f.steps_of(d)))]


def _frame_dtype(rig: Rig):
    return np.uint8 if rig.camera.bit_depth <= 8 else np.uint16


def _source_sets(source, k: int):
    """Yield ``((d, j), stack (N, H, W))`` for every set of position ``k`` of any source.

    Frames are copied into reusable buffers as they arrive (in any order); a
    set is yielded as soon as its N frames are in. A yielded buffer is reused
    once the caller asks for the next set.
    """
    rig: Rig = source.rig
    shape = rig.camera.shape
    free: dict = {}
    pending: dict = {}
    count: dict = {}
    for (d, j, _t, n, big_n), img in source.frames(k):
        img = np.asarray(img)
        key = (d, j)
        buf = pending.get(key)
        if buf is None:
            if img.shape != shape:
                raise ValueError(f"frame ({d}, period level {j}, step {n}) of position {k} has shape"
                                 f" {img.shape}, expected {shape}")
            spare = free.get((big_n, img.dtype))
            buf = spare.pop() if spare else np.empty((big_n, *shape), img.dtype)
            pending[key] = buf
            count[key] = set()
        if n in count[key] or not 0 <= n < big_n:
            raise ValueError(f"step {n} repeated or outside 0..{big_n - 1}")
        buf[n] = img
        count[key].add(n)
        if len(count[key]) == big_n:
            del pending[key]
            yield key, buf
            free.setdefault((big_n, buf.dtype), []).append(buf)
    if pending:
        (d, j), buf = next(iter(pending.items()))
        raise ValueError(f"only {len(count[(d, j)])} of {len(buf)} steps were added")


READ_AHEAD_BYTES = 200 * 2 ** 20
"""The reader's buffers of sets read ahead, at most (but two sets): 3 sets of 8 frames at 5 MP (8 bit),
2 at 12 MP (96 MB each). Two keep a set ready while one is decoded; reading is several times faster
than decoding."""


class _DatasetReader:
    """Reads the sets of some positions of a dataset folder ahead, on its own threads.

    Each set's N files are read in parallel: with the numba kernels, plain
    TIFFs are mapped (:func:`ptpcore.io.fastio.map_frame`: no copy, the kernels
    read the page cache); otherwise, or for a file that cannot be mapped, they
    are decoded into a preallocated buffer (grey PNG and TIFF, uncompressed,
    LZW or deflate, with :func:`ptpcore.io.fastio.read_into`: tifffile and
    imagecodecs, the GIL released; anything else with
    :func:`ptpcore.io.dataset.read_image`, which also names a bad file). At most
    ``depth`` sets are buffered or mapped: reading runs ahead of decoding by that much (default: 3
    sets, fewer where their buffers would pass :data:`READ_AHEAD_BYTES`, at least 2).
    """

    def __init__(self, source, positions, depth: int | None = None, map_files: bool | None = None):
        from ptpcore.io.dataset import bit_shift, read_image
        from ptpcore.io.fastio import map_frame, read_into

        self._read_image, self._read_into, self._map_frame = read_image, read_into, map_frame
        self.shift = bit_shift(source.rig)
        self.map_files = fused_kernels() is not None if map_files is None else bool(map_files)
        self.source = source
        self.rig: Rig = source.rig
        self.positions = list(positions)
        self.sets = _set_order(self.rig)
        n_max = max(n for *_, n in self.sets)
        self.free: queue.Queue = queue.Queue()
        self.dtype = np.dtype(np.float32) if getattr(source, "colour", False) else np.dtype(_frame_dtype(self.rig))
        if self.dtype == np.float32:
            self.map_files = False
        set_bytes = n_max * int(np.prod(self.rig.camera.shape)) * self.dtype.itemsize
        if depth is None:
            depth = min(3, max(2, READ_AHEAD_BYTES // set_bytes))
        for _ in range(depth):
            self.free.put(np.empty((n_max, *self.rig.camera.shape), self.dtype))
        self.out: queue.Queue = queue.Queue()
        self.stop = threading.Event()
        self.pool = ThreadPoolExecutor(tile_workers(), thread_name_prefix="ptp-read")
        self.thread = threading.Thread(target=self._run, name="ptp-reader", daemon=True)
        self.thread.start()

    def _read_one(self, args) -> np.ndarray:
        """One frame: mapped from its file, or read into ``out`` (returned)."""
        path, out = args
        if self.map_files and not self.shift:
            mapped = self._map_frame(path, out.shape, out.dtype)
            if mapped is not None:
                return mapped
        if out.dtype != np.float32 and self._read_into(path, out):
            if self.shift and out.dtype == np.uint16:  # [camera] bit_shift: MSB-aligned samples
                np.right_shift(out, self.shift, out=out)
        else:
            img = self._read_image(path, self.rig)  # shifted there
            if img.dtype.kind == "f" and out.dtype.kind != "f":
                img = np.rint(img)  # a colour image among grey ones (DatasetSource.colour looks at position 0)
            out[...] = img
        return out

    def _run(self) -> None:
        try:
            for k in self.positions:
                for d, j, t, n in self.sets:
                    buf = None
                    while buf is None:
                        if self.stop.is_set():
                            return
                        try:
                            buf = self.free.get(timeout=0.1)
                        except queue.Empty:
                            pass
                    paths = [self.source.path(k, d, t, s, n, j) for s in range(n)]
                    frames = list(self.pool.map(self._read_one, zip(paths, buf[:n])))
                    if all(f.base is buf for f in frames):
                        frames = buf[:n]  # all read into the buffer: the stack itself
                    self.out.put((k, (d, j), buf, frames))
                    del frames
        except BaseException as exc:  # handed to the consumer, raised there
            self.out.put(exc)

    def sets_of(self, k: int):
        """Yield ``((d, j), frames)`` for position ``k`` (the next one in order).

        ``frames``: an (N, H, W) stack, or a list of N (H, W) frames when some
        are mapped from their files (valid until the next set is asked for).
        """
        for _ in self.sets:
            item = self.out.get()
            if isinstance(item, BaseException):
                raise item
            kk, key, buf, frames = item
            del item
            assert kk == k, (kk, k)
            try:
                yield key, frames
            finally:
                del frames  # unmaps the mapped files (with the caller's last reference)
                self.free.put(buf)

    def close(self) -> None:
        self.stop.set()
        while self.thread.is_alive():
            try:  # unblock a reader waiting for a buffer
                item = self.out.get(timeout=0.05)
                if not isinstance(item, BaseException):
                    self.free.put(item[2])
            except queue.Empty:
                pass
        self.pool.shutdown(wait=True)


def _check_alignment(source, positions) -> None:
    """Warn when a dataset's 16-bit samples look MSB-aligned (:func:`ptpcore.io.dataset.check_bit_alignment`)."""
    if not _is_dataset(source) or not positions:
        return
    from ptpcore.io.dataset import check_bit_alignment

    d, _j, t, n, big_n = next(iter(source.rig.fringes.frames()))
    check_bit_alignment(source.path(positions[0], d, t, n, big_n), source.rig)


def _is_dataset(source) -> bool:
    from ptpcore.io.dataset import DatasetSource

    return type(source) is DatasetSource


def _decode_sets(rig: Rig, k: int, sets, options: DecodeOptions, all_photometry: bool,
                 buffers: dict | None = None, source=None) -> DecodedPosition:
    """Wrapped phases of every set, then unwrapping and classification.

    ``buffers``: a dict kept by a streaming caller; the position's maps are
    written into arrays it holds (allocated on first use), so the next
    position overwrites them. ``source``: where Gray-code and reference frames
    come from (Gray-code designs).

    The phase convention (``shift_sign``, ``phase_origin_rad``) is applied to
    each wrapped phase; designs that unwrap by periods with the default
    tolerance take the fused kernels (fractional and per-direction periods
    included), Gray codes and other tolerances the numpy path.
    """
    f = rig.fringes
    options = options.for_rig(rig)
    h, w = rig.camera.shape
    stride = _noise_stride(rig)
    wrapped: dict = {}
    noise_parts: dict = {}
    for (d, j), stack in sets:
        steps = f.steps_of(d)
        last = len(steps) - 1
        photometry = all_photometry or j == last
        out = None
        if buffers is not None:
            out = buffers.get((d, j))
            if out is None:
                # No residual_var: nothing after decoding reads it (the noise comes from
                # harmonic_noise_samples); 20 MB a direction less at 5 MP.
                out = buffers[(d, j)] = WrappedPhase(
                    np.empty((h, w), np.float32), np.empty((h, w), np.float32),
                    np.empty((h, w), np.float32) if photometry else None, np.empty((h, w), bool), None)
        wp = wrapped_phase(stack, rig.camera.max_level, photometry=photometry, out=out)
        apply_convention(wp, f.sign(d), f.origin(d))
        wp.black = black_clipped(stack)
        if j == _noise_level(steps):
            part = harmonic_noise_samples(stack, stride, 1 if d == "x" else 0)
            if part is not None:
                noise_parts[d] = (j, steps[j], part)
        wrapped[(d, j)] = wp
    stack = None  # a set mapped from its files is unmapped once its phases are out
    levels = {d: [wrapped[(d, j)] for j in range(len(f.periods(d)))] for d in f.directions}
    refs = _reference_frames(rig, k, source)
    pos = None
    if fused_kernels() is not None and f.unwrap == "periods" and options.unwrap_tolerance == 0.25:
        outs = None
        if buffers is not None:
            outs = {}
            for d in f.directions:
                outs[d] = buffers.get(d)
                if outs[d] is None:
                    outs[d] = buffers[d] = (np.empty((h, w)), np.empty((h, w), bool))
            outs["reasons"] = buffers.get("reasons")
            if outs["reasons"] is None:
                outs["reasons"] = buffers["reasons"] = np.empty((h, w), np.uint8)
        pos = decode_and_finish(rig, k, levels, options, outs=outs)
    if pos is None:
        z = rig.stage.z_mm[k]
        decoded = {}
        gray = _gray_unwrap(rig, k, source, levels, options, refs) if f.unwrap == "gray" else {}
        for d in f.directions:
            out = None
            if buffers is not None:
                out = buffers.get(d)
                if out is None:
                    out = buffers[d] = (np.empty((h, w)), np.empty((h, w), bool))
            absolute0, failed = gray.get(d, (None, None))
            decoded[d] = decode_direction(levels[d], f.periods(d), f.carrier(d) * z, out=out,
                                          tolerance=options.unwrap_tolerance, absolute0=absolute0,
                                          gray_failed=failed, heterodyne=f.unwrap == "heterodyne")
        out = None
        if buffers is not None:
            out = buffers.get("reasons")
            if out is None:
                out = buffers["reasons"] = np.empty((h, w), np.uint8)
        pos = finish_position(rig, k, decoded, options, out=out)
    pos.info["noise_samples"] = {d: part for d, (_j, _n, part) in noise_parts.items()}
    pos.info["noise_levels"] = {d: (f.periods(d)[j], n) for d, (j, n, _p) in noise_parts.items()}
    if refs:
        pos.info["reference_clipping"] = reference_clipping(refs, rig.camera.max_level)
    flag_more_reasons(rig, pos, options, pos.reasons)
    return pos


def _noise_level(steps) -> int | None:
    """The level whose set measures the harmonic-free noise: the finest when it has 5 steps or
    more, else the (first) level with most steps of at least 5; None when no level has 5."""
    if steps[-1] >= 5:
        return len(steps) - 1
    best = int(np.argmax(steps))
    return best if steps[best] >= 5 else None


def _noise_stride(rig: Rig) -> int:
    h, w = rig.camera.shape
    return max(1, int(np.sqrt(h * w / NOISE_PIXELS)))


def _reference_frames(rig: Rig, k: int, source) -> dict:
    """``{"white": image, "black": image}`` of position ``k`` when the dataset has them, else ``{}``."""
    if not rig.has_references or source is None or not hasattr(source, "reference_frames"):
        return {}
    return source.reference_frames(k)


def reference_clipping(refs: dict, max_level: float) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The clipping check of the reference frames (METHOD.md section 4).

    Parameters
    ----------
    refs : dict
        ``{"white": (H, W) image, "black": (H, W) image}``, either may be absent.
    max_level : float
        The camera's largest grey level.

    Returns
    -------
    saturated, black : (H, W) bool or None
        Where the white frame reaches ``max_level`` (the brightest fringes saturate
        there too) and where the black frame is at 0 (the darkest are clipped).
    """
    white, black = refs.get("white"), refs.get("black")
    sat = None if white is None else np.asarray(white) >= max_level
    clipped = None if black is None else np.asarray(black) <= 0
    return sat, clipped


def _gray_unwrap(rig: Rig, k: int, source, levels: dict, options: DecodeOptions, refs: dict | None = None) -> dict:
    """``{d: (absolute coarse phase, Gray-code failures)}`` from the Gray-code frames of position ``k``
    (``refs``: its white and black frames, the bits' threshold when there are no inverse frames)."""
    from ptpcore.decode.graycode import absolute_coarse_phase, gray_index

    if source is None or not hasattr(source, "gray_frames"):
        raise ValueError("this frame source cannot give Gray-code frames")
    frames = source.gray_frames(k)
    if refs is None:
        refs = _reference_frames(rig, k, source)
    f = rig.fringes
    out = {}
    for d in f.directions:
        coarse = levels[d][0]
        bits = range(f.bits(d))
        imgs = [frames[(d, b, False)] for b in bits]
        inv = [frames[(d, b, True)] for b in bits] if f.gray_inverse else None
        bg = coarse.background if coarse.background is not None else levels[d][-1].background
        index, contrast = gray_index(imgs, inv, white=refs.get("white"), black=refs.get("black"), background=bg)
        # The code counts cycles of u + s: the carrier moves it with the fringes.
        phi0, failed = absolute_coarse_phase(coarse.phase, index, contrast, coarse.modulation,
                                             options.unwrap_tolerance)
        out[d] = (phi0, failed)
    return out


def flag_more_reasons(rig: Rig, pos: DecodedPosition, options: DecodeOptions, reasons: np.ndarray,
                      directions=None) -> None:
    """Black clipping, Gray-code failures, the reference frames' clipping (``pos.info["reference_clipping"]``)
    and spatial consistency (METHOD.md section 4), into ``reasons``.

    Also records in ``pos.info`` the predicted coordinate noise used (``sigma``)
    and where the noise came from (``noise_source``).
    """
    from ptpcore.decode.spatial import spatial_outliers
    from ptpcore.decode.noise import NoiseAccumulator

    f = rig.fringes
    dirs = [d for d in (directions or pos.directions) if d in pos.directions]
    for d in dirs:
        dec = pos.directions[d]
        for wp in dec.wrapped:
            if wp.black is not None:
                _or(reasons, wp.black, Reason.BLACK_CLIPPED)
        if dec.gray_failed is not None:
            _or(reasons, dec.gray_failed, Reason.GRAY_CODE)
    sat, clipped = pos.info.get("reference_clipping", (None, None))
    if dirs and sat is not None:
        _or(reasons, sat, Reason.SATURATED)
    if dirs and clipped is not None:
        _or(reasons, clipped, Reason.BLACK_CLIPPED)
    pos.info.setdefault("sigma", {})
    pos.info.setdefault("noise_source", {})
    if options.spatial_k is None:
        return
    samples = pos.info.get("noise_samples", {})
    levels = pos.info.get("noise_levels", {})
    base = reasons.copy()
    for d in dirs:
        dec = pos.directions[d]
        fine = dec.wrapped[-1]
        valid = base == 0
        sigma = None
        source = "neighbourhood"
        part = samples.get(d)
        if part is not None and fine.background is not None:
            acc = NoiseAccumulator(rig.camera.max_level)
            sub = valid[part["rows"]][:, part["cols"]].ravel()
            acc.add(part["background"], part["var"], sub & np.isfinite(part["var"]), part["dof"])
            model = acc.model()
            if model is not None:
                sigma = _coordinate_sigma(model, fine, f.steps_of(d)[-1], f.amplitude, f.periods(d)[-1])
                t, n = levels[d]
                source = "residual" if float(t) == float(f.periods(d)[-1]) else f"residual of period {t:g} px (N = {n})"
        flagged, used = spatial_outliers(dec.coord, valid, sigma, options.spatial_k)
        del sigma
        _or(reasons, flagged, Reason.SPATIAL)
        pos.info["sigma"][d] = used
        pos.info["noise_source"][d] = source


def _coordinate_sigma(model, fine, n_fine: int, amplitude: float, period: float):
    """Predicted 1-sigma of the decoded coordinate (px) from the noise ``model`` and the finest
    level's background and modulation, as rows: ``sigma(r0, r1)`` -> ``(r1 - r0, W)`` float64
    (:func:`ptpcore.decode.spatial.spatial_outliers` takes them band by band; no whole map)."""
    def rows(r0: int, r1: int) -> np.ndarray:
        bg, mod = fine.background[r0:r1], fine.modulation[r0:r1]
        # The camera's noise and the display's rounding to integer levels (uniform, 1/12
        # of a level squared; a level is B / amplitude camera DN).
        with np.errstate(invalid="ignore", divide="ignore"):
            var_dn = model.sigma_dn(bg) ** 2 + (mod / amplitude) ** 2 / 12.0
            return np.sqrt(2.0 / n_fine) * np.sqrt(var_dn) / mod * period / (2 * np.pi)

    return rows


def _or(reasons: np.ndarray, cond: np.ndarray, bit: int) -> None:
    np.bitwise_or(reasons, cond.view(np.uint8) * np.uint8(bit), out=reasons)


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
    if _is_dataset(source):
        reader = _DatasetReader(source, [k])
        try:
            return _decode_sets(rig, k, reader.sets_of(k), options, True, source=source)
        finally:
            reader.close()
    return _decode_sets(rig, k, _source_sets(source, k), options, True, source=source)


def decode_positions(source, positions, options: DecodeOptions = DecodeOptions(), *, spatial: bool = True):
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

    Yields
    ------
    DecodedPosition
    """
    rig: Rig = source.rig
    if not spatial:
        options = replace(options, spatial_k=None)
    todo = list(positions)
    reader = _DatasetReader(source, todo) if _is_dataset(source) and todo else None
    buffers: dict = {}
    try:
        for k in todo:
            sets = reader.sets_of(k) if reader else _source_sets(source, k)
            yield _decode_sets(rig, k, sets, options, False, buffers, source)
    finally:
        if reader:
            reader.close()


def world_xy(rig: Rig, pos: DecodedPosition) -> tuple[np.ndarray, np.ndarray]:
    """World X, Y (mm) of a decoded position: ``X = u*pitch_x + a*z`` (METHOD.md section 2)."""
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    x = pos.u * px + a * pos.z_mm if pos.u is not None else None
    y = pos.v * py + b * pos.z_mm if pos.v is not None else None
    return x, y


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
    _check_alignment(source, todo)
    shape = rig.camera.shape
    z_all = np.asarray(rig.stage.z_mm, dtype=float)
    if spill is None:
        spill = k_total * shape[0] * shape[1] * 17 > SPILL_BYTES
    store = spill_maps = None
    if spill:
        from ptpcore.store import SpillStore

        store = SpillStore(k_total, shape, {"x": np.float32, "y": np.float32, "reasons": np.uint8,
                                            "modulation": np.float32, "background": np.float32},
                           {"x": np.nan, "y": np.nan, "reasons": 0xFF, "modulation": 0, "background": 0},
                           spill_dir)
        samples = SampleStack(z_all, np.empty((0, *shape), np.float32), np.empty((0, *shape), np.float32),
                              np.full(shape, np.nan), np.full(shape, np.nan), np.empty((0, *shape), np.uint8))
        # Whole position maps only for the numpy path (_store_position). The noise model's binning
        # gets a thread of its own.
        spill_maps = None if fused_kernels() else {name: np.empty(shape, dt) for name, (dt, _off) in store.layout.items()}
        writer = ThreadPoolExecutor(1, thread_name_prefix="ptp-noise")
    else:
        samples = SampleStack.empty(rig.stage.z_mm, shape)
    noise = NoiseAccumulator(rig.camera.max_level)
    fallback: list = []
    reader = _DatasetReader(source, todo) if _is_dataset(source) else None
    buffers: dict = {}
    noise_jobs: list = []
    try:
        for i, k in enumerate(todo):
            if progress:
                progress(i / len(todo), f"decoding {position_label(k, rig.stage.z_mm[k])} ({i + 1} of {len(todo)})")
            sets = reader.sets_of(k) if reader else _source_sets(source, k)
            if on_frame is not None:
                sets = _tapped(sets, rig, k, on_frame)
            # Without a listener the position's maps are scratch: reuse them.
            full = on_position is not None and (full_positions is None or k in full_positions)
            pos = _decode_sets(rig, k, sets, options, full, None if full else buffers, source)
            _store_position(rig, pos, k, samples, store, spill_maps)
            for d, part in pos.info.get("noise_samples", {}).items():
                valid = pos.reasons[part["rows"]][:, part["cols"]].ravel() == 0
                args = (part["background"], part["var"], valid & np.isfinite(part["var"]), part["dof"])
                if store is None:
                    noise.add(*args)
                else:  # on its own thread (in order), off the decoding's path
                    noise_jobs.append(writer.submit(noise.add, *args))
            fallback.extend(_neighbourhood_noise_dn(rig, pos))
            for d, (t, n) in pos.info.get("noise_levels", {}).items():
                if float(t) != float(rig.fringes.periods(d)[-1]):
                    noise.source = f"residual of period {float(t):g} px (N = {n})"
            if on_position:
                on_position(pos)
            release_free_memory()  # the position's transients: keep the heap from growing position by position
    finally:
        if reader:
            reader.close()
        if store is not None:
            writer.shutdown(wait=True)
    if store is not None:
        for w in noise_jobs:
            w.result()  # raise a failure here
        store.finish()
        arrays = store.arrays()
        samples = SampleStack(z_all, arrays["x"], arrays["y"], samples.x_ref, samples.y_ref,
                              arrays["reasons"], arrays["modulation"], arrays["background"])
    samples.noise = noise.model()
    if samples.noise is None and fallback:
        samples.noise = NoiseModel(float(np.median(fallback)) ** 2, 0.0, "neighbourhood")
    if progress:
        progress(1.0, "decoding done")
    return samples


def _tapped(sets, rig: Rig, k: int, on_frame):
    """The sets of position ``k`` unchanged, each frame shown to ``on_frame`` first."""
    f = rig.fringes
    for (d, j), stack in sets:
        period = f.periods(d)[j]
        for n in range(len(stack)):
            on_frame(k, (d, j, period, n, len(stack)), stack[n])
        yield (d, j), stack


def _neighbourhood_noise_dn(rig: Rig, pos: DecodedPosition) -> list[float]:
    """Sample noise (grey levels) implied by the coordinate's spread over the neighbourhood, for
    directions without a harmonic-free residual (every level N <= 4)."""
    f = rig.fringes
    out = []
    for d, dec in pos.directions.items():
        if pos.info.get("noise_source", {}).get(d) != "neighbourhood":
            continue
        sigma_u = pos.info.get("sigma", {}).get(d)
        valid = pos.reasons == 0
        if sigma_u is None or not np.isfinite(sigma_u) or not valid.any():
            continue
        b = float(np.median(dec.wrapped[-1].modulation[valid]))
        n = f.steps_of(d)[-1]
        out.append(sigma_u * b / (np.sqrt(2.0 / n) * f.periods(d)[-1] / (2 * np.pi)))
    return out


def _store_position(rig: Rig, pos: DecodedPosition, k: int, samples: SampleStack, store,
                    spill_maps: dict | None) -> None:
    """Position ``k``'s samples (``pos``) into ``samples`` (in memory) or the spill ``store``, row tile by row tile.

    Each tile writes its rows to the file as soon as it has stored them (while they are in the
    cache; positional writes from the tile pool): with the kernels from a scratch of the tile's
    rows, else from ``spill_maps``, one set of whole maps.
    """
    shape = rig.camera.shape
    fine_x, fine_y = pos.directions["x"].wrapped[-1], pos.directions["y"].wrapped[-1]
    if store is None:
        dest = {"x": samples.x[k], "y": samples.y[k], "reasons": samples.reasons[k],
                "modulation": samples.modulation[k], "background": samples.background[k]}
    else:
        dest = spill_maps
    kern = fused_kernels()

    def rows(r0: int, r1: int) -> None:
        if kern is None:
            _store_rows(rig, pos, fine_x, fine_y, samples, dest, r0, r1)
            tile = {name: a[r0:r1] for name, a in dest.items()}
        else:
            tile = ({name: a[r0:r1] for name, a in dest.items()} if dest is not None else
                    {name: np.empty((r1 - r0, shape[1]), dt) for name, (dt, _off) in store.layout.items()})
            _store_rows_fused(kern, rig, pos, fine_x, fine_y, samples, tile, r0, r1)
        if store is not None:
            for name, a in tile.items():
                store.write_rows(name, k, r0, a)

    run_tiles(rows, *shape, TILE_PIXELS if kern is None else KERNEL_TILE_PIXELS)
    if store is not None:
        for name in store.layout:
            store.mark_written(name, k)


def _store_rows(rig: Rig, pos: DecodedPosition, fine_x: WrappedPhase, fine_y: WrappedPhase,
                samples: SampleStack, dest: dict, r0: int, r1: int) -> None:
    """:func:`world_xy` and :meth:`SampleStack.set_position` of rows ``[r0, r1)``, into ``dest``.

    Same arithmetic as those two, tile by tile (``dest`` holds the ``(H, W)``
    maps of position ``pos.index``: x, y, reasons, modulation, background).
    """
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    z = pos.z_mm
    rs = pos.reasons[r0:r1]
    valid = rs == 0
    invalid = ~valid
    for name, coord, pitch, slope, ref in (("x", pos.u, px, a, samples.x_ref), ("y", pos.v, py, b, samples.y_ref)):
        w = coord[r0:r1] * pitch
        w += slope * z
        rf = ref[r0:r1]
        new_ref = valid & np.isnan(rf)
        np.copyto(rf, w, where=new_ref)
        w -= rf
        w[invalid] = np.nan
        dest[name][r0:r1] = w
    dest["reasons"][r0:r1] = rs
    np.minimum(fine_x.modulation[r0:r1], fine_y.modulation[r0:r1], out=dest["modulation"][r0:r1])
    bg = dest["background"][r0:r1]
    np.add(fine_x.background[r0:r1], fine_y.background[r0:r1], out=bg)
    bg *= 0.5


def _store_rows_fused(kern, rig: Rig, pos: DecodedPosition, fine_x: WrappedPhase, fine_y: WrappedPhase,
                      samples: SampleStack, tile: dict, r0: int, r1: int) -> None:
    """:func:`_store_rows` with the numba kernel :func:`ptpcore.decode._fused.store_rows` (bit-equal),
    into ``tile``: the ``(r1 - r0, W)`` rows of each map (views of whole maps, or a tile's scratch)."""
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    z = pos.z_mm
    with_bg = fine_x.background is not None and fine_y.background is not None
    bgx = fine_x.background if with_bg else fine_x.modulation
    bgy = fine_y.background if with_bg else fine_y.modulation
    rows = slice(r0, r1)
    kern.store_rows(0, r1 - r0, pos.reasons[rows], pos.u[rows], pos.v[rows], float(px), float(py), float(a * z),
                    float(b * z), samples.x_ref[rows], samples.y_ref[rows], fine_x.modulation[rows],
                    fine_y.modulation[rows], bgx[rows], bgy[rows], with_bg,
                    tile["x"], tile["y"], tile["reasons"], tile["modulation"], tile["background"])


def calibrate(source, *, model: str = "poly", degree: int = 3, options: DecodeOptions = DecodeOptions(),
              positions=None, progress: Progress | None = None, spill: bool | None = None) -> tuple[Lut, SampleStack]:
    """Images to LUT in one call.

    Parameters
    ----------
    source : FrameSource
    model, degree : see :func:`ptpcore.fit.fit_lut`
    options : DecodeOptions
    positions : sequence of int, optional
        Positions to calibrate on (default all).
    progress : callable, optional
    spill : bool, optional
        See :func:`collect_samples` (default: a temporary file for big stacks).

    Returns
    -------
    lut : Lut
    samples : SampleStack

    Raises
    ------
    ConfigError
        The stage readings run the wrong way (:func:`ptpcore.run.sanity.check_samples`;
        positions that look stuck are a ``DataWarning``).
    """
    def sub(lo, hi):
        if progress is None:
            return None
        return lambda f, msg: progress(lo + (hi - lo) * f, msg)

    samples = collect_samples(source, options=options, positions=positions, progress=sub(0.0, 0.9), spill=spill)
    from ptpcore.run.sanity import check_samples

    check_samples(samples, positions=positions,
                  source=str(source.folder / "rig.toml") if hasattr(source, "folder") else "rig.toml")
    lut = fit_lut(samples, model, degree, positions=positions, rig_toml=rig_to_toml(source.rig),
                  progress=sub(0.9, 1.0))
    return lut, samples


def repeat_drift(source, samples: SampleStack, rig, *, options: DecodeOptions = DecodeOptions(),
                 stage_sigma_mm: float = 0.0, progress: Progress | None = None):
    """The drift of a sweep's repeat positions (``[stage] repeat_z_mm``), or None without them.

    Decodes the repeats of ``source`` (positions K, K+1, ... after the sweep) and compares each
    with its sweep position in ``samples`` (:func:`ptpcore.fit.drift.sweep_drift`). The command
    line's ``calibrate`` and the wizard's Calibrate page both call this.

    Parameters
    ----------
    source : FrameSource
        The dataset (or simulator) the sweep ``samples`` came from.
    samples : SampleStack
        The decoded sweep, (K, H, W).
    rig : Rig
    options : DecodeOptions
        As the sweep was decoded with.
    stage_sigma_mm : float
        The stage readings' 1-sigma error (mm).
    progress : callable, optional

    Returns
    -------
    ptpcore.fit.drift.Drift or None
    """
    if not rig.stage.repeat_z_mm:
        return None
    from ptpcore.fit.drift import RepeatSource, sweep_drift

    repeats = collect_samples(RepeatSource(source), options=options, progress=progress)
    return sweep_drift(samples, repeats, rig, stage_sigma_mm=stage_sigma_mm)

