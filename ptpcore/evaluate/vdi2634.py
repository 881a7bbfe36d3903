"""Acceptance of an optical 3D scanner by VDI/VDE 2634 Part 2 (docs/method.md section 9).

On artefacts of calibrated geometry, from the point cloud of one scan (one *pose* of the artefact):

- **PF**, probing error form: the range (max - min) of the radial residuals of a least-squares
  sphere (:func:`fit_sphere`);
- **PS**, probing error size: fitted minus calibrated diameter;
- **SD**, sphere-spacing error: measured minus calibrated distance of a ball bar's two centres
  (each ball fitted on its own after the cloud is split in two, :func:`split_ball_bar`);
- **F**, flatness error: the range of the residuals of a least-squares plane (:func:`fit_plane`).

Leaving points out (the guideline allows up to 0.3 % of a fit's points): every fit is done on all
points, then the ``floor(0.003 N)`` points of largest ``|residual|`` are left out and the fit is
done again on the others; the figures are those of the second fit over the points it kept. No
other point is ever left out, so a cloud with more gross outliers than that keeps them (and shows
them in PF or F).

Every figure is per pose and method; :class:`AcceptanceReport` gives the largest magnitude of each
over the poses and the verdict against the maximum permissible errors (MPE) the user states. On
simulated scans (an exact surface known) each pose also gets the same figures against the truth
(:func:`truth_figures`), and :func:`point_distance_errors` extends the paper's distance-error
comparison (:mod:`.protocol`, in X, Y at known Z) to the full 3D point of a scanner.

Lengths are mm in arrays and fields named ``*_mm``; nothing here draws (:mod:`.acceptance_png` does).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from .scanner import VDI_LEAVE_OUT
from .statistics import ErrorStats, distance_curve, jsonable, error_stats

__all__ = ["ACCEPTANCE_FORMAT", "FIGURES", "FIGURE_OF_KIND", "SphereFit", "PlaneFit", "fit_sphere", "fit_plane",
           "left_out_count", "split_ball_bar", "Artefact", "PoseFigures", "pose_figures", "truth_figures",
           "parse_mpe", "AcceptanceReport", "point_distance_errors", "PointDistanceErrors", "ARTEFACT_FILE",
           "scan_artefact", "evaluate_acceptance", "format_acceptance"]

ACCEPTANCE_FORMAT = "ptp-acceptance/1"
FIGURES = ("PF", "PS", "SD", "F")
"""The four figures, in the guideline's order."""
FIGURE_OF_KIND = {"sphere": ("PF", "PS"), "ballbar": ("SD",), "plane": ("F",)}
"""Which figures a pose of each kind of artefact gives."""
SIGNED = {"PS", "SD"}
"""Figures with a sign (fitted minus calibrated): their magnitude is what an MPE bounds."""


def left_out_count(n: int, fraction: float = VDI_LEAVE_OUT) -> int:
    """How many of ``n`` points a fit may leave out: ``floor(fraction * n)`` (never a negative count)."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"the fraction of points left out must be in [0, 1), got {fraction!r}")
    return int(math.floor(fraction * int(n) + 1e-9))


def _check_points(points, need: int, what: str) -> np.ndarray:
    p = np.asarray(points, float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what}: points must be (N, 3), got shape {p.shape}")
    p = p[np.all(np.isfinite(p), axis=1)]
    if p.shape[0] < need:
        raise ValueError(f"{what}: {p.shape[0]} finite points, at least {need} needed")
    return p


@dataclass
class SphereFit:
    """A least-squares sphere.

    Attributes
    ----------
    centre : (3,) float64, mm
    radius : float, mm
    centre_se : (3,) float64, mm
        Standard errors of the centre from the residuals' scatter and the fit's Jacobian.
    radius_se : float, mm
    residuals : (N,) float64, mm
        Radial residual ``|p - centre| - radius`` of every input point (NaN for a non-finite point).
    kept : (N,) bool
        The points the final fit used (all finite points but the ``n_left_out`` largest ``|residual|``).
    n_left_out : int
    """

    centre: np.ndarray
    radius: float
    centre_se: np.ndarray
    radius_se: float
    residuals: np.ndarray
    kept: np.ndarray
    n_left_out: int

    @property
    def form_range(self) -> float:
        """Range of the kept points' radial residuals (mm): PF."""
        r = self.residuals[self.kept]
        return float(r.max() - r.min())


