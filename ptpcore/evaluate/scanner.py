"""The whole scanner against the simulator's exact truth (issue 34's Must show).

- :func:`height_map_accuracy`: a height map at held-out heights, against the true ``u_p -> Z``;
- :func:`scan_accuracy`: a reconstructed scan's points against the true surface, in mm and in units
  of each point's predicted sigma along the surface normal;
- :func:`diff_height_maps`: two height maps of one camera against their predicted sigmas (``ptp diff``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["HeightAccuracy", "height_map_accuracy", "ScanAccuracy", "scan_accuracy", "VDI_LEAVE_OUT",
           "HeightDiff", "diff_height_maps", "N_HEIGHT_POINTS"]

VDI_LEAVE_OUT = 0.003
"""VDI/VDE 2634-2 lets a fit leave out up to 0.3 % of its points."""


@dataclass
class HeightAccuracy:
    """A height map's error at some heights against truth (the map read at the exact ``u_p``).

    Attributes
    ----------
    rms_um, max_um : float
        RMS and largest |error| over every pixel and height (um).
    rms_z : float
        RMS of error / the map's predicted sigma_z.
    per_height_rms_um : (E,) float
    coverage : float
        Fraction of (pixel, height) the map covers (a valid map, ``u_p`` in its calibrated range).
    n : int
    """

    rms_um: float
    max_um: float
    rms_z: float
    per_height_rms_um: np.ndarray
    coverage: float
    n: int


def height_map_accuracy(hm, scanner_rig, z_eval) -> HeightAccuracy:
    """Read ``hm`` at the true ``u_p`` of every pixel on the planes ``Z = z`` (z in ``z_eval``, mm)."""
    errs, zs, per = [], [], []
    total = 0
    for z in np.asarray(z_eval, float):
        ev = hm.evaluate(scanner_rig.true_up(z))
        e = ev.z - z
        ok = np.isfinite(e)
        total += e.size
        errs.append(e[ok])
        zs.append(e[ok] / hm.sigma_z[ok])
        per.append(1e3 * np.sqrt(np.mean(e[ok] ** 2)) if ok.any() else np.nan)
    e, z = np.concatenate(errs), np.concatenate(zs)
    return HeightAccuracy(float(1e3 * np.sqrt(np.mean(e ** 2))), float(1e3 * np.max(np.abs(e))),
                          float(np.sqrt(np.mean(z ** 2))), np.asarray(per), e.size / max(total, 1), int(e.size))


@dataclass
class ScanAccuracy:
    """A scan's points against the true surface.

    Attributes
    ----------
    n_points : int
    rms_um : float
        RMS of the points' distances from the true surface (um).
    rms_normalised : float
        RMS of distance / sigma along the surface normal.
    n_beyond_4 : int
        Points whose |normalised error| exceeds 4.
    allowed_out : int
        How many points VDI/VDE 2634-2 lets a fit leave out (0.3 %, rounded down).
    coverage : float
        Points per camera pixel that sees the object lit (its truth), i.e. how much of it was measured.
    """

    n_points: int
    rms_um: float
    rms_normalised: float
    n_beyond_4: int
    allowed_out: int
    coverage: float
    distance: np.ndarray
    normalised: np.ndarray


def scan_accuracy(result, obj, truth: dict) -> ScanAccuracy:
    """Distances of a :class:`ptpcore.run.scanner.ScanResult`'s points from the true surface ``obj``.

    The sigma along the normal ``n``: a Z error moves the point along the LUT's ray ``(dX/dZ, dY/dZ, 1)``,
    the LUT's own X, Y errors are independent of it:
    ``sigma_n^2 = (n . ray)^2 sigma_Z^2 + n_x^2 sigma_LUT,X^2 + n_y^2 sigma_LUT,Y^2``.
    """
    keep = np.isfinite(result.z)
    p = np.stack([result.x[keep], result.y[keep], result.z[keep]], axis=-1)
    dist = obj.distance(p)
    n = obj.unit_normal(p)
    ray_n = n[:, 0] * result.slope_x[keep] + n[:, 1] * result.slope_y[keep] + n[:, 2]
    sig = np.sqrt((ray_n * result.sigma_z[keep]) ** 2 + (n[:, 0] * result.sigma_lut_x[keep]) ** 2
                  + (n[:, 1] * result.sigma_lut_y[keep]) ** 2)
    zn = dist / sig
    lit = int(np.count_nonzero(truth["lit"]))
    return ScanAccuracy(int(dist.size), float(1e3 * np.sqrt(np.mean(dist ** 2))), float(np.sqrt(np.mean(zn ** 2))),
                        int(np.count_nonzero(np.abs(zn) > 4)), int(VDI_LEAVE_OUT * dist.size),
                        dist.size / max(lit, 1), dist, zn)


N_HEIGHT_POINTS = 9
"""Projector coordinates two height maps are compared at, evenly over each pixel's common u_p range."""


