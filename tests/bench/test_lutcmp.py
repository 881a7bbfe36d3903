"""``python -m benchmarks.lutcmp``: two HDF5 files compared bit for bit, dataset by dataset and attribute
by attribute, every group; the root's ``created`` and ``--ignore`` names left out."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

from benchmarks.lutcmp import main

ROOT = Path(__file__).resolve().parents[2]


def _write(path, created="2026-11-26T10:00:00", x=None, nan_bits=0x7FF8000000000000, scale=16.0, extra=False):
    x = np.arange(12, dtype=np.float64).reshape(3, 4) if x is None else x
    with h5py.File(path, "w") as f:
        f.attrs["created"] = created
        f.attrs["format"] = "ptp-lut/1"
        f["x"] = x
        g = f.create_group("model")
        g.attrs["smoothing_scale_px"] = scale
        g.attrs["method"] = "smooth"
        g["sigma"] = np.array([1.0, np.uint64(nan_bits).view(np.float64)], np.float64)
        g["valid"] = np.array([[True, False]])
        if extra:
            g["extra"] = np.zeros(2, np.float32)


def test_identical_but_for_the_time_of_writing(tmp_path, capsys):
    _write(tmp_path / "a.h5")
    _write(tmp_path / "b.h5", created="2026-11-26T16:00:00")
    assert main([str(tmp_path / "a.h5"), str(tmp_path / "b.h5")]) == 0
    assert capsys.readouterr().out.startswith("identical")


def test_every_difference_is_one_line(tmp_path, capsys):
    _write(tmp_path / "a.h5")
    x = np.arange(12, dtype=np.float64).reshape(3, 4)
    x[1, 2] += 2.5e-9
    x[2, 3] += 1e-12
    # The same NaN with another payload, a changed attribute in a subgroup, a dataset in B only.
    _write(tmp_path / "b.h5", x=x, nan_bits=0x7FF8000000000001, scale=8.0, extra=True)
    assert main([str(tmp_path / "a.h5"), str(tmp_path / "b.h5")]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert lines[-1].startswith("4 difference(s)")
    found = "\n".join(lines[:-1])
    assert "dataset /x: 2 of 12 elements differ, largest |A - B| = 2.5e-09" in found
    assert "dataset /model/sigma: 1 of 2 elements differ, largest |A - B| = 0, NaN with other bits at 1" in found
    assert "attribute /model@smoothing_scale_px: 1 of 1 elements differ, largest |A - B| = 8" in found
    assert "/model/extra: only in B" in found


def test_ignored_attributes_and_dtype_changes(tmp_path, capsys):
    _write(tmp_path / "a.h5")
    _write(tmp_path / "b.h5", scale=8.0)
    assert main([str(tmp_path / "a.h5"), str(tmp_path / "b.h5"), "--ignore", "smoothing_scale_px"]) == 0
    _write(tmp_path / "c.h5", x=np.arange(12, dtype=np.float32).reshape(3, 4))
    assert main([str(tmp_path / "a.h5"), str(tmp_path / "c.h5")]) == 1
    assert "dataset /x: dtype float64 != float32" in capsys.readouterr().out


def test_command_line_exit_codes(tmp_path):
    _write(tmp_path / "a.h5")
    (tmp_path / "bad.h5").write_text("not hdf5")
    run = [sys.executable, "-m", "benchmarks.lutcmp", str(tmp_path / "a.h5")]
    assert subprocess.run(run + [str(tmp_path / "a.h5")], cwd=ROOT, capture_output=True).returncode == 0
    bad = subprocess.run(run + [str(tmp_path / "bad.h5")], cwd=ROOT, capture_output=True, text=True)
    assert bad.returncode == 2 and "bad.h5" in bad.stderr
