"""The decoding of one position: its sets of frames -> LCD coordinates, pixel reasons and noise.

:func:`decode_sets` is the per-position recipe the streaming decode (:mod:`ptpcore.run.pipeline`)
and ``ptp decode`` run: the wrapped phase of every set (in cache-sized row tiles on every core,
:func:`ptpcore.decode.phase.wrapped_phase`; background and noise residuals only at the finest
period, where they are used), the phase convention, unwrapping (by periods on the fused kernels,
by Gray code or heterodyne on the numpy path), the pixel classification and the extra reasons of
:func:`flag_more_reasons` (black clipping, Gray-code failures, the reference frames' clipping,
spatial consistency against the predicted noise of :func:`coordinate_sigma`).

The sets come in as an iterator of ``((direction, level), stack (N, H, W))`` (made in
:mod:`ptpcore.io.readahead`); Gray-code and reference frames are asked of the frame source,
taken duck-typed (``source.gray_frames(k)``, ``source.reference_frames(k)``): nothing here
reads a file.
"""

from __future__ import annotations

import numpy as np

from ptpcore.decode.harmonics import harmonic_noise_samples
from ptpcore.decode.phase import (DecodedPosition, DecodeOptions, Reason, WrappedPhase, apply_convention,
    decode_and_finish, decode_direction, finish_position, fused_kernels, wrapped_phase)
from ptpcore.rig import Rig

__all__ = ["NOISE_PIXELS", "decode_sets", "reference_clipping", "flag_more_reasons", "coordinate_sigma",
           "neighbourhood_noise_dn"]

NOISE_PIXELS = 1 << 18
"""At most about this many pixels per position and direction feed the noise model
(a regular sub-grid: every pixel up to 0.26 MP, every 4th row and column at 5 MP)."""


def decode_sets(rig: Rig, k: int, sets, options: DecodeOptions, all_photometry: bool,
                 buffers: dict | None = None, source=None, per_direction: bool = False) -> DecodedPosition:
    """Wrapped phases of every set, then unwrapping and classification.

    The phase convention (``shift_sign``, ``phase_origin_rad``) is applied to
    each wrapped phase; designs that unwrap by periods with the default
    tolerance take the fused kernels (fractional and per-direction periods
    included), Gray codes and other tolerances the numpy path.

    Parameters
    ----------
    rig : Rig
    k : int
        The position.
    sets : iterable
        ``((direction, level), frames)`` of every set of position ``k``, in any order; ``frames``
        an ``(N, H, W)`` stack or a list of N ``(H, W)`` frames (:mod:`ptpcore.io.readahead`).
    options : DecodeOptions
    all_photometry : bool
        Background and modulation of every level (else the finest level's only).
    buffers : dict, optional
        Kept by a streaming caller; the position's maps are written into arrays it holds
        (allocated on first use), so the next position overwrites them.
    source : FrameSource, optional
        Where Gray-code and reference frames come from (``gray_frames(k)``,
        ``reference_frames(k)``; Gray-code designs and designs with reference frames).
    per_direction : bool
        Classify each direction alone, once (``ptp decode``): ``info["direction_reasons"]`` holds
        ``{d: (H, W) uint8}`` as :func:`ptpcore.decode.phase.finish_position` gives them for that
        direction alone, before :func:`flag_more_reasons`; ``reasons`` is then their OR
        (:func:`ptpcore.decode.phase.decode_and_finish`).

    Returns
    -------
    DecodedPosition
        With ``info["noise_samples"]``, ``info["noise_levels"]``, ``info["sigma"]`` and
        ``info["noise_source"]`` (and ``info["reference_clipping"]`` with reference frames).
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
                    np.empty((h, w), np.float32) if photometry else None, np.empty((h, w), bool), None,
                    np.empty((h, w), bool))
        # Black clipping (any step at 0) in the same pass as the sums.
        wp = wrapped_phase(stack, rig.camera.max_level, photometry=photometry, out=out, black_level=0.0)
        apply_convention(wp, f.sign(d), f.origin(d))
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
            for key in ["reasons"] + ([("reasons", d) for d in f.directions] if per_direction else []):
                outs[key] = buffers.get(key)
                if outs[key] is None:
                    outs[key] = buffers[key] = np.empty((h, w), np.uint8)
        pos = decode_and_finish(rig, k, levels, options, outs=outs, per_direction=per_direction)
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
        if per_direction:
            pos.info["direction_reasons"] = {d: finish_position(rig, k, {d: dec}, options).reasons
                                             for d, dec in decoded.items()}
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
    """The noise samples' sub-grid step (rows and columns): about :data:`NOISE_PIXELS` pixels."""
    h, w = rig.camera.shape
    return max(1, int(np.sqrt(h * w / NOISE_PIXELS)))


