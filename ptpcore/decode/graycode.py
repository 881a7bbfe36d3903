"""Gray-code unwrapping (METHOD.md section 4): the cycle index of the coarsest period.

B binary-reflected Gray-code images (bit 0 the most significant) count the
cycles ``m`` of the coarsest phase-shifted period ``T_0``: cycle ``m`` covers
``u + s`` in ``[m T_0, (m + 1) T_0)``. Each bit is decided against a threshold:
its inverse image when one was captured, else the mean of all-white and
all-black reference frames, else the background ``A`` of the phase-shifted
images. The phase then gives the absolute coarse phase
``Phi_0 = phi_0 + 2 pi m``, corrected by one cycle where the code's edge and
the phase's jump disagree (blur puts them a pixel apart).

A pixel fails ("Gray-code failure") when a bit is undecidable away from its
cycle's edges (its margin from the threshold below a quarter of the fringe
modulation there, where no edge excuses it) or when the phase falls outside its
Gray cell by more than the unwrapping tolerance.
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


def gray_index(frames, inverses=None, *, white=None, black=None, background=None,
               modulation=None) -> tuple[np.ndarray, np.ndarray]:
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
    modulation : (H, W) array, optional
        Fringe modulation ``B``: a bit is undecidable where its margin from the
        threshold is below :data:`UNDECIDED_FRACTION` of it. Without it no bit is.

    Returns
    -------
    index : (H, W) int32
    undecided : (B, H, W) bool
        Per bit, whether it was too close to its threshold to tell.
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
    undecided = np.zeros((n, *shape), bool)
    margin = None if modulation is None else UNDECIDED_FRACTION * np.asarray(modulation, np.float32)
    for b in range(n):
        img = np.asarray(frames[b], np.float32)
        if inverses is not None:
            diff = 0.5 * (img - np.asarray(inverses[b], np.float32))
        else:
            diff = img - thr
        bits[b] = diff > 0
        if margin is not None:
            undecided[b] = ~(np.abs(diff) >= margin)
    return gray_to_index(bits), undecided


def absolute_coarse_phase(phase0, index, undecided=None, tolerance: float = 0.25
                          ) -> tuple[np.ndarray, np.ndarray]:
    """``Phi_0 = phi_0 + 2 pi m``, corrected by the phase at the cells' edges.

    Parameters
    ----------
    phase0 : (H, W) array
        Wrapped phase of the coarsest level (radians, any 2 pi range).
    index : (H, W) int
        Gray-code cycle index m.
    undecided : (B, H, W) bool, optional
        From :func:`gray_index`.
    tolerance : float
        Cycles the phase may lie outside its Gray cell.

    Returns
    -------
    Phi0 : (H, W) float64
        Absolute coarse phase.
    failed : (H, W) bool
        Gray-code failure: an undecided bit away from the cell's edges, or the
        phase more than ``tolerance`` cycles outside its Gray cell.
    """
    two_pi = 2.0 * np.pi
    frac = np.mod(np.asarray(phase0, np.float64), two_pi) / two_pi  # position inside a cycle, [0, 1)
    m = np.asarray(index, np.float64)
    # The cycle nearest the Gray cell's centre m + 1/2 that holds this phase.
    cycle = np.rint(m + 0.5 - frac)
    coord = cycle + frac  # in cycles of T_0
    outside = np.maximum(m - coord, coord - (m + 1.0))  # < 0 inside the Gray cell
    failed = ~(outside <= tolerance)
    if undecided is not None and undecided.shape[0]:
        # An undecided bit is normal at a cell edge, where the code flips: only
        # away from every edge (by the tolerance) is it a failure.
        near_edge = (frac < tolerance) | (frac > 1.0 - tolerance)
        failed |= undecided.any(axis=0) & ~near_edge
    return coord * two_pi, failed
