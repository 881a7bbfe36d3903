"""The progress bar every ``ptp`` command draws (tqdm on stderr), as a ``progress(fraction, message)`` callback."""

from __future__ import annotations

import sys

from ptpcore.cli.safety import raise_if_terminated

__all__ = ["ProgressBar", "progress_bar"]


class ProgressBar:
    """A ``progress(fraction, message)`` callback drawn with tqdm on stderr."""

    def __init__(self, enabled: bool = True):
        from tqdm import tqdm

        self._bar = tqdm(total=1000, disable=not enabled, leave=False, file=sys.stderr,
                         bar_format="{desc:<44.44} {percentage:3.0f}%|{bar}| {elapsed}")

    def __call__(self, fraction: float, message: str) -> None:
        raise_if_terminated()  # a SIGTERM whose exception a C callback swallowed stops the job here
        self._bar.n = int(round(1000 * min(max(fraction, 0.0), 1.0)))
        self._bar.set_description_str(message, refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        self._bar.close()


def progress_bar(args) -> ProgressBar:
    """The progress bar of one command: drawn on a terminal, silent with ``--quiet`` or when piped."""
    return ProgressBar(enabled=not getattr(args, "quiet", False) and sys.stderr.isatty())
