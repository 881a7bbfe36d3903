"""Start-up without a display or without Qt's X11 libraries: one line and exit 2, never Qt's abort (issue 31)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ptp_studio.platform_check import (SONAME_PACKAGES, _qt_folder, missing_sonames, needed_sonames, qt_platform,
                                       startup_problem)

QT = _qt_folder()
PLUGIN = QT / "plugins" / "platforms" / "libqxcb.so"
linux_xcb = pytest.mark.skipif(not sys.platform.startswith("linux") or not PLUGIN.is_file(),
                               reason="the xcb plugin is Linux's")


def _loader(missing: dict[str, str]):
    """A dynamic loader that finds every library except ``missing`` (soname -> the library its message names)."""
    asked = []

    def load(soname):
        asked.append(soname)
        if soname in missing:
            raise OSError(f"{missing[soname]}: cannot open shared object file: No such file or directory")

    load.asked = asked
    return load


@linux_xcb
def test_needed_sonames_reads_the_plugins_elf_entries():
    plugin_needs = needed_sonames(PLUGIN)
    assert "libQt6XcbQpa.so.6" in plugin_needs and "libc.so.6" in plugin_needs
    qpa_needs = needed_sonames(QT / "lib" / "libQt6XcbQpa.so.6")
    # The two the Debian lacked, and the one Qt's own message named.
    assert {"libxcb-icccm.so.4", "libxcb-keysyms.so.1", "libxcb-cursor.so.0"} <= set(qpa_needs)
    assert all(s in SONAME_PACKAGES for s in qpa_needs if s.startswith(("libxcb", "libX", "libxkb")))
    with pytest.raises(ValueError, match="not an ELF file"):
        needed_sonames(Path(__file__))


@linux_xcb
def test_a_missing_library_is_named_with_its_package(tmp_path):
    # libxcb-icccm.so.4 is missing; libxcb-image.so.0 is there but its own libxcb-util.so.1 is not.
    load = _loader({"libxcb-icccm.so.4": "libxcb-icccm.so.4", "libxcb-image.so.0": "libxcb-util.so.1"})
    problem = startup_problem({"DISPLAY": ":0"}, QT, load)
    assert "\n" not in problem
    assert "libxcb-icccm.so.4, libxcb-util.so.1" in problem, problem
    assert "sudo apt install libxcb-icccm4 libxcb-util1" in problem and "libxcb-image0" not in problem
    assert not any(s.startswith("libQt6") for s in load.asked)  # the wheel's own libraries are not asked for
    assert missing_sonames([PLUGIN], QT / "lib", _loader({})) == []


def test_nothing_is_demanded_of_x11_on_wayland_or_offscreen():
    nothing_loads = _loader({s: s for s in SONAME_PACKAGES})
    for env in ({"QT_QPA_PLATFORM": "wayland"}, {"QT_QPA_PLATFORM": "offscreen"},
                {"QT_QPA_PLATFORM": "wayland;xcb"}, {"WAYLAND_DISPLAY": "wayland-0"},
                {"WAYLAND_DISPLAY": "wayland-0", "XDG_SESSION_TYPE": "wayland"}):
        assert qt_platform(env) != "xcb"
        assert startup_problem(env, QT, nothing_loads) is None, env
    assert qt_platform({"WAYLAND_DISPLAY": "wayland-0", "XDG_SESSION_TYPE": "x11"}) == "xcb"
    assert qt_platform({"QT_QPA_PLATFORM": "xcb"}) == qt_platform({}) == "xcb"


@linux_xcb
def test_no_display_is_said_so():
    problem = startup_problem({}, QT, _loader({}))
    assert problem.startswith("no display to connect to (DISPLAY is not set, no Wayland session)")
    problem = startup_problem({"DISPLAY": ":93"}, QT, _loader({}))  # no X server there
    assert problem == "the X display ':93' (DISPLAY) does not answer"


def test_start_without_a_display_exits_2_with_one_line():
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM")}
    r = subprocess.run([sys.executable, "-m", "ptp_studio"], env=env, capture_output=True, text=True, timeout=120)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("ptp-studio: cannot open a window: "), r.stderr
    assert "DISPLAY is not set" in lines[0] and "qt.qpa" not in r.stderr
