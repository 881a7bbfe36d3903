"""Phase retrieval, hierarchical temporal unwrapping and LCD coordinates.

Image stacks use one axis order everywhere: ``(steps, H, W)``. Per-pixel
maps are ``(H, W)`` indexed ``[row, col]``.

Frames are consumed one at a time (:class:`PhaseAccumulator`), so decoding a
position never holds more than a handful of ``(H, W)`` float32 maps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from .rig import Rig

__all__ = [
    "Reason",
    "REASON_NAMES",
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


REASON_NAMES = {
    Reason.LOW_MODULATION: "low modulation",
    Reason.SATURATED: "saturated",
    Reason.UNWRAP: "unwrapping disagreement",
    Reason.OUTSIDE_LCD: "outside the LCD",
    Reason.BORDER: "near the LCD border",
}


@dataclass
class WrappedPhase:
    """N-step result for one period and direction.

    Attributes
    ----------
    phase : (H, W) float32, radians in (-pi, pi]
    modulation : (H, W) float32, grey levels (B)
    background : (H, W) float32, grey levels (A)
    saturated : (H, W) bool, any step at the sensor's maximum level
    """

    phase: np.ndarray
    modulation: np.ndarray
    background: np.ndarray
    saturated: np.ndarray


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
        self.a += tmp
        if self.sat_level is not None:
            self.saturated |= frame >= self.sat_level
        sin_d, cos_d = np.float32(np.sin(delta)), np.float32(np.cos(delta))
        if sin_d != 0:
            self.s += tmp * sin_d
        if cos_d != 0:
            self.c += tmp * cos_d

    def result(self) -> WrappedPhase:
        """Wrapped phase, modulation, background once all N frames were added."""
        if len(self._seen) != self.n_steps:
            raise ValueError(f"only {len(self._seen)} of {self.n_steps} steps were added")
        n = self.n_steps
        phase = np.arctan2(-self.s, self.c)
        modulation = (2.0 / n) * np.hypot(self.s, self.c)
        return WrappedPhase(phase, modulation, self.a / n, self.saturated)


def wrapped_phase(frames: np.ndarray, saturation_level: float | None = None) -> WrappedPhase:
    """N-step wrapped phase of a stack.

    Parameters
    ----------
    frames : (N, H, W) array_like
        Frame ``n`` was shown with phase shift ``2*pi*n/N``.
    saturation_level : float, optional
        Grey level at or above which a sample counts as saturated.
    """
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[0] < 3:
        raise ValueError(f"frames must be (N>=3, H, W), got shape {frames.shape}")
    acc = PhaseAccumulator(frames.shape[1:], frames.shape[0], saturation_level)
    for n, frame in enumerate(frames):
        acc.add(frame, n)
    return acc.result()


def unwrap_hierarchical(phases, periods) -> tuple[np.ndarray, np.ndarray]:
    """Hierarchical temporal unwrapping (METHOD.md section 4).

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
    two_pi = 2.0 * np.pi
    # Coarsest level: its phase in [0, 2*pi) is absolute by design.
    unwrapped = np.mod(np.asarray(phases[0], dtype=np.float64), two_pi)
    disagreement = np.zeros(unwrapped.shape, bool)
    for j in range(1, len(periods)):
        predicted = unwrapped * (periods[j - 1] / periods[j])
        phi = np.asarray(phases[j], dtype=np.float64)
        order = np.rint((predicted - phi) / two_pi)
        unwrapped = phi + two_pi * order
        disagreement |= np.abs(unwrapped - predicted) > (np.pi / 2)
    return unwrapped * (periods[-1] / two_pi), disagreement


@dataclass
class DirectionDecode:
    """One direction at one position.

    Attributes
    ----------
    coord : (H, W) float64
        Real LCD coordinate (``u`` or ``v``) with the carrier removed, LCD px.
    wrapped : list of WrappedPhase, coarse to fine
    disagreement : (H, W) bool
    """

    coord: np.ndarray
    wrapped: list
    disagreement: np.ndarray


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

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: usable sample."""
        return self.reasons == 0


def decode_direction(wrapped, periods, carrier_shift_px: float) -> DirectionDecode:
    """Unwrap one direction and remove the carrier displacement ``s_k`` (LCD px)."""
    coord, disagreement = unwrap_hierarchical([w.phase for w in wrapped], periods)
    coord -= carrier_shift_px
    return DirectionDecode(coord, list(wrapped), disagreement)


def finish_position(rig: Rig, index: int, decoded: dict, options: DecodeOptions = DecodeOptions()) -> DecodedPosition:
    """Combine the decoded directions of one position and classify every pixel.

    Parameters
    ----------
    rig : Rig
    index : int
        Position index k.
    decoded : dict of str -> DirectionDecode
    options : DecodeOptions
    """
    shape = rig.camera.shape
    reasons = np.zeros(shape, np.uint8)
    min_mod = options.min_modulation * rig.camera.max_level
    for d, dec in decoded.items():
        extent = rig.lcd.width if d == "x" else rig.lcd.height
        for w in dec.wrapped:
            reasons[w.modulation < min_mod] |= Reason.LOW_MODULATION
            reasons[w.saturated] |= Reason.SATURATED
        reasons[dec.disagreement] |= Reason.UNWRAP
        outside = ~((dec.coord >= -0.5) & (dec.coord <= extent - 0.5))
        reasons[outside] |= Reason.OUTSIDE_LCD
        if options.border_margin_px > 0:
            # Within the margin of the LCD edge in LCD px, scaled by the local
            # footprint (LCD px per camera px): this also catches an LCD edge
            # that lies just beyond the sensor's edge, where no bezel is seen.
            with np.errstate(invalid="ignore"):
                gr, gc = np.gradient(dec.coord)
                reach = options.border_margin_px * np.hypot(gr, gc)
                near_edge = (dec.coord < -0.5 + reach) | (dec.coord > extent - 0.5 - reach)
            reasons[near_edge & ~outside] |= Reason.BORDER
    m = options.border_margin_px
    if m > 0:
        bezel = (reasons & (Reason.OUTSIDE_LCD | Reason.LOW_MODULATION)) != 0
        if bezel.any():
            near = ndimage.binary_dilation(bezel, structure=np.ones((2 * m + 1, 2 * m + 1), bool))
            reasons[near & ~bezel] |= Reason.BORDER
    u = decoded["x"].coord if "x" in decoded else None
    v = decoded["y"].coord if "y" in decoded else None
    return DecodedPosition(index, float(rig.stage.z_mm[index]), u, v, reasons, dict(decoded))
