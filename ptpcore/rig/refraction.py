"""Refraction by the LCD's cover glass: how far a plane-parallel plate moves what a ray sees.

The physics both the correction (:mod:`ptpcore.fit.glass`) and the simulator
(:mod:`ptpcore.simulate.lcd_physics`) use, kept below both (docs/method.md section 8): a ray meeting
a plate of thickness ``t`` and index ``n`` at ``theta`` from its normal reaches the plane behind
it ``t*(tan(theta) - tan(theta'))``, ``sin(theta') = sin(theta)/n``, closer to the foot of the
normal than the straight ray in air would.
"""

from __future__ import annotations

import numpy as np

__all__ = ["plate_offset_mm"]


def plate_offset_mm(tan_theta, t_mm: float, n: float):
    """``t*(tan(theta) - tan(theta'))`` with ``sin(theta') = sin(theta)/n``.

    Parameters
    ----------
    tan_theta : float or array_like of float
        Tangent of the ray's angle to the plate's normal (in air).
    t_mm : float
        Plate thickness, mm.
    n : float
        Plate's refractive index (1 or more).

    Returns
    -------
    float64 ndarray, same shape as ``tan_theta``
        The offset toward the foot of the normal, mm.
    """
    tt = np.asarray(tan_theta, dtype=float)
    sin_in = tt / np.sqrt(1.0 + tt * tt) / n
    return t_mm * (tt - sin_in / np.sqrt(1.0 - sin_in * sin_in))
