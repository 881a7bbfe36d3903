"""numba's compiled kernels are cached in a per-user folder, never in the package (issue 15)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import ptpcore
from ptpcore.decode.phase import user_cache_dir

ROOT = Path(ptpcore.__file__).resolve().parent.parent


def test_user_cache_dir_follows_xdg(monkeypatch, tmp_path):
    if sys.platform in ("win32", "darwin"):
        pytest.skip("XDG_CACHE_HOME is a Linux convention")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert user_cache_dir() == tmp_path / "ptp-studio"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")  # the spec: relative paths are ignored
    assert user_cache_dir() == Path.home() / ".cache" / "ptp-studio"


def test_kernels_compile_into_the_user_cache(tmp_path):
    pytest.importorskip("numba")
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "PTP_NO_NUMBA")}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    code = ("from ptpcore.decode.phase import fused_kernels; import numba, os;"
            "k = fused_kernels(); assert k is not None; print(numba.config.CACHE_DIR)")
    out = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True,
                         check=True, timeout=300)
    assert out.stdout.strip() == str(tmp_path / "ptp-studio" / "numba")
