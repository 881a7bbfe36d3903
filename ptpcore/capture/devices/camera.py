"""Cameras: open, set the exposure, grab one frame as an array, close.

Three implementations behind one :class:`Camera` protocol:

- :class:`SimulatedCamera` photographs a simulated display on a simulated
  stage with the virtual rig (:class:`ptpcore.simulate.VirtualRig`);
- :class:`OpenCVCamera` reads any ``cv2.VideoCapture`` source (USB/UVC
  cameras, video files, image sequences, stream URLs);
- :class:`HarvestersCamera` drives GenICam cameras (GigE Vision, USB3 Vision)
  through a GenTL producer (``.cti`` file) with the optional ``harvesters``
  package (``pip install "ptp-studio[genicam]"``).

A frame is a ``(H, W)`` uint8 or uint16 array of grey levels (not scaled).
:meth:`Camera.grab` returning ``None`` or raising :class:`FrameError` means the
frame was dropped; the capture asks again.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, Mapping, Protocol, runtime_checkable

import numpy as np

from ptpcore.errors import DeviceError

__all__ = ["Camera", "FrameError", "SimulatedCamera", "OpenCVCamera", "HarvestersCamera"]


class FrameError(DeviceError):
    """One frame could not be grabbed (dropped, incomplete, timed out)."""


@runtime_checkable
class Camera(Protocol):
    """A camera that grabs single grey frames on request."""

    def open(self) -> None:
        """Connect and start acquiring. Raises DeviceError when the camera is not there."""

    def set_exposure(self, us: float) -> None:
        """Exposure time in microseconds. Raises DeviceError when the camera refuses it."""

    def grab(self) -> np.ndarray | None:
        """One frame taken after the call, ``(H, W)`` uint8 or uint16; ``None`` if dropped."""

    def close(self) -> None:
        """Stop and release the camera (safe to call twice)."""


# --------------------------------------------------------------------------- simulated

class SimulatedCamera:
    """A camera that photographs a simulated display with the virtual rig.

    Each :meth:`grab` renders what :attr:`display` shows now with the LCD where
    :attr:`stage` is now. When the image on the display is exactly one of the
    rig's fringe patterns for the stage position it is at, the frame is
    :meth:`VirtualRig.render` of that pattern, bit for bit what
    ``ptp simulate`` writes for it (same noise stream). Anything else (an
    exposure test image, a pattern of another position, a stage between
    positions) is rendered as displayed, at the height the stage reports
    (:meth:`VirtualRig.render_image`), so a capture that shows, moves and
    grabs out of order gets visibly wrong frames.

    Parameters
    ----------
    virtual_rig : VirtualRig
    display : object with ``image`` ((lcd.height, lcd.width) uint8 or None)
        Typically a :class:`~ptpcore.capture.devices.display.SimulatedDisplay`.
    stage : Stage
        Its ``position()`` says where the LCD is.
    faults : mapping or callable, optional
        Injected failures by grab number (0-based, counting every call):
        ``{3: "none"}`` returns ``None`` on the 4th grab, ``"raise"`` raises
        :class:`FrameError`, ``"error"`` raises :class:`DeviceError` (a camera
        gone); a callable ``faults(n) -> str | None`` decides per grab.

    Notes
    -----
    The exposure scales the simulator's ``exposure`` setting:
    :attr:`NOMINAL_EXPOSURE_US` gives the preset's own exposure (and its
    frames bit for bit).
    """

    NOMINAL_EXPOSURE_US = 10_000.0

    def __init__(self, virtual_rig, display, stage, *, faults: Mapping[int, str] | Callable | None = None):
        self._base = virtual_rig
        self.vr = virtual_rig
        self.rig = virtual_rig.rig
        self.display = display
        self.stage = stage
        self.exposure_us = self.NOMINAL_EXPOSURE_US
        self.faults = faults
        self.grabs = 0
        self.is_open = False
        self._patterns: tuple[int, dict] | None = None
        self._other = 0

    def describe(self) -> str:
        s = self._base.settings
        c = self.rig.camera
        return f"simulated camera {c.width}x{c.height} {c.bit_depth}-bit ('{s.name}' rig, seed {self._base.seed})"

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def set_exposure(self, us: float) -> None:
        us = float(us)
        if not np.isfinite(us) or us <= 0:
            raise DeviceError(f"{self.describe()}: exposure must be a positive time in µs, got {us}")
        from ptpcore.simulate.virtual_rig import VirtualRig

        self.exposure_us = us
        if us == self.NOMINAL_EXPOSURE_US:
            self.vr = self._base
        else:
            b = self._base
            settings = replace(b.settings, exposure=b.settings.exposure * us / self.NOMINAL_EXPOSURE_US)
            self.vr = VirtualRig(b.rig, settings, b.seed)
        self._patterns = None

    def _fault(self, n: int) -> str | None:
        if self.faults is None:
            return None
        if callable(self.faults):
            return self.faults(n)
        return self.faults.get(n)

    def grab(self) -> np.ndarray | None:
        if not self.is_open:
            raise DeviceError(f"{self.describe()}: grab() before open()")
        n = self.grabs
        self.grabs += 1
        fault = self._fault(n)
        if fault == "none":
            return None
        if fault == "raise":
            raise FrameError(f"{self.describe()}: frame {n} dropped (injected fault)")
        if fault == "error":
            raise DeviceError(f"{self.describe()}: camera disconnected (injected fault)")
        rig = self.rig
        image = getattr(self.display, "image", None)
        if image is None:  # nothing shown yet: a black screen
            image = np.zeros((rig.lcd.height, rig.lcd.width), np.uint8)
        z = float(self.stage.position())
        k = self._position_index(z)
        if k is not None:
            spec = self._identify(image, k)
            if spec is not None and spec[0] == "gray":
                return self.vr.render_gray(k, *spec[1:])
            if spec is not None and spec[0] == "ref":
                return self.vr.render_reference(k, spec[1])
            if spec is not None:
                d, _j, t, s, big_n = spec
                return self.vr.render(k, d, t, s, big_n)
            profile = self._profile(image)
            if profile is not None:  # another 1-D pattern (e.g. through a measured display response)
                self._other += 1
                return self.vr.render_profile(k, profile[0], profile[1], (4, self._other))
        z_true = z if k is None else float(self.vr.true_height(k))
        self._other += 1
        return self.vr.render_image(image, z_true, noise_key=(3, self._other))

    def position_hint(self, k: int) -> None:
        """The capture is at position ``k`` now (:func:`ptpcore.capture.capture` says so): a repeat of a
        sweep position (``[stage] repeat_z_mm``) is told from it by its index, not its reading."""
        self._hint = int(k)

    def _position_index(self, z: float) -> int | None:
        """The rig position whose stage reading is ``z`` (the stage is exactly there), if any."""
        hint = getattr(self, "_hint", None)
        readings = self.vr.readings
        if hint is not None and 0 <= hint < readings.size and abs(readings[hint] - z) <= 1e-9 * max(1.0, abs(z)):
            return hint
        zs = np.asarray(self.rig.stage.z_mm)
        i = int(np.argmin(np.abs(zs - z)))
        return i if abs(zs[i] - z) <= 1e-9 * max(1.0, abs(z)) else None

    def _profile(self, image: np.ndarray):
        """``(direction, levels)`` of an image that varies along one LCD axis only (not uniform), else None."""
        image = np.asarray(image)
        if not self.vr.settings.pixelated or self.vr.settings.dust or image.dtype != np.uint8 or image.ndim != 2:
            return None
        if (image == image[:1]).all() and not (image == image[0, 0]).all():
            return "x", np.ascontiguousarray(image[0])
        if (image == image[:, :1]).all() and not (image == image[0, 0]).all():
            return "y", np.ascontiguousarray(image[:, 0])
        return None

    def _identify(self, image: np.ndarray, k: int):
        """The rig's fringe spec ``(dir, level, period, step, N)`` shown in ``image`` at position ``k``;
        ``("gray", dir, bit, inverse)`` for a Gray-code frame, ``("ref", "white" | "black")`` for a
        reference frame."""
        from ptpcore.decode.patterns import fringe_profile, gray_profile, reference_profile

        if self._patterns is None or self._patterns[0] != k:
            rig = self.rig
            table = {}
            for spec in rig.fringes.frames():
                d, _j, t, s, big_n = spec
                prof = fringe_profile(rig.lcd, rig.fringes, d, t, s, big_n, float(self.vr.readings[k]), rig.display)
                table.setdefault((d, prof.tobytes()), spec)
            for d, b, inv in rig.fringes.gray_frames():
                prof = gray_profile(rig.lcd, rig.fringes, d, b, inv, rig.stage.z_mm[k])
                table.setdefault((d, prof.tobytes()), ("gray", d, b, inv))
            if rig.has_references:
                for which in ("white", "black"):
                    table.setdefault(("x", reference_profile(rig.lcd, rig.fringes, which).tobytes()), ("ref", which))
            self._patterns = (k, table)
        table = self._patterns[1]
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim != 2:
            return None
        spec = table.get(("x", image[0].tobytes()))
        if spec is not None and (image.strides[0] == 0 or bool((image == image[:1]).all())):
            return spec
        spec = table.get(("y", image[:, 0].tobytes()))
        if spec is not None and (image.strides[1] == 0 or bool((image == image[:, :1]).all())):
            return spec
        return None


# --------------------------------------------------------------------------- OpenCV

class OpenCVCamera:
    """Any source ``cv2.VideoCapture`` opens: a camera index, a video file, an image sequence, a URL.

    Parameters
    ----------
    source : int or str
        Camera index (``0``), file, ``"frames/img_%03d.png"`` sequence or stream URL.
    width, height : int, optional
        Frame size to ask the driver for.
    api : int
        OpenCV backend (``cv2.CAP_ANY``, ``cv2.CAP_V4L2``, ``cv2.CAP_DSHOW``, ...).
    exposure_units_per_us : float
        ``CAP_PROP_EXPOSURE`` units per µs. Backend specific: V4L2 counts
        100 µs (``0.01``, the default); DirectShow takes log2 seconds, for
        which pass ``0`` and set :attr:`exposure_value` yourself.
    warmup : int
        Frames read and discarded after opening and after every exposure
        change (drivers deliver a few stale frames).

    Notes
    -----
    Colour frames are converted to grey. Most UVC cameras deliver 8 bits.
    ``grab`` reads the next frame, so a frame may have started before the
    display changed: let the display's settle time cover one frame period.
    """

    def __init__(self, source: int | str = 0, width: int | None = None, height: int | None = None,
                 api: int | None = None, exposure_units_per_us: float = 0.01, warmup: int = 2):
        self.source = source
        self.width = width
        self.height = height
        self.api = api
        self.exposure_units_per_us = float(exposure_units_per_us)
        self.warmup = int(warmup)
        self._cap = None

    def describe(self) -> str:
        return f"OpenCV camera {self.source!r}"

    def open(self) -> None:
        import cv2

        cap = cv2.VideoCapture(self.source, cv2.CAP_ANY if self.api is None else self.api)
        if not cap.isOpened():
            cap.release()
            raise DeviceError(f"{self.describe()}: cannot open (not connected, busy, or not a video source)")
        if self.width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        if self.height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        self._cap = cap
        self._discard(self.warmup)

    def _discard(self, n: int) -> None:
        for _ in range(n):
            self._cap.grab()

    def set_exposure(self, us: float) -> None:
        import cv2

        if self._cap is None:
            raise DeviceError(f"{self.describe()}: set_exposure() before open()")
        if self.exposure_units_per_us <= 0:
            return
        self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: manual; other backends ignore it
        if not self._cap.set(cv2.CAP_PROP_EXPOSURE, float(us) * self.exposure_units_per_us):
            raise DeviceError(f"{self.describe()}: the driver refused exposure {us:g} µs")
        self._discard(self.warmup)

    def grab(self) -> np.ndarray | None:
        import cv2

        if self._cap is None:
            raise DeviceError(f"{self.describe()}: grab() before open()")
        try:
            ok, frame = self._cap.read()
        except cv2.error as exc:
            raise FrameError(f"{self.describe()}: {exc}") from None
        if not ok or frame is None:
            return None
        if frame.ndim == 3:
            frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2GRAY if frame.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        return np.ascontiguousarray(frame)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


# --------------------------------------------------------------------------- GenICam

class HarvestersCamera:
    """A GenICam camera through a GenTL producer, with ``harvesters`` (optional extra ``genicam``).

    Parameters
    ----------
    cti : str
        Path of the GenTL producer (``.cti``) of the camera's vendor SDK (or a
        generic one).
    device : int or dict
        Which camera: an index into the producer's device list, or a dict of
        device-info fields (``{"serial_number": "21345678"}``).
    timeout_s : float
        How long one frame may take before it counts as dropped.
    pixel_format : str, optional
        ``"Mono8"``, ``"Mono12"``, ``"Mono16"``...; default: the camera's setting.

    Notes
    -----
    Uses the SFNC features ``ExposureAuto`` and ``ExposureTime`` (µs). Only
    monochrome pixel formats are accepted. The import of ``harvesters``
    happens in :meth:`open`, so the engine works without it.
    """

    def __init__(self, cti: str, device: int | dict = 0, timeout_s: float = 5.0, pixel_format: str | None = None):
        self.cti = str(cti)
        self.device = device
        self.timeout_s = float(timeout_s)
        self.pixel_format = pixel_format
        self._h = None
        self._ia = None

    def describe(self) -> str:
        return f"GenICam camera {self.device!r} via {self.cti}"

    def open(self) -> None:
        try:
            from harvesters.core import Harvester
        except ImportError:
            raise DeviceError("GenICam cameras need the optional 'harvesters' package:"
                              " pip install \"ptp-studio[genicam]\"") from None
        h = Harvester()
        try:
            h.add_file(self.cti, check_existence=True)
            h.update()
            if not h.device_info_list:
                raise DeviceError(f"{self.describe()}: the producer lists no camera")
            ia = h.create(self.device)
            nm = ia.remote_device.node_map
            if self.pixel_format:
                nm.PixelFormat.value = self.pixel_format
            ia.start()
        except DeviceError:
            h.reset()
            raise
        except Exception as exc:  # noqa: BLE001 - GenTL errors come in many types
            h.reset()
            raise DeviceError(f"{self.describe()}: cannot open ({exc})") from None
        self._h, self._ia = h, ia

    def set_exposure(self, us: float) -> None:
        if self._ia is None:
            raise DeviceError(f"{self.describe()}: set_exposure() before open()")
        nm = self._ia.remote_device.node_map
        try:
            if hasattr(nm, "ExposureAuto"):
                nm.ExposureAuto.value = "Off"
            nm.ExposureTime.value = float(us)
        except Exception as exc:  # noqa: BLE001
            raise DeviceError(f"{self.describe()}: cannot set exposure {us:g} µs ({exc})") from None

    def grab(self) -> np.ndarray | None:
        if self._ia is None:
            raise DeviceError(f"{self.describe()}: grab() before open()")
        try:
            buffer = self._ia.try_fetch(timeout=self.timeout_s)
        except Exception as exc:  # noqa: BLE001
            raise FrameError(f"{self.describe()}: {exc}") from None
        if buffer is None:
            return None
        with buffer:
            comp = buffer.payload.components[0]
            if getattr(comp, "num_components_per_pixel", 1) != 1:
                raise DeviceError(f"{self.describe()}: pixel format {comp.data_format} is not monochrome;"
                                  " choose a Mono format")
            return np.array(comp.data, copy=True).reshape(comp.height, comp.width)

    def close(self) -> None:
        if self._ia is not None:
            try:
                self._ia.stop()
                self._ia.destroy()
            finally:
                self._ia = None
        if self._h is not None:
            self._h.reset()
            self._h = None
