"""The output guard: every path a command or a wizard action writes, checked before the work starts.

A long job that ends by refusing to write its result loses the engineer's
time; one that writes over its own input loses their data. Every output goes
through :func:`guard_outputs` (the CLI applies it to every argument marked as
an output, the wizard to every file it is about to save) before any decoding:

- an input of the command (an input file, any file inside an input dataset
  folder) is never written, ``force`` or not, nor an existing file of a
  dataset (a folder with ``rig.toml`` and position folders, a capture, a
  scan);
- an existing file is replaced only with ``force``, and never a file of
  another kind, judged by its content (the HDF5 ``format`` attribute, the
  JSON text, the PNG signature, the PLY header), not by its extension;
- an output file that is a folder, a missing parent folder, or a folder that
  does not take a new file (tried with a probe file, not guessed from mode
  bits) is refused;
- two outputs of one command never name the same file.

Each refusal is one :class:`~ptpcore.errors.OutputError` naming the path
(never an errno or a temporary file's name).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from ptpcore.errors import OutputError

__all__ = ["KINDS", "FOLDER", "PLAIN_FOLDER", "Output", "guard_outputs", "check_output_file", "check_output_folder",
           "file_kind", "dataset_marker", "dataset_of", "probe_writable"]

KINDS = {"lut": "ptp-lut/1", "session": "ptp-session/1", "decoded": "ptp-decoded/1",
         "points": "ptp-points/1", "report": "JSON report", "png": "PNG image", "rig": "rig file (TOML)"}
"""The kinds of file an output may be, and the name each is given in messages."""

FOLDER = "dataset"
"""The kind of an output that is a dataset folder (``ptp simulate OUT_DIR``, ``ptp capture --out``)."""

PLAIN_FOLDER = "folder"
"""The kind of an output folder to be created, or written into, file by file (the wizard's Export)."""

_LABELS = {"lut": "ptp-lut/1 file", "session": "ptp-session/1 file", "decoded": "ptp-decoded/1 file",
           "report": "JSON report", "points": "point cloud", "png": "PNG image", "rig": "rig file (TOML)"}
_HDF5_FAMILIES = {"ptp-lut": "lut", "ptp-session": "session", "ptp-decoded": "decoded", "ptp-points": "points"}
_DATASET_MARKERS = ("rig.toml", "capture-state.json", "truth.h5")
_POSITION_FOLDER = re.compile(r"z\d{3}$")
_JSON_LIMIT = 64 << 20  # a JSON file larger than this is not parsed to tell its kind


@dataclass(frozen=True)
class Output:
    """One path a command or an action will write.

    Attributes
    ----------
    path : Path
        The file (or, for ``kind == "dataset"``, the folder) to be written.
    kind : str
        A key of :data:`KINDS`, ``"dataset"`` for a dataset folder, or ``"folder"`` for a folder
        whose files are checked one by one once it exists (created if missing).
    name : str
        How the user gave it (``"--out"``, ``"OUT_DIR"``), for messages about two outputs.
    resume : bool
        A dataset folder whose dataset is being continued (``ptp capture --resume``).
    hint : str
        What the user can do when the output exists and may not be replaced (``{path}`` is
        filled in); default: add ``--force``.
    """

    path: Path
    kind: str
    name: str = ""
    resume: bool = False
    hint: str = ""


def file_kind(path) -> str | None:
    """The kind of an existing file, from its content: a key of :data:`KINDS`, or None (another kind).

    Parameters
    ----------
    path : path
        An existing file.

    Returns
    -------
    str or None
        ``"lut"``, ``"session"``, ``"decoded"``, ``"points"`` (HDF5 by its ``format``
        attribute; a PLY header; a ``.npy`` array), ``"report"`` (any JSON text),
        ``"png"`` (the PNG signature), ``"rig"`` (TOML with a ``[camera]`` table),
        or None for anything else.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError:
        return None
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        return _hdf5_kind(path)
    if head.startswith((b"ply\n", b"ply\r\n", b"\x93NUMPY")):
        return "points"  # a point cloud as ptp apply writes it (PLY, .npy)
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    return _text_kind(path)


def _hdf5_kind(path: Path) -> str | None:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format", "")
    except (OSError, ValueError):
        return None
    fmt = fmt.decode() if isinstance(fmt, bytes) else str(fmt)
    return _HDF5_FAMILIES.get(fmt.split("/")[0])


def _text_kind(path: Path) -> str | None:
    """``"report"`` for JSON text, ``"rig"`` for a rig file, else None."""
    try:
        if path.stat().st_size > _JSON_LIMIT:
            return None
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError):
        return None
    if text.lstrip()[:1] in ("{", "["):
        try:
            json.loads(text)
            return "report"
        except ValueError:
            return None
    import tomllib

    try:
        doc = tomllib.loads(text)
    except ValueError:
        return None
    return "rig" if isinstance(doc.get("camera"), dict) else None


def dataset_marker(folder: Path) -> str | None:
    """The file that makes ``folder`` a dataset (``rig.toml``, a capture's state, ``truth.h5``), or None."""
    for name in _DATASET_MARKERS:
        if (Path(folder) / name).exists():
            return name
    return None


def _is_dataset(folder: Path) -> bool:
    """A dataset's own folder: ``rig.toml`` beside position folders, a capture's state, or a scan."""
    if (folder / "capture-state.json").exists() or (folder / "scan.toml").exists():
        return True
    if not (folder / "rig.toml").exists():
        return False
    with contextlib.suppress(OSError):
        return any(p.is_dir() and _POSITION_FOLDER.match(p.name) for p in folder.iterdir())
    return False


def dataset_of(path, levels: int = 3) -> Path | None:
    """The dataset folder ``path`` lies in (its folder or up to ``levels`` above), or None."""
    folder = Path(path).resolve().parent
    for _ in range(levels):
        if _is_dataset(folder):
            return folder
        if folder.parent == folder:
            break
        folder = folder.parent
    return None


def probe_writable(folder: Path) -> None:
    """Create and remove a probe file in ``folder``; the OSError of a folder that does not take one."""
    fd, probe = tempfile.mkstemp(prefix=".ptp-write-test-", dir=folder)
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def _writable_folder(folder: Path, what: str) -> None:
    """``folder`` exists, is a folder and takes a new file (tried, not guessed from the mode bits)."""
    if not folder.exists():
        raise OutputError(f"{what}: the folder {folder} does not exist; create it first")
    if not folder.is_dir():
        raise OutputError(f"{what}: {folder} is not a folder")
    try:
        probe_writable(folder)
    except OSError as exc:  # the reason only: the probe's name means nothing to the user
        raise OutputError(f"{what}: cannot write in {folder} ({exc.strerror or type(exc).__name__})") from None


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.relative_to(folder)
        return True
    except ValueError:
        return False


def _label(kind: str) -> str:
    return _LABELS.get(kind, KINDS.get(kind, kind))


def _input_clash(path: Path, inputs: list[Path]) -> Path | None:
    """The input that ``path`` is, or lies in (existing files only), or None."""
    if not path.exists():
        return None
    real = path.resolve()
    for src in inputs:
        if real == src or (src.is_dir() and _inside(real, src)):
            return src
    return None


def _check_file(out: Output, inputs: list[Path], force: bool) -> None:
    path, label = Path(out.path), _label(out.kind)
    if path.is_dir():
        raise OutputError(f"{path}: is a folder; give a file name for the {label}")
    src = _input_clash(path, inputs)
    if src is not None:
        what = "is an input of this command" if path.resolve() == src else f"is a file of this command's input {src}"
        raise OutputError(f"{path}: {what}; write the {label} elsewhere")
    _writable_folder(path.parent, str(path))
    if not path.exists():
        return
    found = file_kind(path)
    if found != out.kind:
        what = f"a {_label(found)}" if found else "another kind of file"
        raise OutputError(f"{path}: exists and is {what}, not a {label}; choose another name")
    dataset = dataset_of(path)
    if dataset is not None:
        raise OutputError(f"{path}: is a file of the dataset {dataset}; write the {label} elsewhere")
    if not force:
        hint = out.hint.format(path=path) if out.hint else "add --force to replace it"
        raise OutputError(f"{path}: exists; {hint}")


def _check_folder(out: Output, inputs: list[Path], force: bool) -> None:
    folder = Path(out.path)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{folder}: is a file, not a folder; give a folder")
    real, dataset = folder.resolve(), out.kind == FOLDER
    for src in inputs:
        if real == src or (dataset and (_inside(real, src) or (src.parent == real and not out.resume))):
            raise OutputError(f"{folder}: is, or holds, an input of this command; write into another folder")
    _writable_folder(folder if folder.is_dir() else folder.parent, str(folder))
    marker = dataset_marker(folder) if folder.is_dir() else None
    if marker and not (force or out.resume):
        hint = out.hint.format(path=folder) if out.hint else "add --force to write over it"
        raise OutputError(f"{folder}: already holds a dataset ({marker}); choose an empty folder or {hint}")


def guard_outputs(outputs: Iterable[Output], *, inputs=(), force: bool = False) -> list[Path]:
    """Check every output of one command or action before the work starts.

    Parameters
    ----------
    outputs : iterable of Output
        What will be written (files, dataset folders).
    inputs : iterable of paths
        The command's input files and dataset folders: never written, ``force`` or not.
    force : bool
        Replace an existing file of the same kind; write into a folder that holds a dataset.

    Returns
    -------
    list of Path
        The outputs' paths, in order.

    Raises
    ------
    OutputError
        The first output refused, in one line naming it: an input or a file of
        a dataset; a folder where a file is due (or a file where a folder is);
        a missing or read-only folder; an existing file without ``force`` or of
        another kind; two outputs naming the same file.
    """
    outputs = [o if isinstance(o, Output) else Output(*o) for o in outputs]
    srcs = [Path(s).resolve() for s in inputs if s is not None and str(s) != ""]
    seen: dict[Path, Output] = {}
    for out in outputs:
        real = Path(out.path).resolve()
        if real in seen:
            a, b = seen[real].name or "one output", out.name or "another"
            raise OutputError(f"{out.path}: {a} and {b} name the same file")
        seen[real] = out
    # An output with its own advice first (an existing session file: `ptp resume` it rather than --force).
    for out in sorted(outputs, key=lambda o: not o.hint):
        if out.kind in (FOLDER, PLAIN_FOLDER):
            _check_folder(out, srcs, force or out.kind == PLAIN_FOLDER)
        else:
            _check_file(out, srcs, force)
    return [Path(o.path) for o in outputs]


def check_output_file(path, kind: str, *, force: bool = False, inputs=()) -> Path:
    """Check one output file before the work starts (:func:`guard_outputs` for one file).

    Parameters
    ----------
    path : path
        The file the command will write.
    kind : str
        A key of :data:`KINDS`: what it writes there.
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
        As :func:`guard_outputs`.
    """
    return guard_outputs([Output(Path(path), kind)], inputs=inputs, force=force)[0]


def check_output_folder(folder, *, force: bool = False, resume: bool = False, inputs=()) -> Path:
    """Check an output dataset folder before the work starts (:func:`guard_outputs` for one folder).

    Parameters
    ----------
    folder : path
        The folder a dataset will be written into (created if missing; its
        parent must exist and take files).
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
        As :func:`guard_outputs`.
    """
    return guard_outputs([Output(Path(folder), FOLDER, resume=resume)], inputs=inputs, force=force)[0]
