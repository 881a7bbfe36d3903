"""Gray-code unwrapping (docs/method.md section 4): the cycle index of the coarsest period.

B binary-reflected Gray-code images (bit 0 the most significant) count the
cycles ``m`` of the coarsest phase-shifted period ``T_0``: cycle ``m`` covers
``u + s`` in ``[m T_0, (m + 1) T_0)``. Each bit is decided against a threshold:
its inverse image when one was captured, else the mean of all-white and
all-black reference frames, else the background ``A`` of the phase-shifted
images. The phase then gives the absolute coarse phase
``Phi_0 = phi_0 + 2 pi m``, corrected by one cycle where the code's edge and
the phase's jump disagree (blur puts them a pixel apart).

A pixel fails ("Gray-code failure") when a bit is undecidable (its margin
from the threshold below a quarter of the fringe modulation) other than the
bit that flips at the cell edge the pixel sits on.
"""

from __future__ import annotations

import numpy as np

__all__ = ["gray_bits_of", "gray_to_index", "gray_index", "absolute_coarse_phase"]

UNDECIDED_FRACTION = 0.25
"""A bit is undecidable where its distance from the threshold is below this fraction of the
fringe modulation B (the Gray code's own contrast is about 2.5 B)."""


def gray_bits_of(index: np.ndarray, n_bits: int) -> np.ndarray:
    """``(n_bits, ...)`` bool: the binary-reflected Gray code of ``index``, most significant bit first."""
    index = np.asarray(index, np.int64)
    g = index ^ (index >> 1)
    return np.stack([(g >> (n_bits - 1 - b)) & 1 for b in range(n_bits)]).astype(bool)


def gray_to_index(bits) -> np.ndarray:
    """Index (int32) from Gray-code bits ``(B, ...)``, most significant first."""
    bits = np.asarray(bits, bool)
    binary = np.zeros(bits.shape[1:], bool)
    index = np.zeros(bits.shape[1:], np.int32)
    for b in range(bits.shape[0]):
        binary = binary ^ bits[b]
        index = (index << 1) | binary
    return index


