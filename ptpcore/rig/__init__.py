"""The rig description: camera, LCD, stage and fringe design as dataclasses, and ``rig.toml``
(``ptp-dataset/1`` and ``/2``) read with validation and written back.

The bottom layer: imports only :mod:`ptpcore.errors` and :mod:`ptpcore.atomic`.
"""

from .rigfile import (DATASET_FORMAT, DATASET_FORMAT_2, Camera, Lcd, Stage, Display,
    DirectionFringes, FringeDesign, DecodeSettings, FrameEntry, Rig, format_period, load_rig,
    rig_from_toml, rig_to_toml, save_rig, validate_template)

__all__ = [
    "DATASET_FORMAT",
    "DATASET_FORMAT_2",
    "Camera",
    "Lcd",
    "Stage",
    "Display",
    "DirectionFringes",
    "FringeDesign",
    "DecodeSettings",
    "FrameEntry",
    "Rig",
    "format_period",
    "load_rig",
    "rig_from_toml",
    "rig_to_toml",
    "save_rig",
    "validate_template",
]
