"""The comparison: point-to-point LUTs against 3DSTC on held-out heights (METHOD.md sections 6-7).

All methods (:data:`METHODS`) are calibrated on the same calibration positions
of one :class:`~ptpcore.io.SampleStack` and judged at the held-out positions only:

- **PTP**: a per-pixel LUT (:func:`ptpcore.fit.fit_lut`) evaluated at the
  held-out stage reading ``z_k``.
- **PTP smooth** (``"smooth"``, optional): the per-pixel LUT regularised
  across neighbouring pixels (:func:`ptpcore.fit.smooth.fit_smooth_lut`: a global
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

import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ptpcore.evaluate.report import (METHODS, PAIR_KINDS, SPLITS, CompareResult, Coverage, FeaturePoints, Fold,
    MethodReport, ReferenceReport)
from ptpcore.evaluate.statistics import (DistanceErrors, _curve, _draw_pairs, _verdict, coordinate_stats,
    error_stats)
from ptpcore.fit import fit_lut, fit_smooth_lut
from ptpcore.fit.choice import fit_auto
from ptpcore.io import MODELS, SampleStack
from ptpcore.pinhole import fit_pinhole
from ptpcore.rig import Rig

__all__ = ["split_positions", "draw_features", "smooth_degree_for", "compare", "AUTO_PLAIN"]

AUTO_PLAIN = (("poly", 1), ("poly", 2), ("poly", 3))
"""The plain PTP LUT's candidates for ``model="auto"`` (the smooth LUT is its own method)."""

