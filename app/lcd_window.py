"""The LCD: a frameless full-screen window showing the fringe patterns pixel for pixel.

:class:`LcdWindow` covers one screen (:func:`list_screens` names them with
their resolutions) and draws a ``(height, width)`` uint8 image with one image
pixel per *device* pixel: the image is tagged with the screen's device pixel
ratio, so Qt's high-DPI scaling never resamples a fringe. An image larger
than the screen is cut at the right and bottom, a smaller one sits in the
top-left corner on black; :func:`screen_mismatch` says so before a capture.

:class:`QtDisplay` is the engine's :class:`ptpcore.capture.devices.display.Display`
on top of it, callable from the capture's worker thread: ``show`` hands the
image to the GUI thread and returns once it was painted; ``settle`` then waits
the settle delay on the worker thread.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
from PySide6.QtCore import QObject, QPointF, Qt, QThread, Signal, Slot
from PySide6.QtGui import QColor, QGuiApplication, QImage, QPainter
from PySide6.QtWidgets import QWidget

from ptpcore.capture import check_lcd_image
from ptpcore.errors import Cancelled, DeviceError

__all__ = ["ScreenInfo", "list_screens", "screen_mismatch", "LcdWindow", "QtDisplay"]


@dataclass(frozen=True)
class ScreenInfo:
    """One screen: its index in ``QGuiApplication.screens()``, name and size in device pixels."""

    index: int
    name: str
    width: int
    height: int
    device_pixel_ratio: float

    def label(self) -> str:
        dpr = "" if self.device_pixel_ratio == 1 else f", scale {self.device_pixel_ratio:g}"
        return f"Screen {self.index + 1}: {self.name or 'unnamed'} {self.width}x{self.height}{dpr}"


def _device_size(screen) -> tuple[int, int]:
    dpr = screen.devicePixelRatio()
    g = screen.geometry()
    return int(round(g.width() * dpr)), int(round(g.height() * dpr))


def list_screens() -> list[ScreenInfo]:
    """Every screen Qt knows, with its resolution in device pixels."""
    out = []
    for i, screen in enumerate(QGuiApplication.screens()):
        w, h = _device_size(screen)
        out.append(ScreenInfo(i, screen.name(), w, h, float(screen.devicePixelRatio())))
    return out


def screen_mismatch(screen: ScreenInfo, lcd) -> str | None:
    """A warning when the screen is not the rig's LCD size (``None`` when it is)."""
    if (screen.width, screen.height) == (lcd.width, lcd.height):
        return None
    return (f"{screen.label()} is not the rig's LCD ({lcd.width}x{lcd.height} px in rig.toml): patterns are"
            " drawn pixel for pixel from the top-left corner, so LCD coordinates would not match the panel."
            " Choose the LCD's screen or correct the rig.")


class LcdWindow(QWidget):
    """A frameless full-screen window that shows one grey image at 1:1 device pixels.

    Parameters
    ----------
    screen_index : int
        Which of ``QGuiApplication.screens()`` to cover.

    Signals
    -------
    painted(int)
        After an image was painted (its serial number).
    """

    painted = Signal(int)

    def __init__(self, screen_index: int = 0, parent: QWidget | None = None):
        super().__init__(parent, Qt.Window | Qt.FramelessWindowHint | Qt.WindowStaysOnTopHint)
        self.setWindowTitle("PTP Studio — LCD")
        self.setAttribute(Qt.WA_OpaquePaintEvent, True)
        self.setCursor(Qt.BlankCursor)
        screens = QGuiApplication.screens()
        if not 0 <= screen_index < len(screens):
            raise DeviceError(f"LCD window: there is no screen {screen_index + 1} (found {len(screens)})")
        self.screen_index = screen_index
        self.qscreen = screens[screen_index]
        self.image: np.ndarray | None = None
        self._qimage: QImage | None = None
        self.serial = 0

    def open(self) -> None:
        """Cover the chosen screen."""
        self.setScreen(self.qscreen)
        self.setGeometry(self.qscreen.geometry())
        self.showFullScreen()

    def set_image(self, image: np.ndarray) -> int:
        """Show ``image`` ((h, w) uint8); returns its serial number (``painted`` carries it)."""
        image = np.ascontiguousarray(image, dtype=np.uint8)
        h, w = image.shape
        qimg = QImage(image.data, w, h, image.strides[0], QImage.Format_Grayscale8).copy()
        qimg.setDevicePixelRatio(self.devicePixelRatioF())
        self.image = image
        self._qimage = qimg
        self.serial += 1
        self.repaint()
        return self.serial

    def paintEvent(self, _event) -> None:  # noqa: N802 - Qt API
        p = QPainter(self)
        p.fillRect(self.rect(), QColor(0, 0, 0))
        if self._qimage is not None:
            # Tagged with the device pixel ratio, the image covers w/dpr logical units = w device pixels.
            p.drawImage(QPointF(0.0, 0.0), self._qimage)
        p.end()
        self.painted.emit(self.serial)


