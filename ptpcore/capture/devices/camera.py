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

__all__ = ["Camera", "FrameError", "SimulatedCamera", "OpenCVCamera", "HarvestersCamera", "PylonCamera",
           "camera_from_config", "grey_from_colour", "MONO_FORMATS", "COLOUR_FORMATS"]


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


# --------------------------------------------------------------------------- GenICam pixel formats

MONO_FORMATS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono14": 14, "Mono16": 16}
"""GenICam (PFNC) monochrome pixel formats taken as they are, with their bit depth (unpacked, LSB-aligned)."""

COLOUR_FORMATS = {"RGB8": "RGB", "RGBa8": "RGB", "BGR8": "BGR", "BGRa8": "BGR",
                  "RGB8Packed": "RGB", "BGR8Packed": "BGR", "BGRA8Packed": "BGR"}
"""8-bit colour pixel formats (PFNC names and Basler's older ones) and their channel order: converted to grey."""


def grey_from_colour(image: np.ndarray, order: str, max_level: int = 255) -> np.ndarray:
    """A colour frame as grey levels by the dataset reader's rule (docs/formats.md).

    Parameters
    ----------
    image : (H, W, 3 or 4) uint8 or uint16
        Colour frame; a fourth (alpha) channel is ignored.
    order : {"RGB", "BGR"}
        Channel order of ``image``.
    max_level : int
        Full scale (255 for 8-bit channels).

    Returns
    -------
    (H, W) array of ``image``'s dtype
        ITU-R BT.601 luminance (0.299 R + 0.587 G + 0.114 B) computed in
        floating point, rounded to the nearest level; a pixel with any channel
        at ``max_level`` is ``max_level`` and one with any channel at 0 is 0,
        so the decoder's clipping flags see per-channel clipping.
    """
    from ptpcore.io.dataset import luminance

    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"a colour frame is (H, W, 3 or 4), got shape {image.shape}")
    bgr = image[:, :, 2::-1] if order == "RGB" else image[:, :, :3]
    lum = luminance(bgr, max_level)
    return np.clip(np.rint(lum), 0, max_level).astype(image.dtype)


def _frame_bits(fmt: str) -> int:
    return MONO_FORMATS.get(fmt, 8)


def _unsupported_format(what: str, fmt: str, offered) -> DeviceError:
    usable = [f for f in offered if f in MONO_FORMATS or f in COLOUR_FORMATS]
    readable = ", ".join(usable) if usable else "none (it offers " + ", ".join(offered) + ")"
    return DeviceError(f"{what}: pixel format {fmt!r} is not one PTP Studio reads; set camera.pixel_format to"
                       f" one of the camera's that it reads: {readable}")


def _check_trigger(trigger: str) -> str:
    if trigger not in ("auto", "software", "off"):
        raise ValueError(f"trigger must be 'auto', 'software' or 'off', got {trigger!r}")
    return trigger


# --------------------------------------------------------------------------- GenICam (harvesters)

