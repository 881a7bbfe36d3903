"""The comparison: point-to-point LUTs against 3DSTC on held-out heights (docs/method.md sections 6-7).

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
from dataclasses import dataclass, replace

import numpy as np

from ptpcore.evaluate.report import (METHODS, PAIR_KINDS, SPLITS, CompareResult, Coverage, FeaturePoints, Fold,
    HeldOutMaps, MethodReport, ReferenceReport)
from ptpcore.evaluate.statistics import (CoordinateAccumulator, DistanceErrors, comparison_verdict, coordinate_stats,
    distance_curve, draw_pairs, error_stats)
from ptpcore.fit import fit_lut, fit_smooth_lut
from ptpcore.fit.choice import fit_auto
from ptpcore.io import MODELS, SampleStack
from ptpcore.store import read_block
from ptpcore.pinhole import fit_pinhole
from ptpcore.progress import Progress, sub_progress
from ptpcore.rig import Rig

__all__ = ["split_positions", "draw_features", "smooth_degree_for", "compare", "AUTO_PLAIN"]

AUTO_PLAIN = (("poly", 1), ("poly", 2), ("poly", 3))
"""The plain PTP LUT's candidates for ``model="auto"`` (the smooth LUT is its own method)."""


def split_positions(n_positions: int, split: str = "alternate") -> list[tuple[np.ndarray, np.ndarray]]:
    """Calibration / held-out folds of the positions (docs/method.md section 7).

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
    same rig with and without cover glass, docs/method.md section 8) get the same feature
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
    valid = _valid(samples, positions)
    n_valid = int(np.count_nonzero(valid))  # (the valid slots' index list only when topping up: 8 B a sample)
    if n_valid < 20:
        raise ValueError(f"3DSTC needs feature points: only {n_valid} valid samples at positions"
                         f" {positions.tolist()}")
    m = min(int(n_points), n_valid)
    n_draw = min(valid.size, int(np.ceil(1.3 * m * valid.size / n_valid)) + 64)
    slots = rng.choice(valid.size, size=n_draw, replace=False)
    slots = slots[valid.ravel()[slots]][:m]
    if slots.size < m:  # unlucky: top up from the valid slots not drawn yet
        rest = np.setdiff1d(np.flatnonzero(valid), slots, assume_unique=True)
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
    """Run the evaluation protocol of docs/method.md section 7 for PTP, PTP smooth and 3DSTC.

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

        def fold_report(f, msg, base=base, step=step, tag=tag):
            report(base + step * f, f"{msg} {tag}")

        fold, lut = _fit_fold(samples, rig, fi, cal, held, seed, n_points, rational, model, degree, fold_report)
        folds.append(fold)
        e0 = acc.e
        for k in held:
            fold_report(0.15, f"evaluating held-out position {k} (z = {samples.z[k]:g} mm)")
            acc.judge_position(samples, int(k), fold.pinhole, lut, truth, final=s_degree is None)
        del lut  # the plain LUT is judged: the smooth fit (the command's peak) runs without it
        if s_degree is not None:
            smooth = _fit_fold_smooth(samples, rig, fold, s_degree, seed, fold_report,
                                      {"level_bias": level_bias, "footprint": footprint})
            for e, k in enumerate(held, start=e0):
                fold_report(0.8, f"evaluating PTP smooth at held-out position {k} (z = {samples.z[k]:g} mm)")
                acc.add_smooth(samples, e, int(k), smooth)
            del smooth

    # --- point pairs, and every method's coordinates at their ends
    report(0.92, "drawing point pairs")
    measured_xyz = _measured_points(samples, held_positions, z_held)
    groups = [np.flatnonzero(fold_of_held == fi) for fi in range(len(folds_idx))]
    maps = acc.maps
    pairs = {kind: draw_pairs(maps.mask_at, acc.cov["n_compared"], samples.shape, groups, kind, int(n_pairs),
                               int(n_bins), np.random.default_rng([seed, 1, i]), measured_xyz)
             for i, kind in enumerate(PAIR_KINDS)}

    result = CompareResult(split, seed, int(n_points), bool(rational), model, int(degree) if model == "poly" else None,
                           samples.z.astype(float).copy(), held_positions, z_held, fold_of_held, folds, maps,
                           Coverage(**acc.cov), pairs, methods=methods, smooth_degree=s_degree, notes=notes,
                           corrections=dict(samples.corrections))
    ends = _PairEnds(result, measured_xyz, truth)
    refs = ["measured"] + (["truth"] if truth is not None else [])
    for ref in refs:
        report(0.95, f"statistics against the {ref} reference")
        result.references[ref] = _reference_report(result, ref, ends)
    if truth is not None:
        result.reference_noise = _blocked_stats(len(held_positions), lambda e: _truth_noise_at(maps, e))[0]
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
              model: str, degree: int, report: Progress):
    """Calibrate 3DSTC and the plain PTP LUT on one fold's calibration positions ``cal``.

    Returns
    -------
    fold : Fold
        The fold's 3DSTC fit, feature points, coverage and warnings.
    lut : Lut
        The plain PTP LUT.
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
    if model == "auto":
        fold.lut_degree = int(degree)
    return fold, lut


def _fit_fold_smooth(samples: SampleStack, rig: Rig, fold: Fold, s_degree: int, seed: int, report: Progress,
                     smooth_options: dict | None = None):
    """The smooth LUT on ``fold``'s calibration positions; records its coverage and scale in ``fold``."""
    cal = list(map(int, fold.calibration))
    smooth, info = fit_smooth_lut(samples, rig, s_degree, cal, seed=seed, **(smooth_options or {}),
                                  progress=sub_progress(report, 0.2, 0.8, "PTP smooth: "))
    if not smooth.valid.any():
        raise ValueError(f"no pixel with a usable smooth LUT when calibrating on positions {cal}")
    fold.smooth_valid_fraction = float(smooth.valid.mean())
    fold.smooth_scale_px = float(info.scale_px)
    return smooth


