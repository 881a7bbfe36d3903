"""Phase retrieval, hierarchical temporal unwrapping and LCD coordinates.

Image stacks use one axis order everywhere: ``(steps, H, W)``. Per-pixel
maps are ``(H, W)`` indexed ``[row, col]``.

Two ways in, one result: :class:`PhaseAccumulator` consumes frames one at a
time (a handful of ``(H, W)`` float32 maps, whatever N is), and
:func:`wrapped_phase` reduces a whole ``(N, H, W)`` stack at once. The stack
path is the fast one: it works in row tiles small enough that all N frames of
a tile stay in the CPU cache, the tiles run on all cores (OpenCV and numpy
release the GIL), and the N-step sums are OpenCV accumulations straight from
the camera's integer frames (:func:`_nstep_chain`). Unwrapping and pixel
classification run over the same row tiles.
"""

from __future__ import annotations

import functools
import os
import sys
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from ptpcore.parallel import KERNEL_TILE_PIXELS, TILE_PIXELS, run_tiles
from ptpcore.rig.rigfile import Rig

__all__ = [
    "Reason",
    "REASON_NAMES",
    "REASON_KEYS",
    "apply_convention",
    "black_clipped",
    "PhaseAccumulator",
    "WrappedPhase",
    "wrapped_phase",
    "unwrap_hierarchical",
    "DirectionDecode",
    "DecodedPosition",
    "DecodeOptions",
    "decode_direction",
    "finish_position",
]


class Reason:
    """Bit flags of why a pixel is invalid at a position (combine with ``|``)."""

    LOW_MODULATION = 1
    SATURATED = 2
    UNWRAP = 4
    OUTSIDE_LCD = 8
    BORDER = 16
    BLACK_CLIPPED = 32
    GRAY_CODE = 64
    SPATIAL = 128
    # The robust fit (ptpcore.fit.robust) flags a sample far from its pixel's curve along z with the
    # spatial bit: both say "inconsistent with its neighbours beyond k predicted sigma", and the
    # uint8 reasons have no ninth bit. /quality/n_rejected counts the robust fit's own.
    OUTLIER = SPATIAL


REASON_NAMES = {
    Reason.LOW_MODULATION: "low modulation",
    Reason.SATURATED: "saturated",
    Reason.UNWRAP: "unwrapping disagreement",
    Reason.OUTSIDE_LCD: "outside the LCD",
    Reason.BORDER: "near the LCD border",
    Reason.BLACK_CLIPPED: "clipped at black",
    Reason.GRAY_CODE: "Gray-code failure",
    Reason.SPATIAL: "departs from its neighbours (in the image; or along z: robust fit)",
}

REASON_KEYS = {
    Reason.LOW_MODULATION: "low_modulation",
    Reason.SATURATED: "saturated",
    Reason.UNWRAP: "unwrap",
    Reason.OUTSIDE_LCD: "outside_lcd",
    Reason.BORDER: "border",
    Reason.BLACK_CLIPPED: "black_clipped",
    Reason.GRAY_CODE: "gray_code",
    Reason.SPATIAL: "spatial",
}
"""Attribute names of the reason bits (``/reasons`` of ``ptp-decoded/1``)."""


@dataclass
class WrappedPhase:
    """N-step result for one period and direction.

    Attributes
    ----------
    phase : (H, W) float32, radians in (-pi, pi]
    modulation : (H, W) float32, grey levels (B)
    background : (H, W) float32, grey levels (A)
    saturated : (H, W) bool, any step at the sensor's maximum level
    residual_var : (H, W) float32 or None
        Variance of the samples about the fitted sinusoid (grey levels^2),
        an unbiased noise estimate with N - 3 degrees of freedom; None for N = 3.
    black : (H, W) bool or None
        Any step at the sensor's black (0); None when not checked.
    """

    phase: np.ndarray
    modulation: np.ndarray
    background: np.ndarray
    saturated: np.ndarray
    residual_var: np.ndarray | None = None
    black: np.ndarray | None = None


def apply_convention(wp: WrappedPhase, shift_sign: int = 1, phase_origin_rad: float = 0.0) -> WrappedPhase:
    """Turn the N-step phase of frames shown as ``cos(theta + origin + sign * 2 pi n / N)``
    into ``theta`` (docs/method.md section 3), in place; the identity for ``(1, 0)``.

    With ``sign = -1`` the N-step estimate is ``-(theta + origin)``; the origin is
    then subtracted and the phase wrapped back into ``[-pi, pi)``.
    """
    if shift_sign == 1 and phase_origin_rad == 0.0:
        return wp
    p = wp.phase
    if shift_sign == -1:
        np.negative(p, out=p)
    if phase_origin_rad != 0.0:
        p64 = p.astype(np.float64) - (float(phase_origin_rad) - np.pi)
        np.mod(p64, 2.0 * np.pi, out=p64)
        p64 -= np.pi
        p[...] = p64
    return wp


def black_clipped(frames, black_level: float = 0.0) -> np.ndarray:
    """(H, W) bool: any frame at or below ``black_level`` (the sensor's black clips it)."""
    out = None
    for f in frames:
        f = np.asarray(f)
        # In the frames' own dtype: ``uint8 <= 0.0`` would convert every frame to float64 first.
        hit = f <= (_int_black_threshold(black_level) if f.dtype.kind in "iu" else black_level)
        out = hit if out is None else np.logical_or(out, hit, out=out)
    return out

