"""Fitting LUTs to samples (docs/method.md section 5).

- :mod:`.perpixel` — the per-pixel ``poly``, ``pchip`` and ``linear`` LUTs with residual and LOO;
- :mod:`.sigma` — each sample's noise propagated through a per-pixel fit;
- :mod:`.smooth` — the smooth LUT: global pinhole model plus a per-pixel correction smoothed
  at a cross-validated scale, with its physical corrections and sigma maps (a subpackage, one
  module per step of the estimator);
- :mod:`.kinds` — one LUT of a named kind (``poly``, ``pchip``, ``linear``, ``smooth``);
- :mod:`.choice`, :mod:`.robust` — ``auto`` (the model chosen on held-out positions) and the
  outlier screening, both fitting with :mod:`.kinds`;
- :mod:`.models` — one entry point for every LUT model the CLI and the wizard offer.

May import :mod:`ptpcore.pinhole`, :mod:`ptpcore.io`, :mod:`ptpcore.decode`, :mod:`ptpcore.rig`,
:mod:`ptpcore.store`.
"""

from .perpixel import fit_lut
from .sigma import sample_sigma, predicted_poly_sigma, sigma_parts
from .smooth import (sample_sigma_from_noise, fit_smooth_lut, SmoothInfo, poly_sigma_maps,
    local_linear_smooth, global_pinhole)
from .models import LUT_MODELS, fit_model, lut_model, describe_lut
from .choice import ModelChoice, fit_auto
from .settings import FIT_SETTINGS_KEY, FitSettings, fit_arguments
from .corrected import correct_all, samples_as_fitted
from .glass import corrected_samples, describe_corrections
from .stage_pose import POSE_NAMES

__all__ = [
    "fit_lut",
    "sample_sigma",
    "predicted_poly_sigma",
    "sample_sigma_from_noise",
    "fit_smooth_lut",
    "SmoothInfo",
    "poly_sigma_maps",
    "local_linear_smooth",
    "global_pinhole",
    "LUT_MODELS",
    "fit_model",
    "lut_model",
    "describe_lut",
    "ModelChoice",
    "fit_auto",
    "FitSettings",
    "FIT_SETTINGS_KEY",
    "fit_arguments",
    "correct_all",
    "samples_as_fitted",
    "corrected_samples",
    "describe_corrections",
    "sigma_parts",
    "POSE_NAMES",
]
