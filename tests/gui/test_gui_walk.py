"""The real wizard under Xvfb at each screen size, walked with real X events (``benchmarks.gui_walk``).

Slow (minutes per size): CI runs it with ``-m slow`` after installing Xvfb, xdotool and ImageMagick.
``GUI_WALK_SIZES`` picks the sizes (default all three: 1366x768, 1920x1080, 1536x864).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_every_page_at_every_size_passes_the_layout_checks(tmp_path):
    missing = [t for t in ("Xvfb", "xdotool", "import") if shutil.which(t) is None]
    if missing:
        pytest.skip(f"not installed: {', '.join(missing)} (.ci/run installs them)")
    sizes = os.environ.get("GUI_WALK_SIZES", "1366x768,1920x1080,1536x864")
    env = {k: v for k, v in os.environ.items() if k not in ("QT_QPA_PLATFORM", "DISPLAY")}
    done = subprocess.run([sys.executable, "-m", "benchmarks.gui_walk", str(tmp_path), "--sizes", sizes],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=3600)
    assert done.returncode == 0, done.stdout + done.stderr
    for size in sizes.split(","):
        shots = sorted((tmp_path / size).glob("screen-*.png"))
        names = {p.stem.split("-", 2)[-1] for p in shots}
        assert {"rig", "fringes", "acquire", "phase-validity", "calibrate", "compare", "export"} <= names, size