class HarvestersCamera:
    """A GenICam camera through a GenTL producer, with ``harvesters`` (optional extra ``genicam``).

    Parameters
    ----------
    cti : str
        Path of the GenTL producer (``.cti``) of the camera's vendor SDK (or a
        generic one; the ``genicam`` package ships a simulated one, ``viky.cti``).
    device : int, str or dict
        Which camera: an index into the producer's device list, a serial
        number (str), or a dict of device-info fields
        (``{"serial_number": "21345678"}``).
    timeout_s : float
        How long one frame may take before it counts as dropped.
    pixel_format : str, optional
        ``"Mono8"``, ``"Mono12"``, ``"Mono16"``, ``"RGB8"``...; default: the
        camera's setting.
    trigger : {"auto", "software", "off"}
        ``"auto"``: a software trigger (TriggerSelector FrameStart,
        TriggerSource Software) where the device has one, else free running;
        ``"software"``: the trigger or an error; ``"off"``: free running.
    features : mapping, optional
        Further GenICam features set in this order after opening
        (``{"AcquisitionFrameRate": 10.0, "Gain": 0.0}``).

    Notes
    -----
    Every :meth:`grab` returns a frame whose exposure started after the call:
    with the software trigger it is exposed on the call; free running, the
    frames queued before it and the first one after it (which may have started
    before) are discarded. Exposure goes through the SFNC ``ExposureAuto`` and
    ``ExposureTime`` (µs; ``ExposureTimeAbs`` on older cameras). Mono formats
    are returned as they are (uint8 for Mono8, else uint16, :attr:`bit_depth`
    bits); 8-bit colour formats are converted to grey by
    :func:`grey_from_colour`. The import of ``harvesters`` happens in
    :meth:`open`, so the engine works without it.
    """

    def __init__(self, cti: str, device: int | str | dict = 0, timeout_s: float = 5.0,
                 pixel_format: str | None = None, *, trigger: str = "auto", features: Mapping | None = None):
        self.cti = str(cti)
        self.device = device
        self.timeout_s = float(timeout_s)
        self.pixel_format = pixel_format or None
        self.trigger = _check_trigger(trigger)
        self.features = dict(features or {})
        self.bit_depth: int | None = None
        self.triggered = False
        self.model = self.serial = ""
        self._format = ""
        self._h = None
        self._ia = None

    def describe(self) -> str:
        if self.model:
            return f"GenICam camera {self.model} (serial {self.serial}) via {self.cti}"
        return f"GenICam camera {self.device!r} via {self.cti}"

    def _select(self, infos):
        """The search key for ``Harvester.create`` of :attr:`device`, or a DeviceError naming what is there."""
        listed = ", ".join(f"{i}: {d.model} (serial {d.serial_number})" for i, d in enumerate(infos))
        if isinstance(self.device, bool) or not isinstance(self.device, (int, str, dict)):
            raise DeviceError(f"{self.describe()}: device must be an index, a serial number or a dict of"
                              f" device-info fields, got {self.device!r}")
        if isinstance(self.device, int):
            if not 0 <= self.device < len(infos):
                raise DeviceError(f"{self.describe()}: no camera number {self.device} (the producer lists"
                                  f" {len(infos)}: {listed})")
            return self.device
        key = {"serial_number": self.device} if isinstance(self.device, str) else dict(self.device)
        for i, d in enumerate(infos):
            if all(str(getattr(d, k, None)) == str(v) for k, v in key.items()):
                return i
        raise DeviceError(f"{self.describe()}: no camera with {key} (the producer lists {listed})")

    def open(self) -> None:
        try:
            from harvesters.core import Harvester
        except ImportError:
            raise DeviceError("GenICam cameras need the optional 'harvesters' package:"
                              " pip install \"ptp-studio[genicam]\"") from None
        from pathlib import Path

        if not Path(self.cti).is_file():
            raise DeviceError(f"GenTL producer {self.cti}: no such file (the .cti file of the camera vendor's"
                              " SDK; set camera.cti)")
        self.close()
        h = self._h = Harvester()
        try:
            try:
                h.add_file(self.cti, check_existence=True)
                h.update()
            except Exception as exc:  # noqa: BLE001 - GenTL errors come in many types
                raise DeviceError(f"GenTL producer {self.cti}: cannot be loaded ({type(exc).__name__}: {exc})"
                                  ) from None
            infos = list(h.device_info_list)
            if not infos:  # harvesters only logs a producer it could not load: ask the loader why
                import ctypes

                try:
                    ctypes.CDLL(self.cti)
                except OSError as exc:
                    raise DeviceError(f"GenTL producer {self.cti}: cannot be loaded ({exc})") from None
                raise DeviceError(f"GenTL producer {self.cti}: lists no camera (connected and powered, not"
                                  " open in another program?)")
            index = self._select(infos)
            self.model, self.serial = str(infos[index].model), str(infos[index].serial_number)
            try:
                ia = h.create(index)
            except Exception as exc:  # noqa: BLE001
                raise DeviceError(f"{self.describe()}: cannot open ({type(exc).__name__}: {exc};"
                                  " open in another program?)") from None
            self._ia = ia
            self._configure(ia.remote_device.node_map)
            ia.start()
        except DeviceError:
            self.close()
            raise
        except Exception as exc:  # noqa: BLE001
            self.close()
            raise DeviceError(f"{self.describe()}: cannot open ({type(exc).__name__}: {exc})") from None

    def _configure(self, nm) -> None:
        offered = tuple(nm.PixelFormat.symbolics) if nm.has_node("PixelFormat") else ()
        if self.pixel_format:
            if self.pixel_format not in offered:
                raise DeviceError(f"{self.describe()}: pixel format {self.pixel_format!r} is not offered (it"
                                  f" offers {', '.join(offered)})")
            nm.PixelFormat.value = self.pixel_format
        fmt = str(nm.PixelFormat.value) if offered else "Mono8"
        if fmt not in MONO_FORMATS and fmt not in COLOUR_FORMATS:
            raise _unsupported_format(self.describe(), fmt, offered)
        self._format, self.bit_depth = fmt, _frame_bits(fmt)
        for name, value in self.features.items():
            _set_feature(self.describe(), nm, name, value)
        self.triggered = False
        can = (nm.has_node("TriggerMode") and nm.has_node("TriggerSoftware") and nm.has_node("TriggerSource")
               and "Software" in tuple(nm.TriggerSource.symbolics))
        if self.trigger == "software" and not can:
            raise DeviceError(f"{self.describe()}: has no software trigger (TriggerSoftware); use trigger"
                              " 'auto' or 'off' (free running, frames flushed)")
        if can and self.trigger != "off":
            if nm.has_node("TriggerSelector"):
                nm.TriggerSelector.value = "FrameStart"
            nm.TriggerMode.value = "On"
            nm.TriggerSource.value = "Software"
            self.triggered = True
        elif nm.has_node("TriggerMode"):
            if nm.has_node("TriggerSelector"):
                nm.TriggerSelector.value = "FrameStart"
            nm.TriggerMode.value = "Off"

    @property
    def node_map(self):
        """The open camera's GenICam node map (its features by name)."""
        if self._ia is None:
            raise DeviceError(f"{self.describe()}: not open")
        return self._ia.remote_device.node_map

    def set_exposure(self, us: float) -> None:
        if self._ia is None:
            raise DeviceError(f"{self.describe()}: set_exposure() before open()")
        _set_exposure(self.describe(), self.node_map, us)

    def _fetch(self, timeout: float):
        try:
            return self._ia.try_fetch(timeout=timeout)
        except Exception as exc:  # noqa: BLE001
            raise FrameError(f"{self.describe()}: {type(exc).__name__}: {exc}") from None

    def grab(self) -> np.ndarray | None:
        if self._ia is None:
            raise DeviceError(f"{self.describe()}: grab() before open()")
        while (old := self._fetch(0.001)) is not None:  # frames from before the call
            old.queue()
        if self.triggered:
            try:
                self.node_map.TriggerSoftware.execute()
            except Exception as exc:  # noqa: BLE001
                raise DeviceError(f"{self.describe()}: the software trigger failed ({exc})") from None
        else:  # free running: the frame under way may have started before the call
            first = self._fetch(self.timeout_s)
            if first is None:
                raise FrameError(f"{self.describe()}: no frame within {self.timeout_s:g} s (frame rate below"
                                 " 1/timeout_s, or the camera stopped)")
            first.queue()
        buffer = self._fetch(self.timeout_s)
        if buffer is None:
            raise FrameError(f"{self.describe()}: no frame within {self.timeout_s:g} s (frame rate below"
                             " 1/timeout_s, or the camera stopped)")
        with buffer:
            comp = buffer.payload.components[0]
            fmt = str(comp.data_format)
            h, w = int(comp.height), int(comp.width)
            data = np.array(comp.data, copy=True)
        if fmt in MONO_FORMATS:
            return data.reshape(h, w).astype(np.uint8 if MONO_FORMATS[fmt] == 8 else np.uint16, copy=False)
        if fmt in COLOUR_FORMATS and data.dtype == np.uint8:
            return grey_from_colour(data.reshape(h, w, -1), COLOUR_FORMATS[fmt])
        raise DeviceError(f"{self.describe()}: delivers pixel format {fmt!r}, which PTP Studio does not read;"
                          " set camera.pixel_format to a Mono or 8-bit RGB/BGR format")

    def close(self) -> None:
        ia, h = self._ia, self._h
        self._ia = self._h = None
        try:
            if ia is not None:
                try:
                    ia.stop()
                finally:
                    ia.destroy()
        finally:
            if h is not None:
                h.reset()


