"""Output paths checked before the work starts.

A long job that ends by refusing to write its result loses the engineer's
time; one that writes over its own input loses their data. Every command
checks each output path first (:func:`check_output_file`,
:func:`check_output_folder`): the folder exists and takes files, the path is
not a file of the input dataset, an existing file is of the same kind and is
replaced only when asked (``force``), a dataset folder is not written into
again by accident. Each refusal is one :class:`~ptpcore.errors.OutputError`
naming the path.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from ptpcore.errors import OutputError

__all__ = ["KINDS", "check_output_file", "check_output_folder", "file_kind", "dataset_marker"]

KINDS = {"lut": "ptp-lut/1", "session": "ptp-session/1", "report": "comparison report (JSON)",
         "points": "ptp-points/1", "png": "PNG image"}
"""The kinds of file a command writes, and the format each existing file must have to be replaced."""

_DATASET_MARKERS = ("rig.toml", "capture-state.json", "truth.h5")


def file_kind(path: Path) -> str | None:
    """The kind of an existing file: ``"lut"``, ``"session"``, ``"report"``, ``"points"``, ``"png"`` or None
    (another)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
    except OSError:
        return None
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        return _hdf5_kind(path)
    if head.startswith(b"ply\n") or head.startswith(b"\x93NUMPY"):
        return "points"  # a point cloud as ptp apply writes it (PLY, .npy)
    if head.lstrip()[:1] == b"{" and path.suffix.lower() == ".json":
        return "report"
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"  # a page of plots (ptp acceptance)
    return None


def _hdf5_kind(path: Path) -> str | None:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format", "")
    except (OSError, ValueError):
        return None
    fmt = fmt.decode() if isinstance(fmt, bytes) else str(fmt)
    for kind, name in KINDS.items():
        if fmt == name or fmt.startswith(name.split("/")[0] + "/"):
            return kind
    return None


def dataset_marker(folder: Path) -> str | None:
    """The file that makes ``folder`` a dataset (``rig.toml``, a capture's state, ``truth.h5``), or None."""
    for name in _DATASET_MARKERS:
        if (folder / name).exists():
            return name
    return None


def _writable_folder(folder: Path, what: str) -> None:
    """``folder`` exists, is a folder and takes a new file (tried, not guessed from the mode bits)."""
    if not folder.exists():
        raise OutputError(f"{what}: the folder {folder} does not exist")
    if not folder.is_dir():
        raise OutputError(f"{what}: {folder} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".ptp-write-test-", dir=folder)
    except OSError as exc:
        raise OutputError(f"{what}: cannot write in {folder} ({exc.strerror or exc})") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.relative_to(folder)
        return True
    except ValueError:
        return False


def check_output_file(path, kind: str, *, force: bool = False, inputs=()) -> Path:
    """Check an output file before the work starts.

    Parameters
    ----------
    path : path
        The file the command will write.
    kind : {"lut", "session", "report", "points", "png"}
        What it writes there.
    force : bool
        Replace an existing file of the same kind.
    inputs : iterable of paths
        Input dataset folders and files: never written over, ``force`` or not.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    OutputError
        The path is a folder, its folder is missing or read-only, it is a file
        of an input, or an existing file that must not be replaced.
    """
    path = Path(path)
    label = {"report": "report", "points": "point cloud", "png": "page of plots (PNG)"}.get(kind, KINDS[kind])
    if path.is_dir():
        raise OutputError(f"{path}: is a folder; give a file name for the {label}")
    real = path.resolve()
    for src in inputs:
        src = Path(src).resolve()
        if path.exists() and (real == src or (src.is_dir() and _inside(real, src))):
            raise OutputError(f"{path}: is a file of the input {src}; write the {label} elsewhere")
    _writable_folder(path.parent if str(path.parent) else Path("."), str(path))
    if path.exists():
        found = file_kind(path)
        if found != kind:
            what = f"a {KINDS[found]} file" if found in ("lut", "session", "points") else "another kind of file"
            raise OutputError(f"{path}: exists and is {what}, not a {label}; choose another name")
        if not force:
            raise OutputError(f"{path}: exists; add --force to replace it")
    return path


def check_output_folder(folder, *, force: bool = False, resume: bool = False, inputs=()) -> Path:
    """Check an output dataset folder before the work starts.

    Parameters
    ----------
    folder : path
        The folder a dataset will be written into (created if missing; its
        nearest existing parent must take files).
    force : bool
        Write into a folder that already holds a dataset.
    resume : bool
        The folder's dataset is being continued (``ptp capture --resume``).
    inputs : iterable of paths
        Inputs that must not be written into.

    Returns
    -------
    Path
        ``folder``.

    Raises
    ------
    OutputError
        A file, not a folder; no writable parent; already a dataset.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{folder}: is a file, not a folder")
    for src in inputs:
        if folder.resolve() == Path(src).resolve():
            raise OutputError(f"{folder}: is the input dataset; write into another folder")
    parent = folder
    while not parent.exists():
        parent = parent.parent
    _writable_folder(parent, str(folder))
    marker = dataset_marker(folder) if folder.is_dir() else None
    if marker and not (force or resume):
        raise OutputError(f"{folder}: already holds a dataset ({marker}); choose an empty folder"
                          " or add --force to write over it")
    return folder
