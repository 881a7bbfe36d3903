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


def test_the_app_exits_0_on_sigterm():
    """Not killed by the signal (exit -15, its temporary files left behind): it quits as a closed window does."""
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    proc = subprocess.Popen([sys.executable, "-m", "ptp_studio", "--camera", "64x48"], env=env,
                            stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(6)  # the window is up (no output to wait for)
        assert proc.poll() is None, proc.stderr.read()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
