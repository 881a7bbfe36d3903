"""Judging LUTs: the 3DSTC comparison, accuracy against truth, and the arrays the GUI draws.

- :mod:`.protocol` — the evaluation protocol (docs/method.md section 7): folds, feature points,
  fitting every method on the calibration positions, judging them on the held-out ones;
- :mod:`.statistics` — error statistics, distance pairs and curves, the verdict;
- :mod:`.report` — the comparison's result objects, JSON and text summary;
- :mod:`.accuracy` — a LUT's error at held-out heights against the simulator's exact rays;
- :mod:`.lut_report` — what a LUT says of itself (``ptp inspect``, the wizard's Calibrate summary);
- :mod:`.views` — heatmaps, reason colours, histograms, per-pixel series as arrays.

May import :mod:`ptpcore.simulate` and everything below it; never :mod:`ptpcore.run`,
:mod:`ptpcore.capture` or :mod:`ptpcore.cli`.
"""

from .statistics import (COMPARE_FORMAT, METHOD_LABELS, METHODS, PAIR_KINDS, REFERENCES, SPLITS, CoordinateStats,
    DistanceCurve, DistanceErrors, ErrorStats, PairSet, Verdict, coordinate_stats, error_stats)
from .report import CompareResult, Coverage, FeaturePoints, Fold, MethodReport, ReferenceReport, format_summary
from .protocol import compare, draw_features, smooth_degree_for, split_positions
from .accuracy import HeldOutAccuracy, held_out_accuracy
from .lut_report import DriftRecord, HeightSummary, LutReport, RobustFit
from .residuals import ResidualField, residual_field, residual_png
from .pngtext import write_png
from .vdi2634 import FIGURES, evaluate_acceptance, parse_mpe
from .acceptance_png import acceptance_page
from .diff import LutDiff, diff_luts
from .views import (REASON_ORDER, REASON_COLOURS, VALID_COLOUR, reason_rgba, reason_counts, reason_text, mask_rgba,
    subsample, DISPLAY_PIXELS, display_step, reduce_for_display, robust_levels, histogram, DisplayMap, prepare_display, ScaledMap, PixelSeries, pixel_series, predicted_signal)

__all__ = [
    "COMPARE_FORMAT", "SPLITS", "METHODS", "METHOD_LABELS", "REFERENCES", "PAIR_KINDS",
    "ErrorStats", "CoordinateStats", "DistanceCurve", "PairSet", "DistanceErrors", "Verdict",
    "coordinate_stats", "error_stats",
    "CompareResult", "Coverage", "FeaturePoints", "Fold", "MethodReport", "ReferenceReport", "format_summary",
    "compare", "draw_features", "smooth_degree_for", "split_positions",
    "HeldOutAccuracy", "held_out_accuracy",
    "LutReport", "RobustFit", "DriftRecord", "HeightSummary",
    "ResidualField", "residual_field", "residual_png", "write_png",
    "FIGURES", "evaluate_acceptance", "parse_mpe", "acceptance_page", "LutDiff", "diff_luts",
    "REASON_ORDER", "REASON_COLOURS", "VALID_COLOUR", "reason_rgba", "reason_counts", "reason_text", "mask_rgba",
    "subsample", "DISPLAY_PIXELS", "display_step", "reduce_for_display", "robust_levels", "histogram", "DisplayMap", "prepare_display", "ScaledMap", "PixelSeries", "pixel_series", "predicted_signal",
]
