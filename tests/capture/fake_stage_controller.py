"""A fake motion controller on a pseudo-terminal, for the serial stage tests.

It speaks a small text protocol like many real controllers (commands end
with CR, replies with CR LF):

    HOME       -> OK            (travels to 0)
    MA <z>     -> OK            (absolute move; z in controller units)
    TP         -> TP <z>        (position, 4 decimals)
    MD?        -> 1 when idle, 0 while moving
    anything   -> ERR <why>

Moves travel at ``speed`` units per second, so a move takes real time and
position polls see the stage on its way. Faults: ``stall`` (moves never
progress), ``mute`` (no replies at all), ``limit`` (targets beyond it are
refused with ``ERR limit``).
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty


class FakeController:
    def __init__(self, speed: float = 400.0, stall: bool = False, mute: bool = False, limit: float = 1e9):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self.speed = speed
        self.stall = stall
        self.mute = mute
        self.limit = limit
        self.log: list[str] = []
        self._start = self._target = 0.0
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(5)
        os.close(self.master)
        os.close(self.slave)

    # ---- the simulated mechanics ----------------------------------------
    def position(self) -> float:
        if self.stall:
            return self._start
        travelled = self.speed * (time.monotonic() - self._t0)
        d = self._target - self._start
        if abs(d) <= travelled:
            return self._target
        return self._start + travelled * (1 if d > 0 else -1)

    def _move(self, target: float) -> None:
        self._start = self.position()
        self._target = target
        self._t0 = time.monotonic()

    def _reply(self, command: str) -> str:
        if command == "HOME":
            self._move(0.0)
            return "OK"
        if command.startswith("MA "):
            try:
                target = float(command[3:])
            except ValueError:
                return "ERR bad number"
            if abs(target) > self.limit:
                return f"ERR limit {self.limit:g}"
            self._move(target)
            return "OK"
        if command == "TP":
            return f"TP {self.position():.4f}"
        if command == "MD?":
            return "1" if self.position() == self._target else "0"
        return f"ERR unknown command {command!r}"

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.02)
            if not ready:
                continue
            try:
                buf += os.read(self.master, 1024)
            except OSError:
                return
            while b"\r" in buf:
                line, buf = buf.split(b"\r", 1)
                command = line.decode("ascii").strip()
                if not command:
                    continue
                self.log.append(command)
                if not self.mute:
                    os.write(self.master, (self._reply(command) + "\r\n").encode("ascii"))
