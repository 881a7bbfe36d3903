"""The rig's names in one place, as they were before the room was split (a compatibility face).

The rig now lives in modules of one job each: :mod:`ptpcore.rig.model` (the dataclasses),
:mod:`ptpcore.rig.reading` (``rig.toml`` and ``scan.toml`` read with every validation, helped by
:mod:`~ptpcore.rig.fringe_reading`, :mod:`~ptpcore.rig.templates` and
:mod:`~ptpcore.rig.toml_fields`) and :mod:`ptpcore.rig.writing`. Import from :mod:`ptpcore.rig`;
this module keeps ``from ptpcore.rig.rigfile import ...`` working.
"""

from __future__ import annotations

# The limits and field lists were module attributes of the old rigfile too (hence the noqa: F401).
from .fringe_reading import MAX_GRAY_BITS, MAX_PERIOD_PX, MAX_STEPS, check_heterodyne_span  # noqa: F401
from .model import (DATASET_FORMAT, DATASET_FORMAT_2, DEFAULT_TEMPLATE, SCAN_FORMAT, Camera, DecodeSettings,
                    DirectionFringes, Display, FrameEntry, FringeDesign, HeightSweep, Lcd, Projector, Rig, ScanSpec,
                    Stage, format_period, heterodyne_beats, projector_rig)  # noqa: F401
from .reading import MAX_POSITIONS, load_rig, load_scan, rig_from_toml  # noqa: F401
from .templates import GRAY_TEMPLATE_FIELDS, REFERENCE_TEMPLATE_FIELDS, TEMPLATE_FIELDS, validate_template  # noqa: F401
from .writing import rig_to_toml, save_rig, scan_to_toml

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
    "Projector",
    "HeightSweep",
    "ScanSpec",
    "SCAN_FORMAT",
    "projector_rig",
    "load_scan",
    "scan_to_toml",
    "format_period",
    "load_rig",
    "rig_from_toml",
    "rig_to_toml",
    "save_rig",
    "validate_template",
    "heterodyne_beats",
    "check_heterodyne_span",
]
