"""Driving a real (or simulated) rig: the capture sequence with its exposure check, atomic
writes and resume (:mod:`.sequence`), and the devices (:mod:`.devices`: cameras, stages,
displays, ``capture.toml``).

May import :mod:`ptpcore.simulate` (the devices' simulated twins) and everything below it.
"""

from . import sequence
from .sequence import *  # noqa: F401,F403  (the names of sequence.__all__)

# One list of public names: each module's own __all__.
__all__ = list(sequence.__all__)
