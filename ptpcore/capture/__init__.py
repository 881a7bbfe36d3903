"""Driving a real (or simulated) rig: the capture sequence with its exposure check, atomic
writes and resume (:mod:`.sequence`), and the devices (:mod:`.devices`: cameras, stages,
displays, ``capture.toml``).

May import :mod:`ptpcore.simulate` (the devices' simulated twins) and everything below it.
"""

from . import sequence
from .sequence import *  # noqa: F401,F403  (the names of sequence.__all__)
from .devices import (HarvestersCamera, ManualStage, OpenCVCamera, SerialStage, SimulatedCamera, SimulatedDisplay,
    SimulatedStage, simulated_meta)
from .devices.config import load_capture_config
from .devices.display import check_lcd_image

# One list of public names: sequence's own __all__, and the devices the wizard opens.
__all__ = list(sequence.__all__) + [
    "HarvestersCamera", "ManualStage", "OpenCVCamera", "SerialStage", "SimulatedCamera", "SimulatedDisplay",
    "SimulatedStage", "simulated_meta", "load_capture_config", "check_lcd_image",
]
