"""How every summary, report and window names a stage position.

Positions are counted from 0, as the dataset's folders and file names are (``pos`` in FORMATS.md's
templates) and ``ptp decode`` prints them, and always shown with their height.
"""

from __future__ import annotations

import math

__all__ = ["lut_stage_z", "position_label"]


def position_label(k: int, z_mm: float | None = None) -> str:
    """``"position 3, z = 12 mm"``: position ``k`` (0-based) at the stage reading ``z_mm`` (omitted if None)."""
    if z_mm is None or not math.isfinite(float(z_mm)):
        return f"position {int(k)}"
    return f"position {int(k)}, z = {float(z_mm):g} mm"


def lut_stage_z(lut) -> tuple:
    """The stage readings (mm) of the rig a LUT records in its ``rig_toml``; () if it records none
    or it cannot be read (the names then go without heights)."""
    from ptpcore.errors import PtpError

    from .reading import rig_from_toml

    try:
        return tuple(rig_from_toml(lut.rig_toml, "the LUT's rig").stage.z_mm) if getattr(lut, "rig_toml", "") else ()
    except (PtpError, ValueError):
        return ()
