"""The LCD's cover glass, removed from every sample before any fit (docs/method.md section 8).

The pixel plane sits behind a plane-parallel plate (thickness ``t``, index
``n``: top substrate, polarizer, cover glass). A ray meeting the LCD at
``theta`` from its normal is seen ``delta = t*(tan(theta) - tan(theta'))``,
``sin(theta') = sin(theta)/n``, closer to the foot of the normal than where
the ray in air meets the pixel plane. With the stage moving the LCD along
its normal, ``theta`` of a pixel is the same at every position, so ``delta``
is a constant per pixel along its ray's lateral direction: the correction
moves each pixel's reference ``x_ref, y_ref`` and leaves its samples'
offsets (and any spill file) untouched.

``theta`` comes from the pixels' samples: a straight line fitted to each pixel's
``X(z), Y(z)`` gives the slopes ``sx = dX/dZ``, ``sy = dY/dZ`` in the LCD frame
(its normal is Z; a skewed stage translates the LCD, it does not turn it),
``tan(theta) = hypot(sx, sy)``; the slope maps are then smoothed over the image
(:func:`smoothed_slopes`: the rays' directions vary slowly, a pixel's own line
carries its samples' noise into the correction of every one of its samples). The correction being constant per pixel, the
slopes of the corrected samples are those of the raw ones: the second pass
one might add would give the same ``theta``, so it is not run. Which way the
foot of the normal lies along ``(sx, sy)`` depends on the camera's side of the
LCD, read from where the rays converge (:func:`ptpcore.fit.flatness.away_sign`).

:func:`correct_samples` applies everything ``rig.toml`` declares: the glass,
then a measured flatness (:mod:`ptpcore.fit.flatness`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import numpy as np

from ptpcore.store import read_block
from ptpcore.io.samples import SampleStack
from ptpcore.rig.refraction import plate_offset_mm
from ptpcore.rig.rigfile import Rig

__all__ = ["GlassCorrection", "plate_offset_mm", "pixel_slopes", "smoothed_slopes", "correct_cover_glass", "correct_samples",
           "corrected_samples", "corrections_json", "add_tolerances_to_sigma", "describe_corrections", "glass_of", "BARE_PANEL",
           "NO_GLASS"]

BARE_PANEL = ("no cover glass declared ([lcd] cover_glass_mm): a bare panel is assumed; a real LCD's"
              " glass and polarizer (about 1 mm, see its datasheet) would leave the LUT tens of µm off")
NO_GLASS = "no cover glass (declared: [lcd] cover_glass_mm = 0): nothing to remove"
ROW_BLOCK_PIXELS = 1 << 20
SLOPE_SCALE = 1.0 / 160
"""Gaussian sigma of :func:`smoothed_slopes`, as a fraction of the image's larger side (4 px at 640)."""


def glass_of(rig: Rig) -> tuple[float, float, float, float]:
    """``(t_mm, index, t_sigma_mm, index_sigma)`` declared in ``rig.toml`` (``t_mm`` 0 without glass, declared or not)."""
    lcd = rig.lcd
    return (float(lcd.cover_glass_mm or 0.0), float(lcd.cover_glass_index), float(lcd.cover_glass_mm_sigma),
            float(lcd.cover_glass_index_sigma))


