"""Entry script of the PyInstaller build (the installed one is the `ptp-studio` console script)."""

import sys

from ptp_studio.__main__ import main

if __name__ == "__main__":
    sys.exit(main())
