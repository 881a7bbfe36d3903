"""Camera noise with the display's harmonics taken out (docs/method.md section 4).

A display whose response differs from the gamma pre-compensation puts
harmonics ``h = 2 .. N//2`` into the fringes. The N-step phase is immune to
them (unless ``h = +-1 mod N``), but its residual is not: the N-step fit of
N samples leaves exactly the bins ``2 .. N//2`` of their discrete Fourier
transform, so the plain residual mixes noise and harmonics (the noise model
then reads 10x too much) and no per-pixel fit can separate them.

What separates them is that harmonics are deterministic: demodulated by the
fundamental's phase, ``Z_h = X_h exp(-i h phi) / |X_1|`` is the same smooth
function of the display response at neighbouring pixels, while noise is
independent from pixel to pixel. The difference of ``Z_h`` between
horizontally adjacent pixels therefore holds noise only:
``E |X_h(p) - Z_h(q) |X_1(p)|exp(i h phi_p)|^2 = 2 N sigma^2`` for every bin
``0 < h < N/2`` (the bin ``N/2`` is real and not demodulable; it is left out).
N = 3 and N = 4 have no such bin: the caller takes the noise from another level
or from the neighbourhood (:mod:`ptpcore.decode.spatial`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["noise_bins", "harmonic_noise_samples", "coherent_harmonic", "MeasuredHarmonics", "measured_harmonics"]


BAND_VALUES = 1 << 21
"""Frame values per band of :func:`harmonic_noise_samples` (16 MB of float64, 48 MB complex)."""


def noise_bins(n_steps: int) -> list[int]:
    """The harmonic bins ``2 .. ceil(N/2) - 1`` that carry a noise estimate (empty for N <= 4)."""
    return list(range(2, (n_steps + 1) // 2))


def harmonic_noise_samples(frames, stride: int = 1, axis: int = 1) -> dict | None:
    """Noise variance samples, free of harmonics, on a sub-grid of pixel pairs.

    Parameters
    ----------
    frames : (N, H, W) array or sequence of N (H, W) arrays
        One N-step set, frame n shown with phase shift ``2 pi n / N`` (the sign
        convention does not matter here).
    stride : int
        Rows and columns of the sub-grid.
    axis : {1, 0}
        Pair pixel ``(r, c)`` with ``(r, c + 1)`` (1) or ``(r + 1, c)`` (0): pair along the
        pattern's coding direction (x: 1, y: 0), where neighbours see different phases. Across
        it they see nearly the same level, and a noise-free camera's rounding errors are then
        the same at both and cancel in their difference.

    Returns
    -------
    dict or None
        ``background`` (M,) mean level of each pair; ``var`` (M,) unbiased
        variance estimates (grey levels^2) with ``dof`` degrees of freedom each;
        ``harmonic`` (M,) amplitude of the largest harmonic (grey levels, at the
        first pixel of each pair); ``modulation`` (M,). None for N <= 4 or images
        narrower than 2 pixels.
    """
    n = len(frames)
    bins = noise_bins(n)
    kern = _kernels(frames)
    if axis == 0 and kern is None:
        frames = [np.asarray(f).T for f in frames]
    h, w = np.shape(frames[0])[::-1] if axis == 0 and kern is not None else np.shape(frames[0])
    if not bins or w < 2:
        return None
    rows = np.arange(0, h, stride)
    cols = np.arange(0, w - 1, stride)
    pairs = np.concatenate([cols, cols + 1])
    out = {name: np.empty((rows.size, cols.size)) for name in ("background", "var", "harmonic", "modulation")}
    # Bands of sampled rows: every quantity is a pixel pair's own, and the whole-grid stack (8 frames
    # of float64, then complex) was 300 MB of transients at 5 MP.
    band = max(1, BAND_VALUES // max(1, n * pairs.size))
    if kern is not None:  # the bins straight from the integer frames, bands on the tile pool
        from ptpcore.decode.phase import kernel_frames
        from ptpcore.parallel import map_in_order

        hs = [1, *bins]
        angle = np.stack([2.0 * np.pi * hh * np.arange(n) / n for hh in hs])  # as _dft_bin's, bit for bit
        cos_t, sin_t = np.cos(angle), np.sin(angle)
        kframes = kernel_frames(frames)

        def one(b0):
            r = rows[b0:b0 + band]
            re, im = np.empty((2, len(hs), r.size, pairs.size))
            bg = np.empty((r.size, pairs.size))
            kern.dft_pairs(kframes, axis == 0, r, pairs, cos_t, sin_t, re, im, bg)
            x = {}
            for i, hh in enumerate(hs):
                x[hh] = np.empty(bg.shape, np.complex128)
                x[hh].real, x[hh].imag = re[i], im[i]
            return b0, _pair_maps(x, bg, bins, cols.size, n)

        for b0, maps in map_in_order(one, range(0, rows.size, band)):
            for name, val in maps.items():
                out[name][b0:b0 + band] = val
    else:
        for b0 in range(0, rows.size, band):
            stack = np.stack([np.asarray(f)[rows[b0:b0 + band]][:, pairs] for f in frames]).astype(np.float64)
            for name, val in _pair_noise(stack, bins, cols.size).items():
                out[name][b0:b0 + band] = val
    if axis == 0:  # back to (rows, cols) of the image
        out = {k: v.T for k, v in out.items()}
        rows, cols = cols, rows
    out = {k: v.ravel() for k, v in out.items()}
    out.update(dof=2 * len(bins), rows=rows, cols=cols)
    return out


def _kernels(frames):
    """:mod:`ptpcore.decode._fused` when the numba kernels are on and ``frames`` are integer (H, W) arrays."""
    from ptpcore.decode.phase import fused_kernels

    kern = fused_kernels()
    if kern is None or not all(isinstance(f, np.ndarray) and f.ndim == 2 for f in frames):
        return None
    if len({f.dtype for f in frames}) != 1 or frames[0].dtype not in (np.uint8, np.uint16):
        return None
    return kern


def _pair_noise(stack: np.ndarray, bins: list[int], m: int) -> dict:
    """:func:`harmonic_noise_samples`' maps of a band of sampled rows: ``stack`` (N, rows, 2 m) holds the
    first pixels of the pairs, then their neighbours."""
    x = {hh: _dft_bin(stack, hh) for hh in [1, *bins]}
    return _pair_maps(x, stack.mean(axis=0), bins, m, stack.shape[0])


def _pair_maps(x: dict, bg: np.ndarray, bins: list[int], m: int, n: int) -> dict:
    """The maps of :func:`_pair_noise` from the DFT bins ``x`` (``{h: (rows, 2 m) complex}``) and the mean ``bg``."""
    x1 = x[1]
    amp1 = np.abs(x1)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = x1 / amp1
    p, q = slice(0, m), slice(m, 2 * m)
    acc = np.zeros((bg.shape[0], m))
    harm = np.zeros((bg.shape[0], m))
    for hh in bins:
        rot = unit ** hh
        zq = x[hh][:, q] * np.conj(rot[:, q])  # demodulated at q
        with np.errstate(invalid="ignore", divide="ignore"):
            pred = zq * (amp1[:, p] / amp1[:, q]) * rot[:, p]  # carried to p
        acc += np.abs(x[hh][:, p] - pred) ** 2
        harm = np.maximum(harm, (2.0 / n) * np.abs(x[hh][:, p]))
    return {"background": 0.5 * (bg[:, p] + bg[:, q]), "var": acc / (2.0 * n * len(bins)), "harmonic": harm,
            "modulation": (2.0 / n) * amp1[:, p]}


def _dft_bin(stack: np.ndarray, hh: int) -> np.ndarray:
    """Bin ``hh`` of the DFT over the N frames, ``sum_n exp(-i hh 2 pi n / N) frame_n``, (...) complex128.

    Real and imaginary parts are summed apart, frame by frame, in real arithmetic: a complex
    ``tensordot`` first converts the whole real stack to complex and hands it to BLAS, which took
    0.45 CPU-s for the three bins of a 5 MP position's sampled pairs (issue 33), 15x their arithmetic.
    """
    n = stack.shape[0]
    angle = 2.0 * np.pi * hh * np.arange(n) / n
    cos, sin = np.cos(angle), np.sin(angle)
    re = stack[0] * cos[0]
    im = stack[0] * sin[0]
    for k in range(1, n):
        re += stack[k] * cos[k]
        im += stack[k] * sin[k]
    out = np.empty(re.shape, np.complex128)
    out.real = re
    out.imag = -im
    return out


def coherent_harmonic(frames, harmonic: int = 2, block: int = 8) -> dict:
    """The display's harmonic ``h`` in an N-step set, averaged coherently over blocks of pixels.

    Demodulated by the fundamental's phase, ``Z_h = X_h exp(-i h phi) / |X_1|``
    is the same smooth function of the display response at neighbouring
    pixels while noise is not: its mean over a ``block`` x ``block`` block
    keeps the harmonic and divides the noise's part by the block's size. The
    amplitude in grey levels is ``(2/N) |mean Z_h| * |X_1|`` at the block's
    median ``|X_1|``; the noise left in it is about ``sigma * 2/sqrt(N)/block``.

    Parameters
    ----------
    frames : (N, H, W) array or sequence of N (H, W) arrays
        One N-step set (frame n shown with phase shift ``2 pi n / N``).
    harmonic : int
        ``2 .. N//2 - 1`` (a bin the fit's residual holds apart from the fundamental).
    block : int
        Block side (pixels).

    Returns
    -------
    dict
        ``amplitude`` (Hb, Wb) grey levels and ``relative`` (Hb, Wb), the
        harmonic over the fundamental's amplitude; NaN where a block has no
        modulated pixel.
    """
    n = len(frames)
    if not 2 <= harmonic < (n + 1) // 2 and not (harmonic == n // 2 and n % 2 == 1):
        raise ValueError(f"harmonic {harmonic} is not a residual bin of {n}-step data (2 .. {(n + 1) // 2 - 1})")
    stack = np.stack([np.asarray(f, dtype=np.float64) for f in frames])
    delta = 2.0 * np.pi * np.arange(n) / n
    x1 = np.tensordot(np.exp(-1j * delta), stack, axes=(0, 0))
    xh = np.tensordot(np.exp(-1j * harmonic * delta), stack, axes=(0, 0))
    amp1 = np.abs(x1)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(amp1 > 0, xh * np.conj((x1 / amp1) ** harmonic) / amp1, np.nan)
    h, w = amp1.shape
    hb, wb = h // block, w // block
    zb = z[:hb * block, :wb * block].reshape(hb, block, wb, block)
    ab = amp1[:hb * block, :wb * block].reshape(hb, block, wb, block)
    with np.errstate(invalid="ignore"):
        rel = np.abs(np.nanmean(zb, axis=(1, 3)))
        a1 = np.nanmedian(ab, axis=(1, 3))
    return {"relative": rel, "amplitude": (2.0 / n) * rel * a1}


@dataclass(frozen=True)
class MeasuredHarmonics:
    """The display's harmonics against the camera noise, measured on decoded frames (grey levels).

    Attributes
    ----------
    harmonic_dn : float
        Median over the lit pixels of the largest harmonic's amplitude.
    noise_dn : float
        RMS camera noise there, harmonics taken out.
    modulation_dn : float
        Median fringe modulation B there.
    n_pixels : int
        Pixel pairs measured.
    """

    harmonic_dn: float
    noise_dn: float
    modulation_dn: float
    n_pixels: int


def measured_harmonics(noise_samples: dict) -> MeasuredHarmonics | None:
    """Harmonics and noise of one decoded position, for the design check.

    Parameters
    ----------
    noise_samples : dict
        ``{direction: samples}``, each from :func:`harmonic_noise_samples` (a decoded
        position's ``info["noise_samples"]``).

    Returns
    -------
    MeasuredHarmonics or None
        Over the lit pixels (modulation at least half its median over pixels with any), every
        direction pooled; None without samples (all levels of 4 steps or fewer) or lit pixels.
    """
    harm, var, mod = [], [], []
    for part in noise_samples.values():
        if part is None:
            continue
        m = np.asarray(part["modulation"], float)
        ok = np.isfinite(m) & (m > 0) & np.isfinite(part["var"]) & np.isfinite(part["harmonic"])
        if not ok.any():
            continue
        ok &= m >= 0.5 * np.median(m[ok])
        harm.append(np.asarray(part["harmonic"])[ok])
        var.append(np.asarray(part["var"])[ok])
        mod.append(m[ok])
    if not harm or sum(h.size for h in harm) == 0:
        return None
    harm, var, mod = (np.concatenate(a) for a in (harm, var, mod))
    return MeasuredHarmonics(float(np.median(harm)), float(np.sqrt(np.mean(var))), float(np.median(mod)),
                             int(harm.size))