def _sphere_start(p: np.ndarray) -> np.ndarray:
    """Algebraic sphere: ``|p|^2 = 2 c . p + (r^2 - |c|^2)`` is linear in ``c`` and ``r^2 - |c|^2``."""
    a = np.column_stack([2 * p, np.ones(len(p))])
    b = np.einsum("ij,ij->i", p, p)
    sol = np.linalg.lstsq(a, b, rcond=None)[0]
    c = sol[:3]
    return np.array([*c, math.sqrt(max(sol[3] + c @ c, 1e-12))])


def _sphere_lsq(p: np.ndarray, x0: np.ndarray):
    """Geometric least squares (scipy's Levenberg-Marquardt) from ``x0 = (cx, cy, cz, r)``."""
    from scipy.optimize import least_squares

    def res(x):
        return np.linalg.norm(p - x[:3], axis=1) - x[3]

    def jac(x):
        d = p - x[:3]
        n = np.linalg.norm(d, axis=1)[:, None]
        return np.column_stack([-d / n, -np.ones(len(p))])

    return least_squares(res, x0, jac=jac, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)


def fit_sphere(points, *, leave_out: float = VDI_LEAVE_OUT) -> SphereFit:
    """Least-squares sphere through ``points``, leaving out at most ``leave_out`` of them (module doc).

    Parameters
    ----------
    points : (N, 3) float, mm
        Non-finite rows are ignored (and get NaN residuals).
    leave_out : float
        Fraction of the points the fit may leave out (default 0.003, the guideline's limit).

    Returns
    -------
    SphereFit

    Raises
    ------
    ValueError
        Fewer than 5 finite points, or points that fix no sphere (all on a plane or a line).
    """
    allp = np.asarray(points, float)
    p = _check_points(allp, 5, "sphere fit")
    finite = np.all(np.isfinite(allp), axis=1) if allp.ndim == 2 else None
    fit = _sphere_lsq(p, _sphere_start(p))
    n_out = left_out_count(len(p), leave_out)
    keep = np.ones(len(p), bool)
    if n_out:
        keep[np.argsort(-np.abs(fit.fun), kind="stable")[:n_out]] = False
        fit = _sphere_lsq(p[keep], fit.x)
    x = fit.x
    if not np.all(np.isfinite(x)) or x[3] <= 0:
        raise ValueError("sphere fit: the points fix no sphere")
    dof = max(int(keep.sum()) - 4, 1)
    s2 = float(fit.fun @ fit.fun) / dof
    try:
        cov = s2 * np.linalg.inv(fit.jac.T @ fit.jac)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        raise ValueError("sphere fit: the points fix no sphere (singular normal equations)") from None
    residuals = np.full(len(allp), np.nan)
    kept = np.zeros(len(allp), bool)
    residuals[finite] = np.linalg.norm(p - x[:3], axis=1) - x[3]
    kept[np.flatnonzero(finite)[keep]] = True
    return SphereFit(x[:3].copy(), float(x[3]), se[:3], float(se[3]), residuals, kept, n_out)


@dataclass
class PlaneFit:
    """A least-squares (orthogonal distance) plane.

    Attributes
    ----------
    point : (3,) float64, mm
        The kept points' centroid.
    normal : (3,) float64
        Unit normal, its Z component negative (toward a scanner looking along +Z) or, for a vertical
        plane, as the singular value decomposition gives it.
    residuals : (N,) float64, mm
        Signed distance of every input point (NaN for a non-finite point).
    kept : (N,) bool
    n_left_out : int
    """

    point: np.ndarray
    normal: np.ndarray
    residuals: np.ndarray
    kept: np.ndarray
    n_left_out: int

    @property
    def flatness(self) -> float:
        """Range of the kept points' residuals (mm): F."""
        r = self.residuals[self.kept]
        return float(r.max() - r.min())


