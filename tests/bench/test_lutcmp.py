"""``python -m benchmarks.lutcmp``: the command line of :func:`ptpcore.evaluate.lutcompare.compare_lut_files`
(tested in tests/evaluate/test_lutcompare.py): its lines and exit codes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

from benchmarks.lutcmp import main

ROOT = Path(__file__).resolve().parents[2]


def _write(path, created="2026-11-26T10:00:00", scale=16.0):
    with h5py.File(path, "w") as f:
        f.attrs["created"] = created
        f["x"] = np.arange(12, dtype=np.float64).reshape(3, 4)
        f.create_group("model").attrs["smoothing_scale_px"] = scale


def test_lines_ignore_and_all(tmp_path, capsys):
    _write(tmp_path / "a.h5")
    _write(tmp_path / "b.h5", created="2026-11-26T16:00:00", scale=8.0)
    assert main([str(tmp_path / "a.h5"), str(tmp_path / "b.h5")]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out == ["attribute /model@smoothing_scale_px: 1 of 1 elements differ, largest |A - B| = 8",
                   f"1 difference(s): {tmp_path / 'a.h5'} vs {tmp_path / 'b.h5'}"]
    assert main([str(tmp_path / "a.h5"), str(tmp_path / "b.h5"), "--ignore", "smoothing_scale_px"]) == 0
    assert capsys.readouterr().out.startswith("identical")
    assert main([str(tmp_path / "a.h5"), str(tmp_path / "b.h5"), "--ignore", "smoothing_scale_px", "--all"]) == 1
    assert "attribute /@created" in capsys.readouterr().out


def test_command_line_exit_codes(tmp_path):
    _write(tmp_path / "a.h5")
    (tmp_path / "bad.h5").write_text("not hdf5")
    run = [sys.executable, "-m", "benchmarks.lutcmp", str(tmp_path / "a.h5")]
    assert subprocess.run(run + [str(tmp_path / "a.h5")], cwd=ROOT, capture_output=True).returncode == 0
    bad = subprocess.run(run + [str(tmp_path / "bad.h5")], cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2 and "bad.h5" in bad.stderr
