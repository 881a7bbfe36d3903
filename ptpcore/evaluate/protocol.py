"""The comparison: point-to-point LUTs against 3DSTC on held-out heights (METHOD.md sections 6-7).

All methods (:data:`METHODS`) are calibrated on the same calibration positions
of one :class:`~ptpcore.lut.SampleStack` and judged at the held-out positions only:

- **PTP**: a per-pixel LUT (:func:`ptpcore.lut.fit_lut`) evaluated at the
  held-out stage reading ``z_k``.
- **PTP smooth** (``"smooth"``, optional): the per-pixel LUT regularised
  across neighbouring pixels (:func:`ptpcore.smooth.fit_smooth_lut`: a global
  pinhole + Brown model plus a per-pixel correction smoothed over the image at
  a cross-validated scale), evaluated like PTP.
- **3DSTC**: a pinhole + Brown camera (:func:`ptpcore.pinhole.fit_pinhole`)
  calibrated from M feature points drawn at random (seeded) from the valid
  samples of the calibration positions, camera pixel ``(col, row)`` <-> world
  ``(X, Y, Z = z_k)``; for a pixel at ``z_k`` it undistorts, casts the ray and
  intersects the plane.

Each method gives ``X, Y`` for every pixel at every held-out height. They are
compared against two references:

``measured``
    The held-out samples themselves: the LCD's known geometry as decoded from
    the fringes. Always available; it carries the held-out samples' own noise,
    which adds to both methods' errors alike.
``truth``
    The simulator's exact rays (when a :class:`~ptpcore.simulate.GroundTruth`
    is given), evaluated at the stage reading like the methods.

Pixels are compared where the held-out sample is valid *and* every method gives
a value (the LUTs are within the pixel's calibrated range, the pinhole
back-projection exists), so all methods are judged on exactly the same
pixels and both references on the same pixels.

Coordinate error of a pixel: the vector ``(dX, dY)`` = method minus reference;
its statistics are those of the length ``|(dX, dY)|``. Distance error of a
point pair: the method's 3D distance minus the reference's, with the pair's
points at their held-out heights (same height, or two different heights held
out by the same calibration); pairs are stratified so their distances spread
evenly over the field.

Everything is returned as dataclasses and numpy arrays; nothing is drawn here.
Lengths in arrays are mm; statistics are µm (``*_um``).
"""

from __future__ import annotations

import datetime as _dt
import math
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ptpcore import __version__
from ptpcore.io.lutfile import MODELS
from ptpcore.fit.perpixel import fit_lut
from ptpcore.io.samples import SampleStack
from ptpcore.pinhole.camera import PinholeFit, fit_pinhole
from ptpcore.rig.rigfile import Rig
from ptpcore.fit.smooth import fit_smooth_lut

__all__ = [
    "COMPARE_FORMAT",
    "SPLITS",
    "METHODS",
    "METHOD_LABELS",
    "REFERENCES",
    "PAIR_KINDS",
    "ErrorStats",
    "CoordinateStats",
    "DistanceCurve",
    "PairSet",
    "DistanceErrors",
    "MethodReport",
    "Verdict",
    "ReferenceReport",
    "FeaturePoints",
    "Fold",
    "Coverage",
    "CompareResult",
    "split_positions",
    "draw_features",
    "coordinate_stats",
    "error_stats",
    "compare",
    "smooth_degree_for",
    "format_summary",
]

COMPARE_FORMAT = "ptp-compare/1"
SPLITS = ("alternate", "loo")
#: Every method the comparison knows, in display order (a result holds these or a subset:
#: :attr:`CompareResult.methods`).
METHODS = ("ptp", "smooth", "3dstc")
REFERENCES = ("measured", "truth")
PAIR_KINDS = ("same_height", "across_heights")
METHOD_LABELS = {"ptp": "PTP", "smooth": "PTP smooth", "3dstc": "3DSTC"}

Progress = Callable[[float, str], None]


# ----------------------------------------------------------------------------- statistics

@dataclass
class ErrorStats:
    """Summary of a set of errors ``e`` (µm).

    Attributes
    ----------
    n : int
        Number of errors.
    rms_um : float
        ``sqrt(mean(e**2))``.
    mean_um : float
        ``mean(e)``: the bias for signed errors (distances), the mean length for
        coordinate errors.
    p95_um, max_um : float
        95th percentile and maximum of ``|e|``.

    All values are NaN when ``n == 0``.
    """

    n: int
    rms_um: float
    mean_um: float
    p95_um: float
    max_um: float

    def to_json_dict(self) -> dict:
        return {k: _jsonable(v) for k, v in self.__dict__.items()}


@dataclass
class CoordinateStats(ErrorStats):
    """Coordinate errors: :class:`ErrorStats` of the length ``|(dX, dY)|`` plus per-axis values.

    Attributes
    ----------
    rms_x_um, rms_y_um : float
        RMS of ``dX`` and of ``dY`` (``rms_um**2 = rms_x_um**2 + rms_y_um**2``).
    mean_x_um, mean_y_um : float
        Mean signed ``dX``, ``dY`` (bias).
    """

    rms_x_um: float
    rms_y_um: float
    mean_x_um: float
    mean_y_um: float


def error_stats(e) -> ErrorStats:
    """:class:`ErrorStats` of errors ``e`` (any shape, mm; NaN entries ignored)."""
    e = np.asarray(e, dtype=float).ravel()
    e = e[np.isfinite(e)]
    if e.size == 0:
        return ErrorStats(0, math.nan, math.nan, math.nan, math.nan)
    a = np.abs(e)
    return ErrorStats(int(e.size), float(np.sqrt(np.mean(e * e)) * 1e3), float(np.mean(e) * 1e3),
                      float(np.percentile(a, 95) * 1e3), float(a.max() * 1e3))


