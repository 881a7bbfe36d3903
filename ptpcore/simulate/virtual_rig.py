"""A virtual calibration rig with exact ground truth.

The simulator renders what the camera sees of the LCD at every stage
position: a lens with Brown distortion plus a smooth non-parametric field,
optionally a non-central entrance pupil, a camera pose, piecewise-constant LCD
pixels integrated over each camera pixel's footprint, defocus blur growing
away from the focus height, the LCD's gamma, vignetting, shot and read noise,
quantisation to 8-16 bits, saturation, stage position error, stage travel
skew and the dark bezel around the screen.

Ground truth is each camera pixel's ray, a straight line in the world frame
(docs/method.md section 2): ``X(z) = x0 + sx * z``, ``Y(z) = y0 + sy * z``.

Everything is seeded: the same settings and seed give the same images, bit
for bit, in any order (each frame has its own random stream).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator

import cv2
import h5py
import numpy as np

from ptpcore.atomic import write_bytes_atomic
from ptpcore.errors import ConfigError
from ptpcore.io.lutfile import write_hdf5_atomic
from ptpcore.simulate import lens_models
from ptpcore.simulate.lcd_physics import LcdPhysics, draw_stage_poses, pose_matrix
from ptpcore.decode.patterns import (display_inverse, fringe_profile, fringe_values, gray_profile, gray_values,
                                     reference_profile)
from ptpcore.rig.rigfile import Camera, FringeDesign, Lcd, Rig, Stage, save_rig

__all__ = [
    "LensSettings",
    "SimSettings",
    "PRESETS",
    "preset",
    "scaled_preset",
    "scale_rig",
    "GroundTruth",
    "VirtualRig",
    "simulate_dataset",
    "load_truth",
    "save_truth",
    "TRUTH_FILE",
    "settings_from_json",
]

TRUTH_FILE = "truth.h5"


@dataclass(frozen=True)
class LensSettings:
    """The simulated lens.

    Attributes
    ----------
    focal_px : float
        Focal length in pixels (square pixels).
    principal_offset_px : (2,) float
        Principal point relative to the image centre ``((W-1)/2, (H-1)/2)``.
    dist : (5,) float
        Brown distortion ``k1, k2, p1, p2, k3`` (OpenCV convention).
    field_amplitude_px : float
        Peak amplitude of a smooth non-parametric distortion field added on
        top of Brown (pixels): what a global model cannot follow.
    pupil_shift_mm : float
        Non-central entrance pupil: a ray at normalised radius r leaves from
        ``pupil_shift_mm * r**2`` along the optical axis.
    projection : {"perspective", "equidistant"}
        ``r = f tan(theta)`` (pinhole) or ``r = f theta`` (fisheye-like), before Brown.
    prism : (4,) float
        Thin-prism ``s1, s2, s3, s4`` (OpenCV's convention), with Brown.
    ripple_px, ripple_wavelength_px : float
        A short-scale image-side distortion field: RMS displacement per axis and
        typical wavelength (px). The last three: :mod:`ptpcore.simulate.lens_models`.
    """

    focal_px: float = 800.0
    principal_offset_px: tuple[float, float] = (0.0, 0.0)
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    field_amplitude_px: float = 0.0
    pupil_shift_mm: float = 0.0
    projection: str = "perspective"
    prism: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    ripple_px: float = 0.0
    ripple_wavelength_px: float = 40.0


@dataclass(frozen=True)
class SimSettings:
    """Everything about the virtual rig that ``rig.toml`` does not say.

    Lengths in mm, angles in degrees, light as fractions of the full well.
    """

    name: str = "custom"
    lens: LensSettings = field(default_factory=LensSettings)
    distance_mm: float = 200.0
    tilt_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset_mm: tuple[float, float] = (0.0, 0.0)
    supersample: int = 1
    pixelated: bool = True
    blur_sigma_px: float = 0.0
    blur_per_mm: float = 0.0
    focus_z_mm: float = 20.0
    display_gamma: float = 1.0
    lcd_black: float = 0.0
    vignetting: float = 0.0
    exposure: float = 0.8
    ambient: float = 0.0
    full_well_e: float = 20000.0
    read_noise_e: float = 5.0
    noise: bool = True
    stage_error_um: float = 0.0
    skew: tuple[float, float] = (0.0, 0.0)
    # A real LCD on a real stage (docs/method.md section 8; ptpcore.simulate.lcd_physics).
    cover_glass_mm: float = 0.0
    cover_glass_index: float = 1.52
    tilt_urad: float = 0.0
    roll_urad: float = 0.0
    runout_um: float = 0.0
    bow_um: float = 0.0
    drift_um: tuple[float, float] = (0.0, 0.0)
    """How far the camera moved sideways (world X, Y, um) between the sweep and its repeat positions
    (``[stage] repeat_z_mm``): the drift they should find. The sweep itself is not affected."""
    dust: tuple[tuple[float, float, float, float], ...] = ()
    """Dark disks on the LCD: ``(u, v, diameter, transmission)`` (LCD px; 0..1). Rendered
    exactly only with ``pixelated = False`` (point-sampled footprints)."""
    black_offset: tuple[float, float, float, float, float] | None = None
    """A camera black-level offset in one region: ``(col0, row0, col1, row1, dn)``: the
    camera subtracts ``dn`` there before clipping at 0 (a region clipped at black)."""

    def e_per_dn(self, camera: Camera) -> float:
        """Electrons per grey level."""
        return self.full_well_e / camera.max_level

    def noise_dn(self, camera: Camera, level_dn):
        """Predicted 1-sigma noise (grey levels) of a sample at mean level ``level_dn``.

        Shot noise, read noise and quantisation (1/sqrt(12) DN); zero for a
        noise-free simulation apart from quantisation.
        """
        g = self.e_per_dn(camera)
        level = np.maximum(np.asarray(level_dn, dtype=float), 0.0)
        var = 1.0 / 12.0
        if self.noise:
            var = var + level / g + (self.read_noise_e / g) ** 2
        return np.sqrt(var)


def _default_rig(camera: Camera, z_mm, carrier=(0.0, 0.0), periods=(4096, 640, 128, 32),
                 steps=(4, 4, 4, 8), gamma=1.0, skew=(0.0, 0.0)) -> Rig:
    return Rig(
        camera=camera,
        lcd=Lcd(3840, 2160, (0.05, 0.05)),
        stage=Stage(tuple(float(z) for z in z_mm), (skew[0], skew[1], 1.0)),
        fringes=FringeDesign(("x", "y"), tuple(periods), tuple(steps), 127.5, 100.0,
                             (float(carrier[0]), float(carrier[1])), gamma),
    )


def _presets():
    z11 = np.linspace(0.0, 40.0, 11)
    out = {}
    # Noise-free, point-sampled, continuous fringes: decoding must be exact.
    out["ideal"] = (
        _default_rig(Camera(640, 480, 16), z11),
        SimSettings(name="ideal", lens=LensSettings(800.0, (3.0, -2.0), (-0.05, 0.01, 0.0, 0.0, 0.0)),
                    supersample=1, pixelated=False, noise=False, exposure=0.8),
    )
    # A lens that Brown describes exactly (central pupil, no extra field).
    out["mild"] = (
        _default_rig(Camera(640, 480, 12), z11, carrier=(1.0, 0.5)),
        SimSettings(name="mild", lens=LensSettings(800.0, (4.0, -3.0), (-0.12, 0.05, 4e-4, -3e-4, 0.0)),
                    tilt_deg=(1.5, -1.0, 0.5), offset_mm=(2.0, -1.5), supersample=3,
                    blur_sigma_px=0.6, blur_per_mm=0.02, exposure=0.8, vignetting=0.15,
                    full_well_e=20000.0, read_noise_e=6.0, stage_error_um=0.2),
    )
    out["realistic"] = (
        _default_rig(Camera(640, 480, 12), z11, carrier=(1.5, 1.0), gamma=2.2, skew=(0.002, -0.001)),
        SimSettings(name="realistic",
                    lens=LensSettings(800.0, (6.0, -4.0), (-0.22, 0.08, 8e-4, -5e-4, -0.01), 0.4, 0.5),
                    tilt_deg=(2.0, -1.5, 0.7), offset_mm=(3.0, -2.0), supersample=3,
                    blur_sigma_px=0.7, blur_per_mm=0.03, display_gamma=2.2, lcd_black=0.002,
                    vignetting=0.25, exposure=0.85, ambient=0.01, full_well_e=15000.0,
                    read_noise_e=8.0, stage_error_um=0.3, skew=(0.002, -0.001)),
    )
    out["rough"] = (
        _default_rig(Camera(640, 480, 8), z11, carrier=(2.0, 1.5), gamma=2.2, skew=(0.004, 0.003)),
        SimSettings(name="rough",
                    lens=LensSettings(780.0, (10.0, -7.0), (-0.32, 0.14, 1.5e-3, -1.0e-3, -0.03), 1.5, 2.0),
                    tilt_deg=(3.0, -2.5, 1.0), offset_mm=(4.0, -3.0), supersample=3,
                    blur_sigma_px=0.8, blur_per_mm=0.035, display_gamma=2.4, lcd_black=0.004,
                    vignetting=0.35, exposure=0.97, ambient=0.02, full_well_e=8000.0,
                    read_noise_e=12.0, stage_error_um=0.5, skew=(0.004, 0.003)),
    )
    # A real LCD on a real stage: the realistic camera, 1.1 mm of cover glass,
    # a tilting carriage with run-out and 1 um height errors, a 5 um panel bow
    # and a display response (gamma 1.1) the patterns do not pre-compensate.
    rig, s = out["realistic"]
    out["real"] = (
        replace(rig, lcd=_lcd_with_glass(rig.lcd, 1.1, 1.52), fringes=replace(rig.fringes, gamma=1.0)),
        replace(s, name="real", display_gamma=1.1, stage_error_um=1.0, cover_glass_mm=1.1,
                cover_glass_index=1.52, tilt_urad=20.0, runout_um=1.0, bow_um=5.0),
    )
    return out


def _lcd_with_glass(lcd: Lcd, t_mm: float, index: float) -> Lcd:
    """``lcd`` declaring its cover glass (``[lcd] cover_glass_mm``, ptp-dataset/2)."""
    return replace(lcd, cover_glass_mm=t_mm, cover_glass_index=index)


PRESETS = _presets()


def preset(name: str) -> tuple[Rig, SimSettings]:
    """The rig and simulation settings of a named preset (``ideal`` .. ``rough``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown preset '{name}' (choose from {', '.join(PRESETS)})") from None


def scaled_preset(name: str, width: int, height: int | None = None,
                  positions: int | None = None) -> tuple[Rig, SimSettings]:
    """A preset with another sensor size but the same field of view and lens.

    The focal length, principal-point offset, blur and non-parametric field
    scale with the width (and, for a smaller sensor, the finer fringe periods,
    so each still spans as many camera pixels), so the same scene and the same distortion (in normalised
    coordinates) are seen with fewer or more pixels. Handy for fast tests and
    for big-sensor benchmarks.

    Parameters
    ----------
    name : str
    width : int
    height : int, optional
        Default keeps the preset's aspect ratio.
    positions : int, optional
        Number of stage positions over the same z range.
    """
    return scale_rig(*preset(name), width, height, positions)


def scale_rig(rig: Rig, s: SimSettings, width: int, height: int | None = None,
              positions: int | None = None) -> tuple[Rig, SimSettings]:
    """:func:`scaled_preset` of any rig and settings (e.g. a drawn rig, :mod:`ptpcore.simulate.draws`)."""
    scale = width / rig.camera.width
    if height is None:
        height = int(round(rig.camera.height * scale))
    lens = replace(s.lens, focal_px=s.lens.focal_px * scale,
                   principal_offset_px=tuple(p * scale for p in s.lens.principal_offset_px),
                   field_amplitude_px=s.lens.field_amplitude_px * scale)
    lens = lens_models.scale_lens_extensions(lens, scale)
    s = replace(s, lens=lens, blur_sigma_px=s.blur_sigma_px * scale, blur_per_mm=s.blur_per_mm * scale)
    rig = replace(rig, camera=Camera(width, height, rig.camera.bit_depth))
    if scale < 1:
        # Keep the finest fringe at the same number of camera pixels per period;
        # the levels between it and the (unchanged) coarsest period are spaced
        # geometrically so every unwrapping step keeps the same ratio.
        f = rig.fringes
        fine = min(f.periods_px[-1] / scale, f.periods_px[0] / 2 ** (len(f.periods_px) - 1))
        ratios = (f.periods_px[0] / fine) ** (1.0 / (len(f.periods_px) - 1))
        periods = tuple(int(round(f.periods_px[0] / ratios ** j)) for j in range(len(f.periods_px)))
        rig = replace(rig, fringes=replace(f, periods_px=periods))
    if positions is not None:
        rig = rig.with_z(np.linspace(min(rig.stage.z_mm), max(rig.stage.z_mm), positions))
    return rig, s


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    """Small tilts (degrees) applied to a camera that looks straight at the screen's face, along +Z.

    docs/method.md section 2: the camera's centre has Z < 0 and the stage readings
    grow as the LCD moves away from it; the camera sees the screen unmirrored
    (image columns along LCD columns, image rows along LCD rows).
    """
    def rot(axis, a):
        c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
        m = np.eye(3)
        i, j = [(1, 2), (0, 2), (0, 1)][axis]
        m[i, i] = c
        m[j, j] = c
        m[i, j] = -s
        m[j, i] = s
        return m
    # Camera x = world X, camera y = world Y (down the screen), camera z (viewing) = world Z.
    return rot(0, rx) @ rot(1, ry) @ rot(2, rz)


@dataclass
class GroundTruth:
    """Exact per-pixel rays of the simulated camera.

    Attributes
    ----------
    x0, y0 : (H, W) float64, mm
        Where each pixel's centre ray meets the world plane Z = 0.
    sx, sy : (H, W) float64
        dX/dZ and dY/dZ of each ray.
    z_true : (K,) float64, mm
        True stage heights (readings plus the simulated stage error).
    stage_pose : (K, 6) float64 or None
        True pose error of each position: ``dx, dy, dz`` (um), ``pitch, yaw, roll``
        (urad, about the LCD centre); ``dz`` is ``z_true`` minus the reading.
    """

    x0: np.ndarray
    y0: np.ndarray
    sx: np.ndarray
    sy: np.ndarray
    z_true: np.ndarray
    stage_pose: np.ndarray | None = None

    def xy(self, z) -> tuple[np.ndarray, np.ndarray]:
        """True world X, Y (mm) of every pixel at height ``z`` (scalar or (H, W))."""
        return self.x0 + self.sx * z, self.y0 + self.sy * z


def period_key(period) -> int:
    """A period as an integer of a noise stream's key: itself when whole (the streams of integer
    periods as they always were), else its value in thousandths of a px beyond 10^9."""
    t = float(period)
    return int(t) if t.is_integer() else 10**9 + int(round(t * 1000))


class VirtualRig:
    """A seeded virtual rig: renders camera frames of the LCD at each position.

    Parameters
    ----------
    rig : Rig
        What ``rig.toml`` says (camera size and bit depth, LCD, stage readings, fringes).
    settings : SimSettings
    seed : int
    noise_seed : int, optional
        The noise's own seed (default ``seed``): another sweep of the same rig
        (same lens field, stage errors and poses) with independent noise.
    """

    def __init__(self, rig: Rig, settings: SimSettings, seed: int = 0, noise_seed: int | None = None):
        self.rig = rig
        self.settings = settings
        self.seed = int(seed)
        self.noise_seed = self.seed if noise_seed is None else int(noise_seed)
        rng = np.random.default_rng([self.seed, 1])
        cam = rig.camera
        lens = settings.lens
        self.K = np.array([
            [lens.focal_px, 0.0, (cam.width - 1) / 2 + lens.principal_offset_px[0]],
            [0.0, lens.focal_px, (cam.height - 1) / 2 + lens.principal_offset_px[1]],
            [0.0, 0.0, 1.0],
        ])
        self.dist = np.array(lens.dist, dtype=float)
        self.R = _rotation(*settings.tilt_deg)  # world -> camera
        lcd_centre = np.array([(rig.lcd.width - 1) / 2 * rig.lcd.pitch_mm[0],
                               (rig.lcd.height - 1) / 2 * rig.lcd.pitch_mm[1], 0.0])
        z_mid = 0.5 * (min(rig.stage.z_mm) + max(rig.stage.z_mm))
        # docs/method.md section 2: the camera in front of the screen's face, at Z < 0.
        self.centre = lcd_centre + np.array([settings.offset_mm[0], settings.offset_mm[1],
                                             z_mid - settings.distance_mm])
        # Smooth non-parametric distortion: a few low-frequency modes (pixels).
        n_modes = 4
        self._modes = [
            (rng.uniform(0.6, 2.2, size=2) * 2 * np.pi / np.array([cam.width, cam.height]),
             rng.uniform(0, 2 * np.pi, size=2), rng.normal(size=2))
            for _ in range(n_modes)
        ]
        norm = sum(np.hypot(*m[2]) for m in self._modes)
        self._field_scale = lens.field_amplitude_px / norm if norm > 0 else 0.0
        # A short-scale field (lens_models; its own stream, so lenses without it render as before).
        self._ripple = (lens_models.RippleField(lens.ripple_px, lens.ripple_wavelength_px,
                                                np.random.default_rng([self.seed, 30]))
                        if lens.ripple_px > 0 else None)
        z = np.asarray(rig.stage.z_mm, dtype=float)
        self.z_true = z + rng.normal(0.0, settings.stage_error_um * 1e-3, size=z.size)
        self.skew = np.array([settings.skew[0], settings.skew[1]])
        # Carriage pose per position (its own stream: older presets render bit for bit as before).
        self.stage_pose = draw_stage_poses(np.random.default_rng([self.seed, 4]), z.size, settings.runout_um,
                                           settings.tilt_urad, settings.roll_urad)
        self.stage_pose[:, 2] = 1e3 * (self.z_true - z)
        # Repeat positions (after the sweep, positions K, K+1, ...): their own stage error and pose
        # (own streams: a rig without repeats renders bit for bit as before).
        rep = np.asarray(rig.stage.repeat_z_mm, dtype=float)
        self.readings = np.concatenate([z, rep])
        rep_true = rep + np.random.default_rng([self.seed, 6]).normal(0.0, settings.stage_error_um * 1e-3, rep.size)
        rep_pose = draw_stage_poses(np.random.default_rng([self.seed, 7]), rep.size, settings.runout_um,
                                    settings.tilt_urad, settings.roll_urad)
        rep_pose[:, 2] = 1e3 * (rep_true - rep)
        self.repeat_z_true, self.repeat_pose = rep_true, rep_pose
        self.physics = LcdPhysics(settings.cover_glass_mm, settings.cover_glass_index, settings.bow_um * 1e-3,
                                  ((rig.lcd.width - 1) * rig.lcd.pitch_mm[0], (rig.lcd.height - 1) * rig.lcd.pitch_mm[1]))
        self._coords_cache: tuple[int, dict] | None = None
        # Render a margin around the sensor so blur at its edges sees real scene.
        max_sigma = max(self.blur_sigma(k) for k in range(self.readings.size))
        self.margin = int(np.ceil(4.0 * max_sigma)) + 1 if max_sigma > 0 else 0

    def true_height(self, k: int) -> float:
        """The LCD's true height (mm) at position ``k``: the sweep's, then its repeats (``[stage] repeat_z_mm``)."""
        n = self.z_true.size
        return float(self.z_true[k] if k < n else self.repeat_z_true[k - n])

    def _pose(self, k: int) -> np.ndarray:
        """The carriage pose (6,) at position ``k`` (sweep, then repeats)."""
        n = self.stage_pose.shape[0]
        return self.stage_pose[k] if k < n else self.repeat_pose[k - n]

    # ---- geometry -------------------------------------------------------
    def distortion_field(self, cols, rows) -> tuple[np.ndarray, np.ndarray]:
        """Non-parametric displacement (pixels) added after Brown distortion."""
        dx = np.zeros(np.broadcast(cols, rows).shape)
        dy = np.zeros_like(dx)
        for k, ph, amp in self._modes:
            wave = np.sin(k[0] * cols + ph[0]) * np.cos(k[1] * rows + ph[1])
            dx += amp[0] * wave
            dy += amp[1] * np.cos(k[0] * cols + ph[1]) * np.sin(k[1] * rows + ph[0])
        if self._ripple is not None:
            rx, ry = self._ripple(cols, rows)
            return dx * self._field_scale + rx, dy * self._field_scale + ry
        return dx * self._field_scale, dy * self._field_scale

    def rays(self, cols, rows) -> tuple[np.ndarray, np.ndarray]:
        """World rays of image points.

        Parameters
        ----------
        cols, rows : array_like, same shape S
            Image coordinates (pixel centres at integers).

        Returns
        -------
        origin, direction : (*S, 3) float64
            Ray origin (mm) and direction (unit Z component towards the LCD
            is not assumed; use the ratio) in the world frame.
        """
        cols = np.asarray(cols, dtype=float)
        rows = np.asarray(rows, dtype=float)
        fx, fy = self.distortion_field(cols, rows)
        # The extra field is defined on the image side: the Brown image point
        # is the observed one minus the field.
        xd = (cols - fx - self.K[0, 2]) / self.K[0, 0]
        yd = (rows - fy - self.K[1, 2]) / self.K[1, 1]
        # Brown (plus a thin prism, an equidistant projection: lens_models) -> ray tangents.
        x, y = lens_models.image_to_tangent(xd, yd, self.settings.lens, self.dist)
        if np.any(~np.isfinite(x)):
            raise ConfigError("simulated lens distortion is not invertible over the image; reduce it")
        d_cam = np.stack([x, y, np.ones_like(x)], axis=-1)
        o_cam = np.zeros_like(d_cam)
        o_cam[..., 2] = self.settings.lens.pupil_shift_mm * (x * x + y * y)
        rt = self.R.T
        direction = d_cam @ rt.T
        origin = self.centre + o_cam @ rt.T
        return origin, direction

    def truth(self) -> GroundTruth:
        """Exact rays of every pixel centre."""
        h, w = self.rig.camera.shape
        rows, cols = np.mgrid[0:h, 0:w].astype(float)
        o, d = self.rays(cols, rows)
        sx = d[..., 0] / d[..., 2]
        sy = d[..., 1] / d[..., 2]
        return GroundTruth(o[..., 0] - o[..., 2] * sx, o[..., 1] - o[..., 2] * sy, sx, sy,
                           self.z_true.copy(), self.stage_pose.copy())

    def _lcd_uv(self, k: int, cols: np.ndarray, rows: np.ndarray):
        """LCD coordinates (u, v), LCD px, where image points see the LCD at position k."""
        return self._lcd_uv_at(self.true_height(k), cols, rows, k)

    def _lcd_uv_at(self, z: float, cols: np.ndarray, rows: np.ndarray, k: int | None = None):
        """LCD coordinates (u, v), LCD px, where image points see the LCD at true height ``z`` (mm).

        At a stage position ``k`` the LCD has that position's pose error
        (run-out, tilt); the cover glass and the bow apply everywhere.
        """
        o, d = self.rays(cols, rows)
        pose = self._pose(k) if k is not None else np.zeros(6)
        if k is not None and k >= self.rig.stage.n_positions and any(self.settings.drift_um):
            o = o + np.array([self.settings.drift_um[0], self.settings.drift_um[1], 0.0]) * 1e-3
        if not self.physics.trivial or np.any(pose[[0, 1, 3, 4, 5]] != 0):
            return self._lcd_uv_real(z, o, d, pose)
        t = (z - o[..., 2]) / d[..., 2]
        xw = o[..., 0] + t * d[..., 0]
        yw = o[..., 1] + t * d[..., 1]
        # The LCD at true height z has travelled by (a z, b z) along the skewed stage.
        u = (xw - self.skew[0] * z) / self.rig.lcd.pitch_mm[0]
        v = (yw - self.skew[1] * z) / self.rig.lcd.pitch_mm[1]
        return u, v

    def _lcd_uv_real(self, z: float, o: np.ndarray, d: np.ndarray, pose: np.ndarray):
        """:meth:`_lcd_uv_at` through the cover glass onto a posed, bowed LCD (exact; lcd_physics)."""
        px, py = self.rig.lcd.pitch_mm
        c = np.array([(self.rig.lcd.width - 1) / 2 * px, (self.rig.lcd.height - 1) / 2 * py, 0.0])
        shift = np.array([self.skew[0] * z + 1e-3 * pose[0], self.skew[1] * z + 1e-3 * pose[1], z])
        r = pose_matrix(*pose[3:6])  # LCD -> world about the LCD centre
        # LCD frame: q = R^T (p - shift - c) + c, in row vectors p @ R; lcd_physics
        # measures its third axis toward the camera, i.e. along -Z.
        toward_camera = np.array([1.0, 1.0, -1.0])
        x, y = self.physics.hit(((o - shift - c) @ r + c) * toward_camera, (d @ r) * toward_camera)
        return x / px, y / py

    def _geometry(self, k: int) -> dict:
        """Per-position sampling geometry, cached for the frames of one position.

        For pixelated rendering each camera pixel is split into ``s`` strips
        across the pattern's axis; along each strip the integral of the
        piecewise-constant LCD profile is exact (from its running sum), so the
        footprint integration has no sampling error. For continuous patterns
        the pixel is point-sampled on an ``s`` x ``s`` grid.
        """
        if self._coords_cache is not None and self._coords_cache[0] == k:
            return self._coords_cache[1]
        s = self.settings.supersample
        h, w = self.rig.camera.shape
        m = self.margin
        h, w = h + 2 * m, w + 2 * m
        offs = (np.arange(s) + 0.5) / s - 0.5
        sub_r = (np.arange(h)[:, None] + offs[None, :]).ravel() - m
        sub_c = (np.arange(w)[:, None] + offs[None, :]).ravel() - m
        geo = {}
        if self.settings.pixelated:
            # x patterns: strips along rows; pixel edges at c -/+ 0.5.
            edges_c = np.arange(w + 1) - 0.5 - m
            u_e, v_e = self._lcd_uv(k, edges_c[None, :], sub_r[:, None])
            geo["x"] = (u_e, 0.5 * (v_e[:, 1:] + v_e[:, :-1]), self.rig.lcd.width, self.rig.lcd.height)
            edges_r = np.arange(h + 1) - 0.5 - m
            u_e, v_e = self._lcd_uv(k, sub_c[None, :], edges_r[:, None])
            # y patterns: strips along columns; transpose so the edge axis is last.
            geo["y"] = (v_e.T, 0.5 * (u_e[1:, :] + u_e[:-1, :]).T, self.rig.lcd.height, self.rig.lcd.width)
        else:
            geo["uv"] = self._lcd_uv(k, sub_c[None, :], sub_r[:, None])
        self._coords_cache = (k, geo)
        return geo

    # ---- photometry -----------------------------------------------------
    def _luminance(self, levels: np.ndarray) -> np.ndarray:
        """LCD luminance (fraction of white) for displayed levels 0..255."""
        s = self.settings
        return s.lcd_black + (1.0 - s.lcd_black) * (np.clip(levels, 0, 255) / 255.0) ** s.display_gamma

    def blur_sigma(self, k: int) -> float:
        """Gaussian defocus blur (camera px) at position ``k``."""
        return self.blur_sigma_at(self.true_height(k))

    def blur_sigma_at(self, z: float) -> float:
        """Gaussian defocus blur (camera px) with the LCD at true height ``z`` (mm)."""
        s = self.settings
        return s.blur_sigma_px + s.blur_per_mm * abs(z - s.focus_z_mm)

    def render(self, k: int, direction: str, period: int, step: int, n_steps: int) -> np.ndarray:
        """One camera frame.

        Returns
        -------
        (H, W) uint8 (8-bit camera) or uint16 (9-16 bit, values not scaled)
        """
        z_read = self.readings[k]
        f, lcd, display = self.rig.fringes, self.rig.lcd, self.rig.display
        # Through rig.display's inverse when the rig has a measured response.
        return self._render_pattern(
            k, direction, lambda: fringe_profile(lcd, f, direction, period, step, n_steps, z_read, display),
            lambda coord: fringe_values(coord, f, direction, period, step, n_steps, z_read),
            (2, k, "xy".index(direction), period_key(period), step))

    def _render_pattern(self, k: int, direction: str, profile, values, noise_key: tuple) -> np.ndarray:
        """One camera frame of a pattern varying along ``direction``'s LCD axis.

        ``profile()``: its displayed uint8 levels along the axis (pixelated
        LCD, :meth:`render_profile`); ``values(coord)``: its continuous levels
        before the display's inverse or the gamma pre-compensation (continuous
        LCD). ``noise_key`` selects the noise stream.
        """
        rig, s = self.rig, self.settings
        if s.pixelated:
            return self.render_profile(k, direction, profile(), noise_key)
        f = rig.fringes
        geo = self._geometry(k)
        h, w = rig.camera.shape
        m = self.margin
        h, w = h + 2 * m, w + 2 * m
        ss = s.supersample
        u, v = geo["uv"]
        inside = (u >= -0.5) & (u < rig.lcd.width - 0.5) & (v >= -0.5) & (v < rig.lcd.height - 0.5)
        coord = u if direction == "x" else v
        g = np.clip(values(coord), 0, 255)
        if rig.display is not None and len(rig.display.levels) >= 2:
            g = display_inverse(rig.display, g)
        elif f.gamma != 1.0:
            g = 255.0 * (g / 255.0) ** (1.0 / f.gamma)
        lum = np.where(inside, self._luminance(g), 0.0)
        if s.dust:
            lum = lum * self.dust_transmission(u, v)
        irr = lum.reshape(h, ss, w, ss).mean(axis=(1, 3))
        return self._expose(irr, self.blur_sigma(k), tuple(noise_key))

    def render_profile(self, k: int, direction: str, prof: np.ndarray, noise_key: tuple) -> np.ndarray:
        """One camera frame of any 1-D LCD profile at position ``k``, each LCD pixel integrated exactly.

        Parameters
        ----------
        k : int
        direction : {"x", "y"}
            ``prof`` varies along LCD columns (``x``) or rows (``y``).
        prof : (lcd.width,) or (lcd.height,) uint8
            Displayed levels.
        noise_key : tuple of int
            Selects the noise stream (:meth:`render` uses ``(2, k, ...)``).

        Returns
        -------
        (H, W) uint8 or uint16, like :meth:`render` (needs ``pixelated`` settings).
        """
        rig, s = self.rig, self.settings
        if not s.pixelated:
            raise ConfigError("render_profile needs pixelated = True")
        if s.dust:
            raise ConfigError("dust on the LCD is simulated with pixelated = False only")
        h, w = rig.camera.height + 2 * self.margin, rig.camera.width + 2 * self.margin
        ss = s.supersample
        edges, across, n_along, n_across = self._geometry(k)[direction]
        pad = 2
        lum = np.zeros(n_along + 2 * pad)
        lum[pad:-pad] = self._luminance(np.asarray(prof).astype(float))
        running = np.concatenate([[0.0], np.cumsum(lum)])
        # Antiderivative of the piecewise-constant profile at the pixel edges
        # (LCD pixel i covers [i - 0.5, i + 0.5); the bezel is dark).
        pos = np.clip(edges + 0.5 + pad, 0.0, lum.size - 1e-9)
        idx = pos.astype(np.intp)
        antider = running[idx] + lum[idx] * (pos - idx)
        du = np.diff(edges, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            strip = np.diff(antider, axis=-1) / du
        strip = np.where((across >= -0.5) & (across < n_across - 0.5) & np.isfinite(strip), strip, 0.0)
        if direction == "x":
            irr = strip.reshape(h, ss, w).mean(axis=1)
        else:
            irr = strip.reshape(w, ss, h).mean(axis=1).T
        return self._expose(irr, self.blur_sigma(k), tuple(noise_key))

    def render_gray(self, k: int, direction: str, bit: int, inverse: bool = False) -> np.ndarray:
        """One Gray-code camera frame (:func:`ptpcore.decode.patterns.gray_values`), like :meth:`render`."""
        z_read = self.readings[k]
        f = self.rig.fringes
        return self._render_pattern(
            k, direction, lambda: gray_profile(self.rig.lcd, f, direction, bit, inverse, z_read),
            lambda coord: gray_values(coord, f, direction, bit, inverse, z_read),
            (4, k, "xy".index(direction), bit, int(bool(inverse))))

    def render_reference(self, k: int, which: str) -> np.ndarray:
        """The ``"white"`` or ``"black"`` reference camera frame of position ``k``
        (:func:`ptpcore.decode.patterns.reference_profile`), like :meth:`render`."""
        f = self.rig.fringes
        prof = reference_profile(self.rig.lcd, f, which)
        level = f.offset + (f.amplitude if which == "white" else -f.amplitude)
        return self._render_pattern(k, "x", lambda: prof, lambda coord: np.full(np.shape(coord), level),
                                    (5, k, 0 if which == "white" else 1))

    def gray_frames(self, k: int) -> dict:
        """``{(dir, bit, inverse): image}``: the Gray-code frames of position ``k`` (empty unless
        ``unwrap = "gray"``), as :meth:`ptpcore.io.dataset.DatasetSource.gray_frames`."""
        return {(d, b, inv): self.render_gray(k, d, b, inv) for d, b, inv in self.rig.fringes.gray_frames()}

    def reference_frames(self, k: int) -> dict:
        """``{"white": image, "black": image}`` of position ``k`` when the rig has reference frames."""
        if not self.rig.has_references:
            return {}
        return {which: self.render_reference(k, which) for which in ("white", "black")}

    def dust_transmission(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Transmission (0..1) of the dust disks of the settings at LCD points ``(u, v)``."""
        t = np.ones(np.broadcast(u, v).shape)
        for du, dv, diameter, trans in self.settings.dust:
            t[np.hypot(u - du, v - dv) <= diameter / 2.0] *= trans
        return t

    def render_image(self, image, z_mm: float, noise_key=(3,)) -> np.ndarray:
        """One camera frame of any LCD image, with the LCD at true height ``z_mm``.

        Unlike :meth:`render` (which knows the pattern and integrates each LCD
        pixel exactly), this point-samples the displayed image: every camera
        pixel averages ``supersample**2`` samples of the LCD pixel each one
        hits (the dark bezel outside the screen). Meant for what a live
        capture shows besides its fringes (exposure test images, a pattern
        shown at the wrong height), not for calibration frames.

        Parameters
        ----------
        image : (lcd.height, lcd.width) uint8
            Displayed levels.
        z_mm : float
            True height of the LCD (mm).
        noise_key : tuple of int
            Selects the noise stream (with the seed); frames of :meth:`render`
            use keys starting with 2.

        Returns
        -------
        (H, W) uint8 or uint16, like :meth:`render`.
        """
        rig = self.rig
        image = np.asarray(image)
        if image.shape != (rig.lcd.height, rig.lcd.width):
            raise ValueError(f"LCD image must be {rig.lcd.height}x{rig.lcd.width} (rows x columns),"
                             f" got shape {image.shape}")
        ss = self.settings.supersample
        m = self.margin
        h, w = rig.camera.height + 2 * m, rig.camera.width + 2 * m
        cached = getattr(self, "_image_uv", None)
        if cached is None or cached[0] != float(z_mm):
            # The LCD pixel each sample hits, kept for the next frame at the same height.
            offs = (np.arange(ss) + 0.5) / ss - 0.5
            sub_r = (np.arange(h)[:, None] + offs[None, :]).ravel() - m
            sub_c = (np.arange(w)[:, None] + offs[None, :]).ravel() - m
            u, v = self._lcd_uv_at(float(z_mm), sub_c[None, :], sub_r[:, None])
            inside = (u >= -0.5) & (u < rig.lcd.width - 0.5) & (v >= -0.5) & (v < rig.lcd.height - 0.5)
            iu = np.clip(np.floor(u + 0.5), 0, rig.lcd.width - 1).astype(np.intp)
            iv = np.clip(np.floor(v + 0.5), 0, rig.lcd.height - 1).astype(np.intp)
            self._image_uv = cached = (float(z_mm), inside, iv * rig.lcd.width + iu)
        _z, inside, flat = cached
        table = self._luminance(np.arange(256, dtype=float))
        lum = np.where(inside, table[np.ravel(image)[flat]], 0.0)
        irr = lum.reshape(h, ss, w, ss).mean(axis=(1, 3))
        return self._expose(irr, self.blur_sigma_at(float(z_mm)), tuple(int(v) for v in noise_key))

    def _expose(self, irr: np.ndarray, sigma: float, noise_key: tuple) -> np.ndarray:
        """Irradiance with margin (fraction of white) -> blurred, cropped, noisy grey levels."""
        rig, s = self.rig, self.settings
        m = self.margin
        irr = np.ascontiguousarray(irr)
        h, w = irr.shape
        if sigma > 0:
            irr = cv2.GaussianBlur(irr, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        # Drop the margin: the blur near the sensor edge saw the scene beyond it.
        irr = irr[m:h - m, m:w - m]
        electrons = (irr * self._vignetting() * s.exposure + s.ambient) * s.full_well_e
        if s.noise:
            rng = np.random.default_rng([self.noise_seed, *noise_key])
            electrons = electrons + rng.standard_normal(electrons.shape) * np.sqrt(
                np.maximum(electrons, 0.0) + s.read_noise_e ** 2)
        dn = electrons / s.e_per_dn(rig.camera)
        if s.black_offset is not None:
            c0, r0, c1, r1, off = s.black_offset
            dn[int(r0):int(r1), int(c0):int(c1)] -= off
        dn = np.clip(np.rint(dn), 0, rig.camera.max_level)
        return dn.astype(np.uint8 if rig.camera.bit_depth == 8 else np.uint16)

    def _vignetting(self) -> np.ndarray:
        if not hasattr(self, "_vig"):
            h, w = self.rig.camera.shape
            rows, cols = np.mgrid[0:h, 0:w].astype(float)
            r2 = ((cols - (w - 1) / 2) ** 2 + (rows - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
            self._vig = 1.0 - self.settings.vignetting * r2
        return self._vig

    def frames(self, k: int) -> Iterator[tuple[tuple[str, int, int, int, int], np.ndarray]]:
        """Yield ``((dir, level, period, step, N), image)`` for every frame of position ``k``."""
        for spec in self.rig.fringes.frames():
            d, _j, t, n, big_n = spec
            yield spec, self.render(k, d, t, n, big_n)


def _settings_json(settings: SimSettings, seed: int, noise_seed: int | None = None) -> str:
    record = asdict(settings)
    record["lens"] = lens_models.compact_lens_record(record["lens"])  # older truth files stay byte-identical
    extra = {} if noise_seed is None or noise_seed == seed else {"noise_seed": int(noise_seed)}
    return json.dumps({"seed": seed, **extra, **record})


def settings_from_json(text: str) -> tuple[SimSettings, int]:
    """Inverse of the settings record stored in ``truth.h5``."""
    d = json.loads(text)
    seed = d.pop("seed")
    d.pop("noise_seed", None)  # another sweep of the same rig (VirtualRig's noise_seed)
    lens = LensSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.pop("lens").items()})
    d = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
    if "dust" in d:
        d["dust"] = tuple(tuple(x) for x in d["dust"])
    return SimSettings(lens=lens, **d), seed


def simulate_dataset(out_dir, rig: Rig, settings: SimSettings, seed: int = 0,
                     progress: Callable[[float, str], None] | None = None,
                     image_ext: str = ".png", noise_seed: int | None = None) -> Path:
    """Render a whole dataset folder plus ``truth.h5``.

    ``ptp-dataset/1``, or ``/2`` when the rig uses a ``/2`` key; a Gray-code rig
    (:func:`ptpcore.decode.patterns.gray_code_rig`) gets its Gray-code frames and,
    with white and black templates, its reference frames.

    Parameters
    ----------
    out_dir : path
        Created if needed. Existing images with the same names are replaced.
    rig, settings, seed
        See :class:`VirtualRig`.
    progress : callable, optional
        ``progress(fraction, message)``; may raise to cancel.
    image_ext : {".png", ".tif"}
    noise_seed : int, optional
        See :class:`VirtualRig` (recorded in ``truth.h5`` when it differs from ``seed``).

    Returns
    -------
    Path of the dataset folder.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if image_ext != Path(rig.template).suffix:
        rig = replace(rig, template=str(Path(rig.template).with_suffix(image_ext)))
    for key in ("gray_template", "white_template", "black_template"):
        t = getattr(rig, key)
        if t is not None and Path(t).suffix != image_ext:
            rig = replace(rig, **{key: str(Path(t).with_suffix(image_ext))})
    vr = VirtualRig(rig, settings, seed, noise_seed)
    save_truth(out / TRUTH_FILE, vr)
    k_total = rig.stage.n_positions + len(rig.stage.repeat_z_mm)  # the repeats after the sweep
    for k in range(k_total):
        if progress:
            progress(k / k_total, f"rendering position {k} (0 … {k_total - 1})")
        for (d, _j, t, n, big_n), img in vr.frames(k):
            write_image(out / rig.image_name(k, d, t, n, big_n), img, image_ext)
        for (d, b, inv), img in vr.gray_frames(k).items():
            write_image(out / rig.gray_name(k, d, b, inv), img, image_ext)
        for which, img in vr.reference_frames(k).items():
            write_image(out / rig.reference_name(k, which), img, image_ext)
    # rig.toml last: a folder without it is visibly incomplete.
    save_rig(rig, out / "rig.toml")
    if progress:
        progress(1.0, "simulation done")
    return out


def write_image(path: Path, img: np.ndarray, image_ext: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(image_ext, img)
    if not ok:
        raise OSError(f"{path}: could not encode image")
    write_bytes_atomic(path, buf.tobytes())


def save_truth(path, vr: VirtualRig) -> None:
    """Write the ground truth rays and the simulator settings (HDF5, atomic)."""
    truth = vr.truth()

    def fill(f) -> None:
        f.attrs["format"] = "ptp-truth/1"
        f.attrs["settings"] = _settings_json(vr.settings, vr.seed, vr.noise_seed)
        for name in ("x0", "y0", "sx", "sy"):
            f.create_dataset(name, data=getattr(truth, name), compression="gzip", compression_opts=1)
        f["z_true"] = truth.z_true
        f["stage_pose"] = truth.stage_pose
        f["K"] = vr.K
        f["dist"] = vr.dist
        f["R_cam_world"] = vr.R
        f["centre"] = vr.centre

    write_hdf5_atomic(path, fill)


def load_truth(path) -> tuple[GroundTruth, SimSettings, int]:
    """Read ``truth.h5`` (a file or a dataset folder holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / TRUTH_FILE
    with h5py.File(path, "r") as f:
        truth = GroundTruth(*(f[n][()] for n in ("x0", "y0", "sx", "sy", "z_true")),
                            f["stage_pose"][()] if "stage_pose" in f else None)
        settings, seed = settings_from_json(f.attrs["settings"])
    return truth, settings, seed
