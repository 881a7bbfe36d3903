"""Can Qt open a window here? Asked before Qt is loaded, so a missing piece is one line, not Qt's abort.

Without a display, or without a system library its X11 platform plugin needs, Qt prints a few lines
that name the wrong thing (``xcb-cursor0`` when ``libxcb-icccm4`` and ``libxcb-keysyms1`` were missing)
and aborts the process (exit 134). :func:`startup_problem` finds what is missing from the xcb
plugin's own dependencies (the ELF ``DT_NEEDED`` entries of ``libqxcb.so`` and Qt's ``libQt6XcbQpa``,
each given to the dynamic loader) and whether the display answers, and says it in one line with the
Debian/Ubuntu packages to install (docs/install.md, "System packages for the wizard").

Nothing here imports Qt: only the files of the installed PySide6 wheel are read.
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
import struct
import sys
from pathlib import Path
from typing import Callable, Mapping

__all__ = ["SONAME_PACKAGES", "needed_sonames", "missing_sonames", "qt_platform", "startup_problem"]

#: Debian/Ubuntu package of each library the xcb plugin (and Qt's X11 support) loads.
SONAME_PACKAGES = {
    "libxcb-cursor.so.0": "libxcb-cursor0", "libxcb-icccm.so.4": "libxcb-icccm4",
    "libxcb-keysyms.so.1": "libxcb-keysyms1", "libxcb-image.so.0": "libxcb-image0",
    "libxcb-render-util.so.0": "libxcb-render-util0", "libxcb-util.so.1": "libxcb-util1",
    "libxcb-randr.so.0": "libxcb-randr0", "libxcb-shape.so.0": "libxcb-shape0",
    "libxcb-shm.so.0": "libxcb-shm0", "libxcb-sync.so.1": "libxcb-sync1", "libxcb-xfixes.so.0": "libxcb-xfixes0",
    "libxcb-render.so.0": "libxcb-render0", "libxcb-xkb.so.1": "libxcb-xkb1",
    "libxcb-xinerama.so.0": "libxcb-xinerama0", "libxcb.so.1": "libxcb1", "libX11-xcb.so.1": "libx11-xcb1",
    "libX11.so.6": "libx11-6", "libxkbcommon.so.0": "libxkbcommon0", "libxkbcommon-x11.so.0": "libxkbcommon-x11-0",
    "libGL.so.1": "libgl1", "libEGL.so.1": "libegl1", "libfontconfig.so.1": "libfontconfig1",
    "libglib-2.0.so.0": "libglib2.0-0", "libgthread-2.0.so.0": "libglib2.0-0", "libdbus-1.so.3": "libdbus-1-3",
}

_DT_NEEDED, _DT_STRTAB, _PT_DYNAMIC = 1, 5, 2


def needed_sonames(path) -> list[str]:
    """The ``DT_NEEDED`` entries (sonames) of the ELF shared object ``path``, in file order.

    Raises
    ------
    ValueError
        If ``path`` is not a 64- or 32-bit ELF file.
    """
    data = Path(path).read_bytes()
    if data[:4] != b"\x7fELF":
        raise ValueError(f"{path}: not an ELF file")
    wide, end = data[4] == 2, "<" if data[5] == 1 else ">"
    if wide:
        phoff, phentsize, phnum = struct.unpack_from(end + "Q", data, 32)[0], *struct.unpack_from(end + "HH", data, 54)
    else:
        phoff, phentsize, phnum = struct.unpack_from(end + "I", data, 28)[0], *struct.unpack_from(end + "HH", data, 42)
    segments = []  # (type, offset, vaddr, filesz)
    for i in range(phnum):
        at = phoff + i * phentsize
        if wide:
            p_type, _flags, off, vaddr, _paddr, filesz = struct.unpack_from(end + "IIQQQQ", data, at)
        else:
            p_type, off, vaddr, _paddr, filesz = struct.unpack_from(end + "IIIII", data, at)
        segments.append((p_type, off, vaddr, filesz))
    dynamic = next((s for s in segments if s[0] == _PT_DYNAMIC), None)
    if dynamic is None:
        return []
    entry = struct.Struct(end + ("qQ" if wide else "iI"))
    needed, strtab = [], None
    for at in range(dynamic[1], dynamic[1] + dynamic[3], entry.size):
        tag, value = entry.unpack_from(data, at)
        if tag == 0:
            break
        if tag == _DT_NEEDED:
            needed.append(value)
        elif tag == _DT_STRTAB:
            strtab = value
    if strtab is None:
        return []
    # DT_STRTAB is a virtual address: the file offset of the loadable segment that holds it.
    base = next(off - vaddr for p_type, off, vaddr, filesz in segments
                if p_type == 1 and vaddr <= strtab < vaddr + filesz)
    start = strtab + base
    return [data[start + n:data.index(b"\0", start + n)].decode() for n in needed]


def _dlopen(soname: str) -> None:
    ctypes.CDLL(soname)


def missing_sonames(objects, bundled: Path, load: Callable[[str], None] = _dlopen) -> list[str]:
    """The system libraries ``objects`` (ELF files) need that the dynamic loader cannot find.

    Parameters
    ----------
    objects : iterable of Path
    bundled : Path
        The wheel's own library folder (found through the objects' RPATH, never asked of the loader).
    load : callable
        Loads a soname, raising OSError with the loader's message when it fails (default: ``dlopen``).
        A library that exists but whose own dependency is missing names that dependency: it is the
        one reported.
    """
    missing: list[str] = []
    for obj in objects:
        for soname in needed_sonames(obj):
            if (bundled / soname).exists() or soname in missing:
                continue
            try:
                load(soname)
            except OSError as exc:
                # "libxcb-util.so.1: cannot open shared object file: ..." (the first name is the missing one)
                name = str(exc).split(":", 1)[0].strip()
                name = Path(name).name if name.startswith(("lib", "/")) else soname
                if name not in missing:
                    missing.append(name)
    return missing


def qt_platform(env: Mapping[str, str]) -> str:
    """The platform plugin Qt will try first: ``QT_QPA_PLATFORM``'s first name, else ``wayland`` in a
    Wayland session (WAYLAND_DISPLAY set and XDG_SESSION_TYPE not ``x11``), else ``xcb``."""
    chosen = env.get("QT_QPA_PLATFORM", "").strip()
    if chosen:
        return chosen.split(";")[0].split(":")[0].strip().lower()
    if env.get("WAYLAND_DISPLAY") and env.get("XDG_SESSION_TYPE", "wayland").lower() != "x11":
        return "wayland"
    return "xcb"


def _qt_folder() -> Path | None:
    spec = importlib.util.find_spec("PySide6")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0]) / "Qt"


def _x_display_answers(display: str) -> bool:
    """Whether an X server answers at ``display`` (libxcb's own connect, then disconnect)."""
    xcb = ctypes.CDLL("libxcb.so.1")
    xcb.xcb_connect.restype = ctypes.c_void_p
    xcb.xcb_connect.argtypes = [ctypes.c_char_p, ctypes.c_void_p]
    xcb.xcb_connection_has_error.argtypes = [ctypes.c_void_p]
    xcb.xcb_disconnect.argtypes = [ctypes.c_void_p]
    conn = xcb.xcb_connect(display.encode(), None)
    try:
        return conn is not None and xcb.xcb_connection_has_error(conn) == 0
    finally:
        if conn is not None:
            xcb.xcb_disconnect(conn)


def startup_problem(env: Mapping[str, str] | None = None, qt: Path | None = None,
                    load: Callable[[str], None] = _dlopen) -> str | None:
    """Why Qt could not open a window here, in one line (None: it can, or it is not ours to check).

    Checked only on Linux with the xcb platform: Wayland, offscreen and the others demand nothing
    of X11, and the Windows and macOS wheels bring what they need.
    """
    env = os.environ if env is None else env
    if not sys.platform.startswith("linux") or qt_platform(env) != "xcb":
        return None
    qt = qt or _qt_folder()
    plugin = None if qt is None else qt / "plugins" / "platforms" / "libqxcb.so"
    problems = []
    if plugin is not None and plugin.is_file():
        objects = [plugin, *(qt / "lib" / name for name in needed_sonames(plugin) if (qt / "lib" / name).is_file()
                             and "Xcb" in name)]
        missing = missing_sonames(objects, qt / "lib", load)
        if missing:
            packages = " ".join(dict.fromkeys(SONAME_PACKAGES.get(s, s) for s in missing))
            problems.append(f"Qt's X11 platform needs system libraries that are missing ({', '.join(missing)}):"
                            f" install them, e.g. `sudo apt install {packages}` on Debian/Ubuntu")
    display = env.get("DISPLAY", "")
    if not display:
        problems.append("no display to connect to (DISPLAY is not set, no Wayland session): start it in a"
                        " desktop session, with `ssh -X`, or under `xvfb-run`")
    elif not problems and not _x_display_answers(display):
        problems.append(f"the X display {display!r} (DISPLAY) does not answer")
    return "; ".join(problems) or None