class PhaseAccumulator:
    """Accumulate N phase-shifted frames one at a time (paper Eq. 2).

    ``S = sum I_n sin(delta_n)``, ``C = sum I_n cos(delta_n)``,
    ``phi = atan2(-S, C)``, ``B = (2/N) hypot(S, C)``, ``A = mean(I_n)``.
    """

    def __init__(self, shape: tuple[int, int], n_steps: int, saturation_level: float | None):
        self.n_steps = n_steps
        self.sat_level = saturation_level
        self.s = np.zeros(shape, np.float32)
        self.c = np.zeros(shape, np.float32)
        self.a = np.zeros(shape, np.float32)
        self.sq = np.zeros(shape, np.float64)  # sum of I^2 for the noise estimate
        self.saturated = np.zeros(shape, bool)
        self._seen: set[int] = set()
        self._tmp = np.empty(shape, np.float32)

    def add(self, frame: np.ndarray, step: int) -> None:
        """Add frame ``step`` (0-based) of the N; ``frame`` is (H, W), any real dtype."""
        if frame.shape != self.s.shape:
            raise ValueError(f"frame shape {frame.shape} != expected {self.s.shape}")
        if step in self._seen or not 0 <= step < self.n_steps:
            raise ValueError(f"step {step} repeated or outside 0..{self.n_steps - 1}")
        self._seen.add(step)
        delta = 2.0 * np.pi * step / self.n_steps
        tmp = self._tmp
        tmp[...] = frame
        # OpenCV accumulations: one pass each, no temporaries (np.square and
        # tmp * w would each allocate a full frame).
        cv2.accumulate(tmp, self.a)
        cv2.accumulateSquare(tmp, self.sq)  # float32 values squared exactly in float64
        if self.sat_level is not None:
            self.saturated |= frame >= self.sat_level
        sin_d, cos_d = np.float32(np.sin(delta)), np.float32(np.cos(delta))
        if sin_d != 0:
            cv2.scaleAdd(tmp, float(sin_d), self.s, dst=self.s)
        if cos_d != 0:
            cv2.scaleAdd(tmp, float(cos_d), self.c, dst=self.c)

    def result(self) -> WrappedPhase:
        """Wrapped phase, modulation, background once all N frames were added."""
        if len(self._seen) != self.n_steps:
            raise ValueError(f"only {len(self._seen)} of {self.n_steps} steps were added")
        n = self.n_steps
        phase = np.arctan2(-self.s, self.c)
        modulation = (2.0 / n) * np.hypot(self.s, self.c)
        background = self.a / n
        residual_var = None
        if n > 3:
            # sum (I - A - B cos(phi + delta))^2 = sum I^2 - N A^2 - (N/2) B^2
            # for equally spaced steps; N - 3 degrees of freedom remain.
            a64 = background.astype(np.float64)
            b64 = modulation.astype(np.float64)
            ssr = self.sq - n * a64 * a64 - 0.5 * n * b64 * b64
            residual_var = np.maximum(ssr, 0.0).astype(np.float32) / np.float32(n - 3)
        return WrappedPhase(phase, modulation, background, self.saturated, residual_var)


def wrapped_phase(frames: np.ndarray, saturation_level: float | None = None, *,
                  photometry: bool = True, out: WrappedPhase | None = None,
                  black_level: float | None = None) -> WrappedPhase:
    """N-step wrapped phase of a stack.

    Parameters
    ----------
    frames : (N, H, W) array_like, or a list of N (H, W) arrays
        Frame ``n`` was shown with phase shift ``2*pi*n/N``. Any real dtype;
        uint8, uint16 and float32 are reduced without a conversion pass. A
        list (one shape and dtype) is reduced in place, never stacked: the
        pipeline passes frames mapped straight from their files.
    saturation_level : float, optional
        Grey level at or above which a sample counts as saturated.
    photometry : bool
        Also compute ``background`` and ``residual_var``; without them (None)
        the reduction is about a third cheaper (the pipeline needs them at the
        finest period only).
    out : WrappedPhase, optional
        Arrays to fill instead of new ones (a streaming caller reuses them for
        every position: fresh multi-megabyte arrays cost page faults each time).
        Its ``background``/``residual_var`` decide what is computed.
    black_level : float, optional
        Also fill ``black``: any step at or below this level (:func:`black_clipped`'s test, in the
        same pass as the sums: the kernel keeps the minimum beside the maximum).

    Returns
    -------
    WrappedPhase
        The same values as :class:`PhaseAccumulator` fed frame by frame, to
        float32 rounding.
    """
    if isinstance(frames, (list, tuple)) and frames and all(isinstance(f, np.ndarray) for f in frames):
        # Separate frames (e.g. mapped files): reduced where they are, never stacked.
        if len({(f.shape, f.dtype) for f in frames}) != 1 or frames[0].ndim != 2 or len(frames) < 3:
            raise ValueError("frames must be N>=3 arrays (H, W) of one shape and dtype, got "
                             f"{[(f.shape, str(f.dtype)) for f in frames][:4]}")
        frames = list(frames)
        n, (h, w) = len(frames), frames[0].shape
    else:
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.shape[0] < 3:
            raise ValueError(f"frames must be (N>=3, H, W), got shape {frames.shape}")
        n, h, w = frames.shape
    if out is None:
        out = WrappedPhase(np.empty((h, w), np.float32), np.empty((h, w), np.float32),
                           np.empty((h, w), np.float32) if photometry else None, np.empty((h, w), bool),
                           np.empty((h, w), np.float32) if photometry and n > 3 else None)
    elif out.phase.shape != (h, w) or (out.residual_var is not None and n <= 3):
        raise ValueError(f"out does not fit {n} frames of shape {(h, w)}")
    if black_level is not None and out.black is None:
        out.black = np.empty((h, w), bool)
    fused = fused_kernels() is not None and np.dtype(frames[0].dtype) in _INT_SRC
    run_tiles(functools.partial(_nstep_rows, frames, saturation_level, out, black_level=black_level), h, w,
              KERNEL_TILE_PIXELS if fused else TILE_PIXELS)
    return out