Progress = Callable[[float, str], None]


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
    The draw runs over the whole grid of (position, pixel) slots, keeping the valid
    ones in the order drawn: two datasets whose valid pixels differ a little (the
    same rig with and without cover glass, METHOD.md section 8) get the same feature
    points wherever both are valid, so their fits differ only by what differs.

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
    m = min(int(n_points), flat.size)
    n_draw = min(valid.size, int(np.ceil(1.3 * m * valid.size / flat.size)) + 64)
    slots = rng.choice(valid.size, size=n_draw, replace=False)
    slots = slots[valid.ravel()[slots]][:m]
    if slots.size < m:  # unlucky: top up from the valid slots not drawn yet
        rest = np.setdiff1d(flat, slots, assume_unique=True)
        slots = np.concatenate([slots, rng.choice(rest, size=m - slots.size, replace=False)])
    i, row, col = np.unravel_index(np.sort(slots), valid.shape)
    k = positions[i]
    x = samples.x_ref[row, col] + samples.x[k, row, col].astype(np.float64)
    y = samples.y_ref[row, col] + samples.y[k, row, col].astype(np.float64)
    pw = np.stack([x, y, samples.z[k]], axis=1)
    px = np.stack([col, row], axis=1).astype(np.float64)
    return FeaturePoints(pw, px, k.astype(np.int64))


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
            with_smooth: bool = True, smooth_degree: int | None = None, level_bias: bool = True,
            footprint: bool = True, n_pairs: int = 20000, n_bins: int = 20,
            progress: Progress | None = None) -> CompareResult:
    """Run the evaluation protocol of METHOD.md section 7 for PTP, PTP smooth and 3DSTC.

    Parameters
    ----------
    samples : SampleStack
        Decoded samples of all positions (:func:`ptpcore.run.pipeline.collect_samples`).
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
        The plain PTP LUT (:func:`ptpcore.fit.fit_lut`); ``model="auto"``: poly of the
        degree (1 to 3, :data:`AUTO_PLAIN`) most accurate at held-out positions among each
        fold's calibration positions (:func:`ptpcore.fit.choice.fit_auto`; the chosen degree
        is in ``Fold.lut_degree``).
    with_smooth : bool
        Also compare the smooth LUT (:func:`ptpcore.fit.smooth.fit_smooth_lut`).
        It is left out, with a note in :attr:`CompareResult.notes`, when the
        samples carry no camera noise model or a fold has fewer than 3
        calibration positions.
    smooth_degree : int, optional
        Degree of the smooth LUT (1 to 5); default :func:`smooth_degree_for`.
    level_bias, footprint : bool
        The smooth LUT's corrections (:func:`ptpcore.fit.smooth.fit_smooth_lut`): pass those the
        calibration used, so the comparison judges the same model.
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
    _check_compare_inputs(samples, rig, truth, model, seed, n_points, n_bins, smooth_degree)
    seed = int(seed)
    folds_idx = split_positions(len(samples.z), split)
    held_positions = np.concatenate([f[1] for f in folds_idx]).astype(np.int64)
    fold_of_held = np.concatenate([np.full(len(f[1]), i) for i, f in enumerate(folds_idx)]).astype(np.int64)
    z_held = samples.z[held_positions].astype(float)
    s_degree, notes = _smooth_plan(samples, folds_idx, with_smooth, degree, smooth_degree)
    methods = tuple(m for m in METHODS if m != "smooth" or s_degree is not None)

    def report(frac, msg):
        if progress:
            progress(frac, msg)

    acc = _HeldOutErrors.empty(methods, len(held_positions), samples.shape, truth is not None)
    folds = []
    for fi, (cal, held) in enumerate(folds_idx):
        base, step = fi / len(folds_idx) * 0.9, 0.9 / len(folds_idx)
        tag = f"(fold {fi + 1}/{len(folds_idx)})"
        fold, lut, smooth = _fit_fold(samples, rig, fi, cal, held, seed, n_points, rational, model, degree,
                                      s_degree, lambda f, msg: report(base + step * f, f"{msg} {tag}"),
                                      {"level_bias": level_bias, "footprint": footprint})
        folds.append(fold)
        for k in held:
            report(base + 0.8 * step, f"evaluating held-out position {k} (z = {samples.z[k]:g} mm)")
            acc.judge_position(samples, int(k), fold.pinhole, lut, smooth, truth)

    # --- point pairs, and every method's coordinates at their ends
    report(0.92, "drawing point pairs")
    measured_xyz = _measured_points(samples, held_positions, z_held)
    groups = [np.flatnonzero(fold_of_held == fi) for fi in range(len(folds_idx))]
    pairs = {kind: _draw_pairs(acc.mask, groups, kind, int(n_pairs), int(n_bins),
                               np.random.default_rng([seed, 1, i]), measured_xyz)
             for i, kind in enumerate(PAIR_KINDS)}

    result = CompareResult(split, seed, int(n_points), bool(rational), model, int(degree) if model == "poly" else None,
                           samples.z.astype(float).copy(), held_positions, z_held, fold_of_held, folds, acc.mask,
                           acc.err, acc.measured_minus_truth, Coverage(**acc.cov), pairs, methods=methods,
                           smooth_degree=s_degree, notes=notes, corrections=dict(samples.corrections))
    refs = ["measured"] + (["truth"] if truth is not None else [])
    for ref in refs:
        report(0.95, f"statistics against the {ref} reference")
        result.references[ref] = _reference_report(result, ref, measured_xyz, truth)
    if truth is not None:
        mmt, mask = acc.measured_minus_truth, acc.mask
        result.reference_noise = coordinate_stats(mmt[0][mask], mmt[1][mask])
    report(1.0, "comparison done")
    return result


def _check_compare_inputs(samples, rig: Rig, truth, model: str, seed: int, n_points: int, n_bins: int,
                          smooth_degree) -> None:
    """Refuse inconsistent inputs of :func:`compare` with a ValueError naming the argument."""
    if not isinstance(samples, SampleStack):
        raise ValueError(f"samples must be a SampleStack, got {type(samples).__name__}")
    h, w = samples.shape
    if rig.camera.shape != (h, w):
        raise ValueError(f"rig camera is {rig.camera.width}x{rig.camera.height} px but the samples are {w}x{h}")
    if model not in MODELS + ("auto",):
        raise ValueError(f"model must be one of {MODELS + ('auto',)}, got {model!r}")
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


def _smooth_plan(samples: SampleStack, folds_idx, with_smooth: bool, degree: int,
                 smooth_degree) -> tuple[int | None, list[str]]:
    """The smooth LUT's degree in this comparison (None: left out) and the notes saying why.

    It needs the samples' noise model and a few calibration positions per fold.
    """
    notes = []
    n_cal = min(len(f[0]) for f in folds_idx)
    if not with_smooth:
        return None, notes
    if samples.noise is None or samples.modulation is None:
        notes.append("PTP smooth left out: the samples carry no camera noise model to weight them"
                     " (decode them with collect_samples)")
        return None, notes
    if n_cal < 3:
        notes.append(f"PTP smooth left out: it needs at least 3 calibration positions, a fold has {n_cal}")
        return None, notes
    s_degree = smooth_degree_for(degree, n_cal) if smooth_degree is None else int(smooth_degree)
    if n_cal < s_degree + 2:
        raise ValueError(f"a smooth LUT of degree {s_degree} needs at least {s_degree + 2} calibration"
                         f" positions, a fold has {n_cal}")
    if n_cal < 2 * (s_degree + 1):
        notes.append(f"PTP smooth not smoothed: {n_cal} calibration positions are too few to"
                     f" cross-validate its smoothing scale (degree {s_degree} needs {2 * (s_degree + 1)})")
    return s_degree, notes


def _fit_fold(samples: SampleStack, rig: Rig, fi: int, cal, held, seed: int, n_points: int, rational: bool,
              model: str, degree: int, s_degree: int | None, report: Progress, smooth_options: dict | None = None):
    """Calibrate every method on one fold's calibration positions ``cal``.

    Returns
    -------
    fold : Fold
        The fold's 3DSTC fit, feature points, coverage and warnings.
    lut, smooth : Lut, Lut or None
        The plain PTP LUT and the smooth LUT (None when left out).
    """
    report(0.0, "3DSTC: fitting the pinhole camera")
    feats = draw_features(samples, cal, n_points, np.random.default_rng([seed, 0, fi]))
    with warnings.catch_warnings(record=True) as caught:
        # e.g. no convergence: kept in the report (Fold.warnings) rather than lost in a log
        warnings.simplefilter("always")
        pin = fit_pinhole(feats.points_world, feats.pixels, rational=rational)
    report(0.1, "PTP: fitting the LUT")
    if model == "auto":  # the plain LUT chosen among poly 1-3 on this fold's positions (smooth has its column)
        lut, choice = fit_auto(samples, rig, list(map(int, cal)), candidates=AUTO_PLAIN)
        degree = choice.degree
    else:
        lut = fit_lut(samples, model, degree, positions=cal)
    if not lut.valid.any():
        need = f"poly degree {degree} needs {degree + 2}" if model == "poly" else f"{model} needs 2"
        raise ValueError(f"no pixel with a usable LUT when calibrating on positions {list(map(int, cal))}"
                         f" ({need} valid positions per pixel)")
    fold = Fold(np.asarray(cal, np.int64), np.asarray(held, np.int64), pin, feats,
                float(lut.valid.mean()), [str(w.message) for w in caught])
    smooth = None
    if s_degree is not None:
        smooth, info = fit_smooth_lut(samples, rig, s_degree, list(map(int, cal)), seed=seed,
                                      **(smooth_options or {}),
                                      progress=lambda f, msg: report(0.2 + 0.6 * f, f"PTP smooth: {msg}"))
        if not smooth.valid.any():
            raise ValueError(f"no pixel with a usable smooth LUT when calibrating on positions"
                             f" {list(map(int, cal))}")
        fold.smooth_valid_fraction = float(smooth.valid.mean())
        fold.smooth_scale_px = float(info.scale_px)
    if model == "auto":
        fold.lut_degree = int(degree)
    return fold, lut, smooth


@dataclass
class _HeldOutErrors:
    """Every method's error at every held-out position, filled position by position.

    Attributes
    ----------
    mask : (E, H, W) bool
        Pixels where the held-out sample is valid and every method gives a value.
    err : dict of method -> (2, E, H, W) float32, mm
        Method minus measured, X and Y; NaN outside ``mask``.
    measured_minus_truth : (2, E, H, W) float32 or None, mm
    cov : dict of str -> (E,) int64
        Pixel counts per held-out position (see :class:`Coverage`).
    pixel_cols, pixel_rows : (H, W) float64
        Every pixel's camera coordinates, for the pinhole back-projection.
    """

    mask: np.ndarray
    err: dict
    measured_minus_truth: np.ndarray | None
    cov: dict
    pixel_cols: np.ndarray
    pixel_rows: np.ndarray
    e: int = 0

    @classmethod
    def empty(cls, methods, e_n: int, shape, with_truth: bool) -> "_HeldOutErrors":
        h, w = shape
        cov = {k: np.zeros(e_n, np.int64) for k in ("n_measured", "n_ptp", "n_3dstc", "n_compared")}
        if "smooth" in methods:
            cov["n_smooth"] = np.zeros(e_n, np.int64)
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        return cls(np.zeros((e_n, h, w), bool), {m: np.full((2, e_n, h, w), np.nan, np.float32) for m in methods},
                   np.full((2, e_n, h, w), np.nan, np.float32) if with_truth else None, cov, cols, rows)

    def judge_position(self, samples: SampleStack, k: int, pin, lut, smooth, truth) -> None:
        """Evaluate every method at held-out position ``k`` (the next one) against its samples."""
        e = self.e
        z = float(samples.z[k])
        mx, my = samples.absolute(k)
        xy = {"ptp": lut.evaluate(z)}
        sx, sy = pin.model.pixel_to_world_at_z(self.pixel_cols, self.pixel_rows, z)
        valid = samples.valid[k]
        has_ptp = valid & np.isfinite(xy["ptp"].x) & np.isfinite(xy["ptp"].y)
        has_stc = valid & np.isfinite(sx) & np.isfinite(sy)
        m = has_ptp & has_stc
        if smooth is not None:
            xy["smooth"] = smooth.evaluate(z)
            has_smooth = valid & np.isfinite(xy["smooth"].x) & np.isfinite(xy["smooth"].y)
            self.cov["n_smooth"][e] = has_smooth.sum()
            m &= has_smooth
        self.mask[e] = m
        self.cov["n_measured"][e] = valid.sum()
        self.cov["n_ptp"][e] = has_ptp.sum()
        self.cov["n_3dstc"][e] = has_stc.sum()
        self.cov["n_compared"][e] = m.sum()
        for name, ev in xy.items():
            self.err[name][0, e][m] = (ev.x - mx)[m]
            self.err[name][1, e][m] = (ev.y - my)[m]
        self.err["3dstc"][0, e][m] = (sx - mx)[m]
        self.err["3dstc"][1, e][m] = (sy - my)[m]
        if self.measured_minus_truth is not None:
            tx, ty = truth.xy(z)
            self.measured_minus_truth[0, e][m] = (mx - tx)[m]
            self.measured_minus_truth[1, e][m] = (my - ty)[m]
        self.e += 1


def _measured_points(samples: SampleStack, held_positions: np.ndarray, z_held: np.ndarray):
    """``measured_xyz(ei, r, c)``: (P, 3) measured world points (mm) of held-out position ``ei`` at pixels ``r, c``."""

    def measured_xyz(ei, r, c):
        k = held_positions[ei]
        return np.stack([samples.x_ref[r, c] + samples.x[k, r, c].astype(np.float64),
                         samples.y_ref[r, c] + samples.y[k, r, c].astype(np.float64), z_held[ei]], axis=1)

    return measured_xyz


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
