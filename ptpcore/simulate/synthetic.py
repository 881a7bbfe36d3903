"""Analytic synthetic data with known truth: fringe stacks at any sensor size, and samples without images.

The simulator (:mod:`ptpcore.simulate.virtual_rig`) integrates LCD pixels, blur and lens effects
exactly and is far too slow to render 1000 frames of 5-12 MP. Here the rays are analytic instead:
every camera pixel looks along a straight ray (a pinhole camera with radial and a little tangential
distortion, 500 mm in front of the LCD), so at stage height ``z`` it sees LCD coordinates
``u(col, row, z)``, ``v(col, row, z)``; the frames are

    I = A + B cos(2 pi (u + s_k) / T + 2 pi n / N) + noise

with vignetted ``A``, ``B`` maps, a dark bezel around the LCD (seen at the top and bottom of the
image), Gaussian noise and rounding to the camera's levels. The true rays are known, so a test or a
benchmark can check the LUT it made against them.

- :func:`synthetic_rig` — a rig like the real one at a sensor size given in megapixels;
- :class:`SyntheticStack` — its frames (a frame source) and its true rays (:class:`AnalyticRays`);
- :func:`synthetic_photometric_samples` — a :class:`ptpcore.io.SampleStack` made straight from the
  true rays with each sample's own predicted noise (no images, no decoding);
- :func:`white_noise_samples` — decoded samples with their values replaced by a truth plus white
  noise of each sample's predicted sigma (no model error at all, masks and sigmas kept).

Everything is seeded: the same arguments give the same arrays, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ptpcore.decode import NoiseModel
from ptpcore.fit.smooth.noise import position_sigma_from_noise
from ptpcore.io import SampleStack
from ptpcore.rig import Camera, FringeDesign, Lcd, Rig, Stage
from ptpcore.store import SpillStore, read_block

__all__ = ["SENSOR_SIZES", "SPILL_BYTES", "sensor_size", "synthetic_rig", "AnalyticRays", "SyntheticStack",
           "synthetic_photometric_samples", "white_noise_samples"]

SENSOR_SIZES = {0.3: (640, 480), 5: (2448, 2048), 12: (4000, 3000)}
"""Megapixels -> (width, height) of the benchmark sensors."""

SPILL_BYTES = 256 * 2**20
"""Above this many bytes of samples :func:`synthetic_photometric_samples` spills them to a temporary
file (``numpy.memmap`` arrays), as the product's sample collection does."""


def sensor_size(mp: float) -> tuple[int, int]:
    """``(width, height)`` of a sensor of ``mp`` megapixels (0.3, 5, 12 as listed, any other: 6:5 aspect,
    multiples of 16 px)."""
    if mp in SENSOR_SIZES:
        return SENSOR_SIZES[mp]
    w = int(round(np.sqrt(mp * 1e6 * 6 / 5) / 16) * 16)
    return w, int(round(w * 5 / 6 / 16) * 16)


def synthetic_rig(mp: float = 5, positions: int = 21, steps=(8, 8, 8), periods=(4096, 256, 16),
                  bit_depth: int = 8, ext: str = ".tif") -> Rig:
    """A rig like the real one for :class:`SyntheticStack`.

    Parameters
    ----------
    mp : float
        Sensor size in megapixels (:func:`sensor_size`).
    positions : int
        Stage positions, 0 to ``3 * (positions - 1)`` mm.
    steps, periods : tuple of int
        Phase steps and periods (LCD px) of each fringe level, coarsest first.
    bit_depth : int
    ext : str
        Image file extension of the rig's template (``.tif`` or ``.png``).

    Returns
    -------
    Rig
        A 3840 x 2160 LCD of 50 um pixels, the stage along +Z, a 2 px/mm carrier.
    """
    w, h = sensor_size(mp)
    return Rig(
        camera=Camera(w, h, bit_depth),
        lcd=Lcd(3840, 2160, (0.05, 0.05)),
        stage=Stage(tuple(3.0 * k for k in range(positions)), (0.0, 0.0, 1.0)),
        fringes=FringeDesign(("x", "y"), tuple(periods), tuple(steps), 127.5, 100.0, (2.0, 2.0), 1.0),
        template="z{pos:02d}/{dir}_T{period}_n{step}" + ext,
    )