# ---------------------------------------------------------------------------
# Optional numba kernels (ptpcore.decode._fused)

_fused_mod = None
_fused_tried = False
_fused_lock = threading.Lock()


def user_cache_dir() -> Path:
    """The per-user cache folder of PTP Studio (never inside the installed package).

    ``$XDG_CACHE_HOME/ptp-studio`` (default ``~/.cache/ptp-studio``) on Linux,
    ``~/Library/Caches/ptp-studio`` on macOS, ``%LOCALAPPDATA%\\ptp-studio\\Cache``
    on Windows.
    """
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
        return base / "ptp-studio" / "Cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "ptp-studio"
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    return (Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache") / "ptp-studio"


def _use_user_numba_cache() -> None:
    """Point numba's cache of compiled kernels at :func:`user_cache_dir` ``/ numba``.

    An installed package may be read-only, so the cache never goes next to
    the sources. A ``NUMBA_CACHE_DIR`` the user set is kept. Called before
    :mod:`ptpcore.decode._fused` is imported (numba picks a function's cache
    folder when it is decorated).
    """
    folder = os.environ.setdefault("NUMBA_CACHE_DIR", str(user_cache_dir() / "numba"))
    import numba

    if not numba.config.CACHE_DIR:  # numba was imported before the variable was set
        numba.config.CACHE_DIR = folder


def fused_kernels():
    """The numba kernels module :mod:`ptpcore.decode._fused`, or None.

    None when numba is not installed (``pip install "ptp-studio[fast]"``) or the
    environment sets ``PTP_NO_NUMBA=1``: the numpy/OpenCV path then runs. numba
    is imported on first use only (it takes a fraction of a second).
    """
    global _fused_mod, _fused_tried
    if os.environ.get("PTP_NO_NUMBA", "") not in ("", "0"):
        return None
    if not _fused_tried:
        with _fused_lock:
            if not _fused_tried:
                try:
                    _use_user_numba_cache()
                    from ptpcore.decode import _fused
                except ImportError:
                    _fused = None
                _fused_mod = _fused
                _fused_tried = True
    return _fused_mod


# ---------------------------------------------------------------------------
# The N-step kernel

@functools.lru_cache(maxsize=None)
def _nstep_chain(n: int, kind: str) -> tuple[tuple[tuple[int, float], ...], float]:
    """``cv2.accumulateWeighted`` steps that leave ``lam * sum_n w_n I_n`` in the sum.

    ``accumulateWeighted(I, acc, a)`` does ``acc = (1 - a) acc + a I`` in one
    pass straight from uint8/uint16 frames. Chained over the frames with
    non-zero weight, frame ``i`` ends up with coefficient
    ``a_i * prod_{j > i} (1 - a_j)``; solving backwards for ``a_i`` makes that
    ``lam * w_i``. ``lam`` keeps every ``|a|`` small (the factors near 1), so
    the result is as precise as a plain float32 sum (tests check it).

    Parameters
    ----------
    n : int
        Steps N.
    kind : {"s", "c"}
        Weights ``-sin(delta_n)`` (so the sum is ``-S``, atan2's first
        argument) or ``cos(delta_n)``.

    Returns
    -------
    steps : tuple of (frame index, alpha)
        In the order to apply them.
    lam : float
        The common scale of the result.
    """
    delta = 2.0 * np.pi * np.arange(n) / n
    wts = -np.sin(delta) if kind == "s" else np.cos(delta)
    nz = [i for i in range(n) if abs(wts[i]) > 1e-12]
    lam = 0.25 / float(np.abs(wts).sum())
    alphas = {}
    later = 1.0
    for i in reversed(nz):
        a = lam * wts[i] / later
        alphas[i] = a
        later *= 1.0 - a
    return tuple((i, alphas[i]) for i in nz), lam


_CV_SRC = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))
_INT_SRC = (np.dtype(np.uint8), np.dtype(np.uint16))


@functools.lru_cache(maxsize=None)
def _nstep_weights(n: int) -> tuple[np.ndarray, np.ndarray]:
    """float32 ``-sin(delta_n)``, ``cos(delta_n)``; exactly 0 where the weight is (``_nstep_chain``)."""
    delta = 2.0 * np.pi * np.arange(n) / n
    ws, wc = -np.sin(delta), np.cos(delta)
    ws[np.abs(ws) <= 1e-12] = 0.0
    wc[np.abs(wc) <= 1e-12] = 0.0
    return ws.astype(np.float32), wc.astype(np.float32)


def _int_black_threshold(level) -> int:
    """``x <= level`` as ``x <= t`` for integer ``x``."""
    if np.isnan(level) or level == -np.inf:
        return -(1 << 40)
    if level == np.inf:
        return 1 << 40
    return int(np.floor(level))


def _int_threshold(level) -> int:
    """``x >= level`` as ``x >= t`` for integer ``x`` (never true without a level)."""
    if level is None or np.isnan(level) or level == np.inf:
        return 1 << 40
    if level == -np.inf:
        return -(1 << 40)
    return int(np.ceil(level))


