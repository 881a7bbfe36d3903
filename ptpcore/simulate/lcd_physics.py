"""A real LCD on a real stage: cover glass, carriage pose and panel bow (docs/method.md section 8).

Exact geometry for the simulator. Each stage position places the LCD with a
small rigid pose: translation ``(dx, dy, dz)`` (run-out and height error) and
rotation ``(pitch, yaw, roll)`` about the LCD centre. In the LCD's own frame
(mm; ``x, y`` along its pixel rows and columns from pixel (0, 0), ``h`` along
its normal toward the camera) the pixel plane is ``h = -w(x, y)`` (the panel
bow, + = farther from the camera) and the cover glass's front face is
``h = t - w(x, y)``. A camera ray in air meets the front face, refracts
(Snell, exact), and runs straight through the glass to the pixel plane: that
pixel plane point is what the camera decodes. The ray in air stays the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ptpcore.rig.refraction import plate_offset_mm as refraction_offset_mm  # t*(tan(theta) - tan(theta'))

__all__ = ["LcdPhysics", "pose_matrix", "draw_stage_poses", "refraction_offset_mm"]


def pose_matrix(pitch_urad: float, yaw_urad: float, roll_urad: float) -> np.ndarray:
    """Rotation LCD -> world, ``Rz(roll) @ Ry(yaw) @ Rx(pitch)`` (angles in urad).

    Returns
    -------
    (3, 3) float64
    """
    a, b, c = (1e-6 * float(v) for v in (pitch_urad, yaw_urad, roll_urad))
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def draw_stage_poses(rng: np.random.Generator, n_positions: int, runout_um: float, tilt_urad: float,
                     roll_urad: float) -> np.ndarray:
    """Per-position pose errors, normal with the given 1-sigma sizes.

    Returns
    -------
    (K, 6) float64
        ``dx, dy`` (um, lateral run-out), ``dz`` (0 here: the height error is
        the simulator's ``stage_error_um``), ``pitch, yaw, roll`` (urad).
    """
    poses = np.zeros((n_positions, 6))
    poses[:, 0:2] = rng.normal(0.0, 1.0, size=(n_positions, 2)) * runout_um
    poses[:, 3:5] = rng.normal(0.0, 1.0, size=(n_positions, 2)) * tilt_urad
    poses[:, 5] = rng.normal(0.0, 1.0, size=n_positions) * roll_urad
    return poses


@dataclass(frozen=True)
class LcdPhysics:
    """Cover glass and panel bow of the simulated LCD.

    Attributes
    ----------
    glass_mm, glass_index : float
        Cover glass (all layers above the pixel plane as one plate).
    bow_mm : float
        Peak panel bow at the centre (mm, + = farther from the camera):
        ``w = bow * (1 - xn**2) * (1 - yn**2)``, ``xn, yn`` in -1..1 over the panel.
    size_mm : (2,) float
        Panel extent ``(width, height)`` between the outer pixel centres.
    """

    glass_mm: float = 0.0
    glass_index: float = 1.52
    bow_mm: float = 0.0
    size_mm: tuple[float, float] = (192.0, 108.0)

    @property
    def trivial(self) -> bool:
        return self.glass_mm == 0.0 and self.bow_mm == 0.0

    def bow(self, x, y):
        """Panel bow ``w`` (mm) at LCD-frame ``x, y`` (mm)."""
        if self.bow_mm == 0.0:
            return np.zeros(np.broadcast(x, y).shape)
        xn = 2.0 * np.asarray(x) / self.size_mm[0] - 1.0
        yn = 2.0 * np.asarray(y) / self.size_mm[1] - 1.0
        return self.bow_mm * (1.0 - xn * xn) * (1.0 - yn * yn)

    def _to_surface(self, o, d, h0):
        """Where rays ``o + s d`` meet the surface ``h = h0 - w(x, y)`` (fixed point; w is smooth and small)."""
        x, y = o[..., 0], o[..., 1]
        for _ in range(4 if self.bow_mm else 1):
            s = (h0 - self.bow(x, y) - o[..., 2]) / d[..., 2]
            x = o[..., 0] + s * d[..., 0]
            y = o[..., 1] + s * d[..., 1]
        return x, y, h0 - self.bow(x, y)

    def hit(self, origin, direction):
        """Pixel-plane point that rays (in the LCD frame) see through the glass.

        Parameters
        ----------
        origin, direction : (..., 3) float64
            Rays in the LCD frame (mm), pointing toward the panel (``d_h < 0``).

        Returns
        -------
        x, y : (...) float64, mm
            LCD-frame coordinates of the pixel-plane point.
        """
        if self.glass_mm == 0.0:
            x, y, _ = self._to_surface(origin, direction, 0.0)
            return x, y
        fx, fy, fh = self._to_surface(origin, direction, self.glass_mm)
        i = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
        # Refraction at the front face; its normal (to first order in the bow
        # slope, which is 1e-4 rad) is the panel normal, pointing at the camera.
        cos_i = -i[..., 2]
        eta = 1.0 / self.glass_index
        cos_t = np.sqrt(1.0 - eta * eta * (1.0 - cos_i * cos_i))
        t_dir = eta * i
        t_dir[..., 2] += eta * cos_i - cos_t
        x, y, _ = self._to_surface(np.stack([fx, fy, fh], axis=-1), t_dir, 0.0)
        return x, y
