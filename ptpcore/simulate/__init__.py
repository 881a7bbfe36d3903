"""A virtual rig with exact ground truth: lens, pose, pixelated LCD, blur, gamma, noise and
stage errors, rendering the same datasets a real capture writes, plus every pixel's true ray.

May import :mod:`ptpcore.fit` and everything below it (today it needs only
:mod:`ptpcore.pinhole`, :mod:`ptpcore.decode` and :mod:`ptpcore.rig`).
"""

from .virtual_rig import (LensSettings, SimSettings, PRESETS, preset, scaled_preset, GroundTruth,
    VirtualRig, simulate_dataset, load_truth)

__all__ = [
    "LensSettings",
    "SimSettings",
    "PRESETS",
    "preset",
    "scaled_preset",
    "GroundTruth",
    "VirtualRig",
    "simulate_dataset",
    "load_truth",
]