def _nstep_rows_fused(kern, frames, saturation_level, out: WrappedPhase, r0: int, r1: int,
                      black_level: float | None = None) -> None:
    """:func:`_nstep_rows` with the numba kernel (:func:`ptpcore.decode._fused.nstep_rows`): one pass over
    the tile's frames for all sums, then numpy's (SIMD) ``arctan2`` on the tile.

    ``frames``: the (N, H, W) stack or a sequence of N (H, W) frames (e.g. mapped files).
    """
    n = len(frames)
    w = frames[0].shape[-1]
    ws, wc = _nstep_weights(n)
    photometry = out.background is not None
    want_rv = out.residual_var is not None
    work = np.float32 if frames[0].dtype == np.uint8 and n <= 16 else np.float64
    neg_s = out.phase[r0:r1]  # -S goes straight into the phase rows, atan2 in place
    c = np.empty((r1 - r0, w), np.float32)
    if want_rv:
        rv, rv_r0 = out.residual_var, 0
    elif photometry:  # the kernel computes it with the background anyway (see there): a scratch tile
        rv, rv_r0 = np.empty((r1 - r0, w), np.float32), r0
    else:  # not touched
        rv, rv_r0 = out.modulation, 0
    if black_level is not None:
        black, black_r0, black_thr = out.black, 0, _int_black_threshold(black_level)
    else:  # a scratch tile (a branch in the kernel's pixel loop would stop it vectorising)
        black, black_r0, black_thr = np.empty((r1 - r0, w), bool), r0, -(1 << 40)
    kern.nstep_rows(_kernel_frames(frames), r0, r1, ws, wc, _int_threshold(saturation_level), neg_s, c,
                    out.modulation, out.saturated, photometry, out.background if photometry else out.modulation,
                    work(1), rv, rv_r0, black_thr, black, black_r0)
    np.arctan2(neg_s, c, out=neg_s)


def kernel_frames(frames) -> tuple:
    """The frames as a tuple of read-only C-contiguous (H, W) arrays: one numba type per
    dtype and N, whether they are slices of a stack, separate arrays or mapped files (what every
    numba kernel over a set's frames takes: the N-step sums, the noise samples' DFT bins)."""
    out = []
    for f in frames:
        f = np.ascontiguousarray(f)
        if f.flags.writeable:
            f = f.view()
            f.flags.writeable = False
        out.append(f)
    return tuple(out)


_kernel_frames = kernel_frames


def _nstep_rows(frames, saturation_level, out: WrappedPhase, r0: int, r1: int,
                black_level: float | None = None) -> None:
    """N-step reduction of rows ``[r0, r1)`` of a stack into ``out`` (see :func:`wrapped_phase`).

    ``frames``: an (N, H, W) array, or a list of N (H, W) arrays of one dtype.
    """
    n = len(frames)
    if frames[0].dtype in _INT_SRC:
        kern = fused_kernels()
        if kern is not None:
            _nstep_rows_fused(kern, frames, saturation_level, out, r0, r1, black_level)
            return
    raw = frames[:, r0:r1] if isinstance(frames, np.ndarray) else np.stack([f[r0:r1] for f in frames])
    if black_level is not None:  # in the frames' own dtype (a float comparison would convert them)
        lo = np.min(raw, axis=0)
        if lo.dtype.kind in "iu":
            np.less_equal(lo, _int_black_threshold(black_level), out=out.black[r0:r1])
        else:
            np.less_equal(lo, black_level, out=out.black[r0:r1])
    fr = raw if raw.dtype in _CV_SRC and raw.strides[-1] == raw.itemsize else raw.astype(np.float32)
    rows = fr.shape[1:]
    photometry = out.background is not None
    acc = np.zeros((3 if photometry else 2, *rows), np.float32)
    for k, kind in enumerate("sc"):
        steps, lam = _nstep_chain(n, kind)
        for i, alpha in steps:
            cv2.accumulateWeighted(fr[i], acc[k], alpha)
        np.multiply(acc[k], np.float32(1.0 / lam), out=acc[k])
    neg_s, c = acc[0], acc[1]
    np.arctan2(neg_s, c, out=out.phase[r0:r1])
    zz = cv2.magnitude(neg_s, c)  # |Z| = hypot(S, C)
    np.multiply(zz, 2.0 / n, out=out.modulation[r0:r1])
    if saturation_level is not None:
        np.greater_equal(np.max(raw, axis=0), saturation_level, out=out.saturated[r0:r1])
    else:
        out.saturated[r0:r1] = False
    if not photometry:
        return
    a = acc[2]
    for i in range(n):
        cv2.accumulate(fr[i], a)
    np.divide(a, n, out=out.background[r0:r1])
    if out.residual_var is None:
        return
    # sum (I - A - B cos(phi + delta))^2 = sum I^2 - N A^2 - (N/2) B^2
    #   = (N sum I^2 - (sum I)^2 - 2 |Z|^2) / N   (equally spaced steps),
    # with N - 3 degrees of freedom. For uint8 frames (N <= 16) the first two
    # terms are integers below 2^24, exact in float32; otherwise float64.
    exact32 = fr.dtype == np.uint8 and n <= 16
    work = np.float32 if exact32 else np.float64
    sq = np.zeros(rows, work)
    for i in range(n):
        cv2.accumulateSquare(fr[i], sq)
    sq *= n
    a2 = np.multiply(a, a, dtype=work)
    sq -= a2
    np.multiply(zz, zz, out=a2, dtype=work)
    a2 *= 2.0
    sq -= a2
    np.maximum(sq, 0.0, out=sq)
    np.multiply(sq, 1.0 / (n * (n - 3)), out=out.residual_var[r0:r1], casting="same_kind")


