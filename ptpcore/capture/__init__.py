"""Driving a real (or simulated) rig: the capture sequence with its exposure check, atomic
writes and resume (:mod:`.sequence`), and the devices (:mod:`.devices`: cameras, stages,
displays, ``capture.toml``).

May import :mod:`ptpcore.simulate` (the devices' simulated twins) and everything below it.
"""

from .sequence import (STATE_FILE, ExposureLimits, ExposureReport, ExposureError, CaptureResult,
    display_levels, exposure_report, check_exposure, capture, capture_state, pattern_image)

__all__ = [
    "STATE_FILE",
    "ExposureLimits",
    "ExposureReport",
    "ExposureError",
    "CaptureResult",
    "display_levels",
    "exposure_report",
    "check_exposure",
    "capture",
    "capture_state",
    "pattern_image",
]
