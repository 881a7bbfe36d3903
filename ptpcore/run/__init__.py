"""Running a calibration: the streaming decode of every position into samples, the fit, and
session files that save and resume the run stage by stage.

- :mod:`.pipeline` — :func:`collect_samples`, :func:`calibrate`;
- :mod:`.session` — ``ptp-session/1`` files and :func:`run_session`;
- :mod:`.sanity` — :func:`check_samples`: the readings' sense and stuck positions, from the data.

May import :mod:`ptpcore.simulate` and everything below it.
"""

from .pipeline import decode_position, world_xy, collect_samples, calibrate, SPILL_BYTES, repeat_drift
from .session import (SESSION_FORMAT, SESSION_VERSION, SESSION_SUFFIX, STAGES, Session, next_step,
    new_session, save_session, load_session, run_session)
from .sanity import check_samples

__all__ = [
    "decode_position",
    "world_xy",
    "collect_samples",
    "calibrate",
    "SPILL_BYTES",
    "repeat_drift",
    "SESSION_FORMAT",
    "SESSION_VERSION",
    "SESSION_SUFFIX",
    "STAGES",
    "Session",
    "next_step",
    "new_session",
    "save_session",
    "load_session",
    "run_session",
    "check_samples",
]