def coordinate_stats(dx, dy) -> CoordinateStats:
    """:class:`CoordinateStats` of coordinate errors.

    Parameters
    ----------
    dx, dy : array_like, same shape, mm
        Method minus reference; entries where either is NaN are ignored.
    """
    dx = np.asarray(dx, dtype=float).ravel()
    dy = np.asarray(dy, dtype=float).ravel()
    ok = np.isfinite(dx) & np.isfinite(dy)
    dx, dy = dx[ok], dy[ok]
    base = error_stats(np.hypot(dx, dy))
    if base.n == 0:
        return CoordinateStats(**base.__dict__, rms_x_um=math.nan, rms_y_um=math.nan,
                               mean_x_um=math.nan, mean_y_um=math.nan)
    return CoordinateStats(**base.__dict__,
                           rms_x_um=float(np.sqrt(np.mean(dx * dx)) * 1e3),
                           rms_y_um=float(np.sqrt(np.mean(dy * dy)) * 1e3),
                           mean_x_um=float(np.mean(dx) * 1e3), mean_y_um=float(np.mean(dy) * 1e3))


@dataclass
class DistanceCurve:
    """Distance error against distance, in bins of the reference distance.

    Attributes
    ----------
    edges_mm : (B+1,) float64
        Bin edges of the reference distance (mm).
    count : (B,) int64
        Pairs per bin.
    rms_um, mean_um, p95_um : (B,) float64
        As :class:`ErrorStats`, per bin; NaN for empty bins.
    """

    edges_mm: np.ndarray
    count: np.ndarray
    rms_um: np.ndarray
    mean_um: np.ndarray
    p95_um: np.ndarray

    def to_json_dict(self) -> dict:
        return {k: _jsonable(v) for k, v in self.__dict__.items()}


def _curve(distance_mm: np.ndarray, error_mm: np.ndarray, edges: np.ndarray) -> DistanceCurve:
    nb = max(len(edges) - 1, 0)
    b = np.clip(np.searchsorted(edges, distance_mm, side="right") - 1, 0, max(nb - 1, 0))
    out = {k: np.full(nb, np.nan) for k in ("rms", "mean", "p95")}
    count = np.zeros(nb, np.int64)
    for i in range(nb):
        s = error_stats(error_mm[b == i])
        count[i] = s.n
        out["rms"][i], out["mean"][i], out["p95"][i] = s.rms_um, s.mean_um, s.p95_um
    return DistanceCurve(np.asarray(edges, float), count, out["rms"], out["mean"], out["p95"])


# ----------------------------------------------------------------------------- result types

@dataclass
class PairSet:
    """Point pairs for distance errors.

    Attributes
    ----------
    kind : {"same_height", "across_heights"}
    held_a, held_b : (P,) int64
        Indices into :attr:`CompareResult.held_positions` of each end's height.
    row_a, col_a, row_b, col_b : (P,) int64
        Camera pixels of the two ends.
    edges_mm : (B+1,) float64
        Bins of the measured distance used to spread the pairs over the field
        (equal quotas per bin); also the bins of the error-vs-distance curves.
    """

    kind: str
    held_a: np.ndarray
    held_b: np.ndarray
    row_a: np.ndarray
    col_a: np.ndarray
    row_b: np.ndarray
    col_b: np.ndarray
    edges_mm: np.ndarray

    def __len__(self) -> int:
        return int(self.held_a.size)


@dataclass
class DistanceErrors:
    """Distance errors of one method against one reference over one :class:`PairSet`.

    Attributes
    ----------
    kind, method, reference : str
    reference_mm : (P,) float64
        The reference's 3D distance of every pair (mm).
    error_mm : (P,) float64
        Method's distance minus the reference's (mm).
    stats : ErrorStats
    curve : DistanceCurve
    """

    kind: str
    method: str
    reference: str
    reference_mm: np.ndarray
    error_mm: np.ndarray
    stats: ErrorStats
    curve: DistanceCurve


@dataclass
class MethodReport:
    """One method against one reference at the held-out heights.

    Attributes
    ----------
    method : {"ptp", "smooth", "3dstc"}
    reference : {"measured", "truth"}
    coordinate : CoordinateStats
        Over every compared pixel of every held-out position.
    per_position : list of CoordinateStats
        One per held-out position (order of :attr:`CompareResult.held_positions`).
    heatmap_mm : (H, W) float64, mm
        Per pixel, the RMS over held-out positions of ``|(dX, dY)|``; NaN where
        the pixel was never compared. Per-position maps: :meth:`CompareResult.errors`.
    distance : dict of str to DistanceErrors
        Keyed by pair kind (:data:`PAIR_KINDS`).
    """

    method: str
    reference: str
    coordinate: CoordinateStats
    per_position: list
    heatmap_mm: np.ndarray
    distance: dict


@dataclass
class Verdict:
    """Who is ahead against one reference, and by how much.

    Attributes
    ----------
    reference : str
    coordinate_ahead : {"ptp", "smooth", "3dstc", "tie"}
        Method with the smallest coordinate RMS ("tie" when the best two are equal).
    coordinate_ratio : float
        RMS of the runner-up over RMS of the method ahead (>= 1); with two
        methods, of the method behind.
    distance_ahead : {"ptp", "smooth", "3dstc", "tie"} or None
        Method with the smallest RMS distance error over all pairs of both
        kinds; None without pairs.
    distance_ratio : float
        As ``coordinate_ratio`` for distances (NaN without pairs).
    text : str
        One sentence stating the above, with every method's RMS.
    coordinate_rms_um, distance_rms_um : dict of str to float
        Every method's coordinate RMS and RMS distance error (µm), for
        pairwise ratios (:meth:`ratio`).
    """

    reference: str
    coordinate_ahead: str
    coordinate_ratio: float
    distance_ahead: str | None
    distance_ratio: float
    text: str
    coordinate_rms_um: dict = field(default_factory=dict)
    distance_rms_um: dict = field(default_factory=dict)

    def ratio(self, behind: str, ahead: str, kind: str = "coordinate") -> float:
        """RMS of method ``behind`` over RMS of method ``ahead`` (``kind``: "coordinate" or "distance")."""
        rms = {"coordinate": self.coordinate_rms_um, "distance": self.distance_rms_um}[kind]
        a, b = rms[ahead], rms[behind]
        return b / a if a > 0 else (math.inf if b > 0 else 1.0)


@dataclass
class ReferenceReport:
    """Every method against one reference.

    Attributes
    ----------
    reference : str
    methods : dict of str to MethodReport
        Keyed by method (:attr:`CompareResult.methods`: ``"ptp"``, ``"smooth"``, ``"3dstc"``).
    verdict : Verdict
    """

    reference: str
    methods: dict
    verdict: Verdict