def gray_index(frames, inverses=None, *, white=None, black=None, background=None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Decode the cycle index ``m`` of every pixel.

    Parameters
    ----------
    frames : sequence of B (H, W) arrays
        Gray-code images, bit 0 (most significant) first.
    inverses : sequence of B (H, W) arrays, optional
        Each bit's inverse image (the threshold per bit).
    white, black : (H, W) arrays, optional
        All-on and all-off frames: threshold ``(white + black) / 2``.
    background : (H, W) array, optional
        Threshold when neither is given: the phase-shifted images' mean ``A``.

    Returns
    -------
    index : (H, W) int32
    contrast : (B, H, W) float32
        Per bit, the distance of the image from its threshold (grey levels; with
        inverses half their difference): how clearly the bit was decided.
    """
    n = len(frames)
    if n == 0:
        raise ValueError("no Gray-code frames")
    shape = np.shape(frames[0])
    if inverses is None:
        if white is not None and black is not None:
            thr = 0.5 * (np.asarray(white, np.float32) + np.asarray(black, np.float32))
        elif background is not None:
            thr = np.asarray(background, np.float32)
        else:
            raise ValueError("Gray code needs inverse frames, white and black frames, or the background")
    bits = np.empty((n, *shape), bool)
    contrast = np.empty((n, *shape), np.float32)
    for b in range(n):
        img = np.asarray(frames[b], np.float32)
        if inverses is not None:
            diff = 0.5 * (img - np.asarray(inverses[b], np.float32))
        else:
            diff = img - thr
        bits[b] = diff > 0
        contrast[b] = np.abs(diff)
    return gray_to_index(bits), contrast


def _edge_bit(m: np.ndarray, n_bits: int) -> np.ndarray:
    """Bit (0 = most significant) that flips between cells ``m`` and ``m + 1``; -1 where ``m + 1``
    does not exist (or ``m < 0``)."""
    m = np.asarray(m, np.int64)
    flip = (m ^ (m >> 1)) ^ ((m + 1) ^ ((m + 1) >> 1))
    pos = np.zeros(m.shape, np.int64)
    f = flip.copy()
    for _ in range(n_bits):
        more = f > 1
        pos += more
        f = np.where(more, f >> 1, f)
    bit = n_bits - 1 - pos
    return np.where((m >= 0) & (m + 1 < (1 << n_bits)), bit, -1)


def _contrast_of(contrast: np.ndarray, bit: np.ndarray) -> np.ndarray:
    """``contrast[bit]`` per pixel; where ``bit`` is -1 (no such edge: the first or last cell)
    the clearest bit's contrast, so that the edge that does exist moves the pixel only when
    its own bit is weakly decided."""
    got = np.take_along_axis(contrast, np.maximum(bit, 0)[None], axis=0)[0].astype(np.float64)
    return np.where(bit >= 0, got, contrast.max(axis=0))


def absolute_coarse_phase(phase0, index, contrast=None, modulation=None, tolerance: float = 0.25
                          ) -> tuple[np.ndarray, np.ndarray]:
    """``Phi_0 = phi_0 + 2 pi m``, corrected by the phase at the cells' edges.

    Near a cell's edge (the phase within ``tolerance`` of its jump) blur leaves
    the bit that flips there undecided, and the code may name the neighbouring
    cell. The phase says which edge the pixel is at; of the two cells that edge
    could belong to, the one whose edge bit is the weakly decided one is taken
    (the other's edge bit must then be at most half as clear as the code's own).

    Parameters
    ----------
    phase0 : (H, W) array
        Wrapped phase of the coarsest level (radians, any 2 pi range).
    index : (H, W) int
        Gray-code cycle index m.
    contrast : (B, H, W) array, optional
        From :func:`gray_index`; without it no correction and no failure test.
    modulation : (H, W) array, optional
        Fringe modulation B: a bit is undecided where its contrast is below
        :data:`UNDECIDED_FRACTION` of it.
    tolerance : float
        Cycles: how near the phase jump the edge rule applies.

    Returns
    -------
    Phi0 : (H, W) float64
        Absolute coarse phase.
    failed : (H, W) bool
        Gray-code failure: a bit undecided other than the edge bit of a pixel at
        its cell's edge.
    """
    two_pi = 2.0 * np.pi
    frac = np.mod(np.asarray(phase0, np.float64), two_pi) / two_pi  # position inside a cycle, [0, 1)
    m = np.asarray(index, np.int64)
    failed = np.zeros(m.shape, bool)
    if contrast is None:
        return (m + frac) * two_pi, failed
    n_bits = contrast.shape[0]
    low_bit = _edge_bit(m - 1, n_bits)  # edge between m - 1 and m
    up_bit = _edge_bit(m, n_bits)  # edge between m and m + 1
    c_low, c_up = _contrast_of(contrast, low_bit), _contrast_of(contrast, up_bit)
    start = frac < tolerance  # just after a phase jump: at the lower edge of the true cell
    end = frac > 1.0 - tolerance  # just before one: at its upper edge
    up = start & (c_up < 0.5 * c_low)  # the code has not switched yet: the cell above
    down = end & (c_low < 0.5 * c_up)  # the code switched early: the cell below
    cell = m + up - down
    if modulation is not None:
        undecided = contrast < UNDECIDED_FRACTION * np.asarray(modulation, np.float32)[None]
        allowed = np.where(start, np.where(up, up_bit, low_bit), np.where(end, np.where(down, low_bit, up_bit), -1))
        b = np.arange(n_bits).reshape(-1, *([1] * m.ndim))
        failed = np.any(undecided & (b != allowed[None]), axis=0)
    return (cell + frac) * two_pi, failed
