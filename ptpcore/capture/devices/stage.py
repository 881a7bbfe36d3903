"""Stages: home, move the LCD to a height, read where it is.

- :class:`SimulatedStage` — exact and instant, with injected faults for tests;
- :class:`ManualStage` — a hand-driven stage: it asks the engineer (a dialog in
  the GUI, a prompt in the CLI) to move to ``z`` and type the reading;
- :class:`SerialStage` — a motion controller on a serial port (pyserial)
  whose text protocol (command templates, reply patterns, line endings,
  timeouts) comes from a configuration table, :class:`SerialProtocol`
  (``[stage.serial]`` of a capture configuration file,
  :mod:`ptpcore.capture.devices.config`).

``move_to`` returns once the stage is in position; ``position()`` is the
reading the capture records in ``rig.toml`` (``stage.z_mm``).
"""

from __future__ import annotations

import math
import re
import string
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Protocol, runtime_checkable

from ptpcore.errors import Cancelled, ConfigError, DeviceError

__all__ = ["Stage", "StageTimeout", "SimulatedStage", "ManualStage", "SerialProtocol", "SerialStage"]


class StageTimeout(DeviceError):
    """The stage did not answer, or did not arrive, in time."""


@runtime_checkable
class Stage(Protocol):
    """A translation stage carrying the LCD along z (mm)."""

    def open(self) -> None:
        """Connect."""

    def home(self) -> None:
        """Find the reference position (may take long; a no-op where there is none)."""

    def move_to(self, z_mm: float) -> None:
        """Move to ``z_mm`` and return once there. Raises StageTimeout or DeviceError."""

    def position(self) -> float:
        """The current reading, mm."""

    def close(self) -> None:
        """Disconnect (safe to call twice)."""


# --------------------------------------------------------------------------- simulated

class SimulatedStage:
    """An exact, instant stage (the virtual rig adds its own position errors).

    Parameters
    ----------
    z_mm : float
        Starting reading.
    home_mm : float
        Where :meth:`home` goes.
    faults : mapping or callable, optional
        Injected failures by move number (0-based, counting every
        :meth:`move_to`): ``"timeout"`` raises :class:`StageTimeout` and leaves
        the stage half way, ``"error"`` raises :class:`DeviceError`;
        a callable ``faults(n, z_mm) -> str | None`` decides per move.
    move_s : float
        Seconds every move takes (0 in tests).
    """

    def __init__(self, z_mm: float = 0.0, home_mm: float = 0.0,
                 faults: Mapping[int, str] | Callable | None = None, move_s: float = 0.0):
        self.z = float(z_mm)
        self.home_mm = float(home_mm)
        self.faults = faults
        self.move_s = float(move_s)
        self.moves = 0
        self.is_open = False

    def describe(self) -> str:
        return "simulated stage"

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def home(self) -> None:
        self._check_open("home")
        self.z = self.home_mm

    def _fault(self, n: int, z: float) -> str | None:
        if self.faults is None:
            return None
        if callable(self.faults):
            return self.faults(n, z)
        return self.faults.get(n)

    def move_to(self, z_mm: float) -> None:
        self._check_open("move_to")
        z_mm = float(z_mm)
        n = self.moves
        self.moves += 1
        fault = self._fault(n, z_mm)
        if fault == "timeout":
            self.z = 0.5 * (self.z + z_mm)
            raise StageTimeout(f"{self.describe()}: move to z = {z_mm:g} mm did not finish in time"
                               " (injected fault)")
        if fault == "error":
            raise DeviceError(f"{self.describe()}: controller error on move to z = {z_mm:g} mm (injected fault)")
        if self.move_s > 0:
            time.sleep(self.move_s)
        self.z = z_mm

    def position(self) -> float:
        self._check_open("position")
        return self.z

    def _check_open(self, what: str) -> None:
        if not self.is_open:
            raise DeviceError(f"{self.describe()}: {what}() before open()")


# --------------------------------------------------------------------------- manual