def _plane_lsq(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = p.mean(axis=0)
    n = np.linalg.svd(p - c, full_matrices=False)[2][-1]
    return c, (-n if n[2] > 0 else n)


def fit_plane(points, *, leave_out: float = VDI_LEAVE_OUT) -> PlaneFit:
    """Least-squares plane through ``points`` (the smallest singular vector of the centred points),
    leaving out at most ``leave_out`` of them (module doc).

    Parameters
    ----------
    points : (N, 3) float, mm
    leave_out : float

    Returns
    -------
    PlaneFit

    Raises
    ------
    ValueError
        Fewer than 3 finite points, or all on a line.
    """
    allp = np.asarray(points, float)
    p = _check_points(allp, 3, "plane fit")
    finite = np.all(np.isfinite(allp), axis=1)
    c, n = _plane_lsq(p)
    sv = np.linalg.svd(p - c, compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-300):
        raise ValueError("plane fit: the points lie on a line")
    n_out = left_out_count(len(p), leave_out)
    keep = np.ones(len(p), bool)
    if n_out:
        keep[np.argsort(-np.abs((p - c) @ n), kind="stable")[:n_out]] = False
        c, n = _plane_lsq(p[keep])
    residuals = np.full(len(allp), np.nan)
    kept = np.zeros(len(allp), bool)
    residuals[finite] = (p - c) @ n
    kept[np.flatnonzero(finite)[keep]] = True
    return PlaneFit(c, n, residuals, kept, n_out)


def split_ball_bar(points) -> tuple[np.ndarray, np.ndarray]:
    """Split a ball bar's cloud into its two balls: 2-means (scipy) started from the two points
    farthest apart along the cloud's main axis.

    Parameters
    ----------
    points : (N, 3) float, mm (finite)

    Returns
    -------
    a, b : (N,) bool
        Membership of each ball; ball ``a`` is the one at the lower end of the main axis.
    """
    from scipy.cluster.vq import kmeans2

    p = np.asarray(points, float)
    c = p.mean(axis=0)
    axis = np.linalg.svd(p - c, full_matrices=False)[2][0]
    t = (p - c) @ axis
    init = np.stack([p[np.argmin(t)], p[np.argmax(t)]])
    _centres, label = kmeans2(p, init, minit="matrix", iter=20)
    return label == 0, label == 1


@dataclass(frozen=True)
class Artefact:
    """A calibrated artefact: what a pose is measured against.

    Attributes
    ----------
    kind : {"sphere", "ballbar", "plane"}
    diameter_mm : float
        The sphere's (or each ball's) calibrated diameter; 0 for a plane.
    distance_mm : float
        A ball bar's calibrated centre distance; 0 otherwise.
    """

    kind: str
    diameter_mm: float = 0.0
    distance_mm: float = 0.0

    def __post_init__(self):
        if self.kind not in FIGURE_OF_KIND:
            raise ValueError(f"unknown artefact kind {self.kind!r} (sphere, ballbar, plane)")
        if self.kind in ("sphere", "ballbar") and not self.diameter_mm > 0:
            raise ValueError(f"a {self.kind}'s diameter must be a positive number of mm, got {self.diameter_mm!r}")
        if self.kind == "ballbar" and not self.distance_mm > 0:
            raise ValueError(f"a ball bar's centre distance must be a positive number of mm, got {self.distance_mm!r}")

    @classmethod
    def of(cls, obj) -> "Artefact":
        """The calibrated values of a simulated :class:`~ptpcore.simulate.scanner.ScanObject` (exact)."""
        if obj.kind == "plane":
            return cls("plane")
        d = 2.0 * obj.radius
        if obj.kind == "sphere":
            return cls("sphere", d)
        c = np.asarray(obj.centres, float)
        return cls("ballbar", d, float(np.linalg.norm(c[1] - c[0])))


@dataclass
class PoseFigures:
    """One pose measured by one method.

    Attributes
    ----------
    pose : str
        The scan's name.
    kind : str
    method : str
    n_points : int
        Points the method gave (finite).
    n_left_out : int
        Points the fits left out (summed over a ball bar's two balls).
    figures : dict of str -> float, mm
        ``PF`` and ``PS`` (sphere), ``SD`` (ball bar), ``F`` (plane).
    fit : dict
        The fitted geometry (centre(s), diameter(s), plane point and normal; mm), for the report.
    truth : dict or None
        :func:`truth_figures` when the exact surface is known.
    residuals : (N,) float64, mm
        Each point's fit residual (radial or plane distance; NaN for the ones it left out), for plots.
    """

    pose: str
    kind: str
    method: str
    n_points: int
    n_left_out: int
    figures: dict
    fit: dict
    truth: dict | None = None
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def to_json_dict(self) -> dict:
        return {"pose": self.pose, "kind": self.kind, "method": self.method, "n_points": self.n_points,
                "n_left_out": self.n_left_out, "figures_mm": jsonable(self.figures), "fit": jsonable(self.fit),
                "truth": None if self.truth is None else jsonable(self.truth)}


def pose_figures(points, artefact: Artefact, *, pose: str = "", method: str = "",
                 leave_out: float = VDI_LEAVE_OUT) -> PoseFigures:
    """The figures of one pose from its point cloud.

    Parameters
    ----------
    points : (N, 3) float, mm
        The method's points of the scan (non-finite rows ignored).
    artefact : Artefact
    pose, method : str
        Names for the report.
    leave_out : float

    Raises
    ------
    ValueError
        Too few points for the fit (the message names the pose and method).
    """
    p = np.asarray(points, float)
    p = p[np.all(np.isfinite(p), axis=1)]
    where = f"{pose or 'pose'} ({method or 'method'})"
    try:
        if artefact.kind == "sphere":
            s = fit_sphere(p, leave_out=leave_out)
            figs = {"PF": s.form_range, "PS": 2 * s.radius - artefact.diameter_mm}
            fit = {"centre_mm": s.centre, "diameter_mm": 2 * s.radius, "diameter_se_mm": 2 * s.radius_se}
            return PoseFigures(pose, "sphere", method, len(p), s.n_left_out, figs, fit,
                               residuals=np.where(s.kept, s.residuals, np.nan))
        if artefact.kind == "ballbar":
            return _ball_bar_figures(p, artefact, pose, method, leave_out)
        f = fit_plane(p, leave_out=leave_out)
        return PoseFigures(pose, "plane", method, len(p), f.n_left_out, {"F": f.flatness},
                           {"point_mm": f.point, "normal": f.normal}, residuals=np.where(f.kept, f.residuals, np.nan))
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _ball_bar_figures(p: np.ndarray, artefact: Artefact, pose: str, method: str, leave_out: float) -> PoseFigures:
    a, b = split_ball_bar(p)
    fa, fb = fit_sphere(p[a], leave_out=leave_out), fit_sphere(p[b], leave_out=leave_out)
    dist = float(np.linalg.norm(fb.centre - fa.centre))
    res = np.full(len(p), np.nan)
    res[a] = np.where(fa.kept, fa.residuals, np.nan)
    res[b] = np.where(fb.kept, fb.residuals, np.nan)
    fit = {"centres_mm": np.stack([fa.centre, fb.centre]), "diameters_mm": [2 * fa.radius, 2 * fb.radius],
           "distance_mm": dist, "points_per_ball": [int(a.sum()), int(b.sum())]}
    return PoseFigures(pose, "ballbar", method, len(p), fa.n_left_out + fb.n_left_out,
                       {"SD": dist - artefact.distance_mm}, fit, residuals=res)


def truth_figures(points, true_points, obj, fig: PoseFigures) -> dict:
    """A pose's points against the simulator's exact surface ``obj``
    (:class:`~ptpcore.simulate.scanner.ScanObject`) and each pixel's exact point.

    Parameters
    ----------
    points, true_points : (N, 3) float, mm
        The method's point and the exact point of the same camera pixel, row for row.
    obj : ScanObject
    fig : PoseFigures
        The pose's fitted figures (for the fitted geometry's errors).

    Returns
    -------
    dict
        (:func:`evaluate_acceptance` adds ``exact_points_figures_mm``: the figures of the exact points of
        the same pixels, which must be 0 to rounding: the pixels' sampling and the fits add nothing.)
        ``rms_surface_mm`` (RMS distance of the points from the true surface), ``range_surface_mm``
        (its range after the same leave-out: the form seen against the true surface rather than the
        fitted one), ``rms_point_mm`` (RMS of ``|point - exact point|``, the full 3D error), and the
        fitted geometry's error: ``centre_error_mm`` (sphere; ball bar: both) or ``normal_error_urad``
        and ``offset_mm`` (plane, along the true normal at the true surface's point).
    """
    p = np.asarray(points, float)
    t = np.asarray(true_points, float)
    ok = np.all(np.isfinite(p), axis=1)
    d = obj.distance(p[ok])
    # leave out the floor(0.3 % N) largest |d|, as the fits do
    kept = d[np.argsort(np.abs(d), kind="stable")[: len(d) - left_out_count(len(d))]]
    both = ok & np.all(np.isfinite(t), axis=1)
    out = {"rms_surface_mm": float(np.sqrt(np.mean(d ** 2))), "range_surface_mm": float(kept.max() - kept.min()),
           "rms_point_mm": float(np.sqrt(np.mean(np.sum((p[both] - t[both]) ** 2, axis=1))))}
    if obj.kind == "sphere":
        out["centre_error_mm"] = float(np.linalg.norm(fig.fit["centre_mm"] - np.asarray(obj.centres[0])))
    elif obj.kind == "ballbar":
        tc = np.asarray(obj.centres, float)
        fc = np.asarray(fig.fit["centres_mm"])
        # the fitted balls' order follows the cloud's main axis: match each to its nearer true centre
        same = np.linalg.norm(fc - tc, axis=1).sum() <= np.linalg.norm(fc - tc[::-1], axis=1).sum()
        tc = tc if same else tc[::-1]
        out["centre_error_mm"] = [float(v) for v in np.linalg.norm(fc - tc, axis=1)]
    else:
        n_true = np.asarray(obj.normal, float) / np.linalg.norm(obj.normal)
        n_fit = np.asarray(fig.fit["normal"], float)
        cosang = abs(float(n_fit @ n_true))
        out["normal_error_urad"] = float(1e6 * math.acos(min(cosang, 1.0)))
        out["offset_mm"] = float(obj.distance(np.asarray(fig.fit["point_mm"])[None])[0])
    return out


_MPE_RE = re.compile(r"^\s*([A-Za-z]+)\s*=\s*([^,]*?)\s*([uµ]m|mm)?\s*$")  # µm typed as um too


def parse_mpe(text: str | None) -> dict:
    """``PF=0.05,PS=0.03,SD=0.08,F=0.06`` -> ``{"PF": 0.05, ...}`` (mm; a value may end in ``um`` or ``mm``).

    Raises
    ------
    ValueError
        An unknown key, a repeated key, or a value that is not a positive length (the message names it).
    """
    if text is None or not text.strip():
        return {}
    out = {}
    for part in text.split(","):
        m = _MPE_RE.match(part)
        if not m:
            raise ValueError(f"--mpe: {part.strip()!r} is not KEY=VALUE (keys {', '.join(FIGURES)};"
                             " mm, or µm with the unit)")
        key, value, unit = m.group(1).upper(), m.group(2), m.group(3)
        if key not in FIGURES:
            raise ValueError(f"--mpe: unknown key {m.group(1)!r} (keys {', '.join(FIGURES)})")
        if key in out:
            raise ValueError(f"--mpe: key {key} given twice")
        try:
            v = float(value)
        except ValueError:
            raise ValueError(f"--mpe: {key} value {value!r} is not a number (mm, or µm with the unit)") from None
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"--mpe: {key} value {value!r} must be a positive length")
        out[key] = v * 1e-3 if unit in ("um", "µm") else v
    return out