def pixel_slopes(samples: SampleStack, positions=None) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's straight-line slopes ``dX/dZ``, ``dY/dZ`` from its valid samples.

    Parameters
    ----------
    samples : SampleStack
        In memory or file-backed (read in row blocks).
    positions : sequence of int, optional
        Positions to use (default all).

    Returns
    -------
    sx, sy : (H, W) float64
        NaN where a pixel has fewer than 2 valid samples at distinct heights.
    """
    idx = np.arange(len(samples.z)) if positions is None else np.asarray(positions, dtype=np.intp)
    z = samples.z[idx].astype(float)
    h, w = samples.shape
    out = (np.full((h, w), np.nan), np.full((h, w), np.nan))
    rows = max(1, ROW_BLOCK_PIXELS // max(1, w * len(idx)))
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        # File reads of a spilled stack (read_block), not the memory map's pages: those would stay
        # in the process, 1.7 GB of x and y at 5 MP x 21.
        ok = read_block(samples.reasons, r0 * w, r1 * w, idx).reshape(-1, r1 - r0, w) == 0
        n = ok.sum(axis=0)
        zz = np.where(ok, z[:, None, None], 0.0)
        zm = zz.sum(axis=0) / np.maximum(n, 1)
        dz = np.where(ok, z[:, None, None] - zm, 0.0)
        szz = (dz * dz).sum(axis=0)
        for arr, dest in ((samples.x, out[0]), (samples.y, out[1])):
            v = np.where(ok, read_block(arr, r0 * w, r1 * w, idx).reshape(-1, r1 - r0, w).astype(float), 0.0)
            vm = v.sum(axis=0) / np.maximum(n, 1)
            with np.errstate(invalid="ignore", divide="ignore"):
                s = (dz * np.where(ok, v - vm, 0.0)).sum(axis=0) / szz
            dest[r0:r1] = np.where((n >= 2) & (szz > 0), s, np.nan)
    return out


def smoothed_slopes(slopes, scale: float = SLOPE_SCALE) -> tuple[np.ndarray, np.ndarray]:
    """The pixels' slopes smoothed over the image: the directions the corrections are computed from.

    A pixel's straight line (:func:`pixel_slopes`) is as noisy as its samples: on the x/y-symmetric
    rig of issue 30 (640 x 480 x 11, 1.17 mm glass) its slope error moves the glass correction by
    about 0.08 um, the same at every height and correlated with the samples' own noise (positive
    between the high positions, negative between the low ones: the line's slope leans on both ends),
    which the leave-one-out took for a model error. The rays' directions vary over a fraction of the
    image, so a locally linear smoothing (:func:`ptpcore.fit.smooth.smoothing.local_linear_smooth`:
    unbiased for linear trends, also at the image's edge) at ``scale`` of the image's larger side
    (4 px at 640) keeps the direction and leaves about 1/14 of that noise; even a lens ripple of
    0.05 px at a 32 px wavelength moves a ray's direction by only about 5e-5 (0.02 um of correction).
    On bins above 1 MP (the slope field needs no finer grid).

    Parameters
    ----------
    slopes : (2,) tuple of (H, W) float64
        ``sx, sy`` (NaN where a pixel has none).
    scale : float
        Gaussian sigma as a fraction of ``max(H, W)``.

    Returns
    -------
    sx, sy : (H, W) float64
        NaN where the pixel had no slope of its own.
    """
    from ptpcore.fit.smooth.smoothing import smooth_on_bins

    sx, sy = (np.asarray(s, dtype=np.float64) for s in slopes)
    ok = np.isfinite(sx) & np.isfinite(sy)
    if not ok.any():
        return sx, sy
    b = max(1, int(np.sqrt(sx.size / 1e6)))
    scale_px = max(scale * max(sx.shape), 4.0 * b if b > 1 else 0.0)
    smoothed, _ = smooth_on_bins(np.stack([np.where(ok, sx, 0.0), np.where(ok, sy, 0.0)]), ok.astype(np.float64),
                                 scale_px, b, with_variance=False)
    return tuple(np.where(ok & np.isfinite(m), m, np.where(ok, s, np.nan)) for m, s in zip(smoothed, (sx, sy)))


@dataclass
class GlassCorrection:
    """The cover-glass correction applied to every pixel.

    Attributes
    ----------
    t_mm, index, t_sigma_mm, index_sigma : float
        The plate as declared (thickness mm, index, their 1-sigma tolerances).
    shift_x, shift_y : (H, W) float64, mm
        Added to each pixel's samples (what ignoring the glass would have cost,
        per pixel); 0 where a pixel had no slope.
    sigma : (H, W) float64, mm
        1-sigma of the correction's length from the tolerances (0 without).
    """

    t_mm: float
    index: float
    t_sigma_mm: float
    index_sigma: float
    shift_x: np.ndarray
    shift_y: np.ndarray
    sigma: np.ndarray

    @property
    def shift_um(self) -> np.ndarray:
        """(H, W) length of each pixel's shift, um."""
        return 1e3 * np.hypot(self.shift_x, self.shift_y)

    def record(self, valid=None) -> dict:
        """JSON-ready summary: the plate, and the median and max per-pixel shift (um) over ``valid`` pixels."""
        s = self.shift_um if valid is None else self.shift_um[valid]
        s = s[np.isfinite(s) & (s > 0)]
        return {"kind": "cover_glass", "t_mm": self.t_mm, "index": self.index, "t_sigma_mm": self.t_sigma_mm,
                "index_sigma": self.index_sigma, "pixels": int(s.size),
                "median_um": float(np.median(s)) if s.size else 0.0,
                "max_um": float(np.max(s)) if s.size else 0.0}


