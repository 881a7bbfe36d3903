"""The pinhole camera with Brown distortion (OpenCV's convention): the lens model, DLT
initial guess and Levenberg-Marquardt calibration (METHOD.md section 6). Used by 3DSTC and
by the smooth LUT's global model.

Imports nothing of ptpcore but the base modules.
"""

from .lens import normalise_dist, distort_normalised, undistort_normalised
from .camera import PinholeModel, PinholeFit, dlt_initial_guess, fit_pinhole, opencv_calibrate

__all__ = [
    "normalise_dist",
    "distort_normalised",
    "undistort_normalised",
    "PinholeModel",
    "PinholeFit",
    "dlt_initial_guess",
    "fit_pinhole",
    "opencv_calibrate",
]
