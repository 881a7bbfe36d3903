"""Synthetic fringe stacks at realistic sensor sizes, fast enough to build for benchmarks.

The simulator (:mod:`ptpcore.simulate.virtual_rig`) integrates LCD pixels, blur and lens
effects exactly and is far too slow to render 1000 frames of 5-12 MP. Here the
stack is analytic instead: every camera pixel looks along a straight ray (a
pinhole camera with radial and a little tangential distortion, 500 mm in front of
the LCD), so at stage height ``z`` it sees LCD coordinates ``u(col, row, z)``,
``v(col, row, z)``; the frames are

    I = A + B cos(2 pi (u + s_k) / T + 2 pi n / N) + noise

with vignetted ``A``, ``B`` maps, a dark bezel around the LCD (seen at the top
and bottom of the image), Gaussian noise and rounding to the camera's levels.
The true rays are known, so a benchmark can also check that the LUT it timed
is right.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ptpcore.rig import Camera, FringeDesign, Lcd, Rig, Stage, save_rig

GENERATION = 2
"""Bumped whenever the rendered images change (benchmark folders are named with it, so a
folder written by an older generator is not reused). 2: rays no longer a mirror image."""

SIZES = {0.3: (640, 480), 5: (2448, 2048), 12: (4000, 3000)}
"""Megapixels -> (width, height) of the benchmark sensors."""


def sensor(mp: float) -> tuple[int, int]:
    """``(width, height)`` for a size in megapixels (0.3, 5, 12, or any: 6:5 aspect)."""
    if mp in SIZES:
        return SIZES[mp]
    w = int(round(np.sqrt(mp * 1e6 * 6 / 5) / 16) * 16)
    return w, int(round(w * 5 / 6 / 16) * 16)


def make_rig(mp: float = 5, positions: int = 21, steps=(8, 8, 8), periods=(4096, 256, 16),
             bit_depth: int = 8, ext: str = ".tif") -> Rig:
    """A rig like the real one: 3840 x 2160 LCD (50 um), stage 0..3*(K-1) mm, 2 px/mm carrier."""
    w, h = sensor(mp)
    return Rig(
        camera=Camera(w, h, bit_depth),
        lcd=Lcd(3840, 2160, (0.05, 0.05)),
        stage=Stage(tuple(3.0 * k for k in range(positions)), (0.0, 0.0, 1.0)),
        fringes=FringeDesign(("x", "y"), tuple(periods), tuple(steps), 127.5, 100.0, (2.0, 2.0), 1.0),
        template="z{pos:02d}/{dir}_T{period}_n{step}" + ext,
    )


@dataclass
class Truth:
    """The pixel rays: ``X = x0 + sx * z``, ``Y = y0 + sy * z`` (mm), (H, W) float64 each."""

    x0: np.ndarray
    y0: np.ndarray
    sx: np.ndarray
    sy: np.ndarray

    def xy(self, z: float):
        return self.x0 + self.sx * z, self.y0 + self.sy * z


class SyntheticStack:
    """Renders the frames of :func:`make_rig`'s rig (a :class:`ptpcore.io.dataset.FrameSource`).

    Parameters
    ----------
    rig : Rig
    seed : int
    noise_dn : float
        Gaussian noise, grey levels of an 8-bit camera (scaled with bit depth).
    """

    def __init__(self, rig: Rig, seed: int = 0, noise_dn: float = 1.5):
        self.rig = rig
        h, w = rig.camera.shape
        scale = rig.camera.max_level / 255.0
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        f = w * 500.0 / 160.0  # 160 mm wide at z = 0, from 500 mm
        xn, yn = (cols - (w - 1) / 2) / f, (rows - (h - 1) / 2) / f
        r2 = xn * xn + yn * yn
        # Barrel distortion (about 2.6 % at the corners) plus a little tangential.
        xd = xn * (1 - 0.6 * r2) + 0.0008 * (r2 + 2 * xn * xn)
        yd = yn * (1 - 0.6 * r2) + 0.0005 * xn * yn
        zc = -500.0
        lcd_w, lcd_h = rig.lcd.width * rig.lcd.pitch_mm[0], rig.lcd.height * rig.lcd.pitch_mm[1]
        # METHOD section 2: the camera at Z = zc < 0 looks at the screen's face along +Z, its x
        # axis along +X and its y axis (image rows) along +Y; the stage readings grow away from
        # it. Rays through the pupil: X(z) = centre + xd * (z - zc), Y(z) = centre + yd * (z - zc).
        self.truth = Truth(lcd_w / 2 - xd * zc, lcd_h / 2 - yd * zc, xd, yd)
        vign = (1.0 / (1.0 + 4.0 * r2)) ** 2
        self.a = (20.0 + 100.0 * vign) * scale
        self.b = 80.0 * vign * scale
        self.noise = noise_dn * scale
        rng = np.random.default_rng(seed)
        self._bank = [rng.normal(0.0, self.noise, (h, w)).astype(np.float32) for _ in range(7)]
        self._count = 0

    def uv(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """True LCD coordinates (u, v) in LCD px at position ``k`` (carrier not included)."""
        z = self.rig.stage.z_mm[k]
        x, y = self.truth.xy(z)
        a, b, _ = self.rig.stage.direction
        return (x - a * z) / self.rig.lcd.pitch_mm[0], (y - b * z) / self.rig.lcd.pitch_mm[1]

    def set_frames(self, k: int, d: str, j: int, out: np.ndarray | None = None) -> np.ndarray:
        """The N frames of direction ``d``, level ``j`` at position ``k``: (N, H, W)."""
        rig = self.rig
        f = rig.fringes
        t, n_steps = f.periods_px[j], f.steps[j]
        u, v = self.uv(k)
        c = u if d == "x" else v
        inside = (u >= -0.5) & (u <= rig.lcd.width - 0.5) & (v >= -0.5) & (v <= rig.lcd.height - 0.5)
        cyc = (c + f.carrier(d) * rig.stage.z_mm[k]) / t
        base = (2 * np.pi * (cyc - np.floor(cyc))).astype(np.float32)
        a = np.where(inside, self.a, 6.0 * rig.camera.max_level / 255).astype(np.float32)
        b = np.where(inside, self.b, 0.0).astype(np.float32)
        dtype = np.uint8 if rig.camera.bit_depth <= 8 else np.uint16
        if out is None:
            out = np.empty((n_steps, *rig.camera.shape), dtype)
        for n in range(n_steps):
            val = np.cos(base + np.float32(2 * np.pi * n / n_steps))
            val *= b
            val += a
            val += self._bank[self._count % len(self._bank)]
            self._count += 1
            np.rint(val, out=val)
            np.clip(val, 0, rig.camera.max_level, out=val)
            out[n] = val
        return out

    def frames(self, k: int):
        """Yield ``((dir, level, period, step, N), image)`` like a frame source."""
        f = self.rig.fringes
        for d in f.directions:
            for j, (t, n_steps) in enumerate(zip(f.periods_px, f.steps)):
                stack = self.set_frames(k, d, j)
                for n in range(n_steps):
                    yield (d, j, t, n, n_steps), stack[n]


def write_dataset(folder, rig: Rig, seed: int = 0, tiff_compression: int = 1, png_level: int = 1,
                  workers: int | None = None, progress=None) -> Path:
    """Render every image of ``rig`` into ``folder`` (a ``ptp-dataset/1`` with ``rig.toml``).

    ``tiff_compression``: 1 none (what machine-vision software saves), 5 LZW (OpenCV's default).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_rig(rig, folder / "rig.toml")
    synth = SyntheticStack(rig, seed)
    f = rig.fringes
    params = [cv2.IMWRITE_TIFF_COMPRESSION, tiff_compression] if rig.template.endswith(".tif") else \
        [cv2.IMWRITE_PNG_COMPRESSION, png_level]
    jobs = [(k, d, j) for k in range(rig.stage.n_positions) for d in f.directions for j in range(len(f.periods_px))]

    def one(job):
        k, d, j = job
        stack = synth.set_frames(k, d, j)
        for n in range(len(stack)):
            path = folder / rig.image_name(k, d, f.periods_px[j], n, f.steps[j])
            path.parent.mkdir(parents=True, exist_ok=True)
            if not cv2.imwrite(str(path), stack[n], params):
                raise OSError(f"could not write {path}")

    with ThreadPoolExecutor(workers or os.cpu_count()) as pool:
        for i, _ in enumerate(pool.map(one, jobs)):
            if progress:
                progress((i + 1) / len(jobs))
    return folder
