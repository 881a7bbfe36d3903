"""Progress reports: the one callable type every long engine step takes, and its sub-ranges.

A long step reports ``progress(fraction, message)`` with ``fraction`` in [0, 1]; the callable
may raise (e.g. :class:`~ptpcore.errors.Cancelled`) to stop the step. A step made of parts
hands each part a sub-range of its own bar (:func:`sub_progress`), or, for a pipeline of
stages of very different cost, a bar weighted by each stage's measured cost
(:class:`StagedProgress`), so a bar does not sit at 90 % after the first stage.
"""

from __future__ import annotations

from typing import Callable, Mapping

__all__ = ["Progress", "sub_progress", "StagedProgress"]

Progress = Callable[[float, str], None]
"""``progress(fraction, message)``: ``fraction`` in [0, 1]; may raise to cancel."""


def sub_progress(progress: Progress | None, lo: float, hi: float, prefix: str = "") -> Progress | None:
    """``progress`` seen through the range ``[lo, hi]`` of its bar (None stays None).

    Parameters
    ----------
    progress : callable or None
    lo, hi : float
        The part's range of the whole bar, ``0 <= lo <= hi <= 1``.
    prefix : str
        Put before each message (e.g. ``"height sweep: "``).
    """
    if progress is None:
        return None
    span = hi - lo
    return lambda f, msg: progress(lo + span * min(max(float(f), 0.0), 1.0), prefix + msg)


class StagedProgress:
    """One bar over named stages, each given a share in proportion to its expected cost.

    Parameters
    ----------
    progress : callable or None
        The whole bar.
    costs : mapping of str -> float
        Every stage's expected cost (any unit, e.g. CPU-s); stages are run in this order,
        and a stage that is skipped simply leaves its share (the bar jumps past it).

    Examples
    --------
    >>> bar = StagedProgress(print_progress, {"decode": 6.0, "fit": 3.0, "write": 0.1})
    >>> decode(progress=bar.stage("decode"))  # 0 .. 0.66 of the bar
    """

    def __init__(self, progress: Progress | None, costs: Mapping[str, float]):
        self.progress = progress
        total = float(sum(max(float(c), 0.0) for c in costs.values())) or 1.0
        self.ranges: dict[str, tuple[float, float]] = {}
        lo = 0.0
        for name, cost in costs.items():
            hi = lo + max(float(cost), 0.0) / total
            self.ranges[name] = (lo, min(hi, 1.0))
            lo = hi

    def stage(self, name: str, prefix: str = "") -> Progress | None:
        """The sub-bar of stage ``name`` (None without a bar)."""
        lo, hi = self.ranges[name]
        return sub_progress(self.progress, lo, hi, prefix)

    def done(self, message: str) -> None:
        """The whole bar at 100 %."""
        if self.progress is not None:
            self.progress(1.0, message)
