"""benchmarks.rsswatch: the peak it reports is the command's, its exit code the command's."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads Linux's /proc")


def test_the_peak_covers_a_known_allocation_and_the_exit_code_passes_through(tmp_path):
    # 200 MiB touched (bytearray zero-fills), held 0.6 s, released, then exit 3.
    code = "import sys, time; b = bytearray(200 << 20); time.sleep(0.6); del b; time.sleep(0.3); sys.exit(3)"
    out = tmp_path / "r.json"
    trace = tmp_path / "t.tsv"
    # The watcher as its own small process, as the docs run it (see its docstring: a child's
    # ru_maxrss carries the resident size of the process that forked it, here the test runner's).
    rc = subprocess.run([sys.executable, "-m", "benchmarks.rsswatch", "--interval", "0.05", "--json", str(out),
                         "--trace", str(trace), "--", sys.executable, "-c", code], cwd=ROOT).returncode
    result = json.loads(out.read_text())
    assert rc == 3 and result["exit_code"] == 3
    assert 200 <= result["peak_mib"] < 200 + 100, result  # the allocation plus an interpreter
    assert result["samples"] >= 1 and result["wall_s"] >= 0.9
    rows = [line.split("\t") for line in trace.read_text().splitlines()]
    assert rows and max(float(r[2]) for r in rows) <= result["peak_mib"]


def test_a_peak_after_the_last_read_still_counts(tmp_path):
    # The allocation happens and the process exits inside one interval (20 s, not waited out: the
    # wait ends when the process does): the child's ru_maxrss catches the peak.
    code = "b = bytearray(150 << 20)"
    out = tmp_path / "r.json"
    subprocess.run([sys.executable, "-m", "benchmarks.rsswatch", "--interval", "20", "--json", str(out), "--",
                    sys.executable, "-c", code], cwd=ROOT, check=True)
    result = json.loads(out.read_text())
    assert result["exit_code"] == 0 and 150 <= result["peak_mib"] < 150 + 100
    assert result["wall_s"] < 20.0  # the wait ended with the process