_BLOCK_PIXELS = 1 << 18
"""Pixels per row block when judging a held-out position (whole rows; 2 MB per float64 map)."""


def _valid(samples: SampleStack, positions) -> np.ndarray:
    """(len(positions), H, W) bool: the samples' validity, read from the (spilled) stack by file reads.

    ``samples.valid`` would compare the whole ``(K, H, W)`` reasons through the memory map.
    """
    h, w = samples.shape
    out = np.empty((len(positions), h, w), bool)
    for i, k in enumerate(positions):  # one position's reasons at a time
        out[i] = (read_block(samples.reasons, 0, h * w, [k])[0] == 0).reshape(h, w)
    return out


def _lut_rows(lut, r0: int, r1: int):
    """The LUT of rows ``[r0, r1)`` (views): its evaluation there is the whole LUT's, pixel by pixel."""
    if lut is None:
        return None
    return replace(lut, x=lut.x[:, r0:r1], y=lut.y[:, r0:r1], valid=lut.valid[r0:r1],
                   pixel_z_min=lut.pixel_z_min[r0:r1], pixel_z_max=lut.pixel_z_max[r0:r1])


@dataclass
class _HeldOutErrors:
    """Every method's error at every held-out position, filled position by position, row block by row block.

    Attributes
    ----------
    maps : HeldOutMaps
        The error maps (method minus measured, measured minus truth; float32, mm, NaN outside the mask) and
        the compared pixels (valid held-out sample and every method gives a value), in a temporary file.
    cov : dict of str -> (E,) int64
        Pixel counts per held-out position (see :class:`Coverage`).
    """

    maps: HeldOutMaps
    cov: dict
    e: int = 0

    @classmethod
    def empty(cls, methods, e_n: int, shape, with_truth: bool) -> "_HeldOutErrors":
        cov = {k: np.zeros(e_n, np.int64) for k in ("n_measured", "n_ptp", "n_3dstc", "n_compared")}
        if "smooth" in methods:
            cov["n_smooth"] = np.zeros(e_n, np.int64)
        return cls(HeldOutMaps(methods, e_n, shape, with_truth), cov)

    def judge_position(self, samples: SampleStack, k: int, pin, lut, truth, final: bool = True) -> None:
        """Evaluate PTP and 3DSTC at held-out position ``k`` (the next one) against its samples.

        In row blocks of about :data:`_BLOCK_PIXELS` pixels: every full-image
        float64 temporary (the methods' X, Y, the pinhole's undistortion) is a
        block's, and each block's errors go to the file at once. ``final=False``:
        the smooth LUT comes later (:meth:`add_smooth`) and narrows the mask.
        """
        h, w = self.maps.shape
        for r0 in range(0, h, max(1, _BLOCK_PIXELS // w)):
            counts = self._judge_rows(samples, k, r0, min(h, r0 + max(1, _BLOCK_PIXELS // w)), pin, lut, truth)
            for key, n in counts.items():
                self.cov[key][self.e] += n
        if final:
            self.maps.mark_written(self.e)
        self.e += 1

    def add_smooth(self, samples: SampleStack, e: int, k: int, smooth) -> None:
        """Add the smooth LUT at held-out position ``k`` (index ``e``), judged already by :meth:`judge_position`.

        The compared pixels become those where the smooth LUT gives a value too;
        every stored map is cut to them, row block by row block.
        """
        h, w = self.maps.shape
        self.cov["n_compared"][e] = 0
        for r0 in range(0, h, max(1, _BLOCK_PIXELS // w)):
            counts = self._smooth_rows(samples, e, k, r0, min(h, r0 + max(1, _BLOCK_PIXELS // w)), smooth)
            for key, n in counts.items():
                self.cov[key][e] += n
        self.maps.mark_written(e)

    def _judge_rows(self, samples: SampleStack, k: int, r0: int, r1: int, pin, lut, truth) -> dict:
        """Judge PTP and 3DSTC at rows ``[r0, r1)`` of held-out position ``k``; their pixel counts (keys of ``cov``)."""
        w = self.maps.shape[1]
        z = float(samples.z[k])
        valid, mx, my = _measured_rows(samples, k, r0, r1)
        ev = _lut_rows(lut, r0, r1).evaluate(z)
        xy = {"ptp": (ev.x, ev.y)}
        cols = np.arange(w, dtype=np.float64)[None, :]
        prow = np.arange(r0, r1, dtype=np.float64)[:, None]
        xy["3dstc"] = pin.model.pixel_to_world_at_z(cols, prow, z)
        has = {name: valid & np.isfinite(xy[name][0]) & np.isfinite(xy[name][1]) for name in xy}
        m = has["ptp"] & has["3dstc"]
        fields = {}
        for name, (x, y) in xy.items():
            fields[f"{name}.x"] = np.where(m, x - mx, np.nan).astype(np.float32)
            fields[f"{name}.y"] = np.where(m, y - my, np.nan).astype(np.float32)
        if self.maps.with_truth:  # truth.xy(z), for these rows
            fields["truth.x"] = np.where(m, mx - (truth.x0[r0:r1] + truth.sx[r0:r1] * z), np.nan).astype(np.float32)
            fields["truth.y"] = np.where(m, my - (truth.y0[r0:r1] + truth.sy[r0:r1] * z), np.nan).astype(np.float32)
        self.maps.write_rows(self.e, r0, m, fields)
        return {"n_measured": int(valid.sum()), "n_ptp": int(has["ptp"].sum()), "n_3dstc": int(has["3dstc"].sum()),
                "n_compared": int(m.sum())}

    def _smooth_rows(self, samples: SampleStack, e: int, k: int, r0: int, r1: int, smooth) -> dict:
        """The smooth LUT at rows ``[r0, r1)`` of held-out position ``k``; the mask and every map cut to it."""
        valid, mx, my = _measured_rows(samples, k, r0, r1)
        es = _lut_rows(smooth, r0, r1).evaluate(float(samples.z[k]))
        has_smooth = valid & np.isfinite(es.x) & np.isfinite(es.y)
        m = self.maps.read_rows("mask", e, r0, r1) & has_smooth
        fields = {name: np.where(m, self.maps.read_rows(name, e, r0, r1), np.float32(np.nan))
                  for name in self.maps.float_fields if not name.startswith("smooth.")}
        fields["smooth.x"] = np.where(m, es.x - mx, np.nan).astype(np.float32)
        fields["smooth.y"] = np.where(m, es.y - my, np.nan).astype(np.float32)
        self.maps.write_rows(e, r0, m, fields)
        return {"n_smooth": int(has_smooth.sum()), "n_compared": int(m.sum())}


def _measured_rows(samples: SampleStack, k: int, r0: int, r1: int):
    """Rows ``[r0, r1)`` of position ``k``: valid (n, W) bool and the absolute X, Y (n, W) float64 mm.

    File reads of the (spilled) stack; the same numbers as ``samples.valid[k]``, ``samples.absolute(k)``.
    """
    w = samples.shape[1]
    n0, n1 = r0 * w, r1 * w
    valid = (read_block(samples.reasons, n0, n1, [k])[0] == 0).reshape(r1 - r0, w)
    mx = samples.x_ref[r0:r1] + read_block(samples.x, n0, n1, [k])[0].reshape(r1 - r0, w)
    my = samples.y_ref[r0:r1] + read_block(samples.y, n0, n1, [k])[0].reshape(r1 - r0, w)
    return valid, mx, my


def _measured_points(samples: SampleStack, held_positions: np.ndarray, z_held: np.ndarray):
    """``measured_xyz(ei, r, c)``: (P, 3) measured world points (mm) of held-out position ``ei`` at pixels ``r, c``.

    The samples are read one held-out position at a time with file reads (a
    spilled stack's pages are not mapped into the process).
    """
    h, w = samples.shape

    def measured_xyz(ei, r, c):
        ei = np.asarray(ei)
        out = np.empty((ei.size, 3))
        for e in np.unique(ei):
            sel = ei == e
            k = int(held_positions[e])
            rs, cs = r[sel], c[sel]
            for axis, (ref, stack) in enumerate(((samples.x_ref, samples.x), (samples.y_ref, samples.y))):
                out[sel, axis] = ref[rs, cs] + read_block(stack, 0, h * w, [k])[0].reshape(h, w)[rs, cs].astype(
                    np.float64)
        out[:, 2] = z_held[ei]
        return out

    return measured_xyz


class _PairEnds:
    """The point pairs' ends, gathered once: measured points, the truth's, every method's error there.

    Attributes
    ----------
    measured, truth : dict of kind -> ((P, 3), (P, 3)) float64, mm
        Ends a and b (``truth`` empty without a truth).
    error : dict of method -> kind -> ((2, P), (2, P)) float32, mm
        Method minus measured at ends a and b (read one held-out position at a time).
    """

    def __init__(self, result: CompareResult, measured_xyz, truth):
        ends = {kind: ((p.held_a, p.row_a, p.col_a), (p.held_b, p.row_b, p.col_b)) for kind, p in result.pairs.items()}
        self.measured = {kind: tuple(measured_xyz(*end) for end in two) for kind, two in ends.items()}
        self.truth = {}
        if truth is not None:
            def truth_xyz(ei, r, c):
                z = result.z_held[ei]
                return np.stack([truth.x0[r, c] + truth.sx[r, c] * z, truth.y0[r, c] + truth.sy[r, c] * z, z], axis=1)

            self.truth = {kind: tuple(truth_xyz(*end) for end in two) for kind, two in ends.items()}
        self.error = {m: self._gather(result.maps, m, ends) for m in result.methods}

    @staticmethod
    def _gather(maps: HeldOutMaps, method: str, ends: dict) -> dict:
        """Every pair end's error of ``method`` in one pass over the positions per axis."""
        parts = [end for two in ends.values() for end in two]
        if not parts:
            return {kind: (np.zeros((2, 0), np.float32),) * 2 for kind in ends}
        ei, r, c = (np.concatenate([p[i] for p in parts]) for i in range(3))
        both = np.stack([maps.gather(f"{method}.{a}", ei, r, c) for a in "xy"])
        split = np.split(both, np.cumsum([len(p[0]) for p in parts])[:-1], axis=1)
        return {kind: (split[2 * i], split[2 * i + 1]) for i, kind in enumerate(ends)}


def _blocked_stats(e_n: int, position) -> tuple:
    """Coordinate statistics over every held-out position, read one position at a time.

    Parameters
    ----------
    e_n : int
        E, held-out positions.
    position : callable
        ``position(e)``: (dx, dy, mask) with dx, dy (H, W) float64 mm and mask (H, W) bool.

    Returns
    -------
    overall : CoordinateStats
        Over every compared pixel of every position (n, p95 and max exact; RMS and means
        from per-position sums: :class:`~ptpcore.evaluate.statistics.CoordinateAccumulator`).
    per_position : list of CoordinateStats
    heatmap : (H, W) float64, mm
        Per pixel the RMS over positions of ``|(dX, dY)|``; NaN where never compared.
    """
    acc = CoordinateAccumulator()
    per, sq, n = [], None, None
    for e in range(e_n):
        dx, dy, mk = position(e)
        if sq is None:
            sq, n = np.zeros(dx.shape), np.zeros(dx.shape, np.int64)
        cx, cy = dx[mk], dy[mk]
        dx *= dx  # in place: a position's float64 maps are the largest temporaries here
        dx += dy * dy
        dx[~mk] = 0.0
        sq += dx  # in position order, as a sum over axis 0 adds them
        n += mk
        del dx, dy
        per.append(coordinate_stats(cx, cy))
        acc.add(cx, cy)

    def lengths(e):
        dx, dy, mk = position(e)
        return np.hypot(dx[mk], dy[mk])

    heat = None
    if sq is not None:
        heat = np.full(sq.shape, np.nan)
        np.sqrt(np.divide(sq, n, out=np.zeros_like(sq), where=n > 0), out=heat, where=n > 0)
    return acc.result(lengths, e_n), per, heat


def _truth_noise_at(maps: HeldOutMaps, e: int):
    """(dx, dy, mask) of the measured samples against the truth at held-out position ``e``."""
    return maps.field_at("truth.x", e).astype(np.float64), maps.field_at("truth.y", e).astype(np.float64), maps.mask_at(e)


def _reference_report(result: CompareResult, ref: str, ends: _PairEnds) -> ReferenceReport:
    """Every method against reference ``ref``: statistics, heatmaps (a position at a time), distance errors."""
    e_n = len(result.held_positions)
    methods = {}
    for m in result.methods:
        def position(e, m=m):
            dx, dy = result.errors_at(m, ref, e)
            return dx, dy, result.maps.mask_at(e)

        overall, per, heat = _blocked_stats(e_n, position)
        if heat is None:
            heat = np.full(result.shape, np.nan)
        methods[m] = MethodReport(m, ref, overall, per, heat, _distance_errors(result, m, ref, ends))

    def dist_rms(m):
        e = np.concatenate([d.error_mm for d in methods[m].distance.values()])
        return error_stats(e).rms_um

    v = comparison_verdict(ref, {m: methods[m].coordinate.rms_um for m in result.methods},
                 {m: dist_rms(m) for m in result.methods})
    return ReferenceReport(ref, methods, v)


def _distance_errors(result: CompareResult, m: str, ref: str, ends: _PairEnds) -> dict:
    """Per pair kind, the distance errors of method ``m`` against ``ref`` (a method's point: measured + its error)."""
    dist = {}
    for kind, p in result.pairs.items():
        pts = []
        for meas, em, ref_pt in zip(ends.measured[kind], ends.error[m][kind],
                                    ends.truth[kind] if ref == "truth" else ends.measured[kind]):
            mp = meas.copy()
            mp[:, 0] += em[0]
            mp[:, 1] += em[1]
            pts.append((mp, ref_pt))
        d_method = np.linalg.norm(pts[0][0] - pts[1][0], axis=1)
        d_ref = np.linalg.norm(pts[0][1] - pts[1][1], axis=1)
        err = d_method - d_ref
        dist[kind] = DistanceErrors(kind, m, ref, d_ref, err, error_stats(err), distance_curve(d_ref, err, p.edges_mm))
    return dist