@dataclass
class AcceptanceReport:
    """Every pose of every method, the largest magnitudes and the verdicts.

    Attributes
    ----------
    poses : list of PoseFigures
    methods : tuple of str
        In report order.
    mpe_mm : dict of str -> float
        The maximum permissible errors the user stated (any of :data:`FIGURES`).
    leave_out : float
    distance : dict of method -> PointDistanceErrors, optional
        The 3D distance-error comparison against truth (simulated scans).
    notes : list of str
    """

    poses: list
    methods: tuple
    mpe_mm: dict
    leave_out: float = VDI_LEAVE_OUT
    distance: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    def of(self, method: str) -> list:
        return [p for p in self.poses if p.method == method]

    def largest(self, method: str) -> dict:
        """Per figure, the value of largest magnitude over the method's poses (sign kept) and its pose."""
        out = {}
        for key in FIGURES:
            vals = [(p.figures[key], p.pose) for p in self.of(method) if key in p.figures]
            if vals:
                v, pose = max(vals, key=lambda vp: abs(vp[0]))
                out[key] = {"value_mm": float(v), "pose": pose, "n_poses": len(vals)}
        return out

    def verdicts(self, method: str) -> dict:
        """Per figure with an MPE: ``pass`` when every pose's magnitude is within it, else ``fail``."""
        big = self.largest(method)
        return {k: ("pass" if abs(big[k]["value_mm"]) <= mpe else "fail") if k in big else "no pose"
                for k, mpe in self.mpe_mm.items()}

    def ratio(self, key: str, num: str, den: str) -> float:
        """``|largest of num| / |largest of den|`` for figure ``key`` (NaN when either lacks it)."""
        a, b = self.largest(num).get(key), self.largest(den).get(key)
        if a is None or b is None or b["value_mm"] == 0:
            return float("nan")
        return abs(a["value_mm"]) / abs(b["value_mm"])

    def to_json_dict(self) -> dict:
        out = {"format": ACCEPTANCE_FORMAT, "guideline": "VDI/VDE 2634 Part 2", "leave_out_fraction": self.leave_out,
               "leave_out_rule": "fit all points, leave out the floor(fraction * N) largest |residuals|, fit again",
               "mpe_mm": self.mpe_mm, "methods": list(self.methods), "notes": list(self.notes),
               "largest": {m: self.largest(m) for m in self.methods},
               "verdicts": {m: self.verdicts(m) for m in self.methods},
               "poses": [p.to_json_dict() for p in self.poses]}
        if len(self.methods) == 2:
            a, b = self.methods
            out["ratios"] = {f"{a}/{b}": {k: jsonable(self.ratio(k, a, b)) for k in FIGURES}}
        if self.distance:
            out["distance_errors_3d"] = {m: d.to_json_dict() for m, d in self.distance.items()}
        return out


