"""Atomic writes: a process killed (SIGKILL) mid-write leaves the previous file intact.

A child process writes a large LUT or session over an existing one; the test
kills it once the temporary file beside the target has grown, then checks
that the target holds the previous bytes, still loads, and that the partial
file never took the final name. A real calibration killed while decoding
resumes from its saved stage.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from ptpcore.errors import FileFormatError
from ptpcore.io import load_lut
from ptpcore.run import load_session

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL (POSIX)")

_COMMON = """
import sys
import numpy as np
from ptpcore.io import Lut, SampleStack, save_lut
from ptpcore.rig import Camera
from ptpcore.run.session import Session, save_session
from ptpcore.simulate.virtual_rig import preset
import dataclasses

def big_lut(h, w, degree, seed):
    rng = np.random.default_rng(seed)
    f32 = lambda: rng.random((h, w), dtype=np.float32)
    return Lut("poly", degree, 20.0, 20.0, 0.0, 40.0, rng.random((degree + 1, h, w)),
               rng.random((degree + 1, h, w)), None, np.ones((h, w), bool),
               np.full((h, w), 11, np.uint16), np.zeros((h, w), np.float32),
               np.full((h, w), 40.0, np.float32), f32(), f32(), f32(), f32())

def big_session(h, w, k, seed):
    rig = preset("ideal")[0]
    rig = dataclasses.replace(rig, camera=Camera(w, h, 8)).with_z(np.linspace(0.0, 40.0, k))
    rng = np.random.default_rng(seed)
    s = SampleStack.empty(rig.stage.z_mm, (h, w))
    s.x[:] = rng.random(s.x.shape, dtype=np.float32)
    s.y[:] = rng.random(s.y.shape, dtype=np.float32)
    s.x_ref[:] = 1.0
    s.y_ref[:] = 2.0
    s.reasons[:] = 0
    s.modulation[:] = rng.random(s.x.shape, dtype=np.float32)
    s.background[:] = rng.random(s.x.shape, dtype=np.float32)
    return Session(rig=rig, samples=s, lut=big_lut(h, w, 3, seed))
"""


def _run_child(body: str, tmp_path: Path):
    script = tmp_path / "child.py"
    script.write_text(_COMMON + textwrap.dedent(body))
    return subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            cwd=tmp_path)


def _finish(proc) -> None:
    """Wait for a child that must succeed."""
    _out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err.decode()


def _kill_when_partial_grows(proc, folder: Path, target: Path, min_bytes: int, timeout: float = 60.0) -> int:
    """SIGKILL ``proc`` once a temporary file for ``target`` holds ``min_bytes``; return its size."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        parts = list(folder.glob(f".{target.name}.*.part"))
        size = max((p.stat().st_size for p in parts if p.exists()), default=0)
        if size >= min_bytes:
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=30)
            return size
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"child ended before it could be killed mid-write: {proc.returncode} {err.decode()}")
        time.sleep(0.005)
    proc.kill()
    proc.communicate(timeout=30)
    pytest.fail("no partial file appeared")


def _check_intact(folder: Path, target: Path, before: bytes, loader) -> None:
    assert target.read_bytes() == before  # previous file untouched, byte for byte
    loader(target)  # and still loadable
    others = sorted(p.name for p in folder.iterdir() if p.name not in (target.name, "child.py"))
    assert others and all(n.startswith(f".{target.name}.") and n.endswith(".part") for n in others)
    for part in others:  # the half-written temporary file is refused, not mistaken for a good one
        with pytest.raises(FileFormatError):
            loader(folder / part)


def test_lut_killed_mid_write_keeps_previous(tmp_path):
    target = tmp_path / "calib.lut.h5"
    _finish(_run_child(f"save_lut(big_lut(48, 64, 3, 1), {str(target)!r})\n", tmp_path))
    before = target.read_bytes()
    proc = _run_child(f"save_lut(big_lut(1000, 1500, 5, 2), {str(target)!r})\n", tmp_path)
    _kill_when_partial_grows(proc, tmp_path, target, 4 << 20)
    assert proc.returncode == -signal.SIGKILL
    _check_intact(tmp_path, target, before, load_lut)
    assert load_lut(target).shape == (48, 64)


def test_session_killed_mid_write_keeps_previous(tmp_path):
    target = tmp_path / "run.ptps.h5"
    _finish(_run_child(f"save_session(big_session(48, 64, 5, 1), {str(target)!r})\n", tmp_path))
    before = target.read_bytes()
    proc = _run_child(f"save_session(big_session(600, 800, 30, 2), {str(target)!r})\n", tmp_path)
    _kill_when_partial_grows(proc, tmp_path, target, 4 << 20)
    assert proc.returncode == -signal.SIGKILL
    _check_intact(tmp_path, target, before, load_session)
    assert load_session(target).rig.camera.shape == (48, 64)


def test_calibration_killed_while_decoding_resumes(tmp_path):
    """Kill a session run during its (slowed) decode; `ptp resume` then finishes it."""
    from ptpcore.cli import main
    from ptpcore.rig import Camera
    from ptpcore.simulate import preset, simulate_dataset

    rig, settings = preset("ideal")
    rig = dataclasses.replace(rig, camera=Camera(64, 48, 8)).with_z([0.0, 10.0, 20.0])
    ds = simulate_dataset(tmp_path / "ds", rig, settings, seed=4)
    session = tmp_path / "cal.ptps.h5"
    out = tmp_path / "cal.lut.h5"
    marker = tmp_path / "decoding"
    proc = _run_child(f"""
        import time
        from pathlib import Path
        from ptpcore.run import new_session, run_session
        s = new_session({str(ds)!r}, degree=1, out={str(out)!r})
        save_session(s, {str(session)!r})
        def slow(fraction, message):
            Path({str(marker)!r}).touch()
            time.sleep(0.2)
        run_session(s, {str(session)!r}, progress=slow)
    """, tmp_path)
    t_end = time.monotonic() + 60
    while not marker.exists():
        if proc.poll() is not None or time.monotonic() > t_end:
            proc.kill()
            pytest.fail(proc.communicate()[1].decode())
        time.sleep(0.01)
    time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    assert load_session(session).stage == "new" and not out.exists()
    assert main(["resume", str(session), "-q"]) == 0
    assert load_session(session).stage == "lut"
    lut = load_lut(out)
    assert lut.valid.mean() > 0.9 and np.isfinite(lut.x[:, lut.valid]).all()
    os.remove(marker)