def correct_cover_glass(samples: SampleStack, t_mm: float, index: float, t_sigma_mm: float = 0.0,
                        index_sigma: float = 0.0, positions=None, *, slopes=None,
                        away: int | None = None) -> tuple[SampleStack, GlassCorrection]:
    """Samples with the cover glass removed: where each pixel's ray in air meets the pixel plane.

    Parameters
    ----------
    samples : SampleStack
        As decoded. Not modified: the result shares its ``(K, H, W)`` arrays.
    t_mm, index : float
        The plate (``[lcd] cover_glass_mm``, ``cover_glass_index``).
    t_sigma_mm, index_sigma : float
        Datasheet tolerances (1 sigma), for :attr:`GlassCorrection.sigma`.
    positions : sequence of int, optional
        Positions whose samples give each pixel's slope (default all).
    slopes : (2,) tuple of (H, W) float64, optional
        :func:`smoothed_slopes` of :func:`pixel_slopes` of ``samples`` (computed when not given).
    away : int, optional
        +1 when Z grows away from the camera, -1 toward it
        (:func:`ptpcore.fit.flatness.away_sign`, computed when not given).

    Returns
    -------
    corrected : SampleStack
        New ``x_ref, y_ref``; ``lcd_shift`` records what was added (the decoded LCD
        point is ``absolute - lcd_shift``), ``corrections`` gains the record.
    correction : GlassCorrection
    """
    if not (t_mm >= 0 and index >= 1):
        raise ValueError(f"cover glass needs t >= 0 mm and index >= 1, got {t_mm} mm, {index}")
    from ptpcore.fit.flatness import away_sign

    sx, sy = smoothed_slopes(pixel_slopes(samples, positions)) if slopes is None else slopes
    away = away_sign(samples, (sx, sy)) if away is None else int(away)
    tan = np.hypot(sx, sy)
    ok = np.isfinite(tan)
    delta = np.where(ok, plate_offset_mm(np.where(ok, tan, 0.0), t_mm, index), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(ok & (tan > 0), sx / tan, 0.0)
        uy = np.where(ok & (tan > 0), sy / tan, 0.0)
    # docs/method.md section 2: Z grows away from the camera (away = +1), so away * (sx, sy) points away from
    # the foot of the normal; the decoded point lies delta closer to that foot than the air ray's
    # point: move it back. (run.sanity refuses readings whose sense says otherwise; away is read
    # from the rays all the same, so data on the other side is corrected the right way too.)
    shift_x, shift_y = away * delta * ux, away * delta * uy
    eps_t, eps_n = max(1e-6, 1e-3 * t_mm), 1e-6
    d_t = (plate_offset_mm(tan, t_mm + eps_t, index) - plate_offset_mm(tan, t_mm - eps_t, index)) / (2 * eps_t)
    d_n = (plate_offset_mm(tan, t_mm, index + eps_n) - plate_offset_mm(tan, t_mm, index - eps_n)) / (2 * eps_n)
    sigma = np.where(ok, np.hypot(d_t * t_sigma_mm, d_n * index_sigma), 0.0)
    corr = GlassCorrection(t_mm, index, t_sigma_mm, index_sigma, shift_x, shift_y, sigma)
    prev = samples.lcd_shift if getattr(samples, "lcd_shift", None) is not None else (0.0, 0.0)
    out = replace(samples, x_ref=samples.x_ref + shift_x, y_ref=samples.y_ref + shift_y,
                  lcd_shift=(prev[0] + shift_x, prev[1] + shift_y),
                  corrections={**samples.corrections, "cover_glass": corr.record(ok)})
    return out, corr


def correct_samples(samples: SampleStack, rig: Rig, positions=None) -> tuple[SampleStack, dict]:
    """Every correction ``rig.toml`` asks for, applied right after decoding: the cover glass, then the flatness.

    Parameters
    ----------
    samples : SampleStack
    rig : Rig
    positions : sequence of int, optional
        Positions whose samples give each pixel's slope (default all).

    Returns
    -------
    corrected : SampleStack
        ``samples`` itself (with the bare-panel record) when there is nothing to correct.
    applied : dict
        Name -> the correction object: ``"cover_glass"`` (:class:`GlassCorrection`),
        ``"flatness"`` (:class:`ptpcore.fit.flatness.FlatnessCorrection`).
    """
    from ptpcore.fit.flatness import away_sign, correct_flatness

    t, n, ts, ns = glass_of(rig)
    applied: dict = {}
    slopes = away = None
    if t > 0 or rig.lcd.flatness_um:
        slopes = smoothed_slopes(pixel_slopes(samples, positions))
        away = away_sign(samples, slopes)
    if t > 0:
        samples, applied["cover_glass"] = correct_cover_glass(samples, t, n, ts, ns, positions, slopes=slopes,
                                                              away=away)
    else:
        declared = rig.lcd.cover_glass_mm is not None
        samples = replace(samples, corrections={**samples.corrections, "cover_glass": {
            "kind": "cover_glass", "t_mm": 0.0, "declared": declared, "note": NO_GLASS if declared else BARE_PANEL}})
    if rig.lcd.flatness_um:
        samples, applied["flatness"] = correct_flatness(samples, rig, slopes, away)
    return samples, applied


def add_tolerances_to_sigma(lut, applied: dict) -> None:
    """The datasheet tolerances of the glass into the LUT's sigma maps, in quadrature (in place).

    No data can reveal a wrong thickness or index: a pixel's correction is
    uncertain by :attr:`GlassCorrection.sigma` along its ray's lateral
    direction, the same at every height.

    Parameters
    ----------
    lut : ptpcore.io.lutfile.Lut
        ``sigma_x, sigma_y`` (H, W) float32 mm, or None (then nothing to do).
    applied : dict
        From :func:`correct_samples`.
    """
    corr = applied.get("cover_glass")
    if corr is None or lut.sigma_x is None or lut.sigma_y is None or not np.any(corr.sigma):
        return
    length = np.hypot(corr.shift_x, corr.shift_y)
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(length > 0, np.abs(corr.shift_x) / length, 0.0)
        uy = np.where(length > 0, np.abs(corr.shift_y) / length, 0.0)
    lut.sigma_x = np.hypot(lut.sigma_x, corr.sigma * ux).astype(np.float32)
    lut.sigma_y = np.hypot(lut.sigma_y, corr.sigma * uy).astype(np.float32)


def corrected_samples(samples: SampleStack, rig: Rig) -> SampleStack:
    """``correct_samples(samples, rig)[0]``: the stack every fit and comparison reads."""
    return correct_samples(samples, rig)[0]


def corrections_json(samples: SampleStack) -> str:
    """The corrections a stack carries, as the JSON of ``/provenance`` ``corrections`` (FORMATS.md)."""
    return json.dumps(samples.corrections, sort_keys=True, allow_nan=False)


def describe_corrections(corrections: dict) -> list[str]:
    """One line per correction record (``SampleStack.corrections`` or the LUT's ``/provenance``).

    Parameters
    ----------
    corrections : dict
        Name -> record (as :meth:`GlassCorrection.record` writes).

    Returns
    -------
    list of str
        E.g. ``"cover glass 1.1 mm, n 1.52: per-pixel shift median 120 µm, max 257 µm"``.
    """
    lines = []
    for name, rec in sorted(corrections.items()):
        if not isinstance(rec, dict):
            lines.append(f"{name}: {rec}")
        elif rec.get("kind") == "cover_glass" and not rec.get("t_mm"):
            lines.append(NO_GLASS if rec.get("declared") else rec.get("note", BARE_PANEL))
        elif rec.get("kind") == "cover_glass":
            tol = ""
            if rec.get("t_sigma_mm") or rec.get("index_sigma"):
                tol = f" (± {rec.get('t_sigma_mm', 0):g} mm, ± {rec.get('index_sigma', 0):g})"
            lines.append(f"cover glass {rec['t_mm']:g} mm, n {rec['index']:g}{tol} removed: per-pixel shift"
                         f" median {rec['median_um']:.1f} µm, max {rec['max_um']:.1f} µm over"
                         f" {rec['pixels']} pixels (what ignoring it would have cost)")
        elif rec.get("kind") == "flatness":
            lines.append(f"panel flatness {rec.get('w_min_um', 0):g} .. {rec.get('w_max_um', 0):g} µm applied to the"
                         f" heights: per-pixel shift median {rec.get('median_um', 0):.2f} µm, max"
                         f" {rec.get('max_um', 0):.2f} µm over {rec.get('pixels', 0)} pixels (what ignoring it would"
                         " have cost)")
        elif rec.get("kind") == "stage_refinement" and "median_um" in rec:
            lines.append(f"stage pose refined over {rec.get('n_pixels', 0)} pixels (rays' RMS {rec.get('rms_um', 0):.2f}"
                         f" µm): per-pixel shift median {rec['median_um']:.2f} µm, max {rec.get('max_um', 0):.2f} µm"
                         " (what ignoring it would have cost)")
        else:
            extra = ", ".join(f"{k} {v}" for k, v in rec.items() if k != "kind")
            lines.append(f"{name}: {extra}")
    return lines