@dataclass
class PointDistanceErrors:
    """The paper's distance-error comparison extended to the full 3D point: for random pairs of
    measured points, ``|p_a - p_b| - |t_a - t_b|`` with ``t`` each pixel's exact point.

    Attributes
    ----------
    method : str
    kinds : dict of str -> (stats ErrorStats, curve DistanceCurve)
        ``same_scan`` (both ends in one scan) and ``across_scans`` (ends in two scans: the same
        scanner frame, distances across the volume).
    point : ErrorStats
        Of ``|p - t|`` (the 3D coordinate error) over every point.
    """

    method: str
    kinds: dict
    point: ErrorStats

    def to_json_dict(self) -> dict:
        return {"method": self.method, "point_error": self.point.to_json_dict(),
                **{k: {"stats": s.to_json_dict(), "curve": c.to_json_dict()} for k, (s, c) in self.kinds.items()}}


def point_distance_errors(points: dict, truth: list, *, n_pairs: int = 20000, n_bins: int = 8,
                          seed: int = 0) -> dict:
    """Distance errors of each method's 3D points against the exact points, on the same pairs.

    Parameters
    ----------
    points : dict of method -> list of (N_s, 3) float, mm
        Per scan ``s``, each method's point of the same ``N_s`` pixels, row for row (NaN = none).
    truth : list of (N_s, 3) float, mm
        Per scan, the exact point of those pixels.
    n_pairs : int
        Pairs per kind (fewer when some distances are rare: equal quotas per bin of the true distance).
    n_bins : int
        Bins of the true distance, for the error-vs-distance curve.
    seed : int

    Returns
    -------
    dict of method -> PointDistanceErrors
        Pairs are drawn once among the pixels every method and the truth have, so every method is
        judged on the same pairs.
    """
    methods = list(points)
    scan_of, rows = [], []
    for s, t in enumerate(truth):
        ok = np.all(np.isfinite(t), axis=1)
        for m in methods:
            ok &= np.all(np.isfinite(points[m][s]), axis=1)
        idx = np.flatnonzero(ok)
        scan_of.append(np.full(idx.size, s))
        rows.append(idx)
    scan_of, rows = np.concatenate(scan_of), np.concatenate(rows)
    if rows.size < 2:
        return {}
    # the pooled points are in scan order (scan_of is built scan by scan): pooled index i is
    # scan scan_of[i], row rows[i]
    t_all = np.concatenate([truth[s][rows[scan_of == s]] for s in range(len(truth))])
    pairs = _draw_point_pairs(scan_of, t_all, np.random.default_rng(seed), n_pairs, n_bins)
    out = {}
    for m in methods:
        p_all = np.concatenate([points[m][s][rows[scan_of == s]] for s in range(len(truth))])
        kinds = {}
        for kind, (a, b) in pairs.items():
            d_true = np.linalg.norm(t_all[a] - t_all[b], axis=1)
            err = np.linalg.norm(p_all[a] - p_all[b], axis=1) - d_true
            edges = np.linspace(0.0, float(d_true.max()) if d_true.size else 1.0, n_bins + 1)
            kinds[kind] = (error_stats(err), distance_curve(d_true, err, edges))
        out[m] = PointDistanceErrors(m, kinds, error_stats(np.linalg.norm(p_all - t_all, axis=1)))
    return out