def _set_feature(what: str, nm, name: str, value) -> None:
    """Set one GenICam feature (``nm.<name>.value``, or execute a command for ``value=None``)."""
    try:
        node = getattr(nm, name)
    except Exception:  # noqa: BLE001
        node = None
    if node is None:
        raise DeviceError(f"{what}: has no feature {name!r}")
    try:
        if value is None:
            node.execute()
        else:
            node.value = value
    except Exception as exc:  # noqa: BLE001
        raise DeviceError(f"{what}: cannot set {name} = {value!r} ({type(exc).__name__}: {exc})") from None


def _set_exposure(what: str, nm, us: float) -> None:
    """Manual exposure of ``us`` µs through SFNC ``ExposureAuto``/``ExposureTime`` (or ``ExposureTimeAbs``)."""
    us = float(us)
    if not np.isfinite(us) or us <= 0:
        raise DeviceError(f"{what}: exposure must be a positive time in µs, got {us}")
    has = nm.has_node if hasattr(nm, "has_node") else lambda n: hasattr(nm, n)
    name = next((n for n in ("ExposureTime", "ExposureTimeAbs") if has(n)), None)
    if name is None:
        raise DeviceError(f"{what}: this device has no exposure control (no ExposureTime feature); set its"
                          " exposure with the vendor's tool and leave camera.exposure_us unset")
    node = getattr(nm, name)
    try:
        if has("ExposureAuto"):
            nm.ExposureAuto.value = "Off"
        lo, hi = float(node.min), float(node.max)
    except Exception as exc:  # noqa: BLE001
        raise DeviceError(f"{what}: cannot set exposure {us:g} µs ({type(exc).__name__}: {exc})") from None
    if not lo <= us <= hi:
        raise DeviceError(f"{what}: exposure {us:g} µs is outside the camera's range {lo:g} … {hi:g} µs")
    try:
        node.value = us
    except Exception as exc:  # noqa: BLE001
        raise DeviceError(f"{what}: cannot set exposure {us:g} µs ({type(exc).__name__}: {exc})") from None


