"""The pinhole camera with Brown distortion (OpenCV's convention): the lens model, DLT
initial guess and Levenberg-Marquardt calibration (docs/method.md section 6). Used by 3DSTC, by
the smooth LUT's global model and by the conventional structured-light calibration (camera and
projector as two pinholes, docs/method.md section 9).

Imports nothing of ptpcore but the base modules.
"""

from . import lens
from .lens import *  # noqa: F401,F403  (the names of lens.__all__)
from . import camera
from .camera import *  # noqa: F401,F403  (the names of camera.__all__)
from . import structured_light
from .structured_light import *  # noqa: F401,F403  (the names of structured_light.__all__)

# One list of public names: each module's own __all__.
__all__ = list(lens.__all__ + camera.__all__ + structured_light.__all__)