class _Bridge(QObject):
    """Lives on the GUI thread; the worker reaches the window through its queued signals."""

    show_image = Signal(object, object)  # image, threading.Event
    open_window = Signal(object)
    close_window = Signal(object)

    def __init__(self, window: LcdWindow):
        super().__init__()
        self.window = window
        self.show_image.connect(self._show, Qt.QueuedConnection)
        self.open_window.connect(self._open, Qt.QueuedConnection)
        self.close_window.connect(self._close, Qt.QueuedConnection)

    @Slot(object, object)
    def _show(self, image, done: threading.Event) -> None:
        try:
            self.window.set_image(image)
        finally:
            done.set()

    @Slot(object)
    def _open(self, done: threading.Event) -> None:
        try:
            self.window.open()
        finally:
            done.set()

    @Slot(object)
    def _close(self, done: threading.Event) -> None:
        try:
            self.window.close()
        finally:
            done.set()


class QtDisplay:
    """The LCD window as a :class:`ptpcore.capture.devices.display.Display`, usable from a worker thread.

    Create it on the GUI thread.

    Parameters
    ----------
    screen_index : int
    width, height : int
        The rig's LCD size: the size of every image :meth:`show` accepts.
    settle_s : float
        Wait after each change (liquid-crystal response plus one camera frame).
    timeout_s : float
        How long the GUI thread may take to paint an image.
    """

    def __init__(self, screen_index: int, width: int, height: int, settle_s: float = 0.1, timeout_s: float = 10.0):
        self.window = LcdWindow(screen_index)
        self._bridge = _Bridge(self.window)
        self.width = int(width)
        self.height = int(height)
        self.settle_s = float(settle_s)
        self.timeout_s = float(timeout_s)
        self.image: np.ndarray | None = None
        self.shown = 0
        self.cancel_event: threading.Event | None = None  # set by the job: a wait for the GUI stops on cancel

    def describe(self) -> str:
        s = self.window.qscreen
        w, h = _device_size(s)
        return f"LCD window on screen {self.window.screen_index + 1} ({s.name() or 'unnamed'} {w}x{h})"

    def _on_gui_thread(self) -> bool:
        return QThread.currentThread() is self._bridge.thread()

    def _run(self, what: str, *args) -> None:
        """Have the GUI thread do ``what`` (a bridge signal) and wait until it has."""
        done = threading.Event()
        if self._on_gui_thread():
            getattr(self._bridge, "_" + what.split("_")[0])(*args, done)
            return
        getattr(self._bridge, what).emit(*args, done)
        deadline = time.monotonic() + self.timeout_s
        while not done.wait(0.05):
            if self.cancel_event is not None and self.cancel_event.is_set():
                raise Cancelled("cancelled")
            if time.monotonic() > deadline:
                raise DeviceError(f"{self.describe()}: the GUI did not {what.replace('_', ' ')} within"
                                  f" {self.timeout_s:g} s")

    def open(self) -> None:
        self._run("open_window")

    def show(self, image) -> None:
        image = check_lcd_image(image, self.width, self.height, self.describe())
        self._run("show_image", image)
        self.image = image
        self.shown += 1

    def settle(self) -> None:
        if self.settle_s > 0:
            time.sleep(self.settle_s)

    def close(self) -> None:
        self._run("close_window")
