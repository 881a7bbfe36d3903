"""The capture configuration file: which camera, stage and display, and how to talk to them.

``rig.toml`` describes the rig's geometry and patterns (FORMATS.md, fixed
schema); how to drive its hardware lives in a separate file, by convention
``capture.toml``::

    format = "ptp-capture-config/1"

    [camera]
    kind = "opencv"              # sim | opencv | genicam
    exposure_us = 8000.0         # optional
    source = 0                   # opencv: camera index, file, "img_%03d.png" or URL
    # cti = "/opt/vendor/lib/producer.cti"   # genicam: the GenTL producer
    # device = 0                             # genicam: index (or serial_number = "...")
    # pixel_format = "Mono12"

    [display]
    screen = 1                   # GUI: which screen shows the patterns (index)
    settle_ms = 150.0            # wait after each pattern change

    [stage]
    kind = "serial"              # sim | manual | serial

    [stage.serial]               # see ptpcore.capture.devices.stage.SerialProtocol
    port = "/dev/ttyUSB0"
    baudrate = 115200
    write_ending = "\\r"
    read_ending = "\\r\\n"
    move_command = "MA {z:.4f}"
    move_reply = "^OK$"
    position_command = "TP"
    position_reply = "^TP\\s*(?P<z>[-+0-9.]+)$"
    status_command = "MD?"
    idle_reply = "^1$"
    error_reply = "^ERR\\s*(?P<message>.*)$"

    [exposure_check]             # see ptpcore.capture.ExposureLimits
    max_saturated = 0.001

Unknown keys are errors naming the key, like in ``rig.toml``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

from ptpcore.errors import ConfigError
from ptpcore.rig.toml_fields import Section, read_text, short_repr, tname, toml_document
from ptpcore.capture.devices.stage import SerialProtocol

__all__ = ["CAPTURE_CONFIG_FORMAT", "CaptureConfig", "CameraConfig", "StageConfig", "DisplayConfig",
           "load_capture_config", "capture_config_from_toml", "serial_protocol_from_table"]

CAPTURE_CONFIG_FORMAT = "ptp-capture-config/1"
CAMERA_KINDS = ("sim", "opencv", "genicam", "pylon")
STAGE_KINDS = ("sim", "manual", "serial")


@dataclass(frozen=True)
class CameraConfig:
    kind: str = "sim"
    exposure_us: float | None = None
    source: int | str = 0
    width: int | None = None
    height: int | None = None
    cti: str = ""
    device: int | str = 0
    serial_number: str = ""
    pixel_format: str = ""
    timeout_s: float = 5.0


@dataclass(frozen=True)
class DisplayConfig:
    screen: int | None = None
    settle_ms: float = 0.0


@dataclass(frozen=True)
class StageConfig:
    kind: str = "sim"
    serial: SerialProtocol | None = None


@dataclass(frozen=True)
class CaptureConfig:
    """What a ``capture.toml`` says (every section optional)."""

    camera: CameraConfig = field(default_factory=CameraConfig)
    display: DisplayConfig = field(default_factory=DisplayConfig)
    stage: StageConfig = field(default_factory=StageConfig)
    exposure_check: dict = field(default_factory=dict)


# The kinds Section.get checks, from SerialProtocol's own annotations (a tuple is written as a list).
_SERIAL_KINDS = {f.name: {"tuple[str, ...]": "list[str]"}.get(f.type, f.type) for f in fields(SerialProtocol) if f.init}


def serial_protocol_from_table(table, source: str = "capture.toml", name: str = "stage.serial") -> SerialProtocol:
    """A :class:`SerialProtocol` from a TOML table (already parsed), validated.

    Raises
    ------
    ConfigError
        Naming ``source`` and the key (``stage.serial.move_reply``...).
    """
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: '{name}' must be a table [{name}], got {tname(table)}")
    s = Section({name: table}, name, source)
    values = {}
    for key, kind in _SERIAL_KINDS.items():
        if key in table:
            values[key] = s.get(key, kind)
        s.used.add(key)
    s.finish()
    if "init_commands" in values:
        values["init_commands"] = tuple(values["init_commands"])
    try:
        proto = SerialProtocol(**values)
    except ConfigError as exc:  # "stage.serial: key 'baudrate' ..." -> "<file>: key 'stage.serial.baudrate' ..."
        raise ConfigError(str(exc).replace("stage.serial: key '", f"{source}: key '{name}.", 1)) from None
    return proto


def capture_config_from_toml(text: str, source: str = "capture.toml") -> CaptureConfig:
    """Parse and validate the text of a capture configuration file."""
    doc = toml_document(text, source, CAPTURE_CONFIG_FORMAT, {"format", "camera", "display", "stage", "exposure_check"})

    s = Section(doc, "camera", source, required=False)
    kind = s.get("kind", "str", "sim")
    if kind not in CAMERA_KINDS:
        raise ConfigError(f"{source}: key 'camera.kind' must be one of {', '.join(CAMERA_KINDS)}, got {kind!r}")
    exposure = s.get("exposure_us", "float", None)
    if exposure is not None and exposure <= 0:
        raise ConfigError(f"{source}: key 'camera.exposure_us' must be positive, got {exposure}")
    src = s.table.get("source", 0)
    s.used.add("source")
    if isinstance(src, bool) or not isinstance(src, (int, str)):
        raise ConfigError(f"{source}: key 'camera.source' must be a camera index or a string,"
                          f" got {tname(src)} {short_repr(src)}")
    dev = s.table.get("device", 0)
    s.used.add("device")
    if isinstance(dev, bool) or not isinstance(dev, int) or dev < 0:
        raise ConfigError(f"{source}: key 'camera.device' must be a device index (0, 1, ...), got {short_repr(dev)}")
    camera = CameraConfig(kind, exposure, src, s.get("width", "int", None), s.get("height", "int", None),
                          s.get("cti", "str", ""), dev, s.get("serial_number", "str", ""),
                          s.get("pixel_format", "str", ""), s.get("timeout_s", "float", 5.0))
    s.finish()

    s = Section(doc, "display", source, required=False)
    screen = s.get("screen", "int", None)
    settle = s.get("settle_ms", "float", 0.0)
    s.finish()
    if settle < 0:
        raise ConfigError(f"{source}: key 'display.settle_ms' must be >= 0, got {settle}")
    display = DisplayConfig(screen, settle)

    s = Section(doc, "stage", source, required=False)
    kind = s.get("kind", "str", "sim")
    if kind not in STAGE_KINDS:
        raise ConfigError(f"{source}: key 'stage.kind' must be one of {', '.join(STAGE_KINDS)}, got {kind!r}")
    serial = None
    if "serial" in s.table:
        serial = serial_protocol_from_table(s.table["serial"], source)
    s.used.add("serial")
    s.finish()
    if kind == "serial" and serial is None:
        raise ConfigError(f"{source}: stage.kind is \"serial\" but there is no [stage.serial] table")
    stage = StageConfig(kind, serial)

    s = Section(doc, "exposure_check", source, required=False)
    limits = {}
    from ptpcore.capture.sequence import ExposureLimits

    for f in fields(ExposureLimits):
        v = s.get(f.name, "float", None)
        if v is not None:
            limits[f.name] = v
    s.finish()
    ExposureLimits(**limits).validate(f"{source}: [exposure_check]")
    return CaptureConfig(camera, display, stage, limits)


def load_capture_config(path) -> CaptureConfig:
    """Read and validate a capture configuration file."""
    path = Path(path)
    return capture_config_from_toml(read_text(path), str(path))
