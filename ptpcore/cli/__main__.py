"""``python -m ptpcore.cli``: the ``ptp`` command."""

import sys

from ptpcore.cli.main import main

sys.exit(main())