@dataclass
class HeightDiff:
    """Two height maps of one camera compared (``ptp diff`` when both LUTs have ``/height``).

    Per pixel valid in both, ``d`` is the RMS over :data:`N_HEIGHT_POINTS` projector coordinates of
    the common ``u_p`` range of ``Z_A - Z_B``; the predicted difference is
    ``sqrt(sigma_z,A^2 + sigma_z,B^2)``, as for X and Y (module :mod:`ptpcore.evaluate.diff`).

    Attributes
    ----------
    diff, predicted : (H, W) float64, mm (NaN outside the common pixels)
    common, beyond : (H, W) bool
    n_pixels : int
    rms_um, p95_um, max_um, predicted_rms_um, ratio, fraction_beyond : float
    consistent : bool
        At most ``max_fraction`` of the common pixels beyond the tolerance.
    """

    diff: np.ndarray
    predicted: np.ndarray
    common: np.ndarray
    beyond: np.ndarray
    n_pixels: int
    rms_um: float
    p95_um: float
    max_um: float
    predicted_rms_um: float
    ratio: float
    fraction_beyond: float
    consistent: bool

    def summary(self) -> dict:
        """The numbers (no maps), for JSON."""
        return {k: (float(v) if isinstance(v, (float, np.floating)) and np.isfinite(v) else
                    (None if isinstance(v, (float, np.floating)) else v))
                for k, v in (("n_pixels", self.n_pixels), ("rms_um", self.rms_um), ("p95_um", self.p95_um),
                             ("max_um", self.max_um), ("predicted_rms_um", self.predicted_rms_um),
                             ("ratio", self.ratio), ("fraction_beyond", self.fraction_beyond),
                             ("verdict", "consistent" if self.consistent else "differ"))}


def diff_height_maps(a, b, *, tolerance_sigma: float = 3.0, tolerance_um: float = 0.0,
                     max_fraction: float = 0.01, n_points: int = N_HEIGHT_POINTS) -> HeightDiff:
    """Compare two :class:`~ptpcore.io.heightmap.HeightMap` of one camera over their common ``u_p`` ranges.

    Raises
    ------
    ValueError
        Different cameras, or no pixel with a common ``u_p`` range.
    """
    if a.shape != b.shape:
        raise ValueError(f"the height maps are of different cameras: {a.shape[1]}x{a.shape[0]} and"
                         f" {b.shape[1]}x{b.shape[0]} px")
    lo = np.fmax(a.u_min.astype(float), b.u_min.astype(float))
    hi = np.fmin(a.u_max.astype(float), b.u_max.astype(float))
    with np.errstate(invalid="ignore"):
        common = a.valid & b.valid & (hi > lo)
    if not common.any():
        raise ValueError("the height maps have no pixel with a common u_p range")
    sq = np.zeros(a.shape)
    for f in np.linspace(0.0, 1.0, int(n_points)):
        u = np.where(common, lo + f * (hi - lo), np.nan)
        dz = a.evaluate(u).z - b.evaluate(u).z
        sq += np.where(common, dz * dz, 0.0)
    d = np.where(common, np.sqrt(sq / n_points), np.nan)
    pred = np.where(common, np.sqrt(a.sigma_z.astype(float) ** 2 + b.sigma_z.astype(float) ** 2), np.nan)
    tol = np.fmax(tolerance_sigma * pred, tolerance_um * 1e-3)
    beyond = common & (d > tol)
    dc, pc = 1e3 * d[common], 1e3 * pred[common]
    rms, pred_rms = float(np.sqrt(np.mean(dc ** 2))), float(np.sqrt(np.mean(pc ** 2)))
    frac = float(beyond.sum() / common.sum())
    return HeightDiff(d, pred, common, beyond, int(common.sum()), rms, float(np.percentile(dc, 95)),
                      float(dc.max()), pred_rms, rms / pred_rms if pred_rms > 0 else float("nan"), frac,
                      frac <= max_fraction)
