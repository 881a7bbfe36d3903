"""Two LUT files compared exactly, dataset by dataset and attribute by attribute.

Every group of both HDF5 files is walked. Two datasets (or attributes) are equal when their dtypes
and shapes are and every element is equal (``==``, with NaN equal to NaN); strings are compared as
text. A member of one file only, a group in one and a dataset in the other, a dtype, a shape or a
value that differs is one line of :attr:`LutComparison.differences`, which names the dataset or
attribute and, for numbers, how many elements differ and the largest absolute difference.

Names or paths listed in ``ignore`` are left out: a bare name (``"created"``) matches an attribute,
dataset or group of that name anywhere; a path matches one object (``"/provenance/settings"``, a
group and everything in it) or one attribute (``"/provenance@settings"``, or
``"/provenance/settings"`` for the attribute ``settings`` of ``/provenance``). By default the time of
writing (``created``) and the writing program's version (``software``) are left out.

Works on any HDF5 files (LUTs, decoded maps, session files); the shape of a LUT is not checked.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import h5py
import numpy as np

from ptpcore.errors import FileFormatError

__all__ = ["DEFAULT_IGNORED", "LutComparison", "compare_lut_files"]

DEFAULT_IGNORED = ("created", "software")
"""Left out unless asked otherwise: the time of writing and the writing program's version."""


@dataclass(frozen=True)
class LutComparison:
    """The result of :func:`compare_lut_files`.

    Attributes
    ----------
    a, b : str
        The two files, as given.
    differences : list of str
        One line per difference, in the order the files are walked (attributes of a group, then its
        members by name); empty when the files are equal.
    ignored : tuple of str
        The names and paths that were left out.
    """

    a: str
    b: str
    differences: list[str] = field(default_factory=list)
    ignored: tuple[str, ...] = DEFAULT_IGNORED

    @property
    def equal(self) -> bool:
        """True when no dataset or attribute differs (the ignored ones aside)."""
        return not self.differences

    def lines(self) -> list[str]:
        """Text lines: every difference, then one summary line (``identical: A vs B`` or
        ``N difference(s): A vs B``)."""
        verdict = "identical" if self.equal else f"{len(self.differences)} difference(s)"
        return [*self.differences, f"{verdict}: {self.a} vs {self.b}"]


def compare_lut_files(a, b, *, ignore=DEFAULT_IGNORED) -> LutComparison:
    """Compare two LUT (or any HDF5) files exactly, every group, dataset and attribute.

    Parameters
    ----------
    a, b : str or path-like
        The two files.
    ignore : iterable of str
        Attribute, dataset or group names (anywhere) or paths (``/group/name``, ``/group@attr``) to
        leave out; default :data:`DEFAULT_IGNORED`. Pass ``()`` to compare everything.

    Returns
    -------
    LutComparison

    Raises
    ------
    FileFormatError
        A file that cannot be opened as HDF5 (the message names it).
    """
    ignore = tuple(ignore)
    keys = frozenset(ignore)
    with _open(a) as fa, _open(b) as fb:
        differences = _compare_groups(fa, fb, keys, "/")
    return LutComparison(str(a), str(b), differences, ignore)


def _open(path) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except (OSError, ValueError) as exc:
        raise FileFormatError(f"{path}: not readable as an HDF5 file ({exc})") from None


def _skipped(name: str, path: str, keys: frozenset) -> bool:
    """Whether the object ``path`` (named ``name``) is left out."""
    return name in keys or path in keys


def _attr_skipped(owner: str, name: str, keys: frozenset) -> bool:
    """Whether the attribute ``name`` of the object at ``owner`` is left out."""
    return name in keys or f"{owner}@{name}" in keys or f"{owner.rstrip('/')}/{name}" in keys


def _compare_attrs(path: str, a, b, keys: frozenset) -> list[str]:
    names_a = {n for n in a.attrs if not _attr_skipped(path, n, keys)}
    names_b = {n for n in b.attrs if not _attr_skipped(path, n, keys)}
    out = [f"attribute {path}@{n}: only in A" for n in sorted(names_a - names_b)]
    out += [f"attribute {path}@{n}: only in B" for n in sorted(names_b - names_a)]
    for n in sorted(names_a & names_b):
        out += _compare_values(f"attribute {path}@{n}", a.attrs[n], b.attrs[n])
    return out


