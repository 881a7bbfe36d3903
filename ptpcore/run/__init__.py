"""Running a calibration: the streaming decode of every position into samples, the fit, and
session files that save and resume the run stage by stage.

- :mod:`.calibration` — the one door: :func:`calibrate_session` (decode, fit, drift, height,
  write; every front end runs it) and :func:`calibrate` (images to the LUT ``ptp calibrate`` writes);
- :mod:`.pipeline` — :func:`collect_samples`: the streaming decode;
- :mod:`.session` — ``ptp-session/1`` files and :func:`run_session`;
- :mod:`.sanity` — :func:`check_samples`: the readings' sense and stuck positions, from the data.

May import :mod:`ptpcore.simulate` and everything below it.
"""

from .pipeline import decode_position, world_xy, collect_samples, SPILL_BYTES
from .session import (SESSION_FORMAT, SESSION_VERSION, SESSION_SUFFIX, STAGES, Session, next_step,
    new_session, save_session, load_session)
from .sanity import check_samples
from .calibration import Calibration, calibrate_session, calibrate, run_session, write_lut
from .decoding import direction_reasons
from .diagnose import convention_check, position_report
from .acceptance import conventional_calibration, reconstruct_scans, scan_folders
from .scanner import reconstruct

__all__ = [
    "decode_position",
    "world_xy",
    "collect_samples",
    "calibrate",
    "calibrate_session",
    "Calibration",
    "write_lut",
    "SPILL_BYTES",
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
    "direction_reasons",
    "convention_check",
    "position_report",
    "conventional_calibration",
    "reconstruct_scans",
    "scan_folders",
    "reconstruct",
]