def unwrap_hierarchical(phases, periods) -> tuple[np.ndarray, np.ndarray]:
    """Hierarchical temporal unwrapping (docs/method.md section 4).

    Parameters
    ----------
    phases : sequence of (H, W) arrays, radians
        Wrapped phases, coarse to fine.
    periods : sequence of int
        Periods (LCD px), coarse to fine; the coarsest is unambiguous.

    Returns
    -------
    coord : (H, W) float64
        Absolute virtual coordinate ``Phi_fine * T_fine / (2*pi)``, LCD px.
    disagreement : (H, W) bool
        True where some step's prediction and result differ by more than a
        quarter period of the finer level.
    """
    if len(phases) != len(periods) or not phases:
        raise ValueError("need one wrapped phase per period")
    phases = [np.asarray(p) for p in phases]
    shape = phases[0].shape
    coord = np.empty(shape, np.float64)
    disagreement = np.zeros(shape, bool)
    if len(shape) != 2:
        _unwrap_rows(phases, periods, 0.0, coord, disagreement, slice(None))
    else:
        run_tiles(lambda r0, r1: _unwrap_rows(phases, periods, 0.0, coord, disagreement, slice(r0, r1)),
                  *shape)
    return coord, disagreement


def _unwrap_rows(phases, periods, shift: float, coord: np.ndarray, disagreement: np.ndarray, rows,
                 tolerance: float = 0.25, absolute0: np.ndarray | None = None) -> None:
    """:func:`unwrap_hierarchical` of ``rows``, minus a carrier ``shift``, into ``coord``/``disagreement``.

    The arithmetic is the reference's, operation for operation, in float64.
    ``tolerance``: disagreement limit in periods of the finer level (a quarter
    is the reference's ``pi / 2``, exactly). ``absolute0``: the absolute coarse
    phase (e.g. from a Gray code) instead of the coarsest phase in ``[0, 2 pi)``.
    """
    two_pi = 2.0 * np.pi
    limit = two_pi * tolerance  # 0.25: exactly pi / 2
    # Coarsest level: its phase in [0, 2*pi) is absolute by design. For
    # phases in [-2pi, 2pi) (atan2's are) mod is one conditional add, the same
    # numbers as np.mod, which is ten times slower.
    if absolute0 is not None:
        unwrapped = np.array(absolute0[rows], dtype=np.float64)
    else:
        unwrapped = np.array(phases[0][rows], dtype=np.float64)
    if absolute0 is not None:
        pass
    elif unwrapped.size and np.min(unwrapped) >= -two_pi and np.max(unwrapped) < two_pi:
        np.add(unwrapped, two_pi, out=unwrapped, where=unwrapped < 0)
        unwrapped += 0.0  # -0.0 -> +0.0, as np.mod gives
    else:
        np.mod(unwrapped, two_pi, out=unwrapped)
    dis = disagreement[rows]
    tmp = np.empty_like(unwrapped)
    step = np.empty_like(unwrapped)
    for j in range(1, len(periods)):
        predicted = unwrapped
        predicted *= periods[j - 1] / periods[j]
        phi = phases[j][rows]
        order = np.subtract(predicted, phi, out=tmp, dtype=np.float64)
        # x (1/2pi) instead of / 2pi: the orders differ only where the
        # residual is +-pi, which the quarter-period test flags either way.
        order *= 1.0 / two_pi
        np.rint(order, out=order)
        np.multiply(order, two_pi, out=step)
        unwrapped = np.add(phi, step, dtype=np.float64)
        np.subtract(unwrapped, predicted, out=tmp)
        np.abs(tmp, out=tmp)
        dis |= tmp > limit
    out = coord[rows]
    np.multiply(unwrapped, periods[-1] / two_pi, out=out)
    if shift:
        out -= shift


@dataclass
class DirectionDecode:
    """One direction at one position.

    Attributes
    ----------
    coord : (H, W) float64
        Real LCD coordinate (``u`` or ``v``) with the carrier removed, LCD px.
    wrapped : list of WrappedPhase, coarse to fine
    disagreement : (H, W) bool
    gray_failed : (H, W) bool or None
        Gray-code failures (Gray-code unwrapping only).
    periods : tuple of float, optional
        The direction's periods (coarse to fine).
    """

    coord: np.ndarray
    wrapped: list
    disagreement: np.ndarray
    gray_failed: np.ndarray | None = None
    periods: tuple | None = None


@dataclass(frozen=True)
class DecodeOptions:
    """Thresholds of pixel validity.

    Attributes
    ----------
    min_modulation : float
        Minimum modulation B as a fraction of the sensor's full scale, at every level.
    border_margin_px : int
        Pixels within this many camera pixels of the bezel (outside the LCD or
        low modulation) are rejected: blur mixes the bezel into them.
    """

    min_modulation: float = 0.03
    border_margin_px: int = 3
    unwrap_tolerance: float = 0.25
    spatial_k: float | None = 5.0

    def for_rig(self, rig: Rig) -> "DecodeOptions":
        """These options with the rig's ``[decode]`` thresholds where these are the defaults."""
        d, base = rig.decode, DecodeOptions()
        changes = {}
        for name in ("min_modulation", "border_margin_px", "unwrap_tolerance"):
            val = getattr(d, name)
            if val is not None and getattr(self, name) == getattr(base, name):
                changes[name] = val
        return replace(self, **changes) if changes else self


