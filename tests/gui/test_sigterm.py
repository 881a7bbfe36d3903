"""``ptp-studio`` quits cleanly on SIGTERM (a logout, ``kill``): jobs stopped, no question, a normal exit."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")


def test_sigterm_stops_the_jobs_and_quits_without_asking(qapp, qtbot, monkeypatch):
    from ptp_studio.__main__ import _quit_on_sigterm

    class Wizard:
        closing = False
        stopped = False

        def stop_jobs(self):
            self.stopped = True
            return True

    wiz, quits = Wizard(), []
    monkeypatch.setattr(qapp, "quit", lambda: quits.append(wiz.closing))
    previous = signal.getsignal(signal.SIGTERM)
    try:
        _quit_on_sigterm(qapp, wiz)
        os.kill(os.getpid(), signal.SIGTERM)
        qtbot.waitUntil(lambda: bool(quits), timeout=5000)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert wiz.stopped and quits == [True]  # marked closing first: no "unsaved work" dialog


def _wait_for_sigterm_handler(proc: subprocess.Popen, timeout: float = 120.0) -> None:
    """Wait until ``proc`` catches SIGTERM: ptp-studio installs its handler right after showing the
    window, so the bit in /proc's SigCgt mask says the window is up (a fixed sleep was too short on a
    loaded machine). Without /proc, a fixed wait."""
    status = f"/proc/{proc.pid}/status"
    if not os.path.exists(status):
        time.sleep(10)
        return
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        with open(status) as f:
            caught = next(int(line.split()[1], 16) for line in f if line.startswith("SigCgt:"))
        if caught & (1 << (signal.SIGTERM - 1)):
            return
        time.sleep(0.1)
    why = proc.stderr.read() if proc.poll() is not None else "still starting"
    pytest.fail(f"ptp-studio caught no SIGTERM after {timeout:g} s: {why}")


def test_the_app_exits_0_on_sigterm():
    """Not killed by the signal (exit -15, its temporary files left behind): it quits as a closed window does."""
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    proc = subprocess.Popen([sys.executable, "-m", "ptp_studio", "--camera", "64x48"], env=env,
                            stderr=subprocess.PIPE, text=True)
    try:
        _wait_for_sigterm_handler(proc)
        assert proc.poll() is None, proc.stderr.read()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