@dataclass
class FeaturePoints:
    """3DSTC feature points.

    Attributes
    ----------
    points_world : (M, 3) float64, mm
        Measured ``X, Y`` of the sample and ``Z`` = its stage reading.
    pixels : (M, 2) float64, px
        Camera pixel ``(col, row)`` (integers: pixel centres).
    position : (M,) int64
        Position index of each point.
    """

    points_world: np.ndarray
    pixels: np.ndarray
    position: np.ndarray


@dataclass
class Fold:
    """One calibration of every method.

    Attributes
    ----------
    calibration : (Kc,) int64
        Positions every method was calibrated on.
    held_out : (Kh,) int64
        Positions this calibration is judged on.
    pinhole : PinholeFit
        The 3DSTC camera fitted on ``features``.
    features : FeaturePoints
    lut_valid_fraction : float
        Fraction of pixels with a usable LUT.
    warnings : list of str
        Warnings of the 3DSTC fit (e.g. Levenberg-Marquardt did not converge,
        as happens for the rational model when the lens has no rational part).
    smooth_valid_fraction : float or None
        Fraction of pixels with a usable smooth LUT (None without it).
    smooth_scale_px : float or None
        The smooth LUT's smoothing scale chosen by cross-validation (camera
        px; 0: not smoothed).
    """

    calibration: np.ndarray
    held_out: np.ndarray
    pinhole: PinholeFit
    features: FeaturePoints
    lut_valid_fraction: float
    warnings: list = field(default_factory=list)
    smooth_valid_fraction: float | None = None
    smooth_scale_px: float | None = None


@dataclass
class Coverage:
    """Pixels per held-out position (each ``(E,)`` int64).

    Attributes
    ----------
    n_measured : valid held-out samples
    n_ptp : of those, pixels where the LUT gives a value (within its calibrated range)
    n_3dstc : of those, pixels where the pinhole back-projection exists
    n_compared : pixels where every method does (the compared set)
    n_smooth : of the valid samples, pixels where the smooth LUT gives a value
        (None without the smooth method)
    """

    n_measured: np.ndarray
    n_ptp: np.ndarray
    n_3dstc: np.ndarray
    n_compared: np.ndarray
    n_smooth: np.ndarray | None = None


@dataclass
class CompareResult:
    """Everything the comparison found.

    Attributes
    ----------
    split : {"alternate", "loo"}
    seed, n_points : int
    rational : bool
    lut_model : str
    lut_degree : int or None
        The plain PTP LUT's model and degree.
    z_mm : (K,) float64
        Stage readings of all positions (mm).
    held_positions : (E,) int64
        Held-out positions, ascending.
    z_held : (E,) float64
        Their stage readings (mm).
    fold_of_held : (E,) int64
        Index into ``folds`` of the calibration that judged each held-out position.
    folds : list of Fold
        One for ``alternate``; one per held-out position for ``loo``.
    mask : (E, H, W) bool
        Compared pixels.
    error_vs_measured : dict of str to (2, E, H, W) float32, mm
        Per method, ``(dX, dY)`` = method minus measured sample; NaN outside ``mask``.
    measured_minus_truth : (2, E, H, W) float32 or None, mm
        The held-out samples' own error against the truth (NaN outside ``mask``).
    coverage : Coverage
    pairs : dict of str to PairSet
        Keyed by :data:`PAIR_KINDS`.
    references : dict of str to ReferenceReport
        ``"measured"`` always, ``"truth"`` when a truth was given.
    reference_noise : CoordinateStats or None
        Measured held-out samples against the truth: the noise that the
        ``measured`` reference adds to every method's errors.
    methods : tuple of str
        The methods compared, in :data:`METHODS` order.
    smooth_degree : int or None
        Polynomial degree of the smooth LUT (None without it).
    notes : list of str
        What the reader should know about the run (e.g. why the smooth LUT
        was left out, or fitted without smoothing).
    """

    split: str
    seed: int
    n_points: int
    rational: bool
    lut_model: str
    lut_degree: int | None
    z_mm: np.ndarray
    held_positions: np.ndarray
    z_held: np.ndarray
    fold_of_held: np.ndarray
    folds: list
    mask: np.ndarray
    error_vs_measured: dict
    measured_minus_truth: np.ndarray | None
    coverage: Coverage
    pairs: dict
    references: dict = field(default_factory=dict)
    reference_noise: CoordinateStats | None = None
    methods: tuple = METHODS
    smooth_degree: int | None = None
    notes: list = field(default_factory=list)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the camera."""
        return self.mask.shape[1:]

    @property
    def pinhole(self) -> PinholeFit:
        """The 3DSTC fit of the first fold (the only one for ``alternate``)."""
        return self.folds[0].pinhole

    def errors(self, method: str, reference: str) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel coordinate errors at every held-out position.

        Parameters
        ----------
        method : one of :attr:`methods` ({"ptp", "smooth", "3dstc"})
        reference : {"measured", "truth"}

        Returns
        -------
        dx, dy : (E, H, W) float64, mm
            Method minus reference; NaN outside :attr:`mask`. Error heatmaps
            are ``np.hypot(dx, dy)``.
        """
        if method not in self.methods:
            raise ValueError(f"method must be one of {self.methods}, got {method!r}")
        if reference not in REFERENCES:
            raise ValueError(f"reference must be one of {REFERENCES}, got {reference!r}")
        if reference == "truth" and self.measured_minus_truth is None:
            raise ValueError("no truth was given to compare(): only the 'measured' reference exists")
        e = self.error_vs_measured[method].astype(np.float64)
        if reference == "truth":
            e = e + self.measured_minus_truth
        return e[0], e[1]

    def to_json_dict(self) -> dict:
        """The report as plain JSON types (``ptp-compare/1``; NaN as null).

        Keys: ``format``, ``software``, ``created``, ``units``, ``camera``,
        ``config`` (split, seed, n_points, rational, lut, smooth, methods),
        ``z_mm``, ``held_out``, ``pinhole``, ``folds``, ``coverage``,
        ``pairs``, ``reference_noise``, ``notes`` and ``references``: per
        reference (``measured``, ``truth``) a ``verdict`` and per method
        (``ptp``, ``smooth``, ``3dstc``: those of ``config.methods``) the
        ``coordinate`` statistics, ``per_position`` statistics, ``distance``
        statistics and error-vs-distance ``curve`` per pair kind, and the
        ``heatmap`` as block RMS maps (``block_px`` square blocks, µm).

        ``"pinhole"`` holds the 3DSTC model of the first fold in OpenCV's
        convention (``K``, ``dist``, ``rvec``, ``tvec``: world to camera, mm;
        :meth:`ptpcore.pinhole.PinholeModel.from_dict` reads it back) plus
        ``param_names``, ``param_values``, ``param_std`` (1 sigma),
        ``reprojection_rms_px`` and ``n_points``.
        """
        h, w = self.shape
        block = max(1, int(math.ceil(max(h, w) / 64)))
        out = {
            "format": COMPARE_FORMAT,
            "software": f"ptpcore {__version__}",
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "units": {"lengths": "mm", "errors": "um", "pixels": "px"},
            "camera": {"width": w, "height": h},
            "config": {"split": self.split, "seed": self.seed, "n_points": self.n_points,
                       "rational": self.rational,
                       "lut": {"model": self.lut_model, "degree": self.lut_degree},
                       "smooth": None if "smooth" not in self.methods else {"degree": self.smooth_degree},
                       "methods": list(self.methods)},
            "z_mm": self.z_mm.tolist(),
            "held_out": [int(k) for k in self.held_positions],
            "pinhole": _pinhole_json(self.pinhole),
            "folds": [{"calibration": f.calibration.tolist(), "held_out": f.held_out.tolist(),
                       "lut_valid_fraction": f.lut_valid_fraction, "pinhole": _pinhole_json(f.pinhole),
                       "warnings": list(f.warnings),
                       "smooth_valid_fraction": _jsonable(f.smooth_valid_fraction),
                       "smooth_scale_px": _jsonable(f.smooth_scale_px)}
                      for f in self.folds],
            "coverage": {k: v.tolist() for k, v in self.coverage.__dict__.items() if v is not None},
            "pairs": {k: {"n": len(p), "edges_mm": _jsonable(p.edges_mm)} for k, p in self.pairs.items()},
            "reference_noise": None if self.reference_noise is None else self.reference_noise.to_json_dict(),
            "notes": list(self.notes),
            "references": {},
        }
        for ref, rr in self.references.items():
            r = {"verdict": {k: _jsonable(v) for k, v in rr.verdict.__dict__.items()}}
            for m, mr in rr.methods.items():
                r[m] = {
                    "coordinate": mr.coordinate.to_json_dict(),
                    "per_position": [dict(position=int(k), z_mm=float(z), **s.to_json_dict())
                                     for k, z, s in zip(self.held_positions, self.z_held, mr.per_position)],
                    "distance": {kind: {"stats": d.stats.to_json_dict(), "curve": d.curve.to_json_dict()}
                                 for kind, d in mr.distance.items()},
                    "heatmap": {"block_px": block, "rms_um": _jsonable(_block_rms(mr.heatmap_mm, block) * 1e3)},
                }
            out["references"][ref] = r
        return out