# --------------------------------------------------------------------------- Basler pylon

class PylonCamera:
    """A Basler camera through Basler's own SDK, ``pypylon`` (optional extra ``pylon``).

    Parameters
    ----------
    device : int or str
        An index into the cameras pylon finds, or a serial number (str).
    timeout_s : float
        How long one frame may take before it counts as dropped.
    pixel_format : str, optional
        ``"Mono8"``, ``"Mono12"``, ``"Mono16"``, ``"RGB8Packed"``...; default:
        the camera's setting.
    trigger : {"auto", "software", "off"}
        As :class:`HarvestersCamera`: the software trigger (TriggerSelector
        FrameStart, TriggerSource Software) where the camera has one.
    features : mapping, optional
        Further features set in this order after opening, e.g.
        ``{"Width": 160, "Height": 120}`` or, on the emulation,
        ``{"ImageFileMode": "On", "ImageFilename": "frames/"}``.

    Notes
    -----
    Without a camera, pylon's own emulation stands in when the environment
    variable ``PYLON_CAMEMU`` is set (``PYLON_CAMEMU=1``: one camera, model
    "Emulation", serial 0815-0000). Frames and exposure as
    :class:`HarvestersCamera`; ``pypylon`` is imported in :meth:`open`.
    """

    def __init__(self, device: int | str = 0, timeout_s: float = 5.0, pixel_format: str | None = None, *,
                 trigger: str = "auto", features: Mapping | None = None):
        self.device = device
        self.timeout_s = float(timeout_s)
        self.pixel_format = pixel_format or None
        self.trigger = _check_trigger(trigger)
        self.features = dict(features or {})
        self.bit_depth: int | None = None
        self.triggered = False
        self.model = self.serial = ""
        self._cam = None
        self._pylon = None

    def describe(self) -> str:
        if self.model:
            return f"Basler camera {self.model} (serial {self.serial})"
        return f"Basler camera {self.device!r}"

    def open(self) -> None:
        try:
            from pypylon import pylon
        except ImportError:
            raise DeviceError("Basler cameras need the optional 'pypylon' package:"
                              " pip install \"ptp-studio[pylon]\"") from None
        self.close()
        self._pylon = pylon
        infos = list(pylon.TlFactory.GetInstance().EnumerateDevices())
        if not infos:
            raise DeviceError(f"{self.describe()}: pylon finds no camera (connected and powered, not open in"
                              " pylon Viewer? To try without one, set PYLON_CAMEMU=1 for pylon's emulation)")
        listed = ", ".join(f"{i}: {d.GetModelName()} (serial {d.GetSerialNumber()})" for i, d in enumerate(infos))
        if isinstance(self.device, bool) or not isinstance(self.device, (int, str)):
            raise DeviceError(f"{self.describe()}: device must be an index or a serial number, got {self.device!r}")
        if isinstance(self.device, int):
            if not 0 <= self.device < len(infos):
                raise DeviceError(f"{self.describe()}: no camera number {self.device} (pylon finds {listed})")
            info = infos[self.device]
        else:
            info = next((d for d in infos if d.GetSerialNumber() == self.device), None)
            if info is None:
                raise DeviceError(f"{self.describe()}: no camera with serial number {self.device!r} (pylon"
                                  f" finds {listed})")
        self.model, self.serial = str(info.GetModelName()), str(info.GetSerialNumber())
        try:
            cam = pylon.InstantCamera(pylon.TlFactory.GetInstance().CreateDevice(info))
            cam.Open()
        except Exception as exc:  # noqa: BLE001 - pylon and GenICam exceptions
            raise DeviceError(f"{self.describe()}: cannot open ({type(exc).__name__}: {exc}; open in another"
                              " program?)") from None
        self._cam = cam
        try:
            self._configure(cam)
            cam.StartGrabbing(pylon.GrabStrategy_OneByOne)
        except DeviceError:
            self.close()
            raise
        except Exception as exc:  # noqa: BLE001
            self.close()
            raise DeviceError(f"{self.describe()}: cannot start ({type(exc).__name__}: {exc})") from None

    def _configure(self, cam) -> None:
        offered = tuple(cam.PixelFormat.Symbolics)
        if self.pixel_format:
            if self.pixel_format not in offered:
                raise DeviceError(f"{self.describe()}: pixel format {self.pixel_format!r} is not offered (it"
                                  f" offers {', '.join(offered)})")
            cam.PixelFormat.Value = self.pixel_format
        for name, value in self.features.items():
            _set_feature(self.describe(), _PylonNodes(cam), name, value)
        fmt = str(cam.PixelFormat.Value)
        if fmt not in MONO_FORMATS and fmt not in COLOUR_FORMATS:
            raise _unsupported_format(self.describe(), fmt, offered)
        self.bit_depth = _frame_bits(fmt)
        self.triggered = False
        nodes = _PylonNodes(cam)
        can = (nodes.has_node("TriggerMode") and nodes.has_node("TriggerSoftware")
               and "Software" in tuple(cam.TriggerSource.Symbolics))
        if self.trigger == "software" and not can:
            raise DeviceError(f"{self.describe()}: has no software trigger (TriggerSoftware); use trigger"
                              " 'auto' or 'off' (free running, frames flushed)")
        if nodes.has_node("TriggerSelector") and "FrameStart" in tuple(cam.TriggerSelector.Symbolics):
            cam.TriggerSelector.Value = "FrameStart"
        if can and self.trigger != "off":
            cam.TriggerMode.Value = "On"
            cam.TriggerSource.Value = "Software"
            self.triggered = True
        elif nodes.has_node("TriggerMode"):
            cam.TriggerMode.Value = "Off"

    @property
    def node_map(self):
        """The open camera's features by name (``node_map.ExposureTime.value``)."""
        if self._cam is None:
            raise DeviceError(f"{self.describe()}: not open")
        return _PylonNodes(self._cam)

    def set_exposure(self, us: float) -> None:
        if self._cam is None:
            raise DeviceError(f"{self.describe()}: set_exposure() before open()")
        _set_exposure(self.describe(), self.node_map, us)

    def _retrieve(self, timeout_s: float):
        """The next grab result (released by the caller), or None after ``timeout_s``."""
        pylon = self._pylon
        try:
            r = self._cam.RetrieveResult(max(0, int(round(timeout_s * 1000))), pylon.TimeoutHandling_Return)
        except Exception as exc:  # noqa: BLE001
            raise self._lost(exc) from None
        if r is None or not r.IsValid():
            return None
        return r

    def _lost(self, exc) -> DeviceError:
        cam = self._cam
        if cam is not None and cam.IsCameraDeviceRemoved():
            return DeviceError(f"{self.describe()}: camera disconnected")
        return FrameError(f"{self.describe()}: {type(exc).__name__}: {exc}")

    def grab(self) -> np.ndarray | None:
        if self._cam is None:
            raise DeviceError(f"{self.describe()}: grab() before open()")
        while (old := self._retrieve(0)) is not None:  # frames from before the call
            old.Release()
        late = FrameError(f"{self.describe()}: no frame within {self.timeout_s:g} s (frame rate below"
                          " 1/timeout_s, or the camera stopped)")
        if self.triggered:
            try:
                if not self._cam.WaitForFrameTriggerReady(int(self.timeout_s * 1000),
                                                          self._pylon.TimeoutHandling_Return):
                    raise late
                self._cam.ExecuteSoftwareTrigger()
            except FrameError:
                raise
            except Exception as exc:  # noqa: BLE001
                raise self._lost(exc) from None
        else:  # free running: the frame under way may have started before the call
            first = self._retrieve(self.timeout_s)
            if first is None:
                raise late
            first.Release()
        r = self._retrieve(self.timeout_s)
        if r is None:
            raise late
        try:
            if not r.GrabSucceeded():
                raise FrameError(f"{self.describe()}: frame incomplete ({r.GetErrorDescription()})")
            frame = np.array(r.GetArray(), copy=True)
        finally:
            r.Release()
        fmt = str(self._cam.PixelFormat.Value)
        if fmt in MONO_FORMATS:
            return frame.astype(np.uint8 if MONO_FORMATS[fmt] == 8 else np.uint16, copy=False)
        return grey_from_colour(frame, COLOUR_FORMATS[fmt])

    def close(self) -> None:
        cam, self._cam = self._cam, None
        if cam is not None:
            try:
                if cam.IsGrabbing():
                    cam.StopGrabbing()
            finally:
                cam.Close()