class ManualStage:
    """A stage the engineer moves by hand and reads off its scale or gauge.

    Parameters
    ----------
    ask : callable
        ``ask(z_mm, prompt) -> float | None``: shows ``prompt`` (move to
        ``z_mm``), returns the reading the engineer typed, or ``None`` if they
        cancel (the capture then stops, resumable). The GUI passes a dialog,
        the CLI a terminal prompt.
    """

    def __init__(self, ask: Callable[[float, str], float | None]):
        self.ask = ask
        self._z: float | None = None

    def describe(self) -> str:
        return "manual stage"

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def home(self) -> None:
        """Nothing to do: the first move asks for the first position."""

    def move_to(self, z_mm: float) -> None:
        reading = self.ask(float(z_mm), f"Move the stage to z = {z_mm:g} mm, then enter its reading (mm).")
        if reading is None:
            raise Cancelled(f"{self.describe()}: the move to z = {z_mm:g} mm was cancelled")
        try:
            reading = float(reading)
        except (TypeError, ValueError):
            raise DeviceError(f"{self.describe()}: reading {reading!r} is not a number") from None
        if not math.isfinite(reading):
            raise DeviceError(f"{self.describe()}: reading {reading!r} is not a finite number")
        self._z = reading

    def position(self) -> float:
        if self._z is None:
            raise DeviceError(f"{self.describe()}: no reading yet (the stage was never moved)")
        return self._z


# --------------------------------------------------------------------------- serial

_TEMPLATE_FIELDS = ("z", "z_mm", "steps")


@dataclass(frozen=True)
class SerialProtocol:
    """How to talk to a motion controller on a serial port.

    Commands are Python format templates with the fields ``{z}`` (target in
    controller units, float: ``z_mm * units_per_mm``), ``{z_mm}`` and
    ``{steps}`` (``z`` rounded to an integer). Replies are one line each,
    matched with regular expressions (``re.search``; anchor with ``^``/``$``).
    An empty reply pattern means the controller does not answer that command.

    Attributes
    ----------
    port : str
        ``/dev/ttyUSB0``, ``COM3``, or any pyserial URL (``socket://host:port``).
    baudrate, bytesize, parity, stopbits
        Line settings (parity ``N``, ``E``, ``O``, ``M``, ``S``).
    write_ending, read_ending : str
        Appended to every command; ends every reply (``"\\r\\n"``, ``"\\r"``...).
    timeout_s : float
        How long one reply may take.
    move_timeout_s, home_timeout_s : float
        How long a move, or homing, may take to finish.
    poll_interval_s : float
        Pause between polls while waiting for a move to finish.
    units_per_mm : float
        Controller units per mm (1 when the controller speaks mm).
    tolerance_mm : float
        A move is finished when the position is this close to the target.
    init_commands : list of str
        Sent once after opening (units, servo on...), each acknowledged by ``init_reply``.
    home_command, home_reply : str
        Homing (empty: the stage has no homing).
    move_command, move_reply : str
        Absolute move.
    position_command, position_reply : str
        Position query; the reply pattern captures the value in a group named ``z``.
    status_command, idle_reply : str
        Optional: polled after a move until the reply matches ``idle_reply``.
        Without it, the position is polled until it is within ``tolerance_mm``.
    error_reply : str
        Optional: a reply matching this is a controller error (its group
        ``message``, if any, is shown).
    """

    port: str = ""
    baudrate: int = 9600
    bytesize: int = 8
    parity: str = "N"
    stopbits: float = 1.0
    write_ending: str = "\r\n"
    read_ending: str = "\r\n"
    timeout_s: float = 1.0
    move_timeout_s: float = 60.0
    home_timeout_s: float = 120.0
    poll_interval_s: float = 0.05
    units_per_mm: float = 1.0
    tolerance_mm: float = 0.001
    init_commands: tuple[str, ...] = ()
    init_reply: str = ""
    home_command: str = ""
    home_reply: str = ""
    move_command: str = "MOVE {z:.4f}"
    move_reply: str = ""
    position_command: str = "POS?"
    position_reply: str = r"(?P<z>[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)"
    status_command: str = ""
    idle_reply: str = ""
    error_reply: str = ""
    _compiled: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        self.validate()

    def validate(self, source: str = "stage.serial") -> None:
        """Check every value; raises ConfigError naming the key."""
        def bad(key, msg):
            return ConfigError(f"{source}: key '{key}' {msg}")

        for key in ("timeout_s", "move_timeout_s", "home_timeout_s", "units_per_mm", "tolerance_mm"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v > 0):
                raise bad(key, f"must be a positive number, got {v!r}")
        if not (math.isfinite(self.poll_interval_s) and self.poll_interval_s >= 0):
            raise bad("poll_interval_s", f"must be >= 0, got {self.poll_interval_s!r}")
        if self.baudrate <= 0:
            raise bad("baudrate", f"must be positive, got {self.baudrate}")
        if self.bytesize not in (5, 6, 7, 8):
            raise bad("bytesize", f"must be 5, 6, 7 or 8, got {self.bytesize}")
        if self.parity not in ("N", "E", "O", "M", "S"):
            raise bad("parity", f"must be one of N, E, O, M, S, got {self.parity!r}")
        if self.stopbits not in (1, 1.5, 2):
            raise bad("stopbits", f"must be 1, 1.5 or 2, got {self.stopbits!r}")
        if not self.read_ending:
            raise bad("read_ending", "must not be empty (replies are lines)")
        for key in ("move_command", "position_command"):
            if not getattr(self, key):
                raise bad(key, "must not be empty")
        for key in ("home_command", "move_command", "position_command", "status_command"):
            _check_template(getattr(self, key), f"{source}: key '{key}'")
        for i, cmd in enumerate(self.init_commands):
            _check_template(cmd, f"{source}: key 'init_commands[{i}]'")
        for key in ("init_reply", "home_reply", "move_reply", "position_reply", "idle_reply", "error_reply"):
            text = getattr(self, key)
            try:
                self._compiled[key] = re.compile(text) if text else None
            except re.error as exc:
                raise bad(key, f"is not a valid regular expression ({exc})") from None
        if "z" not in self._compiled["position_reply"].groupindex:
            raise bad("position_reply", "must capture the position in a group named z: (?P<z>...)")
        if self.status_command and not self.idle_reply:
            raise bad("idle_reply", "is needed with status_command (the reply meaning 'not moving')")

    def pattern(self, key: str):
        return self._compiled[key]