def _compare_groups(a: h5py.Group, b: h5py.Group, keys: frozenset, path: str) -> list[str]:
    """Every difference between two groups at ``path``, recursively."""
    out = _compare_attrs(path, a, b, keys)
    prefix = path.rstrip("/") + "/"
    names_a = {n for n in a.keys() if not _skipped(n, prefix + n, keys)}
    names_b = {n for n in b.keys() if not _skipped(n, prefix + n, keys)}
    out += [f"{prefix}{n}: only in A" for n in sorted(names_a - names_b)]
    out += [f"{prefix}{n}: only in B" for n in sorted(names_b - names_a)]
    for n in sorted(names_a & names_b):
        ia, ib, sub = a[n], b[n], prefix + n
        if isinstance(ia, h5py.Group) and isinstance(ib, h5py.Group):
            out += _compare_groups(ia, ib, keys, sub)
        elif isinstance(ia, h5py.Dataset) and isinstance(ib, h5py.Dataset):
            out += _compare_attrs(sub, ia, ib, keys)
            out += _compare_values(f"dataset {sub}", ia[()], ib[()])
        else:
            out.append(f"{sub}: a {_kind(ia)} in A, a {_kind(ib)} in B")
    return out


def _kind(obj) -> str:
    return "group" if isinstance(obj, h5py.Group) else "dataset" if isinstance(obj, h5py.Dataset) else "link"


def _as_array(value) -> np.ndarray:
    """An attribute or dataset value as an array (strings, bytes and object arrays as their text)."""
    if isinstance(value, (str, bytes)):
        return np.array([_text(value)], dtype=object)
    a = np.asarray(value)
    if a.dtype.kind in "OSU":
        return np.array([_text(v) for v in a.ravel().tolist()], dtype=object).reshape(a.shape)
    return a


def _text(v) -> str:
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


def _compare_values(what: str, a, b) -> list[str]:
    """The difference between two values named ``what`` (dataset contents or attributes), as lines.

    Returns ``[]`` when their dtypes (strings aside: text equals text), shapes and elements are equal,
    NaN equal to NaN.
    """
    a, b = _as_array(a), _as_array(b)
    if a.dtype != b.dtype:
        return [f"{what}: dtype {a.dtype} != {b.dtype}"]
    if a.shape != b.shape:
        return [f"{what}: shape {a.shape} != {b.shape}"]
    if a.dtype.kind == "O":
        differ = int(np.sum(a != b))
        return [f"{what}: {differ} of {a.size} strings differ"] if differ else []
    if a.dtype.fields is not None or a.dtype.kind not in "biufc":
        same = a.tobytes() == b.tobytes()  # compound or opaque data: bytes are its only equality
        return [] if same else [f"{what}: values differ"]
    return _numeric(what, a, b)


def _numeric(what: str, a: np.ndarray, b: np.ndarray) -> list[str]:
    """``n of N elements differ, largest |A - B| = x`` for two numeric arrays of one dtype and shape."""
    with np.errstate(invalid="ignore", over="ignore"):
        if a.dtype.kind in "fc":
            nan_a, nan_b = np.isnan(a), np.isnan(b)
            differ = (a != b) & ~(nan_a & nan_b)
        else:
            nan_a = nan_b = np.zeros(a.shape, bool)
            differ = a != b
        n_diff = int(np.sum(differ))
        if not n_diff:
            return []
        d = np.abs(a[differ & ~nan_a & ~nan_b].astype(np.complex128 if a.dtype.kind == "c" else np.float64)
                   - b[differ & ~nan_a & ~nan_b])
    finite = d[np.isfinite(d)]
    largest = f"{float(finite.max()):.6g}" if finite.size else "n/a"
    text = f"{what}: {n_diff} of {a.size} elements differ, largest |A - B| = {largest}"
    mismatch = int(np.sum(nan_a != nan_b))
    return [text + (f", NaN in one only at {mismatch}" if mismatch else "")]