def _pinhole_json(fit: PinholeFit) -> dict:
    d = fit.model.to_dict()
    d.update(param_names=list(fit.param_names), param_values=fit.param_values.tolist(),
             param_std=_jsonable(fit.param_std), reprojection_rms_px=fit.reprojection_rms_px,
             n_points=fit.n_points)
    return d


def _block_rms(img: np.ndarray, block: int) -> np.ndarray:
    """RMS of the finite values of ``img`` (H, W) in ``block`` x ``block`` tiles (NaN where none)."""
    h, w = img.shape
    hb, wb = -(-h // block), -(-w // block)
    pad = np.full((hb * block, wb * block), np.nan)
    pad[:h, :w] = img
    t = pad.reshape(hb, block, wb, block)
    ok = np.isfinite(t)
    n = ok.sum(axis=(1, 3))
    ms = np.full((hb, wb), np.nan)
    np.divide(np.where(ok, t * t, 0.0).sum(axis=(1, 3)), n, out=ms, where=n > 0)
    return np.sqrt(ms)


def _jsonable(v):
    """Plain JSON value: numpy scalars and arrays to Python, NaN/inf to None."""
    if isinstance(v, np.ndarray):
        return [_jsonable(x) for x in v.tolist()] if v.ndim else _jsonable(v.item())
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


# ----------------------------------------------------------------------------- protocol pieces

def split_positions(n_positions: int, split: str = "alternate") -> list[tuple[np.ndarray, np.ndarray]]:
    """Calibration / held-out folds of the positions (METHOD.md section 7).

    Held-out positions are always interior (neither the first nor the last
    position), so the LUT never has to extrapolate.

    Parameters
    ----------
    n_positions : int
        K, at least 3.
    split : {"alternate", "loo"}
        ``alternate``: one fold holding out every second position (1, 3, 5, ...,
        at most K-2), calibrated on the others. ``loo``: leave one position out,
        one fold per interior position, each calibrated on all the others.

    Returns
    -------
    list of (calibration (Kc,) int64, held_out (Kh,) int64)

    Raises
    ------
    ValueError
        Unknown split or fewer than 3 positions.
    """
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    k = int(n_positions)
    if k < 3:
        raise ValueError(f"the comparison needs at least 3 positions (calibrate on the ends, judge between), got {k}")
    allk = np.arange(k)
    if split == "alternate":
        held = np.arange(1, k - 1, 2)
        return [(np.setdiff1d(allk, held), held)]
    return [(np.setdiff1d(allk, [i]), np.array([i])) for i in range(1, k - 1)]


def draw_features(samples: SampleStack, positions, n_points: int, rng: np.random.Generator) -> FeaturePoints:
    """Draw 3DSTC feature points at random from the valid samples of ``positions``.

    Every valid (position, pixel) sample is equally likely; no sample is drawn twice.

    Parameters
    ----------
    samples : SampleStack
    positions : sequence of int
        Calibration positions.
    n_points : int
        M; all valid samples are used if there are fewer.
    rng : numpy.random.Generator

    Returns
    -------
    FeaturePoints

    Raises
    ------
    ValueError
        Fewer than 20 valid samples in ``positions``.
    """
    positions = np.asarray(positions, dtype=np.int64)
    valid = samples.valid[positions]
    flat = np.flatnonzero(valid)
    if flat.size < 20:
        raise ValueError(f"3DSTC needs feature points: only {flat.size} valid samples at positions"
                         f" {positions.tolist()}")
    pick = np.sort(rng.choice(flat.size, size=min(int(n_points), flat.size), replace=False))
    i, row, col = np.unravel_index(flat[pick], valid.shape)
    k = positions[i]
    x = samples.x_ref[row, col] + samples.x[k, row, col].astype(np.float64)
    y = samples.y_ref[row, col] + samples.y[k, row, col].astype(np.float64)
    pw = np.stack([x, y, samples.z[k]], axis=1)
    px = np.stack([col, row], axis=1).astype(np.float64)
    return FeaturePoints(pw, px, k.astype(np.int64))


def _draw_pairs(mask: np.ndarray, groups, kind: str, n_pairs: int, n_bins: int, rng: np.random.Generator,
                measured_xyz) -> PairSet:
    """Random point pairs whose measured distances spread over the field.

    Candidates: a random compared pixel, and a second one at a random offset
    (length uniform up to the image diagonal, random direction), at the same
    height or at another height of the same fold. They are binned by measured
    3D distance into ``n_bins`` equal bins and each bin keeps at most
    ``n_pairs // n_bins`` of them.
    """
    e_n, h, w = mask.shape
    flat = [np.flatnonzero(mask[e]) for e in range(e_n)]
    sizes = np.array([f.size for f in flat], dtype=np.int64)
    if kind == "same_height":
        combos = [(e, e) for e in range(e_n) if sizes[e] >= 2]
    else:
        combos = [(a, b) for g in groups for a in g for b in g if a < b and sizes[a] and sizes[b]]
    empty = np.zeros(0, np.int64)
    if not combos or n_pairs < 1:
        return PairSet(kind, empty, empty, empty, empty, empty, empty, np.zeros(0))
    combos = np.asarray(combos, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    all_flat = np.concatenate(flat)
    diag = math.hypot(h - 1, w - 1)
    want = 10 * n_pairs
    got = []
    n_got = 0
    for _ in range(50):
        m = 2 * want
        c = combos[rng.integers(len(combos), size=m)]
        swap = rng.random(m) < 0.5  # either end may be the higher one
        ea = np.where(swap, c[:, 1], c[:, 0])
        eb = np.where(swap, c[:, 0], c[:, 1])
        pa = all_flat[offsets[ea] + (rng.random(m) * sizes[ea]).astype(np.int64)]
        ra, ca = np.divmod(pa, w)
        length = rng.random(m) * diag
        theta = rng.random(m) * 2 * np.pi
        cb = np.rint(ca + length * np.cos(theta)).astype(np.int64)
        rb = np.rint(ra + length * np.sin(theta)).astype(np.int64)
        ok = (cb >= 0) & (cb < w) & (rb >= 0) & (rb < h)
        ok[ok] = mask[eb[ok], rb[ok], cb[ok]]
        ok &= ~((ea == eb) & (ra == rb) & (ca == cb))
        got.append((ea[ok], eb[ok], ra[ok], ca[ok], rb[ok], cb[ok]))
        n_got += int(ok.sum())
        if n_got >= want:
            break
    ea, eb, ra, ca, rb, cb = (np.concatenate(a) for a in zip(*got))
    pa = measured_xyz(ea, ra, ca)
    pb = measured_xyz(eb, rb, cb)
    d = np.linalg.norm(pa - pb, axis=1)
    edges = np.linspace(d.min(), d.max(), n_bins + 1) if d.size else np.zeros(0)
    if d.size == 0:
        keep = np.zeros(0, np.int64)
    else:
        b = np.clip(np.searchsorted(edges, d, side="right") - 1, 0, n_bins - 1)
        quota = max(1, n_pairs // n_bins)
        keep = np.concatenate([np.flatnonzero(b == i)[:quota] for i in range(n_bins)])
        keep.sort()
    return PairSet(kind, ea[keep], eb[keep], ra[keep], ca[keep], rb[keep], cb[keep], edges)


def _rank(values: dict) -> tuple[str | None, float, list]:
    """(method ahead or "tie" or None, runner-up over best, methods best first) of RMS values."""
    if len(values) < 2 or not all(math.isfinite(v) for v in values.values()):
        return None, math.nan, []
    order = sorted(values, key=lambda m: values[m])  # stable: METHODS order breaks ties
    a, b = values[order[0]], values[order[1]]
    if a == b:
        return "tie", 1.0, order
    return order[0], (b / a if a > 0 else math.inf), order


def _versus(values: dict, order: list) -> str:
    """ "b µm (r x)" with two methods, else "b µm for B (r x) and c µm for C (s x)" against the first."""
    best = values[order[0]]

    def ratio(m):
        return values[m] / best if best > 0 else math.inf

    if len(order) == 2:
        return f"{values[order[1]]:.3g} µm ({ratio(order[1]):.3g}x)"
    parts = [f"{values[m]:.3g} µm for {METHOD_LABELS[m]} ({ratio(m):.3g}x)" for m in order[1:]]
    return ", ".join(parts[:-1]) + " and " + parts[-1]


def _verdict(reference: str, coord: dict, dist: dict) -> Verdict:
    """The verdict from every method's coordinate RMS and RMS distance error (µm, keyed by method)."""
    c_ahead, c_ratio, c_order = _rank(coord)
    d_ahead, d_ratio, d_order = _rank(dist)
    where = {"truth": "against the exact truth", "measured": "against the measured held-out samples"}[reference]
    if c_ahead is None:
        text = f"no pixels to compare {where}"
        c_ahead = "tie"
    elif c_ahead == "tie":
        best = coord[c_order[0]]
        tied = [m for m in c_order if coord[m] == best]
        text = f"{' and '.join(METHOD_LABELS[m] for m in tied)} are equal {where}: coordinate RMS {best:.3g} µm"
        rest = [m for m in c_order if m not in tied]
        if rest:
            text += "; " + ", ".join(f"{METHOD_LABELS[m]} {coord[m]:.3g} µm" for m in rest)
    else:
        text = (f"{METHOD_LABELS[c_ahead]} is ahead {where}: coordinate RMS {coord[c_ahead]:.3g} µm against "
                + _versus(coord, c_order))
    if d_ahead is not None:
        if d_ahead == "tie":
            text += f"; distance errors equal ({dist[d_order[0]]:.3g} µm RMS)"
        else:
            text += (f"; distances: {METHOD_LABELS[d_ahead]} ahead, RMS {dist[d_ahead]:.3g} µm against "
                     + _versus(dist, d_order))
    return Verdict(reference, c_ahead, c_ratio, d_ahead, d_ratio, text, dict(coord), dict(dist))


# ----------------------------------------------------------------------------- the comparison

def smooth_degree_for(degree: int, n_calibration: int) -> int:
    """The smooth LUT's default degree in a comparison.

    The plain LUT's ``degree``, lowered to the largest degree whose smoothing
    scale can be cross-validated on ``n_calibration`` positions (two folds of
    alternate positions, each needing ``D + 1``: ``2 (D + 1) <= n``), and at
    least 1.
    """
    return int(max(1, min(int(degree), n_calibration // 2 - 1)))


def compare(samples: SampleStack, rig: Rig, truth=None, seed: int = 0, *, split: str = "alternate",
            n_points: int = 2000, rational: bool = False, model: str = "poly", degree: int = 3,
            with_smooth: bool = True, smooth_degree: int | None = None,
            n_pairs: int = 20000, n_bins: int = 20, progress: Progress | None = None) -> CompareResult:
    """Run the evaluation protocol of METHOD.md section 7 for PTP, PTP smooth and 3DSTC.

    Parameters
    ----------
    samples : SampleStack
        Decoded samples of all positions (:func:`ptpcore.pipeline.collect_samples`).
    rig : Rig
        The rig they came from (camera size is checked against ``samples``).
    truth : GroundTruth, optional
        Exact rays (simulated data); adds the ``"truth"`` reference.
    seed : int
        Seeds the feature points, the point pairs and the smooth LUT's global model (>= 0).
    split : {"alternate", "loo"}
        See :func:`split_positions`.
    n_points : int
        M, 3DSTC feature points per calibration (default 2000).
    rational : bool
        Fit the rational distortion ``k4..k6`` too.
    model, degree
        The plain PTP LUT (:func:`ptpcore.lut.fit_lut`).
    with_smooth : bool
        Also compare the smooth LUT (:func:`ptpcore.smooth.fit_smooth_lut`).
        It is left out, with a note in :attr:`CompareResult.notes`, when the
        samples carry no camera noise model or a fold has fewer than 3
        calibration positions.
    smooth_degree : int, optional
        Degree of the smooth LUT (1 to 5); default :func:`smooth_degree_for`.
    n_pairs : int
        Point pairs per kind (at most; fewer when long distances are rare).
    n_bins : int
        Distance bins for spreading the pairs and for the error-vs-distance curves.
    progress : callable, optional
        ``progress(fraction, message)``; may raise to cancel.

    Returns
    -------
    CompareResult

    Raises
    ------
    ValueError
        Inconsistent inputs (shapes, split, too few positions or samples).
    """
    if not isinstance(samples, SampleStack):
        raise ValueError(f"samples must be a SampleStack, got {type(samples).__name__}")
    h, w = samples.shape
    if rig.camera.shape != (h, w):
        raise ValueError(f"rig camera is {rig.camera.width}x{rig.camera.height} px but the samples are {w}x{h}")
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if int(seed) < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    if int(n_points) < 20:
        raise ValueError(f"n_points must be at least 20, got {n_points}")
    if int(n_bins) < 1:
        raise ValueError(f"n_bins must be at least 1, got {n_bins}")
    if smooth_degree is not None and not 1 <= int(smooth_degree) <= 5:
        raise ValueError(f"smooth_degree must be 1 to 5, got {smooth_degree}")
    if truth is not None and np.shape(truth.x0) != (h, w):
        raise ValueError(f"truth is for a {np.shape(truth.x0)} camera, the samples are {(h, w)}")
    seed = int(seed)
    folds_idx = split_positions(len(samples.z), split)
    held_positions = np.concatenate([f[1] for f in folds_idx]).astype(np.int64)
    fold_of_held = np.concatenate([np.full(len(f[1]), i) for i, f in enumerate(folds_idx)]).astype(np.int64)
    e_n = len(held_positions)
    z_held = samples.z[held_positions].astype(float)

    # --- which methods: the smooth LUT needs the noise model and a few calibration positions
    notes = []
    n_cal = min(len(f[0]) for f in folds_idx)
    s_degree = None
    if with_smooth:
        if samples.noise is None or samples.modulation is None:
            notes.append("PTP smooth left out: the samples carry no camera noise model to weight them"
                         " (decode them with collect_samples)")
        elif n_cal < 3:
            notes.append(f"PTP smooth left out: it needs at least 3 calibration positions, a fold has {n_cal}")
        else:
            s_degree = smooth_degree_for(degree, n_cal) if smooth_degree is None else int(smooth_degree)
            if n_cal < s_degree + 2:
                raise ValueError(f"a smooth LUT of degree {s_degree} needs at least {s_degree + 2} calibration"
                                 f" positions, a fold has {n_cal}")
            if n_cal < 2 * (s_degree + 1):
                notes.append(f"PTP smooth not smoothed: {n_cal} calibration positions are too few to"
                             f" cross-validate its smoothing scale (degree {s_degree} needs {2 * (s_degree + 1)})")
    methods = tuple(m for m in METHODS if m != "smooth" or s_degree is not None)

    def report(frac, msg):
        if progress:
            progress(frac, msg)

    mask = np.zeros((e_n, h, w), bool)
    err = {m: np.full((2, e_n, h, w), np.nan, np.float32) for m in methods}
    mmt = None if truth is None else np.full((2, e_n, h, w), np.nan, np.float32)
    cov = {k: np.zeros(e_n, np.int64) for k in ("n_measured", "n_ptp", "n_3dstc", "n_compared")}
    if s_degree is not None:
        cov["n_smooth"] = np.zeros(e_n, np.int64)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    folds = []
    e = 0
    for fi, (cal, held) in enumerate(folds_idx):
        base = fi / len(folds_idx) * 0.9
        step = 0.9 / len(folds_idx)
        tag = f"(fold {fi + 1}/{len(folds_idx)})"
        report(base, f"3DSTC: fitting the pinhole camera {tag}")
        feats = draw_features(samples, cal, n_points, np.random.default_rng([seed, 0, fi]))
        with warnings.catch_warnings(record=True) as caught:
            # e.g. no convergence: kept in the report (Fold.warnings) rather than lost in a log
            warnings.simplefilter("always")
            pin = fit_pinhole(feats.points_world, feats.pixels, rational=rational)
        report(base + 0.1 * step, f"PTP: fitting the LUT {tag}")
        lut = fit_lut(samples, model, degree, positions=cal)
        if not lut.valid.any():
            need = f"poly degree {degree} needs {degree + 2}" if model == "poly" else f"{model} needs 2"
            raise ValueError(f"no pixel with a usable LUT when calibrating on positions {list(map(int, cal))}"
                             f" ({need} valid positions per pixel)")
        fold = Fold(np.asarray(cal, np.int64), np.asarray(held, np.int64), pin, feats,
                    float(lut.valid.mean()), [str(w.message) for w in caught])
        smooth = None
        if s_degree is not None:
            lo, span = base + 0.2 * step, 0.6 * step
            smooth, info = fit_smooth_lut(samples, rig, s_degree, list(map(int, cal)), seed=seed,
                                          progress=lambda f, msg: report(lo + span * f, f"PTP smooth: {msg} {tag}"))
            if not smooth.valid.any():
                raise ValueError(f"no pixel with a usable smooth LUT when calibrating on positions"
                                 f" {list(map(int, cal))}")
            fold.smooth_valid_fraction = float(smooth.valid.mean())
            fold.smooth_scale_px = float(info.scale_px)
        folds.append(fold)
        for k in held:
            report(base + 0.8 * step, f"evaluating held-out position {k} (z = {samples.z[k]:g} mm)")
            z = float(samples.z[k])
            mx, my = samples.absolute(k)
            xy = {"ptp": lut.evaluate(z)}
            sx, sy = pin.model.pixel_to_world_at_z(cols, rows, z)
            valid = samples.valid[k]
            has_ptp = valid & np.isfinite(xy["ptp"].x) & np.isfinite(xy["ptp"].y)
            has_stc = valid & np.isfinite(sx) & np.isfinite(sy)
            m = has_ptp & has_stc
            if smooth is not None:
                xy["smooth"] = smooth.evaluate(z)
                has_smooth = valid & np.isfinite(xy["smooth"].x) & np.isfinite(xy["smooth"].y)
                cov["n_smooth"][e] = has_smooth.sum()
                m &= has_smooth
            mask[e] = m
            cov["n_measured"][e] = valid.sum()
            cov["n_ptp"][e] = has_ptp.sum()
            cov["n_3dstc"][e] = has_stc.sum()
            cov["n_compared"][e] = m.sum()
            for name, ev in xy.items():
                err[name][0, e][m] = (ev.x - mx)[m]
                err[name][1, e][m] = (ev.y - my)[m]
            err["3dstc"][0, e][m] = (sx - mx)[m]
            err["3dstc"][1, e][m] = (sy - my)[m]
            if truth is not None:
                tx, ty = truth.xy(z)
                mmt[0, e][m] = (mx - tx)[m]
                mmt[1, e][m] = (my - ty)[m]
            e += 1

    # --- point pairs, and every method's coordinates at their ends
    report(0.92, "drawing point pairs")

    def measured_xyz(ei, r, c):
        k = held_positions[ei]
        return np.stack([samples.x_ref[r, c] + samples.x[k, r, c].astype(np.float64),
                         samples.y_ref[r, c] + samples.y[k, r, c].astype(np.float64), z_held[ei]], axis=1)

    groups = [np.flatnonzero(fold_of_held == fi) for fi in range(len(folds_idx))]
    pairs = {kind: _draw_pairs(mask, groups, kind, int(n_pairs), int(n_bins),
                               np.random.default_rng([seed, 1, i]), measured_xyz)
             for i, kind in enumerate(PAIR_KINDS)}

    result = CompareResult(split, seed, int(n_points), bool(rational), model, int(degree) if model == "poly" else None,
                           samples.z.astype(float).copy(), held_positions, z_held, fold_of_held, folds, mask, err,
                           mmt, Coverage(**cov), pairs, methods=methods, smooth_degree=s_degree, notes=notes)
    refs = ["measured"] + (["truth"] if truth is not None else [])
    for ref in refs:
        report(0.95, f"statistics against the {ref} reference")
        result.references[ref] = _reference_report(result, ref, measured_xyz, truth)
    if truth is not None:
        result.reference_noise = coordinate_stats(mmt[0][mask], mmt[1][mask])
    report(1.0, "comparison done")
    return result


def _reference_report(result: CompareResult, ref: str, measured_xyz, truth) -> ReferenceReport:
    mask = result.mask
    e_n = mask.shape[0]

    def ref_xyz(ei, r, c):
        """(P, 3) the reference's points at pair ends (a method's are measured + its error)."""
        if ref == "measured":
            return measured_xyz(ei, r, c)
        z = result.z_held[ei]
        return np.stack([truth.x0[r, c] + truth.sx[r, c] * z, truth.y0[r, c] + truth.sy[r, c] * z, z], axis=1)

    methods = {}
    for m in result.methods:
        dx, dy = result.errors(m, ref)
        per = [coordinate_stats(dx[i][mask[i]], dy[i][mask[i]]) for i in range(e_n)]
        overall = coordinate_stats(dx[mask], dy[mask])
        sq = np.where(mask, dx * dx + dy * dy, 0.0).sum(axis=0)
        n = mask.sum(axis=0)
        heat = np.full(result.shape, np.nan)
        np.sqrt(np.divide(sq, n, out=np.zeros_like(sq), where=n > 0), out=heat, where=n > 0)
        dist = {}
        em = result.error_vs_measured[m]
        for kind, p in result.pairs.items():
            ends = []
            for ei, r, c in ((p.held_a, p.row_a, p.col_a), (p.held_b, p.row_b, p.col_b)):
                meas = measured_xyz(ei, r, c)
                mp = meas.copy()
                mp[:, 0] += em[0, ei, r, c]
                mp[:, 1] += em[1, ei, r, c]
                ends.append((mp, ref_xyz(ei, r, c)))
            d_method = np.linalg.norm(ends[0][0] - ends[1][0], axis=1)
            d_ref = np.linalg.norm(ends[0][1] - ends[1][1], axis=1)
            err = d_method - d_ref
            dist[kind] = DistanceErrors(kind, m, ref, d_ref, err, error_stats(err), _curve(d_ref, err, p.edges_mm))
        methods[m] = MethodReport(m, ref, overall, per, heat, dist)

    def dist_rms(m):
        e = np.concatenate([d.error_mm for d in methods[m].distance.values()])
        return error_stats(e).rms_um

    v = _verdict(ref, {m: methods[m].coordinate.rms_um for m in result.methods},
                 {m: dist_rms(m) for m in result.methods})
    return ReferenceReport(ref, methods, v)


# ----------------------------------------------------------------------------- text

def format_summary(result: CompareResult) -> str:
    """A plain-text summary of a :class:`CompareResult` (for the CLI).

    Returns
    -------
    str
        Several lines, no trailing newline.
    """
    fit = result.pinhole
    nd = 8 if result.rational else 5
    lut = f"poly degree {result.lut_degree}" if result.lut_model == "poly" else result.lut_model
    f0 = result.folds[0]
    if result.split == "alternate":
        split = (f"calibrated on {len(f0.calibration)} positions, judged at the {len(result.held_positions)} "
                 "held out between them")
    else:
        split = f"leave one position out, {len(result.folds)} folds"
    names = dict(zip(fit.param_names, zip(fit.param_values, fit.param_std)))

    def par(n):
        v, s = names[n]
        if not (math.isfinite(s) and s > 0):
            return f"{n} {v:.6g}"
        digits = min(10, max(0, 1 - math.floor(math.log10(s))))  # down to the std's second digit
        return f"{n} {v:.{digits}f} ± {s:.2g}"

    lines = [
        f"3DSTC comparison ({split}; seed {result.seed})",
        f"  PTP                 per-pixel LUT, {lut}",
    ]
    if "smooth" in result.methods:
        scales = sorted({f.smooth_scale_px for f in result.folds})
        scale = (f"{scales[0]:g}" if len(scales) == 1 else f"{scales[0]:g} .. {scales[-1]:g}") + " px"
        lines.append(f"  PTP smooth          global pinhole + Brown plus a per-pixel correction smoothed across"
                     f" pixels, poly degree {result.smooth_degree}, smoothing scale {scale} (cross-validated)")
    lines += [
        f"  3DSTC               pinhole + Brown ({nd} coefficients) from {fit.n_points} feature points,"
        f" reprojection RMS {fit.reprojection_rms_px:.3g} px",
        "                      " + "  ".join(par(n) for n in ("fx", "fy", "cx", "cy")),
        "                      " + "  ".join(par(n) for n in fit.param_names[4:4 + nd]),
    ]
    for i, f in enumerate(result.folds):
        for msg in f.warnings:
            lines.append(f"  3DSTC warning      {'' if len(result.folds) == 1 else f'(fold {i + 1}) '}{msg}")
    for msg in result.notes:
        lines.append(f"  note                {msg}")
    c = result.coverage
    nm = max(int(c.n_measured.sum()), 1)
    has = {"ptp": c.n_ptp, "smooth": c.n_smooth, "3dstc": c.n_3dstc}
    have = ", ".join(f"{METHOD_LABELS[m]}{' has' if i == 0 else ''} {100 * has[m].sum() / nm:.1f} %"
                     for i, m in enumerate(result.methods))
    lines.append(f"  pixels compared     {100 * c.n_compared.sum() / nm:.1f} % of the valid held-out samples"
                 f" ({have})")
    for kind, label in (("same_height", "same height"), ("across_heights", "across heights")):
        p = result.pairs[kind]
        span = f", distances {p.edges_mm[0]:.3g} .. {p.edges_mm[-1]:.3g} mm" if len(p) else ""
        lines.append(f"  point pairs, {label:<15}{len(p)}{span}")
    order = [r for r in ("truth", "measured") if r in result.references]
    for ref in order:
        rr = result.references[ref]
        if ref == "truth":
            head = "against the simulator's exact truth"
        else:
            head = "against the measured held-out samples"
            if result.reference_noise is not None:
                head += f" (their own noise: {result.reference_noise.rms_um:.3g} µm RMS)"
        ms = result.methods
        lines.append(f"  {head}, µm:")
        lines.append(f"    {'':<26}" + "".join(f"{METHOD_LABELS[m]:^25}" for m in ms))
        lines.append(f"    {'':<26}" + f"{'RMS  mean   p95   max':^25}" * len(ms))

        def row(label, getter):
            cells = []
            for m in ms:
                s = getter(rr.methods[m])
                cells.append(" ".join(_g(v) for v in (s.rms_um, s.mean_um, s.p95_um, s.max_um)) if s.n else "n/a")
            lines.append(f"    {label:<26}" + "".join(f"{c:^25}" for c in cells))

        row("coordinate |(dX, dY)|", lambda mr: mr.coordinate)
        cells = [f"{rr.methods[m].coordinate.rms_x_um:.3g} / {rr.methods[m].coordinate.rms_y_um:.3g}" for m in ms]
        lines.append(f"    {'  per axis, RMS X / Y':<26}" + "".join(f"{c:^25}" for c in cells))
        row("distance, same height", lambda mr: mr.distance["same_height"].stats)
        row("distance, across heights", lambda mr: mr.distance["across_heights"].stats)
        per = ", ".join(f"z={z:g}: " + "/".join(f"{rr.methods[m].per_position[i].rms_um:.3g}" for m in ms)
                        for i, z in enumerate(result.z_held))
        lines.append(f"    coordinate RMS per height, {'/'.join(METHOD_LABELS[m] for m in ms)}: {per}")
        lines.append(f"    -> {rr.verdict.text}")
    return "\n".join(line.rstrip() for line in lines)


def _g(v: float) -> str:
    """Compact number for tables: 3 significant digits, at most 5 characters wide where possible."""
    if not math.isfinite(v):
        return "  nan"
    a = abs(v)
    if a >= 1000:
        return f"{v:5.0f}"
    if a >= 100:
        return f"{v:5.0f}"
    if a >= 10:
        return f"{v:5.1f}"
    return f"{v:5.2f}"
