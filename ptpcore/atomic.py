"""Atomic file writes: temporary file in the same folder, then rename.

A process killed at any moment leaves either the old file or the new one,
never a half-written one (``os.replace`` is atomic on POSIX and Windows when
source and target are on the same file system, hence the same folder).

Every temporary path in use is registered (:func:`live_temporaries`), so a
signal handler or a last ``finally`` can remove them (:func:`remove_temporaries`)
even when the exception that stopped the write never reached the writer. A
disk that fills during a write raises :class:`DiskFullError`
naming the file and the space it needs, the temporary file removed.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Iterator

from ptpcore.errors import PtpError


class DiskFullError(OSError, PtpError):
    """The disk filled while a file was written; nothing half-written is left.

    The message (one line) names the file and the space it needs. Both an
    ``OSError`` (``errno.ENOSPC``, for code that handles the system's errors)
    and a :class:`~ptpcore.errors.PtpError` (a user-facing error: the CLI and
    the GUI show it as one line).
    """

    def __str__(self) -> str:
        return self.strerror or super().__str__()


_LIVE: set[Path] = set()
_LIVE_LOCK = threading.Lock()
_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EFBIG}


def register_temporary(path: str | os.PathLike) -> None:
    """Register a temporary file to be removed by :func:`remove_temporaries`."""
    with _LIVE_LOCK:
        _LIVE.add(Path(path))


def forget_temporary(path: str | os.PathLike) -> None:
    """The temporary file was renamed or removed by its owner: forget it."""
    with _LIVE_LOCK:
        _LIVE.discard(Path(path))


def live_temporaries() -> list[Path]:
    """Temporary files being written right now (registered, not yet renamed or removed)."""
    with _LIVE_LOCK:
        return sorted(_LIVE)


def remove_temporaries() -> list[Path]:
    """Remove every registered temporary file (after a signal or a failure); return those removed."""
    with _LIVE_LOCK:
        paths = sorted(_LIVE)
        _LIVE.clear()
    removed = []
    for p in paths:
        with contextlib.suppress(OSError):
            p.unlink()
            removed.append(p)
    return removed


# ---------------------------------------------------------------------------
# Temporary files of processes that were killed (SIGKILL, a power cut): a name says whose it is.
# On POSIX the spill files are unlinked at creation and need none of this; the atomic writes'
# ``.part`` files (h5py writes by path) and every temporary file on Windows carry their owner's
# process id and start time, and the next run that writes there removes those whose owner is gone.

def _start_token(pid: int) -> str | None:
    """When process ``pid`` started, as a short token, or None where this cannot be read.

    Linux: field 22 of ``/proc/PID/stat`` (clock ticks since boot), so that a process id reused by a
    later process is not taken for the owner. Elsewhere None: the owner is judged by its id alone.
    """
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return None
    # The command name (field 2) may hold spaces and parentheses: count fields after its last ')'.
    fields = stat[stat.rindex(b")") + 2:].split()
    return fields[19].decode() if len(fields) > 19 else None


def _pid_alive(pid: int) -> bool:
    if os.name == "nt":  # pragma: no cover - Windows: os.kill(pid, 0) would terminate the process
        import ctypes

        handle = ctypes.windll.kernel32.OpenProcess(0x1000, False, pid)  # QUERY_LIMITED_INFORMATION
        if not handle:
            return False
        code = ctypes.c_ulong()
        ctypes.windll.kernel32.GetExitCodeProcess(handle, ctypes.byref(code))
        ctypes.windll.kernel32.CloseHandle(handle)
        return code.value == 259  # STILL_ACTIVE
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True


def _own_tag() -> str:
    return f"{os.getpid()}-{_start_token(os.getpid()) or 0}"


_OWNER = _own_tag()
_SWEPT: set[tuple[str, str, str]] = set()  # (folder, prefix, suffix) this process has swept already


def _after_fork() -> None:
    global _OWNER
    _OWNER = _own_tag()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork)


def owner_tag() -> str:
    """``PID-START`` of this process, put into the names of its temporary files."""
    return _OWNER


def _owner_gone(tag: str) -> bool:
    pid_text, _, start = tag.partition("-")
    if not pid_text.isdigit() or not start.isdigit():
        return False  # not a name of ours: never touched
    pid = int(pid_text)
    if pid != os.getpid() and not _pid_alive(pid):
        return True
    now = _start_token(pid)
    return start != "0" and now is not None and now != start  # the id was reused by a later process


# ``PID-START-`` and mkstemp's 8 random characters, at the end of the name (before the suffix).
_OWNED = re.compile(r"(?:^|\.)(\d+-\d+)-[a-z0-9_]{8}$")


def sweep_orphans(folder: str | os.PathLike, prefix: str, suffix: str = "") -> list[Path]:
    """Remove this user's temporary files ``{prefix}...PID-START-XXXXXXXX{suffix}`` in ``folder``
    whose process is gone; return those removed. Files of running processes, of other users and
    of other names are left alone."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    uid = os.getuid() if hasattr(os, "getuid") else None
    for entry in entries:
        name = entry.name
        if not (name.startswith(prefix) and name.endswith(suffix)):
            continue
        tag = _OWNED.search(name[len(prefix):len(name) - len(suffix)])
        if tag is None:
            continue
        try:
            mine = uid is None or entry.stat(follow_symlinks=False).st_uid == uid
        except OSError:
            continue
        if mine and entry.is_file(follow_symlinks=False) and _owner_gone(tag.group(1)):
            with contextlib.suppress(OSError):
                os.unlink(entry.path)
                removed.append(Path(entry.path))
    return removed


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` is an out-of-space error (ENOSPC, EDQUOT, EFBIG; h5py's wrapped ones too)."""
    if isinstance(exc, DiskFullError):
        return True
    if isinstance(exc, OSError) and exc.errno in _FULL:
        return True
    text = str(exc)
    return "No space left on device" in text or "errno = 28," in text


def disk_full_error(target: str | os.PathLike, need_bytes: int | None = None, hint: str = "") -> DiskFullError:
    """The one-line :class:`DiskFullError` for ``target`` (the space needed and the space free).

    Parameters
    ----------
    target : path
        The file that did not fit.
    need_bytes : int, optional
        Its size.
    hint : str, optional
        What the file is and what to do, appended in parentheses.
    """
    target = Path(target)
    folder = target.parent if not target.is_dir() else target
    try:
        free = f", {_mb(shutil.disk_usage(folder).free)} free in {folder}"
    except OSError:
        free = ""
    need = f"it needs {_mb(need_bytes)}" if need_bytes else "it needs more space"
    hint = f" ({hint})" if hint else ""
    return DiskFullError(errno.ENOSPC, f"{target}: disk full while writing ({need}{free});"
                                       f" nothing was left half-written{hint}")


def _mb(n: int | None) -> str:
    return f"{(n or 0) / 1e6:.1f} MB"


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, need_bytes: int | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success rename it over ``target``.

    Parameters
    ----------
    target : path
        The file to write.
    need_bytes : int, optional
        The file's size, if known: named by the disk-full message.

    Raises
    ------
    DiskFullError
        The disk filled (the temporary file is removed).

    Notes
    -----
    On any exception (including :class:`KeyboardInterrupt`, a SIGTERM turned
    into one, and cancellation) the temporary file is removed and ``target``
    is left untouched.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    key = (str(target.parent), ".", ".part")
    if key not in _SWEPT:  # once per folder and process: capture writes thousands of files into a few
        _SWEPT.add(key)
        sweep_orphans(*key)  # left in this folder by killed runs
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.{owner_tag()}-", suffix=".part", dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    register_temporary(tmp_path)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        # mkstemp creates 0600: give the file the mode it replaces, or what a plain open() gives.
        with contextlib.suppress(OSError):
            os.chmod(tmp_path, _file_mode(target))
        os.replace(tmp_path, target)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        if is_disk_full(exc) and not isinstance(exc, DiskFullError):
            raise disk_full_error(target, need_bytes) from None
        raise
    finally:
        forget_temporary(tmp_path)


def _read_umask() -> int:
    mask = os.umask(0o022)  # the only way to read it; done once, at import, before any threads write
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def _file_mode(target: Path) -> int:
    """The mode of the file being replaced, else ``0o666`` minus the umask."""
    try:
        return target.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_UMASK


def write_text_atomic(target: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_bytes_atomic(target: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``target`` atomically."""
    with atomic_path(target, need_bytes=len(data)) as tmp:
        tmp.write_bytes(data)