@dataclass
class AnalyticRays:
    """The pixel rays: ``X = x0 + sx * z``, ``Y = y0 + sy * z`` (mm), (H, W) float64 each."""

    x0: np.ndarray
    y0: np.ndarray
    sx: np.ndarray
    sy: np.ndarray

    def xy(self, z):
        """``(X, Y)`` (mm) at height ``z`` (mm, a number or an (H, W) map)."""
        return self.x0 + self.sx * z, self.y0 + self.sy * z


class SyntheticStack:
    """Renders the frames of :func:`synthetic_rig`'s rig (a :class:`ptpcore.io.dataset.FrameSource`).

    Parameters
    ----------
    rig : Rig
    seed : int
        Seeds the bank of noise images the frames draw from.
    noise_dn : float
        Gaussian noise, grey levels of an 8-bit camera (scaled with bit depth).

    Attributes
    ----------
    truth : AnalyticRays
        Every pixel's true ray.
    a, b : (H, W) float64
        Background and modulation (grey levels) inside the LCD.
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
        # docs/method.md section 2: the camera at Z = zc < 0 looks at the screen's face along +Z, its x
        # axis along +X and its y axis (image rows) along +Y; the stage readings grow away from
        # it. Rays through the pupil: X(z) = centre + xd * (z - zc), Y(z) = centre + yd * (z - zc).
        self.truth = AnalyticRays(lcd_w / 2 - xd * zc, lcd_h / 2 - yd * zc, xd, yd)
        vign = (1.0 / (1.0 + 4.0 * r2)) ** 2
        self.a = (20.0 + 100.0 * vign) * scale
        self.b = 80.0 * vign * scale
        self.noise = noise_dn * scale
        rng = np.random.default_rng(seed)
        self._bank = [rng.normal(0.0, self.noise, (h, w)).astype(np.float32) for _ in range(7)]
        self._count = 0

    def uv(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """True LCD coordinates ``(u, v)``, (H, W) LCD px, at position ``k`` (carrier not included)."""
        z = self.rig.stage.z_mm[k]
        x, y = self.truth.xy(z)
        a, b, _ = self.rig.stage.direction
        return (x - a * z) / self.rig.lcd.pitch_mm[0], (y - b * z) / self.rig.lcd.pitch_mm[1]

    def set_frames(self, k: int, d: str, j: int, out: np.ndarray | None = None) -> np.ndarray:
        """The N frames of direction ``d``, level ``j`` at position ``k``: (N, H, W) uint8 or uint16."""
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
        """Yield ``((dir, level, period, step, N), image)`` of position ``k``, like a frame source."""
        f = self.rig.fringes
        for d in f.directions:
            for j, (t, n_steps) in enumerate(zip(f.periods_px, f.steps)):
                stack = self.set_frames(k, d, j)
                for n in range(n_steps):
                    yield (d, j, t, n, n_steps), stack[n]


def synthetic_photometric_samples(mp: float, k: int, seed: int = 0,
                                  spill: bool | None = None) -> tuple[SampleStack, Rig, AnalyticRays]:
    """Samples made straight from :class:`SyntheticStack`'s true rays, with photometry and noise.

    X and Y are the exact rays plus Gaussian noise of each sample's own predicted sigma (from its
    modulation and background through a :class:`ptpcore.decode.NoiseModel`, as the smooth fit
    predicts it); a few % of the samples are invalid in regions (bezel, border, saturation) that move
    with z, and the modulation falls by 1 % per position (a little defocus).

    Parameters
    ----------
    mp : float
        Sensor size in megapixels (:func:`sensor_size`).
    k : int
        Positions (:func:`synthetic_rig`'s stage).
    seed : int
    spill : bool, optional
        Keep the samples in a temporary file (``numpy.memmap`` arrays); default: above
        :data:`SPILL_BYTES`.

    Returns
    -------
    samples : SampleStack
        ``x``, ``y`` (K, H, W) float32 mm (NaN where invalid), with ``modulation``, ``background``
        and the noise model.
    rig : Rig
    truth : AnalyticRays
    """
    rig = synthetic_rig(mp, k)
    synth = SyntheticStack(rig, seed)
    truth = synth.truth
    h, w = rig.camera.shape
    z = np.asarray(rig.stage.z_mm, dtype=float)
    noise = NoiseModel(read_var=1.5 ** 2, gain=0.02)
    f = rig.fringes
    bg = synth.a.astype(np.float32)
    mod = synth.b.astype(np.float32)
    # The smooth fit's own noise prediction (ptpcore.fit.smooth.noise.sample_sigma_from_noise).
    sig = (np.sqrt(2.0 / f.steps[-1]) * noise.sigma_dn(bg) / mod * f.periods_px[-1] / (2 * np.pi)
           * max(rig.lcd.pitch_mm)).astype(np.float32)
    del synth
    spill = k * h * w * 17 > SPILL_BYTES if spill is None else spill
    fields = {"x": np.float32, "y": np.float32, "reasons": np.uint8, "modulation": np.float32,
              "background": np.float32}
    if spill:
        store = SpillStore(k, (h, w), fields, {})
    else:
        arrays = {n: np.empty((k, h, w), dt) for n, dt in fields.items()}
    rng = np.random.default_rng(seed)
    x_ref, y_ref = truth.x0.copy(), truth.y0.copy()
    for i in range(k):
        reasons = np.zeros((h, w), np.uint8)
        # Invalid samples come in regions (bezel, border, saturation) that move with z.
        reasons[: int(h * (0.02 + 0.002 * i))] = 1
        reasons[:, w - int(w * (0.03 - 0.001 * (i % 7))):] = 8
        m = (mod * np.float32(1.0 - 0.01 * i)).astype(np.float32)  # a little defocus with z
        s = sig / np.float32(1.0 - 0.01 * i)
        pos = {"x": (truth.sx * z[i] + s * rng.standard_normal((h, w), np.float32)).astype(np.float32),
               "y": (truth.sy * z[i] + s * rng.standard_normal((h, w), np.float32)).astype(np.float32),
               "reasons": reasons, "modulation": m, "background": bg}
        pos["x"][reasons != 0] = np.nan
        pos["y"][reasons != 0] = np.nan
        for n, a in pos.items():
            if spill:
                store.write(n, i, a)
            else:
                arrays[n][i] = a
        del pos
    if spill:
        arrays = store.arrays()
    samples = SampleStack(z, arrays["x"], arrays["y"], x_ref, y_ref, arrays["reasons"], arrays["modulation"],
                          arrays["background"], noise)
    return samples, rig, truth


def white_noise_samples(samples: SampleStack, rig: Rig, truth, seed: int | None, heights=None) -> SampleStack:
    """``samples`` with every valid value replaced by the truth plus white noise of its predicted sigma.

    The masks, heights, photometry and noise model are kept, so the samples' predicted sigma
    (:func:`ptpcore.fit.smooth.noise.position_sigma_from_noise`) is exactly the sigma of their noise and
    no model error exists: what a fit of them gets wrong is its own noise and its own bias.

    Parameters
    ----------
    samples : SampleStack
        Decoded samples with ``modulation``, ``background`` and a noise model; not modified.
    rig : Rig
    truth
        The rays: an object whose ``xy(z)`` gives ``(X, Y)`` (H, W) mm at an (H, W) height map
        (:class:`ptpcore.simulate.GroundTruth`, :class:`AnalyticRays`).
    seed : int or None
        The noise's seed; None: no noise (the truth itself).
    heights : (K,) float, mm, optional
        Where each position's truth is taken (default the readings ``samples.z``; a simulator's
        ``truth.z_true`` carries the sweep's stage errors).

    Returns
    -------
    SampleStack
        A copy with new ``x``, ``y`` (K, H, W) float32 arrays (NaN where a sample is invalid).
    """
    h, w = samples.shape
    k_all = samples.z.size
    rng = None if seed is None else np.random.default_rng(seed)
    heights = samples.z if heights is None else heights
    xs, ys = np.empty((k_all, h, w), np.float32), np.empty((k_all, h, w), np.float32)
    for k in range(k_all):
        ok = read_block(samples.reasons, 0, h * w, [k])[0].reshape(h, w) == 0
        tx, ty = truth.xy(np.full((h, w), heights[k]))
        nx = ny = 0.0
        if rng is not None:
            sig = position_sigma_from_noise(samples, rig, k)
            nx, ny = sig * rng.standard_normal((h, w)), sig * rng.standard_normal((h, w))
        xs[k] = np.where(ok, tx + nx - samples.x_ref, np.nan)
        ys[k] = np.where(ok, ty + ny - samples.y_ref, np.nan)
    return replace(samples, x=xs, y=ys)