@dataclass
class DecodedPosition:
    """LCD coordinates and validity at one stage position.

    Attributes
    ----------
    index : int
    z_mm : float
    u, v : (H, W) float64 or None
        Real LCD coordinates (carrier removed), LCD px; None for a direction not shown.
    reasons : (H, W) uint8
        Bit flags of :class:`Reason`; 0 where valid.
    directions : dict of str -> DirectionDecode
    """

    index: int
    z_mm: float
    u: np.ndarray | None
    v: np.ndarray | None
    reasons: np.ndarray
    directions: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    """Per-position diagnostics: ``noise_samples`` (harmonic-free noise samples per direction),
    ``noise_source``, ``sigma`` (median predicted coordinate sigma per direction, LCD px)."""

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: usable sample."""
        return self.reasons == 0


def _heterodyne_rows(phases, periods, shift: float, coord: np.ndarray, disagreement: np.ndarray,
                     rows, tolerance: float) -> None:
    """Heterodyne unwrapping of rows ``rows`` (FORMATS.md ``unwrap = "heterodyne"``).

    ``phases`` and ``periods`` run longest first (``T3, T2, T1`` or ``T2, T1``, as the rig
    sorts them). The phase difference of two periods is the phase of their beat
    ``T12 = T1 T2 / (T2 - T1)``; the beat of the beats ``T123 = T12 T23 / |T23 - T12|``
    (three periods) is absolute. Each cascade step (``T123 -> T12 -> T1``) unwraps the
    finer phase from the coarser as hierarchical unwrapping does, and flags pixels
    whose two disagree by more than ``tolerance`` periods of the finer one.
    """
    from ptpcore.rig.rigfile import heterodyne_beats

    two_pi = 2.0 * np.pi
    beats = heterodyne_beats(periods)
    t = beats["periods"]
    p = [np.asarray(phases[len(phases) - 1 - i][rows], np.float64) for i in range(len(t))]  # T1, T2 (, T3)
    b12 = p[0] - p[1]
    if len(t) == 2:
        absolute = np.mod(b12, two_pi)
        chain = [(absolute, beats["absolute"])]
    else:
        b23 = p[1] - p[2]
        t12, t23 = beats["steps"][1][1], beats["t23"]
        absolute = np.mod(b12 - b23 if t23 > t12 else b23 - b12, two_pi)
        chain = [(absolute, beats["absolute"]), (b12, t12)]
    chain.append((p[0], t[0]))
    dis = disagreement[rows]
    limit = two_pi * tolerance
    unwrapped, t_prev = chain[0]
    for phi, t_this in chain[1:]:
        predicted = unwrapped * (t_prev / t_this)
        unwrapped = phi + two_pi * np.rint((predicted - phi) / two_pi)
        dis |= np.abs(unwrapped - predicted) > limit
        t_prev = t_this
    out = coord[rows]
    np.multiply(unwrapped, t[0] / two_pi, out=out)
    if shift:
        out -= shift


def decode_direction(wrapped, periods, carrier_shift_px: float, *, out=None, tolerance: float = 0.25,
                     absolute0: np.ndarray | None = None, gray_failed: np.ndarray | None = None,
                     heterodyne: bool = False) -> DirectionDecode:
    """Unwrap one direction and remove the carrier displacement ``s_k`` (LCD px).

    ``out``: optional ``(coord, disagreement)`` arrays to fill (reused by a streaming caller).
    ``tolerance``: unwrapping disagreement limit (periods of the finer level).
    ``absolute0``: the absolute coarse phase (Gray-code unwrapping), with its ``gray_failed`` pixels.
    ``heterodyne``: unwrap by the beats of two or three periods (:func:`_heterodyne_rows`);
    ``periods`` longest first.
    """
    if heterodyne:
        phases = [w.phase for w in wrapped]
        shape = np.shape(phases[0])
        coord, disagreement = (np.empty(shape, np.float64), np.zeros(shape, bool)) if out is None else out
        disagreement[...] = False
        if len(shape) != 2:
            _heterodyne_rows(phases, periods, carrier_shift_px, coord, disagreement, slice(None), tolerance)
        else:
            run_tiles(lambda r0, r1: _heterodyne_rows(phases, periods, carrier_shift_px, coord, disagreement,
                                                      slice(r0, r1), tolerance), *shape)
        return DirectionDecode(coord, list(wrapped), disagreement, None, tuple(periods))
    phases = [w.phase for w in wrapped]
    shape = np.shape(phases[0])
    if out is None:
        coord = np.empty(shape, np.float64)
        disagreement = np.zeros(shape, bool)
    else:
        coord, disagreement = out
        disagreement[...] = False
    if len(shape) != 2:
        _unwrap_rows(phases, periods, carrier_shift_px, coord, disagreement, slice(None), tolerance, absolute0)
    else:
        run_tiles(lambda r0, r1: _unwrap_rows(phases, periods, carrier_shift_px, coord, disagreement,
                                              slice(r0, r1), tolerance, absolute0), *shape)
    return DirectionDecode(coord, list(wrapped), disagreement, gray_failed, tuple(periods))


def _flag(reasons: np.ndarray, cond: np.ndarray, bit: int) -> None:
    """``reasons[cond] |= bit`` without a gather/scatter (cond is bool, same shape)."""
    np.bitwise_or(reasons, cond.view(np.uint8) * np.uint8(bit), out=reasons)


def _gradient_at(coord: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.gradient(coord)`` at some pixels: central differences ``/ 2.0`` inside,
    one-sided at the image's edges (numpy's ``edge_order=1``), the same numbers."""
    h, w = coord.shape
    up, dn = np.maximum(rows - 1, 0), np.minimum(rows + 1, h - 1)
    lf, rt = np.maximum(cols - 1, 0), np.minimum(cols + 1, w - 1)
    gr = (coord[dn, cols] - coord[up, cols]) / (dn - up).astype(float)
    gc = (coord[rows, rt] - coord[rows, lf]) / (rt - lf).astype(float)
    return gr, gc


