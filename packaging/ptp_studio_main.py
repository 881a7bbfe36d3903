"""Launcher of the PyInstaller bundle: one script for its two executables.

``ptp-studio`` starts the wizard (``ptp_studio.__main__``), ``ptp`` the command line
(``ptpcore.cli``): the executable's own file name picks which (an installed package has one
console script for each instead). Both executables being built from this one script keeps them
byte-identical, so numba's cache of the fused kernels, keyed on the frozen executable's content,
serves both.
"""

import multiprocessing
import os
import sys


def program(executable: str) -> str:
    """``"ptp"`` for the command line (``ptp``, ``ptp.exe``), ``"ptp-studio"`` for anything else."""
    stem = os.path.basename(executable).lower()
    if stem.endswith(".exe"):
        stem = stem[:-4]
    return "ptp" if stem == "ptp" else "ptp-studio"


def main() -> int:
    multiprocessing.freeze_support()
    if program(sys.executable) == "ptp":
        from ptpcore.cli import main as cli_main

        return cli_main()
    from ptp_studio.__main__ import main as studio_main

    return studio_main()


if __name__ == "__main__":
    sys.exit(main())
