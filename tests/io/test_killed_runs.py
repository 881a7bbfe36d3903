"""A run killed with SIGKILL leaves no temporary file behind (issue 33).

On POSIX the spill files are unlinked at creation (the open file is all they need); the atomic
writes' ``.part`` files carry their owner's process id and start time and are removed by the next
write into their folder once that process is gone. Only this user's files of that naming are ever
removed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from ptpcore import atomic
from ptpcore.store import SpillStore, remove_orphaned_spill_files

pytestmark = pytest.mark.skipif(os.name != "posix", reason="SIGKILL and unlinked open files: POSIX")


def _killed_child(body: str, env: dict) -> int:
    """Run ``body`` in a fresh interpreter that SIGKILLs itself at its end; return the exit code."""
    code = textwrap.dedent(body) + "\nimport os, signal\nos.kill(os.getpid(), signal.SIGKILL)\n"
    return subprocess.run([sys.executable, "-c", code], env=env, timeout=120).returncode


def test_a_spill_file_has_no_name_while_it_is_used(tmp_path):
    store = SpillStore(3, (4, 5), {"x": np.float32}, {"x": np.nan}, directory=tmp_path)
    assert list(tmp_path.iterdir()) == []  # nothing to leave behind, whatever ends the process
    store.write("x", 1, np.full((4, 5), 2.0, np.float32))
    store.finish()
    maps = store.arrays()["x"]
    maps[2] = 7.0  # written through the map of the unnamed file, read back with file reads
    np.testing.assert_array_equal(store.read("x", 0, 2), [[np.nan, np.nan], [2.0, 2.0], [7.0, 7.0]])


def test_sigkill_mid_run_leaves_no_spill_file(tmp_path):
    spill = tmp_path / "spill"
    spill.mkdir()
    env = dict(os.environ, PTP_SPILL_DIR=str(spill))
    rc = _killed_child("""
        import numpy as np
        from ptpcore.store import SpillStore
        store = SpillStore(4, (300, 400), {"x": np.float32, "r": np.uint8}, {})
        store.write("x", 0, np.ones((300, 400), np.float32))
        maps = store.arrays()
    """, env)
    assert rc == -signal.SIGKILL
    assert list(spill.iterdir()) == []


def test_sigkill_mid_write_leaves_a_part_file_the_next_write_removes(tmp_path):
    target = tmp_path / "calib.lut.h5"
    rc = _killed_child(f"""
        from ptpcore.atomic import atomic_path
        with atomic_path({str(target)!r}) as part:
            part.write_bytes(b"half a LUT")
            import os, signal
            os.kill(os.getpid(), signal.SIGKILL)
    """, dict(os.environ))
    assert rc == -signal.SIGKILL
    left = [p.name for p in tmp_path.iterdir()]
    assert len(left) == 1 and left[0].startswith(".calib.lut.h5.") and left[0].endswith(".part")
    atomic.write_text_atomic(tmp_path / "other.txt", "next run")  # any write into the folder
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.txt"]


def test_the_sweep_spares_running_owners_and_foreign_names(tmp_path):
    alive = tmp_path / f".a.h5.{atomic.owner_tag()}-abcdefgh.part"  # this process: running
    foreign = tmp_path / ".b.png.abc123.part"  # not of our naming (another tool's, an old version's)
    unrelated = tmp_path / "notes.part"
    # A dead owner: a child that has exited; its pid is not reused within this test's run.
    dead_pid = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                              text=True, check=True).stdout.strip()
    dead = tmp_path / f".c.h5.{dead_pid}-12345-abcdefgh.part"
    reused = tmp_path / f".d.h5.{os.getpid()}-1-abcdefgh.part"  # our pid, an earlier process's start
    for p in (alive, foreign, unrelated, dead, reused):
        p.write_bytes(b"x")
    removed = atomic.sweep_orphans(tmp_path, ".", ".part")
    expected = [dead, reused] if atomic._start_token(os.getpid()) else [dead]  # start times: Linux
    assert sorted(removed) == sorted(expected)
    assert alive.exists() and foreign.exists() and unrelated.exists()


def test_orphaned_spill_files_with_names_are_removed_at_start(tmp_path):
    """Where spill files keep their names (Windows), the next program start removes those of gone owners."""
    dead_pid = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                              text=True, check=True).stdout.strip()
    orphan = tmp_path / f"ptp-samples-{dead_pid}-777-abcdefgh.tmp"
    mine = tmp_path / f"ptp-samples-{atomic.owner_tag()}-abcdefgh.tmp"
    orphan.write_bytes(b"x" * 10)
    mine.write_bytes(b"x")
    assert remove_orphaned_spill_files(tmp_path) == [orphan]
    assert not orphan.exists() and mine.exists()


def test_the_owner_tag_names_this_process_and_its_start():
    pid, start = atomic.owner_tag().split("-")
    assert int(pid) == os.getpid()
    if Path(f"/proc/{pid}/stat").exists():
        assert start == atomic._start_token(os.getpid()) and int(start) > 0
