"""Compare two HDF5 files (LUT, decoded samples, session) bit for bit, dataset by dataset and attribute by attribute.

    python -m benchmarks.lutcmp A.h5 B.h5 [--ignore NAME ...]

Every group is walked recursively. Two datasets are equal when their dtype, shape and raw bytes are
(NaN equals NaN only with the same bits); two attributes when their values are, bit for bit for
numbers. The root attribute ``created`` (the time of writing) is left out, and so is every
attribute named with ``--ignore`` (at any level). One line per difference, with the number of
elements that differ and the largest absolute difference for numeric arrays.

Exit status: 0 identical, 1 different, 2 a file that cannot be read.
"""

from __future__ import annotations

import argparse
import sys

import h5py
import numpy as np

ALWAYS_IGNORED_ROOT_ATTRS = ("created",)


def _as_array(value) -> np.ndarray:
    """An attribute or dataset value as an array whose bytes can be compared (strings as UTF-8 bytes)."""
    if isinstance(value, str):
        return np.frombuffer(value.encode("utf-8"), np.uint8)
    a = np.asarray(value)
    if a.dtype.kind == "O":  # variable-length strings or references: compare their text
        return np.frombuffer(repr([v.decode("utf-8", "replace") if isinstance(v, bytes) else v
                                   for v in a.ravel().tolist()]).encode("utf-8"), np.uint8)
    return a


def _numeric_summary(a: np.ndarray, b: np.ndarray) -> str:
    """``n of N elements differ, largest |A - B| = x`` for two numeric arrays of one shape."""
    fa, fb = a.astype(np.float64, copy=False), b.astype(np.float64, copy=False)
    bits_differ = a.view(np.uint8).reshape(a.size, -1) != b.view(np.uint8).reshape(b.size, -1) if a.size else None
    n_diff = int(bits_differ.any(axis=1).sum()) if bits_differ is not None else 0
    with np.errstate(invalid="ignore", over="ignore"):
        d = np.abs(fa - fb)
    nan_a, nan_b = np.isnan(fa), np.isnan(fb)
    nan_mismatch = int((nan_a != nan_b).sum())
    nan_bits = int((nan_a & nan_b & bits_differ.any(axis=1).reshape(a.shape)).sum()) if a.size else 0
    finite = d[np.isfinite(d)]
    largest = f"{finite.max():.6g}" if finite.size else "n/a"
    text = f"{n_diff} of {a.size} elements differ, largest |A - B| = {largest}"
    text += f", NaN in one only at {nan_mismatch}" if nan_mismatch else ""
    return text + (f", NaN with other bits at {nan_bits}" if nan_bits else "")


def compare_values(what: str, a, b) -> list[str]:
    """The differences between two values (dataset contents or attributes): [] when bit-identical."""
    a, b = _as_array(a), _as_array(b)
    if a.dtype != b.dtype:
        return [f"{what}: dtype {a.dtype} != {b.dtype}"]
    if a.shape != b.shape:
        return [f"{what}: shape {a.shape} != {b.shape}"]
    if np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes():
        return []
    if a.dtype.kind in "biufc" and a.dtype.fields is None:
        return [f"{what}: {_numeric_summary(np.ascontiguousarray(a), np.ascontiguousarray(b))}"]
    return [f"{what}: values differ"]


def _compare_attrs(path: str, a, b, ignore: set[str]) -> list[str]:
    skip = set(ignore) | (set(ALWAYS_IGNORED_ROOT_ATTRS) if path == "/" else set())
    names_a, names_b = set(a.attrs) - skip, set(b.attrs) - skip
    out = [f"attribute {path}@{n}: only in A" for n in sorted(names_a - names_b)]
    out += [f"attribute {path}@{n}: only in B" for n in sorted(names_b - names_a)]
    for n in sorted(names_a & names_b):
        out += compare_values(f"attribute {path}@{n}", a.attrs[n], b.attrs[n])
    return out


def compare_groups(a: h5py.Group, b: h5py.Group, ignore: set[str], path: str = "/") -> list[str]:
    """Every difference between two groups, recursively (members, datasets, attributes)."""
    out = _compare_attrs(path.rstrip("/") or "/", a, b, ignore)
    names_a, names_b = set(a.keys()), set(b.keys())
    out += [f"{path}{n}: only in A" for n in sorted(names_a - names_b)]
    out += [f"{path}{n}: only in B" for n in sorted(names_b - names_a)]
    for n in sorted(names_a & names_b):
        ia, ib = a[n], b[n]
        sub = f"{path}{n}"
        if isinstance(ia, h5py.Group) and isinstance(ib, h5py.Group):
            out += compare_groups(ia, ib, ignore, sub + "/")
        elif isinstance(ia, h5py.Dataset) and isinstance(ib, h5py.Dataset):
            out += _compare_attrs(sub, ia, ib, ignore)
            out += compare_values(f"dataset {sub}", ia[()], ib[()])
        else:
            out.append(f"{sub}: a {type(ia).__name__} in A, a {type(ib).__name__} in B")
    return out


def compare_files(path_a, path_b, ignore=()) -> list[str]:
    """Every difference between two HDF5 files ([] when identical but for the ignored attributes)."""
    with h5py.File(path_a, "r") as a, h5py.File(path_b, "r") as b:
        return compare_groups(a, b, set(ignore))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.lutcmp", description=__doc__.splitlines()[0])
    ap.add_argument("a", help="first HDF5 file")
    ap.add_argument("b", help="second HDF5 file")
    ap.add_argument("--ignore", action="append", default=[], metavar="NAME",
                    help="an attribute name to leave out at every level (repeatable); the root's 'created' always is")
    args = ap.parse_args(argv)
    try:
        diffs = compare_files(args.a, args.b, args.ignore)
    except OSError as exc:
        print(f"lutcmp: cannot read {args.a} or {args.b} as HDF5: {exc}", file=sys.stderr)
        return 2
    for line in diffs:
        print(line)
    print(f"{'identical' if not diffs else f'{len(diffs)} difference(s)'}: {args.a} vs {args.b}")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
