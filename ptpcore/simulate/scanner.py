"""The whole scanner in the simulator: a projector fixed to the camera, its height sweep, object scans.

docs/method.md section 9. The camera is a :class:`~ptpcore.simulate.virtual_rig.VirtualRig` (its lens,
pose, noise model); the projector is a pinhole with its own Brown distortion, an optional smooth
non-parametric field (projector px, added to the Brown image point), a response gamma and a black
level. What the camera sees of a surface lit by the projector: for every sub-pixel sample, the
camera ray meets the surface at ``P``; the projector pixel that lights ``P`` is
``project(P)`` (an explicit forward map, no inversion needed); the pattern's level there goes through
the design's gamma pre-compensation and the projector's response, times the surface's albedo and
its Lambertian shading; then the camera's defocus blur, exposure, ambient light, shot and read
noise and quantisation (:meth:`VirtualRig._expose`).

Surfaces: the matte plate of the height sweep (an albedo that varies smoothly, a flatness bow and a
tilt against the stage axis) and objects of exact geometry (a sphere, a ball bar, a tilted plane).

Truth is exact: the true ``u_p`` a camera pixel's centre ray sees on any plane ``Z = z``
(:meth:`ScannerRig.true_up`), the height a pixel sees at any ``u_p`` (:meth:`ScannerRig.true_z`),
and each scanned object's surface and every pixel's true point on it.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from ptpcore.errors import ConfigError
from ptpcore.io.lutfile import write_hdf5_atomic
from ptpcore.rig.rigfile import (FringeDesign, HeightSweep, Projector, Rig, ScanSpec, format_period, projector_rig,
                                 save_rig, scan_to_toml)
from ptpcore.decode.patterns import fringe_values
from ptpcore.simulate.virtual_rig import SimSettings, VirtualRig, period_key, write_image, preset, scale_rig
from ptpcore.atomic import write_text_atomic

__all__ = ["ProjectorSettings", "ScannerSettings", "ScanObject", "ScannerRig", "SCANNER_PRESETS",
           "scanner_preset", "simulate_scanner_dataset", "simulate_scan", "default_objects", "load_scanner",
           "load_scan_truth", "SCANNER_TRUTH_FILE", "SCAN_TRUTH_FILE", "HeightSweepSource", "ScanSource",
           "ACCEPTANCE_FOLDER", "measuring_volume", "exact_lut", "acceptance_objects", "simulate_acceptance_scans"]

SCANNER_TRUTH_FILE = "scanner_truth.h5"
SCAN_TRUTH_FILE = "truth.h5"


@dataclass(frozen=True)
class ProjectorSettings:
    """The simulated projector: a pinhole fixed to the camera.

    Attributes
    ----------
    focal_px : float
        Focal length, projector px.
    principal_offset_px : (2,) float
        Principal point relative to the projector image's centre.
    dist : (5,) float
        Brown ``k1, k2, p1, p2, k3`` (OpenCV's convention), world -> projector image.
    field_amplitude_px : float
        Peak amplitude of a smooth non-parametric field (projector px) added to the Brown image point.
    position_mm : (3,) float
        Projector centre relative to the camera centre (world frame, mm).
    aim_z_mm : float
        The projector's axis passes through the point of the camera's axis at this world Z.
    gamma : float
        Projector response: luminance = black + (1 - black) * (level / 255) ** gamma.
    black : float
        Black level (fraction of white).
    blur_px, blur_per_mm, focus_z_mm : float
        Defocus on the camera image (camera px at the full camera width of the preset):
        ``blur_px + blur_per_mm * |z - focus_z_mm|``.
    """

    focal_px: float = 1100.0
    principal_offset_px: tuple[float, float] = (5.0, -3.0)
    dist: tuple[float, ...] = (-0.05, 0.0, 0.0, 0.0, 0.0)
    field_amplitude_px: float = 0.0
    position_mm: tuple[float, float, float] = (-80.0, 0.0, 0.0)
    aim_z_mm: float = 20.0
    gamma: float = 1.0
    black: float = 0.002
    blur_px: float = 0.6
    blur_per_mm: float = 0.02
    focus_z_mm: float = 20.0


@dataclass(frozen=True)
class ScannerSettings:
    """Everything of the simulated scanner that ``rig.toml`` does not say.

    Attributes
    ----------
    projector : ProjectorSettings
    plate_albedo_variation : float
        Relative peak-to-mean variation of the plate's (smooth) albedo.
    plate_tilt_urad : (2,) float
        The plate's tilt against the stage axis: dZ/dX and dZ/dY (urad).
    plate_bow_um : float
        The plate's flatness: a bow of this peak height (um) over the field, the same at every height.
    plate_z_error_um : float
        1-sigma error of the plate's true height against its reading (um).
    ambient : float
        Ambient light on the camera (fraction of its full well), instead of the camera preset's.
    exposure : float
        Camera exposure of a white, lit surface (fraction of the full well).
    supersample : int
        Point samples per camera pixel and axis.
    """

    name: str = "custom"
    projector: ProjectorSettings = field(default_factory=ProjectorSettings)
    plate_albedo_variation: float = 0.1
    plate_tilt_urad: tuple[float, float] = (0.0, 0.0)
    plate_bow_um: float = 0.0
    plate_z_error_um: float = 0.0
    ambient: float = 0.02
    exposure: float = 0.8
    supersample: int = 2


@dataclass(frozen=True)
class ScanObject:
    """An object of exact geometry under the scanner (world frame, mm).

    ``kind``: ``"sphere"`` (``centres`` one (3,), ``radius``), ``"ballbar"`` (two centres, one
    radius) or ``"plane"`` (``point`` (3,), ``normal`` (3,) toward the scanner, a square of side
    ``size`` about ``point``).
    """

    kind: str
    centres: tuple[tuple[float, float, float], ...] = ()
    radius: float = 0.0
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (0.0, 0.0, -1.0)
    size: float = 0.0
    albedo: float = 0.9

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray parameters ``t`` of the first hit (inf where none) and the unit normal there.

        Parameters
        ----------
        o, d : (..., 3) float64
            Ray origins and directions (world, mm).

        Returns
        -------
        t : (...) float64
        normal : (..., 3) float64, pointing toward the camera side of the surface
        """
        t = np.full(o.shape[:-1], np.inf)
        nrm = np.zeros(o.shape)
        if self.kind in ("sphere", "ballbar"):
            for c in self.centres:
                oc = o - np.asarray(c)
                a = np.einsum("...i,...i", d, d)
                b = np.einsum("...i,...i", oc, d)
                cc = np.einsum("...i,...i", oc, oc) - self.radius ** 2
                disc = b * b - a * cc
                with np.errstate(invalid="ignore"):
                    tc = (-b - np.sqrt(disc)) / a
                hit = (disc >= 0) & (tc > 0) & (tc < t)
                t = np.where(hit, tc, t)
                p = o + tc[..., None] * d
                nrm = np.where(hit[..., None], (p - np.asarray(c)) / self.radius, nrm)
            return t, nrm
        if self.kind == "plane":
            n = np.asarray(self.normal, float) / np.linalg.norm(self.normal)
            p0 = np.asarray(self.point, float)
            den = d @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                tc = ((p0 - o) @ n) / den
            p = o + tc[..., None] * d
            # a square of side ``size`` about p0, in the plane's own axes
            e1 = np.cross(n, [0.0, 1.0, 0.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(n, e1)
            rel = p - p0
            inside = (np.abs(rel @ e1) <= self.size / 2) & (np.abs(rel @ e2) <= self.size / 2)
            hit = inside & (tc > 0) & np.isfinite(tc)
            t = np.where(hit, tc, t)
            facing = np.where((d @ n)[..., None] < 0, n, -n)
            return t, np.where(hit[..., None], facing, nrm)
        raise ConfigError(f"unknown scan object kind {self.kind!r} (sphere, ballbar, plane)")

    def distance(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of points ``p`` (..., 3) from the true surface (+ outside / toward the camera)."""
        p = np.asarray(p, float)
        if self.kind in ("sphere", "ballbar"):
            dists = [np.linalg.norm(p - np.asarray(c), axis=-1) - self.radius for c in self.centres]
            return np.min(np.stack(dists), axis=0)
        n = np.asarray(self.normal, float) / np.linalg.norm(self.normal)
        return (p - np.asarray(self.point)) @ n

    def unit_normal(self, p: np.ndarray) -> np.ndarray:
        """Outward unit normal of the true surface nearest to points ``p`` (..., 3)."""
        p = np.asarray(p, float)
        if self.kind in ("sphere", "ballbar"):
            cs = np.asarray(self.centres, float)
            dist = np.linalg.norm(p[..., None, :] - cs, axis=-1)
            c = cs[np.argmin(dist, axis=-1)]
            v = p - c
            return v / np.linalg.norm(v, axis=-1, keepdims=True)
        n = np.asarray(self.normal, float) / np.linalg.norm(self.normal)
        return np.broadcast_to(n, p.shape)

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> "ScanObject":
        d = json.loads(text)
        d["centres"] = tuple(tuple(c) for c in d["centres"])
        for key in ("point", "normal"):
            d[key] = tuple(d[key])
        return cls(**d)


def _scanner_design(camera_width: int) -> Projector:
    """The projector's pattern design: 1280 x 800 px, periods 1280 (absolute), 160, 20 px, steps 4, 4, 8,
    directions ``x`` and ``y``.

    The height sweep shows both directions: ``x`` gives the heights, ``y`` adds ``v_p``, which the
    conventional (pinhole) calibration of the projector needs (FORMATS.md ``[projector]``); the
    coarsest period, 1280 px, covers ``v_p``'s 800 px too. Scans show ``x`` alone
    (:attr:`ScannerRig.scan_projector`). A camera narrower than 640 px sees each projector pixel on
    fewer camera pixels: the finest period grows as the camera shrinks (at 160 px: 80 px; ratios kept
    geometric), so each period spans as many camera pixels.
    """
    scale = camera_width / 640.0
    fine = round(20.0 / min(scale, 1.0), 1)  # one decimal: readable file names
    mid = float(np.sqrt(1280.0 * fine))
    return Projector(1280, 800, FringeDesign(("x", "y"), (1280.0, round(mid, 1), fine), (4, 4, 8), 127.5, 100.0))


def _presets() -> dict:
    """``scanner-mild``: the ``mild`` camera, projector k1 = -0.05. ``scanner-rough``: the ``rough``
    camera, projector k1 = -0.25, k2 = 0.08, p1 = p2 = 0.002 plus a 1 projector px smooth field,
    gamma 2.2 not pre-compensated, a 5 um plate bow, 10 urad of tilt, albedo varying by 30 %."""
    out = {}
    mild = ScannerSettings(name="scanner-mild", projector=ProjectorSettings(dist=(-0.05, 0.0, 0.0, 0.0, 0.0)),
                           plate_albedo_variation=0.1, plate_tilt_urad=(5.0, -3.0), plate_bow_um=1.0,
                           ambient=0.02)
    rough = ScannerSettings(name="scanner-rough",
                            projector=ProjectorSettings(dist=(-0.25, 0.08, 0.002, 0.002, 0.0), field_amplitude_px=1.0,
                                                        gamma=1.1, black=0.004, blur_px=0.8, blur_per_mm=0.03),
                            plate_albedo_variation=0.3, plate_tilt_urad=(10.0, -7.0), plate_bow_um=5.0,
                            plate_z_error_um=0.3, ambient=0.05, exposure=0.85)
    out["scanner-mild"] = ("mild", mild)
    out["scanner-rough"] = ("rough", rough)
    return out


SCANNER_PRESETS = _presets()


def scanner_preset(name: str, width: int | None = None, height: int | None = None,
                   heights: int = 21) -> tuple[Rig, SimSettings, ScannerSettings]:
    """A scanner preset: the camera preset's rig and settings with ``[projector]`` and ``[height]``.

    Parameters
    ----------
    name : {"scanner-mild", "scanner-rough"}
    width, height : int, optional
        Another camera size, same field of view (:func:`ptpcore.simulate.scale_rig`).
    heights : int
        Plate heights of the sweep, evenly over the LCD sweep's z range (default 21).
    """
    try:
        camera_preset, scanner = SCANNER_PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown scanner preset '{name}' (choose from {', '.join(SCANNER_PRESETS)})") from None
    rig, sim = preset(camera_preset)
    if width is not None or height is not None:
        rig, sim = scale_rig(rig, sim, width or rig.camera.width, height)
    z = np.linspace(min(rig.stage.z_mm), max(rig.stage.z_mm), int(heights))
    rig = replace(rig, projector=_scanner_design(rig.camera.width),
                  height=HeightSweep(tuple(float(v) for v in z)))
    # ptp-dataset/2: the projector and height tables make it so.
    return rig, sim, scanner


class ScannerRig:
    """A seeded virtual scanner: camera (a :class:`VirtualRig`) plus projector, rendering its frames.

    Parameters
    ----------
    rig : Rig
        With ``projector`` and ``height`` (:func:`scanner_preset`).
    sim : SimSettings
        The camera's settings.
    scanner : ScannerSettings
    seed : int
        The camera's seed (its lens field, stage, noise) and the scanner's own streams.
    """

    def __init__(self, rig: Rig, sim: SimSettings, scanner: ScannerSettings, seed: int = 0):
        if rig.projector is None or rig.height is None:
            raise ConfigError("the rig has no [projector] and [height]: use scanner_preset()")
        self.rig, self.sim, self.scanner, self.seed = rig, sim, scanner, int(seed)
        # The camera of the LCD sweep (same lens, pose and seed: the same rays), with the scanner's exposure
        # and ambient light.
        self.camera = VirtualRig(rig, replace(sim, exposure=scanner.exposure, ambient=scanner.ambient), seed)
        self.width_scale = rig.camera.width / 640.0
        p = scanner.projector
        pw, ph = rig.projector.width, rig.projector.height
        self.K = np.array([[p.focal_px, 0.0, (pw - 1) / 2 + p.principal_offset_px[0]],
                           [0.0, p.focal_px, (ph - 1) / 2 + p.principal_offset_px[1]], [0.0, 0.0, 1.0]])
        self.dist = np.asarray(p.dist, float)
        cam_c, r_cam = self.camera.centre, self.camera.R
        self.centre = cam_c + np.asarray(p.position_mm, float)
        # Aim: the projector's axis through the camera axis's point at Z = aim_z.
        axis_cam = r_cam.T @ np.array([0.0, 0.0, 1.0])
        target = cam_c + axis_cam * (p.aim_z_mm - cam_c[2]) / axis_cam[2]
        self.R = _look_at(target - self.centre)  # world -> projector
        rng = np.random.default_rng([self.seed, 40])
        self._modes = [(rng.uniform(0.6, 2.2, 2) * 2 * np.pi / np.array([pw, ph]), rng.uniform(0, 2 * np.pi, 2),
                        rng.normal(size=2)) for _ in range(4)]
        norm = sum(np.hypot(*m[2]) for m in self._modes)
        self._field_scale = p.field_amplitude_px / norm if norm > 0 else 0.0
        self._albedo_modes = [(rng.uniform(0.02, 0.08, 2), rng.uniform(0, 2 * np.pi, 2)) for _ in range(3)]
        zr = np.asarray(rig.height.z_mm, float)
        self.plate_z_true = zr + rng.normal(0.0, scanner.plate_z_error_um * 1e-3, zr.size)
        self.plate_centre = np.array([(rig.lcd.width - 1) / 2 * rig.lcd.pitch_mm[0],
                                      (rig.lcd.height - 1) / 2 * rig.lcd.pitch_mm[1]])
        self.plate_half = np.array([rig.lcd.width * rig.lcd.pitch_mm[0], rig.lcd.height * rig.lcd.pitch_mm[1]]) / 2
        ss = scanner.supersample
        max_blur = max(self.blur_sigma(z) for z in zr)
        self.margin = int(np.ceil(4.0 * max_blur)) + 1
        self.camera.margin = self.margin  # the camera's _expose crops this margin
        h, w = rig.camera.shape
        m = self.margin
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        self._sub_r = (np.arange(h + 2 * m)[:, None] + offs[None, :]).ravel() - m
        self._sub_c = (np.arange(w + 2 * m)[:, None] + offs[None, :]).ravel() - m
        self._geo_cache: tuple | None = None

    @property
    def scan_projector(self) -> Projector:
        """The projector's design as a scan shows it: direction ``x`` alone (what heights need,
        FORMATS.md ``ptp-scan/1``; half the frames of the height sweep's ``x`` and ``y``)."""
        p = self.rig.projector
        return replace(p, fringes=replace(p.fringes, directions=("x",)))

    # ---- projector geometry -----------------------------------------------------------------
    def field(self, ub: np.ndarray, vb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The smooth non-parametric displacement (projector px) at Brown image points."""
        dx = np.zeros(np.broadcast(ub, vb).shape)
        dy = np.zeros_like(dx)
        for k, ph, amp in self._modes:
            dx += amp[0] * np.sin(k[0] * ub + ph[0]) * np.cos(k[1] * vb + ph[1])
            dy += amp[1] * np.cos(k[0] * ub + ph[1]) * np.sin(k[1] * vb + ph[0])
        return dx * self._field_scale, dy * self._field_scale

    def project(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projector pixel ``(u_p, v_p)`` that lights world points ``p`` (..., 3) (mm)."""
        q = (np.asarray(p, float) - self.centre) @ self.R.T
        x, y = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        ub = self.K[0, 0] * xd + self.K[0, 2]
        vb = self.K[1, 1] * yd + self.K[1, 2]
        fx, fy = self.field(ub, vb)
        return ub + fx, vb + fy

    # ---- truth ------------------------------------------------------------------------------
    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Every camera pixel centre's ray: origin, direction (H, W, 3), world mm."""
        h, w = self.rig.camera.shape
        rows, cols = np.mgrid[0:h, 0:w].astype(float)
        return self.camera.rays(cols, rows)

    def true_up(self, z, rays=None) -> np.ndarray:
        """True ``u_p`` (projector px) each camera pixel's centre ray sees on the plane ``Z = z``.

        Parameters
        ----------
        z : float or (H, W) array, mm
        rays : (origin, direction), optional
            :meth:`pixel_rays`, when the caller has them.

        Returns
        -------
        (H, W) float64
        """
        o, d = self.pixel_rays() if rays is None else rays
        t = (np.asarray(z, float) - o[..., 2]) / d[..., 2]
        return self.project(o + t[..., None] * d)[0]

    def true_z(self, up: np.ndarray, z_lo: float = -20.0, z_hi: float = 60.0) -> np.ndarray:
        """The height (mm) at which each pixel's centre ray meets projector coordinate ``up`` (H, W).

        ``u_p`` is monotonic in z along a ray over the scanner's volume: 60 bisection steps
        (machine precision). NaN where ``up`` is NaN or outside the ray's range of u_p.
        """
        up = np.asarray(up, float)
        rays = self.pixel_rays()
        lo = np.full(up.shape, z_lo)
        hi = np.full(up.shape, z_hi)
        u_lo, u_hi = self.true_up(lo, rays), self.true_up(hi, rays)
        rising = u_hi > u_lo
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            above = (self.true_up(mid, rays) > up) == rising
            hi = np.where(above, mid, hi)
            lo = np.where(above, lo, mid)
        z = 0.5 * (lo + hi)
        inside = (np.minimum(u_lo, u_hi) <= up) & (up <= np.maximum(u_lo, u_hi))
        return np.where(inside, z, np.nan)

    def plate_up(self, k: int) -> np.ndarray:
        """True ``u_p`` (H, W) each camera pixel's centre ray sees on the plate at sweep height ``k``
        (its true height, tilt and bow): the truth of the height sweep's samples."""
        o, d = self.pixel_rays()
        return self.project(self.plate_point(o, d, k))[0]

    def plate_point(self, o: np.ndarray, d: np.ndarray, k: int) -> np.ndarray:
        """Where rays meet the plate at sweep height ``k``: its true height, tilt and bow (world mm)."""
        z0 = self.plate_z_true[k]
        z = np.full(o.shape[:-1], z0)
        for _ in range(4):  # the plate's departure from Z = z0 is microns: a few fixed-point steps
            t = (z - o[..., 2]) / d[..., 2]
            x, y = o[..., 0] + t * d[..., 0], o[..., 1] + t * d[..., 1]
            z = z0 + self.plate_shape(x, y)
        t = (z - o[..., 2]) / d[..., 2]
        return o + t[..., None] * d

    def plate_shape(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The plate's departure from its nominal plane (mm): tilt plus a bow, at world X, Y."""
        s = self.scanner
        dx, dy = x - self.plate_centre[0], y - self.plate_centre[1]
        r2 = (dx / self.plate_half[0]) ** 2 + (dy / self.plate_half[1]) ** 2
        return 1e-6 * (s.plate_tilt_urad[0] * dx + s.plate_tilt_urad[1] * dy) + 1e-3 * s.plate_bow_um * (1 - r2)

    def albedo(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The plate's smooth albedo (0..1) at world X, Y."""
        a = np.zeros(np.broadcast(x, y).shape)
        for k, ph in self._albedo_modes:
            a += np.sin(k[0] * x + ph[0]) * np.cos(k[1] * y + ph[1])
        return 0.9 * (1 + self.scanner.plate_albedo_variation * a / len(self._albedo_modes))

    # ---- rendering ----------------------------------------------------------------------------
    def blur_sigma(self, z: float) -> float:
        """Defocus (camera px) of the projected fringes seen at height ``z``."""
        p = self.scanner.projector
        return self.width_scale * (p.blur_px + p.blur_per_mm * abs(z - p.focus_z_mm))

    def _geometry(self, key, surface) -> dict:
        """Sub-pixel samples of one surface: projector coordinates, irradiance factor; cached per surface."""
        if self._geo_cache is not None and self._geo_cache[0] == key:
            return self._geo_cache[1]
        o, d = self.camera.rays(self._sub_c[None, :], self._sub_r[:, None])
        p, gain = surface(o, d)
        up, vp = self.project(p)
        lit = np.isfinite(up) & np.isfinite(vp) & (gain > 0)
        pw, ph = self.rig.projector.width, self.rig.projector.height
        lit &= (up >= -0.5) & (up < pw - 0.5) & (vp >= -0.5) & (vp < ph - 0.5)
        geo = {"up": np.where(lit, up, 0.0), "vp": np.where(lit, vp, 0.0), "gain": np.where(lit, gain, 0.0)}
        self._geo_cache = (key, geo)
        return geo

    def _plate_surface(self, k: int):
        def surface(o, d):
            p = self.plate_point(o, d, k)
            to_proj = self.centre - p
            # Lambertian: the plate's normal is -Z (toward the scanner), to within its microradians
            cos_i = -to_proj[..., 2] / np.linalg.norm(to_proj, axis=-1)
            return p, self.albedo(p[..., 0], p[..., 1]) * np.maximum(cos_i, 0.0)
        return surface

    def _object_surface(self, obj: ScanObject):
        def surface(o, d):
            t, nrm = obj.intersect(o, d)
            hit = np.isfinite(t)
            p = o + np.where(hit, t, 0.0)[..., None] * d
            to_proj = self.centre - p
            dist = np.linalg.norm(to_proj, axis=-1)
            cos_i = np.einsum("...i,...i", nrm, to_proj) / dist
            lit = hit & (cos_i > 0) & ~_shadowed(obj, p, to_proj / dist[..., None])
            p = np.where(hit[..., None], p, np.nan)
            return p, np.where(lit, obj.albedo * cos_i, 0.0)
        return surface

    def _frame(self, geo: dict, direction: str, period: float, step: int, n_steps: int, blur: float,
               noise_key: tuple) -> np.ndarray:
        """One camera frame of a projector pattern on a surface (:meth:`_geometry`)."""
        f = self.rig.projector.fringes
        coord = geo["up"] if direction == "x" else geo["vp"]
        g = np.clip(fringe_values(coord, f, direction, period, step, n_steps, 0.0), 0, 255)
        if f.gamma != 1.0:
            g = 255.0 * (g / 255.0) ** (1.0 / f.gamma)
        p = self.scanner.projector
        lum = p.black + (1 - p.black) * (g / 255.0) ** p.gamma
        h, w = self.rig.camera.shape
        m, ss = self.margin, self.scanner.supersample
        irr = (lum * geo["gain"]).reshape(h + 2 * m, ss, w + 2 * m, ss).mean(axis=(1, 3))
        return self.camera._expose(irr, blur, noise_key)

    def height_frames(self, k: int, directions: tuple[str, ...] | None = None):
        """Yield ``((dir, level, period, step, N), image)`` of the plate at sweep height ``k``
        (only ``directions``' frames when given; default every direction of ``[projector]``)."""
        geo = self._geometry(("plate", k), self._plate_surface(k))
        blur = self.blur_sigma(self.plate_z_true[k])
        f = self.rig.projector.fringes
        for d, j, t, n, big_n in f.frames():
            if directions is not None and d not in directions:
                continue
            yield (d, j, t, n, big_n), self._frame(geo, d, t, n, big_n, blur,
                                                   (20, k, "xy".index(d), period_key(t), n))

    def scan_frames(self, obj: ScanObject, scan_id: int = 0):
        """Yield ``((dir, level, period, step, N), image)`` of an object (defocus at its middle height)."""
        geo = self._geometry(("object", obj, scan_id), self._object_surface(obj))
        z_mid = float(np.mean([c[2] for c in obj.centres])) if obj.centres else float(obj.point[2])
        blur = self.blur_sigma(z_mid)
        for d, j, t, n, big_n in self.scan_projector.fringes.frames():
            yield (d, j, t, n, big_n), self._frame(geo, d, t, n, big_n, blur,
                                                   (21, scan_id, "xy".index(d), period_key(t), n))

    def scan_truth(self, obj: ScanObject) -> dict:
        """Per camera pixel centre: the true point on the object (NaN off it) and whether it is lit."""
        o, d = self.pixel_rays()
        t, nrm = obj.intersect(o, d)
        hit = np.isfinite(t)
        p = o + np.where(hit, t, 0.0)[..., None] * d
        to_proj = self.centre - p
        dist = np.linalg.norm(to_proj, axis=-1)
        lit = hit & (np.einsum("...i,...i", nrm, to_proj) > 0) & ~_shadowed(obj, p, to_proj / dist[..., None])
        p = np.where(hit[..., None], p, np.nan)
        return {"xyz": p, "hit": hit, "lit": lit}

    def settings_json(self) -> str:
        return json.dumps({"seed": self.seed, "scanner": asdict(self.scanner)})


class HeightSweepSource:
    """The height sweep rendered on demand (a frame source for :func:`ptpcore.run.scanner.decode_projector`).

    ``directions``: render only these (default every direction of ``[projector]``); see :meth:`showing`.
    """

    def __init__(self, sr: ScannerRig, directions: tuple[str, ...] | None = None):
        self.scanner_rig = sr
        rig = sr.rig.height_rig()
        if directions is not None:
            rig = replace(rig, fringes=replace(rig.fringes, directions=tuple(directions)))
        self.rig = rig

    def showing(self, directions: tuple[str, ...]) -> "HeightSweepSource":
        """The same sweep rendering only ``directions`` (a decoder asking for fewer skips the rest)."""
        return HeightSweepSource(self.scanner_rig, directions)

    def frames(self, k: int):
        return self.scanner_rig.height_frames(k, self.rig.fringes.directions)


class ScanSource:
    """One object's scan rendered on demand (a frame source; its rig has one position)."""

    def __init__(self, sr: ScannerRig, obj: ScanObject, scan_id: int = 0):
        self.scanner_rig, self.obj, self.scan_id = sr, obj, scan_id
        self.rig = projector_rig(sr.rig.camera, sr.scan_projector, (0.0,), "{dir}_T{period}_n{step:02d}.png")

    def frames(self, k: int):
        return self.scanner_rig.scan_frames(self.obj, self.scan_id)


def _shadowed(obj: ScanObject, p: np.ndarray, to_proj: np.ndarray) -> np.ndarray:
    """Points of a ball bar that its other ball hides from the projector (a single sphere or a plane
    shadows nothing that its own shading does not already darken)."""
    if obj.kind != "ballbar":
        return np.zeros(p.shape[:-1], bool)
    t, _ = obj.intersect(p + 1e-6 * to_proj, to_proj)
    return np.isfinite(t)


def _look_at(axis: np.ndarray) -> np.ndarray:
    """World -> projector rotation whose z axis is ``axis`` and whose x axis stays along world X."""
    z = axis / np.linalg.norm(axis)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def default_objects(rig: Rig) -> dict:
    """The scans :func:`simulate_scanner_dataset` renders: a sphere, a ball bar and a tilted plane
    in the middle of the volume, sized against its diagonal (VDI/VDE 2634-2 suggests 0.1 to 0.2 of it)."""
    cx = (rig.lcd.width - 1) / 2 * rig.lcd.pitch_mm[0]
    cy = (rig.lcd.height - 1) / 2 * rig.lcd.pitch_mm[1]
    z0, z1 = min(rig.height.z_mm), max(rig.height.z_mm)
    zm = 0.5 * (z0 + z1)
    tilt = np.radians(20.0)
    return {
        "sphere": ScanObject("sphere", ((cx + 5.0, cy - 4.0, zm + 5.0),), 12.5),
        "ballbar": ScanObject("ballbar", ((cx - 30.0, cy - 10.0, zm - 4.0), (cx + 28.0, cy + 12.0, zm + 8.0)), 9.0),
        "plane": ScanObject("plane", point=(cx, cy, zm), normal=(np.sin(tilt), 0.0, -np.cos(tilt)), size=90.0),
    }


def exact_lut(sr: ScannerRig, height_map=None):
    """A degree-1 XY LUT of the simulated camera's exact rays over the height sweep's range, sigma 0,
    with ``height_map`` as its ``/height``: what tests use to judge a height map or a scan alone.

    Returns
    -------
    ptpcore.io.lutfile.Lut
    """
    from ptpcore.io.lutfile import Lut

    o, d = sr.pixel_rays()
    sx, sy = d[..., 0] / d[..., 2], d[..., 1] / d[..., 2]
    x0, y0 = o[..., 0] - o[..., 2] * sx, o[..., 1] - o[..., 2] * sy
    z0, z1 = min(sr.rig.height.z_mm), max(sr.rig.height.z_mm)
    zc, zs = 0.5 * (z0 + z1), 0.5 * (z1 - z0)
    h, w = sx.shape
    zero = np.zeros((h, w), np.float32)
    return Lut("poly", 1, zc, zs, z0, z1, np.stack([x0 + sx * zc, sx * zs]), np.stack([y0 + sy * zc, sy * zs]), None,
               np.ones((h, w), bool), np.full((h, w), len(sr.rig.height.z_mm), np.uint16),
               np.full((h, w), z0, np.float32), np.full((h, w), z1, np.float32), zero, zero, zero, zero,
               sigma_x=zero, sigma_y=zero, height=height_map)


ACCEPTANCE_FOLDER = "acceptance"
"""Where :func:`simulate_scanner_dataset` puts the acceptance scans (``DATASET/acceptance/NAME/``)."""


def measuring_volume(sr: ScannerRig, margin: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """The scanner's measuring volume: a box (world mm) every point of which a camera pixel sees and the
    projector lights, between the height sweep's first and last heights.

    X and Y: the camera's field at both end heights intersected with the projector's, shrunk by
    ``margin`` of its width on each side (so an artefact at the box's edge is whole in the image).

    Returns
    -------
    lo, hi : (3,) float64, mm
    """
    z0, z1 = min(sr.rig.height.z_mm), max(sr.rig.height.z_mm)
    o, d = sr.pixel_rays()
    pw, ph = sr.rig.projector.width, sr.rig.projector.height
    lo, hi = np.full(2, -np.inf), np.full(2, np.inf)
    ends = []
    for z in (z0, z1):
        p = o + ((z - o[..., 2]) / d[..., 2])[..., None] * d
        # the box inside the camera's field: each image edge's innermost world coordinate
        for axis, (first, last) in enumerate(((p[:, 0, 0], p[:, -1, 0]), (p[0, :, 1], p[-1, :, 1]))):
            if first.mean() > last.mean():
                first, last = last, first
            lo[axis], hi[axis] = max(lo[axis], first.max()), min(hi[axis], last.min())
        up, vp = sr.project(p)
        ends.append((p, (up >= 0) & (up <= pw - 1) & (vp >= 0) & (vp <= ph - 1)))
    for _ in range(50):  # shrink about the middle until the projector lights all of it
        inside_dark = False
        for p, lit in ends:
            inside = np.all((p[..., :2] >= lo) & (p[..., :2] <= hi), axis=-1)
            inside_dark |= bool(np.any(inside & ~lit))
        if not inside_dark:
            break
        mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        lo, hi = mid - 0.97 * half, mid + 0.97 * half
    span = hi - lo
    return np.array([*(lo + margin * span), z0]), np.array([*(hi - margin * span), z1])


def acceptance_objects(sr: ScannerRig) -> dict:
    """The VDI/VDE 2634-2 acceptance set, sized against the measuring volume's diagonal ``L0``
    (:func:`measuring_volume`).

    - ``sphere-01`` .. ``sphere-10``: a sphere of diameter 0.13 ``L0`` (the guideline: 0.1 to 0.2) at
      the eight corners of a box inset from the volume (centres low and high in Z) and twice in the
      middle (low and high);
    - ``ballbar-01`` .. ``ballbar-07``: two balls of diameter 0.1 ``L0`` whose centres are 0.5 ``L0``
      apart (the guideline: at least 0.3; less where the volume is too narrow for both balls to be
      whole in it, never under 0.3 ``L0``), along the volume's four space diagonals, its X and Y axes
      and one diagonal of its XY face, all through the volume's centre;
    - ``plane-01`` .. ``plane-06``: a square plane of side 0.5 ``L0`` tilted 15 degrees about X, Y
      and both XY diagonals, both ways about each of X and Y, at two heights.

    Every visible point lies within the volume's Z range (its depth allows the tilts and heights
    chosen here); the plane's square may overhang the camera's field in X, Y (the points it shows
    are what a scanner measures).

    Returns
    -------
    dict of name -> ScanObject
    """
    lo, hi = measuring_volume(sr)
    span = hi - lo
    l0 = float(np.linalg.norm(span))
    c = 0.5 * (lo + hi)
    out = {}
    r = round(0.065 * l0, 2)
    z_low, z_high = lo[2] + r + 0.1 * span[2], hi[2] - 0.1 * span[2]
    corners = [(x, y) for x in (lo[0] + r + 0.12 * span[0], hi[0] - r - 0.12 * span[0])
               for y in (lo[1] + r + 0.12 * span[1], hi[1] - r - 0.12 * span[1])]
    centres = [(x, y, z) for i, (x, y) in enumerate(corners) for z in ((z_low, z_high) if i % 2 == 0
                                                                          else (z_high, z_low))]
    centres += [(c[0], c[1], z_low), (c[0], c[1], z_high)]
    for i, cen in enumerate(centres):
        out[f"sphere-{i + 1:02d}"] = ScanObject("sphere", (tuple(float(v) for v in cen),), r)
    rb, half = round(0.05 * l0, 2), 0.25 * l0
    zc = c[2] + 0.5 * rb  # the balls' visible caps reach below their centres: keep them in the volume
    dirs = [np.array([sx * span[0], sy * span[1], span[2]]) for sx, sy in ((1, 1), (-1, 1), (1, -1), (-1, -1))]
    dirs += [np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([span[0], -span[1], 0.0])]
    for i, d in enumerate(dirs):
        d = d / np.linalg.norm(d)
        # both balls whole inside the volume's X, Y (a bar along Y is shorter than 0.5 L0 when the
        # volume is narrower in Y): at least the guideline's 0.3 L0 apart
        room = min((span[k] / 2 - rb) / abs(d[k]) for k in (0, 1) if abs(d[k]) > 1e-12)
        h = max(min(half, room), 0.15 * l0)
        a, b = np.array([c[0], c[1], zc]) - h * d, np.array([c[0], c[1], zc]) + h * d
        out[f"ballbar-{i + 1:02d}"] = ScanObject("ballbar", (tuple(map(float, a)), tuple(map(float, b))), rb)
    tilt = np.radians(15.0)  # side 0.5 L0 (rounded up to 0.1 mm): the guideline's least length
    axes = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1)]
    for i, (ax, ay) in enumerate(axes):
        g = np.array([ax, ay], float) / np.hypot(ax, ay)  # the direction the plane rises toward
        normal = (float(np.sin(tilt) * g[0]), float(np.sin(tilt) * g[1]), float(-np.cos(tilt)))
        z = lo[2] + span[2] * (0.4 if i % 2 == 0 else 0.6)
        out[f"plane-{i + 1:02d}"] = ScanObject("plane", point=(float(c[0]), float(c[1]), float(z)),
                                               normal=normal, size=float(np.ceil(5.0 * l0)) / 10)
    return out


def simulate_acceptance_scans(out_dir, sr: ScannerRig, objects: dict | None = None, *,
                              progress: Callable[[float, str], None] | None = None,
                              image_ext: str = ".png", first_id: int = 100) -> list[Path]:
    """Render the acceptance set (default :func:`acceptance_objects`), one ``ptp-scan/1`` folder with
    its ``truth.h5`` per pose, in ``out_dir/NAME/`` (:func:`simulate_scan`).

    ``first_id``: the scans' noise streams are ``first_id``, ``first_id + 1``, ... (the default
    scans of :func:`simulate_scanner_dataset` use 0, 1, 2).

    Returns
    -------
    list of Path, the scan folders in order.
    """
    objects = acceptance_objects(sr) if objects is None else objects
    out = Path(out_dir)
    paths = []
    for i, (name, obj) in enumerate(objects.items()):
        if progress:
            progress(i / max(len(objects), 1), f"rendering acceptance scan {name} ({i + 1} of {len(objects)})")
        paths.append(simulate_scan(out / name, sr, obj, first_id + i, image_ext))
    if progress:
        progress(1.0, "acceptance scans rendered")
    return paths


def _write_scanner_truth(path: Path, sr: ScannerRig) -> None:
    def fill(f) -> None:
        f.attrs["format"] = "ptp-scanner-truth/1"
        f.attrs["settings"] = sr.settings_json()
        f["plate_z_true"] = sr.plate_z_true
        f["projector_K"] = sr.K
        f["projector_dist"] = sr.dist
        f["projector_R_proj_world"] = sr.R
        f["projector_centre"] = sr.centre
        # What each pixel sees on the real plate (tilt, bow, height error): the samples' truth.
        f.create_dataset("u_plate", data=np.stack([sr.plate_up(k) for k in range(sr.plate_z_true.size)]),
                         compression="gzip", compression_opts=1)

    write_hdf5_atomic(path, fill)


def simulate_scan(out_dir, sr: ScannerRig, obj: ScanObject, scan_id: int = 0, image_ext: str = ".png") -> Path:
    """Render one object scan folder (``ptp-scan/1``, one view) with its ``truth.h5``.

    Returns
    -------
    Path of the scan folder.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    template = "{dir}_T{period}_n{step:02d}" + image_ext
    spec = ScanSpec(sr.rig.camera, sr.scan_projector, template)
    for (d, _j, t, n, big_n), img in sr.scan_frames(obj, scan_id):
        write_image(out / template.format(dir=d, period=format_period(t), step=n), img, image_ext)
    truth = sr.scan_truth(obj)

    def fill(f) -> None:
        f.attrs["format"] = "ptp-scan-truth/1"
        f.attrs["object"] = obj.to_json()
        f.attrs["settings"] = sr.settings_json()
        f.create_dataset("xyz", data=truth["xyz"], compression="gzip", compression_opts=1)
        f["hit"] = truth["hit"].astype(np.uint8)
        f["lit"] = truth["lit"].astype(np.uint8)

    write_hdf5_atomic(out / SCAN_TRUTH_FILE, fill)
    write_text_atomic(out / "scan.toml", scan_to_toml(spec))  # last: a folder without it is incomplete
    return out


def simulate_scanner_dataset(out_dir, rig: Rig, sim: SimSettings, scanner: ScannerSettings, seed: int = 0,
                             objects: dict | None = None, progress: Callable[[float, str], None] | None = None,
                             image_ext: str = ".png", acceptance: bool = False) -> Path:
    """A ``ptp-dataset/2`` with the LCD sweep, the plate's height sweep and object scans, with truth.

    Writes ``rig.toml`` (``[projector]``, ``[height]``), the LCD sweep's frames and ``truth.h5``
    (:func:`ptpcore.simulate.simulate_dataset`), the height sweep's frames, ``scanner_truth.h5``
    (the projector, the plate's true heights, the true ``u_p`` each pixel sees on it), and ``scans/NAME/``, one
    ``ptp-scan/1`` folder per object (default :func:`default_objects`), each with its ``truth.h5``.
    ``acceptance``: also the VDI/VDE 2634-2 acceptance set in ``acceptance/NAME/``
    (:func:`simulate_acceptance_scans`).

    Returns
    -------
    Path of the dataset folder.
    """
    from ptpcore.simulate.virtual_rig import simulate_dataset

    out = Path(out_dir)
    lcd_rig = replace(rig, projector=None, height=None)

    def lcd_progress(frac, msg):
        if progress:
            progress(0.5 * frac, msg)

    simulate_dataset(out, lcd_rig, sim, seed, progress=lcd_progress, image_ext=image_ext)
    (out / "rig.toml").unlink()  # written again last, with the height sweep
    if Path(rig.height.template).suffix != image_ext:
        rig = replace(rig, height=replace(rig.height, template=str(Path(rig.height.template).with_suffix(image_ext))))
    sr = ScannerRig(rig, sim, scanner, seed)
    h_rig = rig.height_rig()
    k_total = len(rig.height.z_mm)
    for k in range(k_total):
        if progress:
            progress(0.5 + 0.4 * k / k_total, f"rendering plate height {k} (0 … {k_total - 1})")
        for (d, _j, t, n, big_n), img in sr.height_frames(k):
            write_image(out / h_rig.image_name(k, d, t, n, big_n), img, image_ext)
    _write_scanner_truth(out / SCANNER_TRUTH_FILE, sr)
    objects = default_objects(rig) if objects is None else objects
    share = 0.05 if acceptance else 0.1
    for i, (name, obj) in enumerate(objects.items()):
        if progress:
            progress(0.9 + share * i / max(len(objects), 1), f"rendering scan {name}")
        simulate_scan(out / "scans" / name, sr, obj, i, image_ext)
    if acceptance:
        simulate_acceptance_scans(out / ACCEPTANCE_FOLDER, sr, image_ext=image_ext,
                                  progress=(lambda f, m: progress(0.95 + 0.05 * f, m)) if progress else None)
    save_rig(rig, out / "rig.toml")
    if progress:
        progress(1.0, "simulation done")
    return out


def load_scanner(dataset_dir) -> ScannerRig:
    """The simulated scanner of a dataset folder (its ``rig.toml``, ``truth.h5`` and ``scanner_truth.h5``):
    exact truth at any height (:meth:`ScannerRig.true_up`, :meth:`ScannerRig.true_z`)."""
    from ptpcore.rig.rigfile import load_rig
    from ptpcore.simulate.virtual_rig import load_truth

    folder = Path(dataset_dir)
    rig = load_rig(folder)
    _truth, sim, seed = load_truth(folder)
    with h5py.File(folder / SCANNER_TRUTH_FILE, "r") as f:
        d = json.loads(f.attrs["settings"])
    sc = d["scanner"]
    proj = ProjectorSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in sc.pop("projector").items()})
    scanner = ScannerSettings(projector=proj, **{k: tuple(v) if isinstance(v, list) else v for k, v in sc.items()})
    return ScannerRig(rig, sim, scanner, d["seed"])


def load_scan_truth(scan_dir) -> tuple[ScanObject, dict]:
    """A simulated scan's object and per-pixel truth (``xyz`` (H, W, 3) mm, ``hit``, ``lit`` (H, W) bool)."""
    with h5py.File(Path(scan_dir) / SCAN_TRUTH_FILE, "r") as f:
        obj = ScanObject.from_json(f.attrs["object"])
        truth = {"xyz": f["xyz"][()], "hit": f["hit"][()].astype(bool), "lit": f["lit"][()].astype(bool)}
    return obj, truth
