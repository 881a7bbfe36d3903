"""The LCD: what shows the fringe patterns to the camera.

A :class:`Display` shows one ``(height, width)`` uint8 image at a time, pixel
for pixel, and :meth:`~Display.settle` waits until the panel has settled
(liquid-crystal response, backlight, the next camera exposure starting after
the change). The real screen is a Qt window and lives in the GUI
(``ptp_studio.lcd_window``): the engine never imports Qt.
"""

from __future__ import annotations

import time
from typing import Protocol, runtime_checkable

import numpy as np

from ptpcore.errors import DeviceError

__all__ = ["Display", "SimulatedDisplay", "check_lcd_image"]


@runtime_checkable
class Display(Protocol):
    """An LCD that shows images pixel for pixel.

    Attributes
    ----------
    width, height : int
        Pixels of the panel.
    settle_s : float
        Seconds :meth:`settle` waits after a change.
    """

    width: int
    height: int
    settle_s: float

    def open(self) -> None:
        """Make the display ready (show the window, ...)."""

    def show(self, image: np.ndarray) -> None:
        """Show ``image`` ((height, width) uint8, grey levels); returns once it is on screen."""

    def settle(self) -> None:
        """Wait until what :meth:`show` put up is stable enough to photograph."""

    def close(self) -> None:
        """Release the display."""


def check_lcd_image(image, width: int, height: int, who: str = "display") -> np.ndarray:
    """Refuse anything but a ``(height, width)`` uint8 image (the caller's bug, said plainly)."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.shape != (height, width):
        raise ValueError(f"{who}: expected a ({height}, {width}) uint8 image, got {image.dtype} {image.shape}")
    return image


class SimulatedDisplay:
    """A display that only records what it was asked to show.

    The simulated camera (:class:`ptpcore.capture.devices.camera.SimulatedCamera`)
    photographs :attr:`image`, so a capture that grabs before showing the
    right pattern gets the wrong frame, as it would on a real rig.

    Parameters
    ----------
    width, height : int
        Panel pixels (the rig's LCD).
    settle_s : float
        Seconds :meth:`settle` sleeps (0 in tests).

    Attributes
    ----------
    image : (height, width) uint8 or None
        What is on screen now (the array passed to :meth:`show`, not a copy:
        callers must not modify it afterwards).
    shown : int
        How many images were shown.
    """

    def __init__(self, width: int, height: int, settle_s: float = 0.0):
        self.width = int(width)
        self.height = int(height)
        self.settle_s = float(settle_s)
        self.image: np.ndarray | None = None
        self.shown = 0
        self.is_open = False

    def describe(self) -> str:
        return f"simulated display {self.width}x{self.height}"

    def open(self) -> None:
        self.is_open = True

    def show(self, image: np.ndarray) -> None:
        if not self.is_open:
            raise DeviceError(f"{self.describe()}: show() before open()")
        self.image = check_lcd_image(image, self.width, self.height, self.describe())
        self.shown += 1

    def settle(self) -> None:
        if self.settle_s > 0:
            time.sleep(self.settle_s)

    def close(self) -> None:
        self.is_open = False
