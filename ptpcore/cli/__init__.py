"""The ``ptp`` command line: one thin layer over one engine call per subcommand.

- :mod:`.main` — the parser and the calibration, inspection and comparison commands;
- :mod:`.capture` — ``ptp capture``;
- :mod:`.progress` — the progress bar every command draws.

The top layer: may import anything of the engine, and nothing imports it.
"""

from .main import main

__all__ = ["main"]