def _near_edge(coord: np.ndarray, r0: int, r1: int, extent: int, margin: int) -> np.ndarray:
    """Rows ``[r0, r1)`` of the reference test

    ``reach = margin * hypot(*np.gradient(coord))``,
    ``(coord < -0.5 + reach) | (coord > extent - 0.5 - reach)``,

    with the same result, but the gradient only where the test is in doubt: a
    tile-wide bound ``reach <= margin * (max|row step| + max|column step|)``
    (``hypot(a, b) <= |a| + |b|``, and a central difference is at most the
    larger of its two steps) leaves that to pixels near the LCD's edges.
    """
    h, w = coord.shape
    c = coord[r0:r1]
    lo, hi = max(r0 - 1, 0), min(r1 + 1, h)
    block = coord[lo:hi]
    with np.errstate(invalid="ignore"):
        bound = 0.0
        if hi - lo > 1:
            d = np.subtract(block[1:], block[:-1])
            bound += max(float(np.max(d)), -float(np.min(d)))
        if w > 1:
            d = np.subtract(c[:, 1:], c[:, :-1])
            bound += max(float(np.max(d)), -float(np.min(d)))
        if not np.isfinite(bound):  # NaN coordinates: test every pixel
            doubt = np.ones(c.shape, bool)
        else:
            bound = margin * bound * (1 + 1e-9) + 1e-9
            doubt = (c < -0.5 + bound) | (c > (extent - 0.5) - bound)
        n_doubt = int(np.count_nonzero(doubt))
        if n_doubt > doubt.size // 16:  # e.g. noise in the bezel: the whole tile, exactly
            gr, gc = _gradient_rows(coord, r0, r1)
            reach = np.hypot(gr, gc)
            reach *= margin
            return (c < -0.5 + reach) | (c > extent - 0.5 - reach)
        near = np.zeros(c.shape, bool)
        if n_doubt:
            ii, jj = np.nonzero(doubt)
            gr, gc = _gradient_at(coord, ii + r0, jj)
            reach = np.hypot(gr, gc) * margin
            cc = c[ii, jj]
            near[ii, jj] = (cc < -0.5 + reach) | (cc > extent - 0.5 - reach)
    return near


