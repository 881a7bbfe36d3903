"""Decoding fringe images into LCD coordinates (docs/method.md sections 3 and 4).

- :mod:`.patterns` — what the LCD shows, and the design check;
- :mod:`.phase` — N-step phase, temporal unwrapping, validity reasons, LCD coordinates;
- :mod:`.noise` — the camera noise measured from the N-step residuals;
- :mod:`.display` — the bias of the LCD's integer levels;
- :mod:`.position` — one position's sets of frames to coordinates, reasons and noise samples
  (the recipe the streaming decode and ``ptp decode`` run);
- :mod:`._fused` — optional numba kernels, exact-equal to the numpy path.

Pure computation on arrays: may import :mod:`ptpcore.rig` and the base modules, never files
or anything above.
"""

from .patterns import (fringe_values, fringe_profile, fringe_image, DesignItem, DesignReport,
    design_check, phase_noise_rad, GRAY_TEMPLATE, gray_bits_needed)
from .phase import (Reason, REASON_NAMES, PhaseAccumulator, WrappedPhase, wrapped_phase,
    unwrap_hierarchical, DirectionDecode, DecodedPosition, DecodeOptions, decode_direction,
    finish_position)
from .noise import NoiseModel, NoiseAccumulator
from .display import level_bias_px, level_bias_table, level_bias_at, level_phase_errors_px
from .position import decode_sets, flag_more_reasons, reference_clipping, coordinate_sigma
from .harmonics import measured_harmonics

__all__ = [
    "fringe_values",
    "fringe_profile",
    "fringe_image",
    "DesignItem",
    "DesignReport",
    "design_check",
    "phase_noise_rad",
    "GRAY_TEMPLATE",
    "gray_bits_needed",
    "Reason",
    "REASON_NAMES",
    "PhaseAccumulator",
    "WrappedPhase",
    "wrapped_phase",
    "unwrap_hierarchical",
    "DirectionDecode",
    "DecodedPosition",
    "DecodeOptions",
    "decode_direction",
    "finish_position",
    "NoiseModel",
    "NoiseAccumulator",
    "level_bias_px",
    "level_bias_table",
    "level_bias_at",
    "level_phase_errors_px",
    "decode_sets",
    "flag_more_reasons",
    "reference_clipping",
    "coordinate_sigma",
    "measured_harmonics",
]