class _PylonNodes:
    """A pylon camera's features with the node-map interface of ``harvesters`` (``.value``, ``has_node``)."""

    def __init__(self, cam):
        self._cam = cam

    def has_node(self, name: str) -> bool:
        from pypylon import genicam

        try:
            return bool(genicam.IsAvailable(getattr(self._cam, name)))
        except Exception:  # noqa: BLE001
            return False

    def __getattr__(self, name: str):
        if not self.has_node(name):
            raise AttributeError(name)
        return _PylonNode(getattr(self._cam, name))


class _PylonNode:
    def __init__(self, node):
        self._node = node

    value = property(lambda self: self._node.Value, lambda self, v: setattr(self._node, "Value", v))
    min = property(lambda self: self._node.Min)
    max = property(lambda self: self._node.Max)

    def execute(self) -> None:
        self._node.Execute()


# --------------------------------------------------------------------------- from capture.toml

def camera_from_config(cfg, source: str | int | None = None, width: int | None = None,
                       height: int | None = None) -> Camera:
    """The real camera a ``[camera]`` table of ``capture.toml`` names (not yet open).

    Parameters
    ----------
    cfg : CameraConfig
        ``kind`` "opencv", "genicam" or "pylon" (the simulated camera needs a rig: see
        :func:`ptpcore.capture.devices.simulated_devices`).
    source : str or int, optional
        Overrides ``cfg.source`` (opencv) or ``cfg.cti`` (genicam).
    width, height : int, optional
        The frame size to ask an OpenCV source for.
    """
    from ptpcore.errors import ConfigError

    if cfg.kind == "opencv":
        src = cfg.source if source is None else source
        if isinstance(src, str) and src.strip().isdigit():
            src = int(src)
        return OpenCVCamera(src, width=cfg.width or width, height=cfg.height or height)
    device = cfg.serial_number or cfg.device
    if cfg.kind == "genicam":
        cti = str(source or cfg.cti)
        if not cti:
            raise ConfigError("the GenICam camera needs its GenTL producer: camera.cti = \"/path/producer.cti\"")
        return HarvestersCamera(cti, device, cfg.timeout_s, cfg.pixel_format or None)
    if cfg.kind == "pylon":
        return PylonCamera(device, cfg.timeout_s, cfg.pixel_format or None)
    raise ConfigError(f"camera kind {cfg.kind!r} is not a real camera (opencv, genicam, pylon)")