def _gradient_rows(coord: np.ndarray, r0: int, r1: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.gradient(coord)`` on rows ``[r0, r1)`` (one halo row each side: the same numbers)."""
    h, w = coord.shape
    lo, hi = max(r0 - 1, 0), min(r1 + 1, h)
    f = coord[lo:hi]
    gr = np.empty(f.shape)
    gr[1:-1] = f[2:] - f[:-2]
    gr[1:-1] /= 2.0
    gr[0] = f[1] - f[0]
    gr[-1] = f[-1] - f[-2]
    gc = np.empty(f.shape)
    gc[:, 1:-1] = f[:, 2:] - f[:, :-2]
    gc[:, 1:-1] /= 2.0
    gc[:, 0] = f[:, 1] - f[:, 0]
    gc[:, -1] = f[:, -1] - f[:, -2]
    sl = slice(r0 - lo, r1 - lo)
    return gr[sl], gc[sl]


def finish_position(rig: Rig, index: int, decoded: dict, options: DecodeOptions = DecodeOptions(), *,
                    out: np.ndarray | None = None) -> DecodedPosition:
    """Combine the decoded directions of one position and classify every pixel.

    Parameters
    ----------
    rig : Rig
    index : int
        Position index k.
    decoded : dict of str -> DirectionDecode
        Only ``modulation`` and ``saturated`` of the wrapped levels are read.
    options : DecodeOptions
    out : (H, W) uint8, optional
        The array to hold ``reasons`` (reused by a streaming caller).
    """
    shape = rig.camera.shape
    h, w = shape
    if out is None:
        reasons = np.zeros(shape, np.uint8)
    else:
        reasons = out
        reasons[...] = 0
    min_mod = options.min_modulation * rig.camera.max_level
    m = options.border_margin_px
    items = [(dec, rig.lcd.width if d == "x" else rig.lcd.height) for d, dec in decoded.items()]

    def rows(r0: int, r1: int) -> None:
        rs = reasons[r0:r1]
        low = np.empty(rs.shape, bool)
        for dec, extent in items:
            for wp in dec.wrapped:
                np.less(wp.modulation[r0:r1], min_mod, out=low)
                _flag(rs, low, Reason.LOW_MODULATION)
                _flag(rs, wp.saturated[r0:r1], Reason.SATURATED)
            _flag(rs, dec.disagreement[r0:r1], Reason.UNWRAP)
            coord = dec.coord[r0:r1]
            outside = ~((coord >= -0.5) & (coord <= extent - 0.5))
            _flag(rs, outside, Reason.OUTSIDE_LCD)
            if m > 0:
                # Within the margin of the LCD edge in LCD px, scaled by the local
                # footprint (LCD px per camera px): this also catches an LCD edge
                # that lies just beyond the sensor's edge, where no bezel is seen.
                near_edge = _near_edge(dec.coord, r0, r1, extent, m)
                _flag(rs, near_edge & ~outside, Reason.BORDER)

    run_tiles(rows, h, w)
    if m > 0:
        bezel = np.bitwise_and(reasons, Reason.OUTSIDE_LCD | Reason.LOW_MODULATION)
        if bezel.any():
            # A square dilation (scipy's binary_dilation with a full square
            # structure, outside the image False) as OpenCV's separable one.
            near = cv2.dilate(bezel, np.ones((2 * m + 1, 2 * m + 1), np.uint8))

            def border(r0: int, r1: int) -> None:
                nb = np.greater(near[r0:r1], 0)
                nb &= bezel[r0:r1] == 0
                _flag(reasons[r0:r1], nb, Reason.BORDER)

            run_tiles(border, h, w)
    u = decoded["x"].coord if "x" in decoded else None
    v = decoded["y"].coord if "y" in decoded else None
    return DecodedPosition(index, float(rig.stage.z_mm[index]), u, v, reasons, dict(decoded))


def decode_and_finish(rig: Rig, index: int, levels: dict, options: DecodeOptions = DecodeOptions(), *,
                      outs: dict | None = None, per_direction: bool = False) -> DecodedPosition | None:
    """:func:`decode_direction` of every direction, then :func:`finish_position`, fused.

    With the numba kernels (:func:`fused_kernels`), unwrapping and the per-pixel
    classification of both directions are one pass per row tile, and the border
    test another; the results are bit-equal to the two functions (tests check).
    Returns None without the kernels (the caller then runs the two functions).

    Parameters
    ----------
    rig : Rig
    index : int
        Position index k.
    levels : dict of str -> list of WrappedPhase
        Each direction's wrapped levels, coarse to fine.
    options : DecodeOptions
    outs : dict, optional
        ``{d: (coord, disagreement), "reasons": reasons}`` arrays to fill
        (reused by a streaming caller; with ``per_direction`` also ``("reasons", d)``).
    per_direction : bool
        Classify each direction alone (``ptp decode`` writes them apart): ``info["direction_reasons"]``
        is ``{d: (H, W) uint8}``, each bit-equal to ``finish_position(rig, index, {d: ...}).reasons``,
        and the position's ``reasons`` their OR (which differs from both directions classified
        together only in the bezel's border: there each direction's own bezel sets ``BORDER``).
    """
    kern = fused_kernels()
    if kern is None:
        return None
    f = rig.fringes
    h, w = rig.camera.shape
    if h < 2 or w < 2:
        return None
    z = float(rig.stage.z_mm[index])
    outs = {} if outs is None else outs
    reasons = outs.get("reasons")
    if reasons is None:
        reasons = np.zeros((h, w), np.uint8)
    else:
        reasons[...] = 0
    two_pi = 2.0 * np.pi
    if options.unwrap_tolerance != 0.25 or f.unwrap != "periods":
        return None  # the kernel's limit is a quarter period; Gray codes take the numpy path
    min_mod = np.float32(options.min_modulation * rig.camera.max_level)  # as numpy compares float32 maps
    m = options.border_margin_px
    jobs = []
    decoded = {}
    for d, wrapped in levels.items():
        periods = list(f.periods(d))
        if len(wrapped) != len(periods):
            raise ValueError("need one wrapped phase per period")
        ratios = np.array([1.0] + [periods[j - 1] / periods[j] for j in range(1, len(periods))])
        scale = periods[-1] / two_pi
        coord, dis = outs.get(d) or (np.empty((h, w), np.float64), np.empty((h, w), bool))
        extent = float(rig.lcd.width if d == "x" else rig.lcd.height)
        own = reasons
        if per_direction:
            own = outs.get(("reasons", d))
            if own is None:
                own = np.zeros((h, w), np.uint8)
            else:
                own[...] = 0
        jobs.append((tuple(wp.phase for wp in wrapped), float(f.carrier(d) * z),
                     tuple(wp.modulation for wp in wrapped), tuple(wp.saturated for wp in wrapped),
                     extent, coord, dis, ratios, scale, own))
        decoded[d] = DirectionDecode(coord, list(wrapped), dis, None, tuple(periods))

    def rows(r0: int, r1: int) -> None:
        for phases, shift, mods, sats, extent, coord, dis, ratios, scale, own in jobs:
            kern.unwrap_classify_rows(r0, r1, phases, ratios, scale, shift, mods, sats, min_mod,
                                      extent, coord, dis, own)

    run_tiles(rows, h, w, KERNEL_TILE_PIXELS)
    if m > 0:
        def edges(r0: int, r1: int) -> None:
            for *_, extent, coord, _dis, _ratios, _scale, own in jobs:
                kern.near_edge_rows(r0, r1, coord, extent, float(m), own)

        run_tiles(edges, h, w, KERNEL_TILE_PIXELS)
        for own in ([job[-1] for job in jobs] if per_direction else [reasons]):
            _bezel_border(kern, own, m)
    u = decoded["x"].coord if "x" in decoded else None
    v = decoded["y"].coord if "y" in decoded else None
    pos = DecodedPosition(index, z, u, v, reasons, decoded)
    if per_direction:
        for job in jobs:
            np.bitwise_or(reasons, job[-1], out=reasons)
        pos.info["direction_reasons"] = {d: job[-1] for d, job in zip(decoded, jobs)}
    return pos


def _bezel_border(kern, reasons: np.ndarray, m: int) -> None:
    """``BORDER`` within ``m`` pixels of the bezel (outside the LCD or low modulation) of ``reasons``."""
    h, w = reasons.shape
    bezel = np.bitwise_and(reasons, Reason.OUTSIDE_LCD | Reason.LOW_MODULATION)
    if bezel.any():
        near = cv2.dilate(bezel, np.ones((2 * m + 1, 2 * m + 1), np.uint8))
        run_tiles(lambda r0, r1: kern.border_rows(r0, r1, near, reasons), h, w, KERNEL_TILE_PIXELS)