def _check_template(template: str, where: str) -> None:
    try:
        parsed = list(string.Formatter().parse(template))
    except ValueError as exc:
        raise ConfigError(f"{where} is not a valid template ({exc})") from None
    for _lit, name, _spec, conv in parsed:
        if name is not None and (name not in _TEMPLATE_FIELDS or conv):
            raise ConfigError(f"{where}: field '{{{name}}}' is not allowed (only {', '.join(_TEMPLATE_FIELDS)})")
    try:
        template.format(z=1.5, z_mm=1.5, steps=2)
    except (ValueError, TypeError, IndexError, KeyError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


class SerialStage:
    """A motion controller on a serial port, speaking the text protocol of a :class:`SerialProtocol`.

    Parameters
    ----------
    protocol : SerialProtocol
    port : str, optional
        Overrides ``protocol.port``.
    """

    def __init__(self, protocol: SerialProtocol, port: str | None = None):
        self.protocol = protocol
        self.port = port or protocol.port
        if not self.port:
            raise ConfigError("stage.serial: key 'port' is needed (e.g. \"/dev/ttyUSB0\" or \"COM3\")")
        self._ser = None

    def describe(self) -> str:
        return f"serial stage on {self.port}"

    # ---- connection ------------------------------------------------------
    def open(self) -> None:
        try:
            import serial
        except ImportError:  # pragma: no cover - a runtime dependency
            raise DeviceError("serial stages need pyserial: pip install pyserial") from None
        p = self.protocol
        try:
            self._ser = serial.serial_for_url(self.port, baudrate=p.baudrate, bytesize=p.bytesize, parity=p.parity,
                                              stopbits=p.stopbits, timeout=p.timeout_s, write_timeout=p.timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"{self.describe()}: cannot open the port ({exc})") from None
        for cmd in p.init_commands:
            self._command(self._fill(cmd, 0.0), "init_reply")

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            finally:
                self._ser = None

    # ---- the protocol ----------------------------------------------------
    def _fill(self, template: str, z_mm: float) -> str:
        z = z_mm * self.protocol.units_per_mm
        return template.format(z=z, z_mm=z_mm, steps=int(round(z)))

    def _io(self, what: str, fn, *args):
        import serial

        if self._ser is None:
            raise DeviceError(f"{self.describe()}: {what} before open()")
        try:
            return fn(*args)
        except (serial.SerialException, OSError) as exc:
            raise DeviceError(f"{self.describe()}: {what} failed ({exc})") from None

    def _send(self, text: str) -> None:
        data = (text + self.protocol.write_ending).encode("ascii", errors="strict")
        self._io(f"sending {text!r}", self._ser.reset_input_buffer)
        self._io(f"sending {text!r}", self._ser.write, data)
        self._io(f"sending {text!r}", self._ser.flush)

    def _read_line(self, command: str, timeout: float) -> str:
        ending = self.protocol.read_ending.encode("ascii")
        self._ser.timeout = timeout
        raw = self._io(f"reading the reply to {command!r}", self._ser.read_until, ending)
        if not raw.endswith(ending):
            got = f" (got {raw.decode('ascii', 'replace')!r} so far)" if raw else ""
            raise StageTimeout(f"{self.describe()}: no reply to {command!r} within {timeout:g} s{got}")
        return raw[:-len(ending)].decode("ascii", errors="replace").strip()

    def _command(self, text: str, reply_key: str | None, timeout: float | None = None):
        """Send one command; read and check its reply line. Returns the match (or None)."""
        pattern = self.protocol.pattern(reply_key) if reply_key else None
        if pattern is None:
            self._send(text)
            return None
        line = self._query(text, timeout)
        m = pattern.search(line)
        if m is None:
            raise DeviceError(f"{self.describe()}: unexpected reply {line!r} to {text!r}"
                              f" (expected /{pattern.pattern}/)")
        return m

    def _query(self, text: str, timeout: float | None = None) -> str:
        """Send a command and read its reply line (any line: status polls), checked for an error reply."""
        self._send(text)
        line = self._read_line(text, timeout or self.protocol.timeout_s)
        self._check_error(text, line)
        return line

    def _check_error(self, command: str, line: str) -> None:
        err = self.protocol.pattern("error_reply")
        if err is not None:
            m = err.search(line)
            if m is not None:
                msg = m.groupdict().get("message") or line
                raise DeviceError(f"{self.describe()}: the controller reports an error after {command!r}: {msg}")

    # ---- Stage -----------------------------------------------------------
    def home(self) -> None:
        p = self.protocol
        if not p.home_command:
            return
        self._command(self._fill(p.home_command, 0.0), "home_reply", timeout=p.home_timeout_s)
        if p.status_command:
            self._wait_idle(p.home_timeout_s, "homing")

    def position(self) -> float:
        p = self.protocol
        m = self._command(self._fill(p.position_command, 0.0), "position_reply")
        try:
            value = float(m.group("z"))
        except (TypeError, ValueError):
            raise DeviceError(f"{self.describe()}: position {m.group('z')!r} is not a number") from None
        return value / p.units_per_mm

    def _wait_idle(self, timeout: float, what: str) -> None:
        p = self.protocol
        idle = p.pattern("idle_reply")
        deadline = time.monotonic() + timeout
        while True:
            line = self._query(self._fill(p.status_command, 0.0))
            if idle.search(line):
                return
            if time.monotonic() > deadline:
                raise StageTimeout(f"{self.describe()}: {what} not finished after {timeout:g} s"
                                   f" (status {line!r})")
            time.sleep(p.poll_interval_s)

    def move_to(self, z_mm: float) -> None:
        p = self.protocol
        z_mm = float(z_mm)
        self._command(self._fill(p.move_command, z_mm), "move_reply")
        what = f"move to z = {z_mm:g} mm"
        if p.status_command:
            self._wait_idle(p.move_timeout_s, what)
            z = self.position()
            if abs(z - z_mm) > p.tolerance_mm:
                raise DeviceError(f"{self.describe()}: {what} stopped at {z:g} mm"
                                  f" (more than {p.tolerance_mm:g} mm away)")
            return
        deadline = time.monotonic() + p.move_timeout_s
        while True:
            z = self.position()
            if abs(z - z_mm) <= p.tolerance_mm:
                return
            if time.monotonic() > deadline:
                raise StageTimeout(f"{self.describe()}: {what} not finished after {p.move_timeout_s:g} s"
                                   f" (last reading {z:g} mm)")
            time.sleep(p.poll_interval_s)