def _reference_frames(rig: Rig, k: int, source) -> dict:
    """``{"white": image, "black": image}`` of position ``k`` when the dataset has them, else ``{}``."""
    if not rig.has_references or source is None or not hasattr(source, "reference_frames"):
        return {}
    return source.reference_frames(k)


def reference_clipping(refs: dict, max_level: float) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The clipping check of the reference frames (docs/method.md section 4).

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
    and spatial consistency (docs/method.md section 4), into ``reasons``.

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
                sigma = coordinate_sigma(model, fine, f.steps_of(d)[-1], f.amplitude, f.periods(d)[-1])
                t, n = levels[d]
                source = "residual" if float(t) == float(f.periods(d)[-1]) else f"residual of period {t:g} px (N = {n})"
        flagged, used = spatial_outliers(dec.coord, valid, sigma, options.spatial_k)
        del sigma
        _or(reasons, flagged, Reason.SPATIAL)
        pos.info["sigma"][d] = used
        pos.info["noise_source"][d] = source


def coordinate_sigma(model, fine, n_fine: int, amplitude: float, period: float):
    """Predicted 1-sigma of the decoded coordinate (px) from the noise ``model`` and the finest
    level's background and modulation, as rows: ``sigma(r0, r1)`` -> ``(r1 - r0, W)`` float64
    (:func:`ptpcore.decode.spatial.spatial_outliers` takes them band by band; no whole map)."""
    from ptpcore.decode.noise import NoiseModel

    kern = fused_kernels()
    if kern is not None and type(model).sigma_dn is NoiseModel.sigma_dn and fine.background.dtype == np.float32 \
            and fine.modulation.dtype == np.float32:
        def fused(r0: int, r1: int) -> np.ndarray:  # one pass, the same bits
            out = np.empty((r1 - r0, fine.modulation.shape[1]))
            kern.coordinate_sigma_rows(fine.background[r0:r1], fine.modulation[r0:r1], float(model.read_var),
                                       float(model.gain), np.float32(amplitude), n_fine, float(period), out)
            return out

        return fused

    def rows(r0: int, r1: int) -> np.ndarray:
        bg, mod = fine.background[r0:r1], fine.modulation[r0:r1]
        # The camera's noise and the display's rounding to integer levels (uniform, 1/12
        # of a level squared; a level is B / amplitude camera DN).
        with np.errstate(invalid="ignore", divide="ignore"):
            var_dn = model.sigma_dn(bg) ** 2 + (mod / amplitude) ** 2 / 12.0
            return np.sqrt(2.0 / n_fine) * np.sqrt(var_dn) / mod * period / (2 * np.pi)

    return rows


def _or(reasons: np.ndarray, cond: np.ndarray, bit: int) -> None:
    """``reasons |= bit`` where ``cond`` (in place)."""
    np.bitwise_or(reasons, cond.view(np.uint8) * np.uint8(bit), out=reasons)


def neighbourhood_noise_dn(rig: Rig, pos: DecodedPosition) -> list[float]:
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
