"""Every pixel's samples over all positions: the data every fit reads.

A :class:`SampleStack` holds ``(z_k, X_k, Y_k)`` and the validity reasons of every
camera pixel at every stage position, in memory or spilled to a file
(:class:`ptpcore.store.SpillStore`) on big sensors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ptpcore.decode.noise import NoiseModel

__all__ = ["SampleStack"]


@dataclass
class SampleStack:
    """Every pixel's samples ``(z_k, X_k, Y_k)`` over all positions.

    Attributes
    ----------
    z : (K,) float64, mm
        Stage readings in capture order.
    x, y : (K, H, W) float32, mm
        World coordinates relative to ``x_ref``/``y_ref`` (float32 offsets keep
        nanometre precision at half the memory of float64). NaN where invalid.
    x_ref, y_ref : (H, W) float64, mm
        Per-pixel reference (first valid sample); NaN for never-valid pixels.
    reasons : (K, H, W) uint8
        :class:`ptpcore.decode.phase.Reason` flags; 0 where valid.
    modulation : (K, H, W) float32 or None
        Finest-period modulation (worse direction), grey levels.
    background : (K, H, W) float32 or None
        Background level A (grey levels).
    noise : ptpcore.decode.noise.NoiseModel or None
        The camera noise measured from the N-step fit residuals.
    corrections : dict
        Name -> JSON-ready record of every correction applied since decoding
        (:mod:`ptpcore.fit.glass`); empty as decoded.
    lcd_shift : (2,) tuple of (H, W) float64 arrays (mm), or None
        What those corrections added to each pixel's X, Y: the decoded LCD
        point is ``absolute - lcd_shift``. None as decoded.
    """

    z: np.ndarray
    x: np.ndarray
    y: np.ndarray
    x_ref: np.ndarray
    y_ref: np.ndarray
    reasons: np.ndarray
    modulation: np.ndarray | None = None
    background: np.ndarray | None = None
    noise: NoiseModel | None = None  # measured from the N-step residuals (ptpcore.decode.noise)
    corrections: dict = field(default_factory=dict)
    lcd_shift: tuple | None = None

    @classmethod
    def empty(cls, z, shape, with_photometry: bool = True) -> "SampleStack":
        k = len(z)
        full = (k, *shape)
        return cls(
            np.asarray(z, dtype=float),
            np.full(full, np.nan, np.float32), np.full(full, np.nan, np.float32),
            np.full(shape, np.nan), np.full(shape, np.nan),
            np.full(full, 0xFF, np.uint8),
            np.zeros(full, np.float32) if with_photometry else None,
            np.zeros(full, np.float32) if with_photometry else None,
        )

    @property
    def shape(self) -> tuple[int, int]:
        return self.x.shape[1:]

    @property
    def valid(self) -> np.ndarray:
        """(K, H, W) bool."""
        return self.reasons == 0

    def set_position(self, k: int, x: np.ndarray, y: np.ndarray, reasons: np.ndarray,
                     modulation=None, background=None) -> None:
        """Store position ``k``: ``x, y`` (H, W) float64 mm; invalid where ``reasons != 0``."""
        valid = reasons == 0
        new_ref = valid & np.isnan(self.x_ref)
        self.x_ref[new_ref] = x[new_ref]
        self.y_ref[new_ref] = y[new_ref]
        self.x[k] = np.where(valid, x - self.x_ref, np.nan)
        self.y[k] = np.where(valid, y - self.y_ref, np.nan)
        self.reasons[k] = reasons
        if self.modulation is not None and modulation is not None:
            self.modulation[k] = modulation
        if self.background is not None and background is not None:
            self.background[k] = background

    def plane(self, name: str, k: int) -> np.ndarray:
        """Position ``k``'s ``(H, W)`` map of ``name`` (``"x"``, ``"reasons"``, ...), as a new array.

        A spilled stack's map is read with a file read (:func:`ptpcore.store.read_block`):
        indexing its ``numpy.memmap`` would map the pages into the process, where they stay
        (and count in its resident memory) until the stack is gone.
        """
        from ptpcore.store import read_block

        h, w = self.shape
        return read_block(getattr(self, name), 0, h * w, [k]).reshape(h, w)

    def absolute(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Absolute X, Y (H, W) float64 mm at position ``k`` (NaN where invalid)."""
        return self.x_ref + self.plane("x", k), self.y_ref + self.plane("y", k)

    def position(self, k: int) -> "SampleStack":
        """The stack of position ``k`` alone, its maps read into memory (:meth:`plane`: file reads of a
        spilled stack, whose memory maps would leave the pages resident: the model choice's noise
        sums, through :meth:`subset`, left 800 MB of them at 5 MP x 21)."""
        def one(name):
            return None if getattr(self, name) is None else self.plane(name, k)[None]

        return SampleStack(self.z[[k]], one("x"), one("y"), self.x_ref, self.y_ref, one("reasons"),
                           one("modulation"), one("background"), self.noise, self.corrections, self.lcd_shift)

    def subset(self, positions) -> "SampleStack":
        """The stack restricted to some positions (views where possible)."""
        idx = np.asarray(positions)
        return SampleStack(self.z[idx], self.x[idx], self.y[idx], self.x_ref, self.y_ref,
                           self.reasons[idx],
                           None if self.modulation is None else self.modulation[idx],
                           None if self.background is None else self.background[idx], self.noise,
                           self.corrections, self.lcd_shift)
