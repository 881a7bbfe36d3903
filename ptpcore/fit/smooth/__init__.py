"""The ``smooth`` LUT: a global camera model plus a per-pixel correction smoothed over the image.

Why: a plain per-pixel LUT is noise-limited (each pixel fits only its own
noisy samples); a pinhole model is bias-limited (it cannot follow a real
lens). Here

1. a pinhole + Brown model (:mod:`ptpcore.pinhole`) is fitted to a large
   random subset of all calibration samples: it carries the bulk of the
   geometry with almost no noise;
2. every pixel fits a polynomial in z to its residuals against that model,
   weighted by each sample's predicted phase noise (from the modulation and
   the camera noise measured in the data, :mod:`ptpcore.decode.noise`);
3. each coefficient map of that correction is smoothed over the image by a
   locally linear, inverse-variance weighted Gaussian regression (built from
   ``scipy.ndimage.gaussian_filter`` moments), so the correction keeps
   non-parametric lens features larger than the smoothing scale;
4. the smoothing scale is chosen by cross-validation on held-out calibration
   positions (the prediction error against measured samples is the true
   error plus the measurement noise, so both have the same minimum).

The result is written as ordinary ``poly`` coefficients per pixel, so
scanners read it unchanged; ``/model`` carries ``method = "smooth"`` and the
chosen scale as extra attributes.

The package also propagates the per-sample phase noise to per-pixel
uncertainty maps ``sigma_x``, ``sigma_y`` for plain and smooth LUTs.

Its modules are the estimator's steps, in the order :func:`fit_smooth_lut` runs them:

- :mod:`.noise` — each sample's predicted noise (docs/method.md section 4) and its calibration
  (:func:`sigma_scale`), the stage readings' leverage;
- :mod:`.global_model` — step 1: the global pinhole + Brown model, its rays, the level and
  footprint biases, every sample's residual to the model;
- :mod:`.pixel_fits` — steps 2 and 4: every pixel's own fit in z, the one pass over the samples that
  makes them and cross-validates the scale, the smoothed coefficients;
- :mod:`.smoothing` — step 3: locally linear Gaussian smoothing, per pixel or on bins;
- :mod:`.leave_one_out` — the real leave-one-position-out and the model error it reveals;
- :mod:`.uncertainty` — the sigma maps (noise, stage, the global model's leak, model error) and
  :func:`poly_sigma_maps` for plain LUTs;
- :mod:`.estimator` — :func:`fit_smooth_lut`, the pipeline;
- :mod:`.blocks` — the row blocks every step works in.

Where the big maps live (memory or a temporary file) is :mod:`ptpcore.store`'s business.
"""

from .noise import (phase_sigma_mm, sample_sigma_from_noise, position_sigma_from_noise, sigma_scale,
    stage_leverage)
from .global_model import global_pinhole, footprint_bias, FOOTPRINT_M2_MAX_PX2
from .smoothing import local_linear_smooth, CV_PIXELS
from .uncertainty import poly_model_variance, poly_sigma_maps
from .estimator import fit_smooth_lut, SmoothInfo, smooth_global_fit

__all__ = [
    "phase_sigma_mm",
    "sample_sigma_from_noise",
    "position_sigma_from_noise",
    "sigma_scale",
    "stage_leverage",
    "global_pinhole",
    "footprint_bias",
    "FOOTPRINT_M2_MAX_PX2",
    "local_linear_smooth",
    "CV_PIXELS",
    "poly_sigma_maps",
    "poly_model_variance",
    "fit_smooth_lut",
    "smooth_global_fit",
    "SmoothInfo",
]