def _draw_point_pairs(scan_of: np.ndarray, t_all: np.ndarray, rng: np.random.Generator, n_pairs: int,
                      n_bins: int) -> dict:
    """Pairs (indices into the pooled points), ``same_scan`` and ``across_scans`` (when there are two
    scans or more), spread over the true distance as :mod:`.protocol`'s are: candidates drawn at random,
    then equal quotas per bin of the true distance (a bin with too few keeps what it has)."""
    n = scan_of.size
    a = rng.integers(0, n, 8 * n_pairs)
    b = rng.integers(0, n, 8 * n_pairs)
    distinct = a != b
    kinds = {"same_scan": distinct & (scan_of[a] == scan_of[b]), "across_scans": distinct & (scan_of[a] != scan_of[b])}
    out = {}
    for kind, sel in kinds.items():
        if not sel.any():
            continue
        ka, kb = a[sel], b[sel]
        d = np.linalg.norm(t_all[ka] - t_all[kb], axis=1)
        edges = np.linspace(0.0, d.max() * (1 + 1e-9), n_bins + 1)
        bins = np.clip(np.searchsorted(edges, d, side="right") - 1, 0, n_bins - 1)
        quota = max(1, n_pairs // n_bins)
        keep = np.concatenate([np.flatnonzero(bins == i)[:quota] for i in range(n_bins)])
        out[kind] = (ka[keep], kb[keep])
    return out


ARTEFACT_FILE = "artefact.toml"
"""A real scan's calibrated artefact, beside its ``scan.toml``: ``kind = "sphere"`` (``diameter_mm``),
``"ballbar"`` (``diameter_mm``, ``distance_mm``) or ``"plane"``."""


def scan_artefact(scan_dir, truth_object=None) -> Artefact:
    """The artefact a scan shows: ``artefact.toml`` in the folder (a calibration certificate's values)
    or, for a simulated scan, its exact object.

    Raises
    ------
    ValueError
        Neither is there, or ``artefact.toml`` is wrong (the message names the file and key).
    """
    import tomllib
    from pathlib import Path

    path = Path(scan_dir) / ARTEFACT_FILE
    if path.exists():
        try:
            d = tomllib.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ValueError(f"{path}: unreadable ({exc})") from None
        unknown = set(d) - {"kind", "diameter_mm", "distance_mm"}
        if unknown:
            raise ValueError(f"{path}: unknown key '{sorted(unknown)[0]}' (kind, diameter_mm, distance_mm)")
        for key in ("diameter_mm", "distance_mm"):
            if key in d and (isinstance(d[key], bool) or not isinstance(d[key], (int, float))):
                raise ValueError(f"{path}: key '{key}' must be a number of mm, got {d[key]!r}")
        try:
            return Artefact(str(d.get("kind", "")), float(d.get("diameter_mm", 0.0)), float(d.get("distance_mm", 0.0)))
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    if truth_object is not None:
        return Artefact.of(truth_object)
    raise ValueError(f"{scan_dir}: no {ARTEFACT_FILE} saying which artefact it shows (kind, diameter_mm,"
                     " distance_mm) and no simulator truth")


def evaluate_acceptance(scans, *, mpe_mm: dict | None = None, leave_out: float = VDI_LEAVE_OUT,
                        seed: int = 0, n_pairs: int = 20000) -> AcceptanceReport:
    """Every pose of every method, judged on the pixels where all methods give a point.

    Parameters
    ----------
    scans : sequence of ScanPoints
        :func:`ptpcore.run.acceptance.reconstruct_scans` (``name``, ``scan_dir``, ``points``,
        ``truth_xyz``, ``truth_object``, ``common()``).
    mpe_mm : dict, optional
        :func:`parse_mpe`.
    leave_out : float
    seed, n_pairs : int
        Of the 3D distance-error pairs (simulated scans only).

    Raises
    ------
    ValueError
        A scan without a point every method gives, or too few for its fit (named).
    """
    methods = tuple(scans[0].points) if scans else ()
    poses, notes = [], []
    truth_pts, method_pts = [], {m: [] for m in methods}
    for sp in scans:
        art = scan_artefact(sp.scan_dir, sp.truth_object)
        if sp.truth_object is not None and art.kind != sp.truth_object.kind:
            raise ValueError(f"{sp.scan_dir}: artefact.toml says {art.kind}, its truth.h5 a {sp.truth_object.kind}")
        common = sp.common()
        if not common.any():
            counts = ", ".join(f"{k} {v}" for k, v in sp.counts.items())
            raise ValueError(f"{sp.scan_dir}: no pixel where every method gives a point ({counts})")
        figs = [pose_figures(sp.points[m][common], art, pose=sp.name, method=m, leave_out=leave_out)
                for m in methods]  # first: a pose with too few points is named with its method
        if sp.truth_xyz is not None:  # the figures of the exact points of the same pixels: the fits' floor
            exact = pose_figures(sp.truth_xyz[common], art, pose=sp.name, method="exact", leave_out=leave_out)
            for m, fig in zip(methods, figs):
                fig.truth = truth_figures(sp.points[m][common], sp.truth_xyz[common], sp.truth_object, fig)
                fig.truth["exact_points_figures_mm"] = exact.figures
        poses += figs
        if sp.truth_xyz is not None:
            truth_pts.append(sp.truth_xyz[common])
            for m in methods:
                method_pts[m].append(sp.points[m][common])
    distance = {}
    if scans and len(truth_pts) == len(scans):
        distance = point_distance_errors(method_pts, truth_pts, n_pairs=n_pairs, seed=seed)
    elif truth_pts:
        notes.append("some scans have no simulator truth: no 3D distance errors")
    return AcceptanceReport(poses, methods, dict(mpe_mm or {}), leave_out, distance, notes)


def format_acceptance(report: AcceptanceReport) -> str:
    """The report as a few lines of text: per figure and method the largest magnitude, its pose and
    verdict; with truth, each method's 3D point and distance errors."""
    lines = [f"VDI/VDE 2634-2 ({len({p.pose for p in report.poses})} poses; up to"
             f" {100 * report.leave_out:g} % of each fit's points left out)"]
    head = f"  {'':4s}" + "".join(f"  {m:>32s}" for m in report.methods)
    lines.append(head + ("      MPE" if report.mpe_mm else ""))
    for key in FIGURES:
        cells = []
        for m in report.methods:
            big = report.largest(m).get(key)
            if big is None:
                cells.append(f"  {'-':>32s}")
                continue
            verdict = report.verdicts(m).get(key, "")
            cell = f"{1e3 * big['value_mm']:+.2f} µm ({big['pose']})" + (f" {verdict}" if verdict else "")
            cells.append(f"  {cell:>32s}")
        mpe = report.mpe_mm.get(key)
        lines.append(f"  {key:4s}" + "".join(cells) + (f"  {1e3 * mpe:g} µm" if mpe else ""))
    for m, d in report.distance.items():
        parts = [f"point |error| RMS {d.point.rms_um:.2f} µm"]
        parts += [f"{k.replace('_', ' ')} distance error RMS {s.rms_um:.2f} µm (max {s.max_um:.1f})"
                  for k, (s, _c) in d.kinds.items()]
        lines.append(f"  3D against truth, {m}: " + "; ".join(parts))
    lines += [f"  note: {n}" for n in report.notes]
    return "\n".join(lines)
