"""The rig description: camera, LCD, stage and fringe design as dataclasses, and ``rig.toml``
(``ptp-dataset/1`` and ``/2``) read with validation and written back.

One job a module: :mod:`.model` (the dataclasses), :mod:`.reading` (``rig.toml`` and
``scan.toml`` in, every check and its message; helped by :mod:`.fringe_reading`,
:mod:`.templates` and :mod:`.toml_fields`), :mod:`.writing` (the text back, saved atomically),
:mod:`.refraction` (the cover glass's plate offset, used by the fit and the simulator),
:mod:`.naming` (how a position is named). :mod:`.rigfile` keeps the names of the room before it
was split.

The bottom layer: imports only :mod:`ptpcore.errors` and :mod:`ptpcore.atomic`.
"""

from . import naming, rigfile  # noqa: F401  (rigfile: the names of the room before the split)
from .fringe_reading import check_heterodyne_span
from .model import *  # noqa: F401,F403  (the names of model.__all__)
from .naming import *  # noqa: F401,F403  (the names of naming.__all__)
from .reading import load_rig, load_scan, rig_from_toml
from .refraction import plate_offset_mm
from .templates import validate_template
from .writing import rig_to_toml, save_rig, scan_to_toml

# One list of public names, in the order of the room's former single module.
__all__ = [
    "DATASET_FORMAT", "DATASET_FORMAT_2", "Camera", "Lcd", "Stage", "Display", "DirectionFringes", "FringeDesign",
    "DecodeSettings", "FrameEntry", "Rig", "Projector", "HeightSweep", "ScanSpec", "SCAN_FORMAT", "projector_rig",
    "load_scan", "scan_to_toml", "format_period", "load_rig", "rig_from_toml", "rig_to_toml", "save_rig",
    "validate_template", "heterodyne_beats", "check_heterodyne_span",
] + list(naming.__all__) + ["plate_offset_mm"]
