"""Compare two HDF5 files (LUT, decoded samples, session) exactly, dataset by dataset and attribute by attribute.

    python -m benchmarks.lutcmp A.h5 B.h5 [--ignore NAME ...] [--all]

The command line of :func:`ptpcore.evaluate.lutcompare.compare_lut_files`, for the checks of
docs/performance.md ("the LUT is identical"): every group walked, dtypes, shapes and every element
equal (NaN equal to NaN). ``created`` and ``software`` are left out (``--all``: nothing is), and so
is every attribute or dataset named with ``--ignore`` (a name at any level, or a path such as
``/provenance@settings``). One line per difference, naming it, with the number of elements that
differ and the largest absolute difference for numeric arrays.

Exit status: 0 identical, 1 different, 2 a file that cannot be read.
"""

from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    from ptpcore.errors import FileFormatError
    from ptpcore.evaluate.lutcompare import DEFAULT_IGNORED, compare_lut_files

    ap = argparse.ArgumentParser(prog="python -m benchmarks.lutcmp", description=__doc__.splitlines()[0])
    ap.add_argument("a", help="first HDF5 file")
    ap.add_argument("b", help="second HDF5 file")
    ap.add_argument("--ignore", action="append", default=[], metavar="NAME",
                    help="an attribute or dataset name (any level) or path to leave out (repeatable)")
    ap.add_argument("--all", action="store_true", help=f"compare {' and '.join(DEFAULT_IGNORED)} too")
    args = ap.parse_args(argv)
    try:
        result = compare_lut_files(args.a, args.b, ignore=[*(() if args.all else DEFAULT_IGNORED), *args.ignore])
    except FileFormatError as exc:
        print(f"lutcmp: {exc}", file=sys.stderr)
        return 2
    print("\n".join(result.lines()))
    return 0 if result.equal else 1


if __name__ == "__main__":
    sys.exit(main())
