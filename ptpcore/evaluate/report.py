"""The comparison's result: what was fitted, every error map and statistic, its JSON and text forms.

:class:`CompareResult` is what :func:`ptpcore.evaluate.compare` returns; ``to_json_dict``
writes the ``ptp-compare/1`` report and :func:`format_summary` the text the CLI prints.
Nothing is drawn here: the GUI and the export render these arrays.
"""

from __future__ import annotations

import datetime as _dt
import errno
import math
from dataclasses import dataclass, field

import numpy as np

from ptpcore import __version__
from ptpcore.evaluate.statistics import (COMPARE_FORMAT, METHOD_LABELS, METHODS, PAIR_KINDS, REFERENCES, SPLITS,
    CoordinateStats, Verdict, block_rms, jsonable)
from ptpcore.atomic import DiskFullError
from ptpcore.fit.glass import describe_corrections
from ptpcore.rig import position_label
from ptpcore.store import SpillStore
from ptpcore.pinhole import PinholeFit

__all__ = ["COMPARE_FORMAT", "SPLITS", "METHODS", "METHOD_LABELS", "REFERENCES", "PAIR_KINDS", "MethodReport",
           "ReferenceReport", "FeaturePoints", "Fold", "Coverage", "CompareResult", "format_summary", "HeldOutMaps",
           "ErrorMaps"]



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
    lut_degree : int or None
        The plain LUT's degree when it was chosen (``model="auto"``), else None.
    """

    calibration: np.ndarray
    held_out: np.ndarray
    pinhole: PinholeFit
    features: FeaturePoints
    lut_valid_fraction: float
    warnings: list = field(default_factory=list)
    smooth_valid_fraction: float | None = None
    smooth_scale_px: float | None = None
    lut_degree: int | None = None


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


class HeldOutMaps:
    """Every held-out position's error maps and compared pixels, in a temporary file.

    Written one held-out position at a time, in row blocks (:meth:`write_rows`),
    and read back one position at a time: the comparison never holds more than
    a position's maps, whatever the number of positions. The file (float32 maps,
    ``(2 M + 2) 4 + 1`` bytes per pixel and position for M methods with a truth)
    goes where the decoder's spill file goes (``PTP_SPILL_DIR`` or the system's
    temporary folder) and is removed when the last reference to this object is
    gone, or at exit.

    Parameters
    ----------
    methods : sequence of str
        The methods compared.
    e_n : int
        E, held-out positions.
    shape : (H, W)
    with_truth : bool
        Also store the measured samples' error against the truth.

    Raises
    ------
    DiskFullError
        The file does not fit (naming it and the space it needs).

    Notes
    -----
    Fields: ``"{m}.x"``, ``"{m}.y"`` (method minus measured, mm, NaN outside the
    mask), ``"truth.x"``, ``"truth.y"`` (measured minus truth), ``"mask"``.
    """

    def __init__(self, methods, e_n: int, shape, with_truth: bool):
        self.methods = tuple(methods)
        self.e_n = int(e_n)
        self.shape = tuple(int(s) for s in shape)
        self.with_truth = bool(with_truth)
        names = [f"{m}.{a}" for m in self.methods for a in "xy"] + (["truth.x", "truth.y"] if with_truth else [])
        fields = {n: np.float32 for n in names}
        fields["mask"] = np.bool_
        try:
            self._store = SpillStore(self.e_n, self.shape, fields, {n: np.nan for n in names} | {"mask": False})
        except DiskFullError as exc:  # the store's message names the file and calls it the samples': say what it is
            raise DiskFullError(errno.ENOSPC, str(exc).replace("the decoded samples' spill file",
                                                               "the comparison's per-position error maps")) from None
        self._pixels = self.shape[0] * self.shape[1]

    def write_rows(self, e: int, row0: int, mask: np.ndarray, fields: dict) -> None:
        """Store rows ``[row0, row0 + len(mask))`` of held-out position ``e``.

        Parameters
        ----------
        mask : (n, W) bool
        fields : dict of str -> (n, W) float
            Every float field (see Notes of the class); cast to float32.
        """
        self._store.write_rows("mask", e, row0, mask)
        for name, rows in fields.items():
            self._store.write_rows(name, e, row0, rows)

    def mark_written(self, e: int) -> None:
        """Every row of held-out position ``e`` is in."""
        for name in self._store.layout:
            self._store.mark_written(name, e)

    @property
    def float_fields(self) -> list[str]:
        """Names of the float32 maps (every field but ``"mask"``)."""
        return [n for n in self._store.layout if n != "mask"]

    def read_rows(self, name: str, e: int, r0: int, r1: int) -> np.ndarray:
        """(r1 - r0, W) rows of one field at held-out position ``e``."""
        w = self.shape[1]
        return self._store.read(name, r0 * w, r1 * w, [e]).reshape(r1 - r0, w)

    def field_at(self, name: str, e: int) -> np.ndarray:
        """(H, W) one field at held-out position ``e`` (float32 maps, mm; bool mask), read from the file."""
        return self._store.read(name, 0, self._pixels, [e]).reshape(self.shape)

    def mask_at(self, e: int) -> np.ndarray:
        """(H, W) bool: the compared pixels of held-out position ``e``."""
        return self.field_at("mask", e)

    def gather(self, name: str, e: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """(P,) one field at pixels ``(row, col)`` of held-out positions ``e`` (one position read at a time)."""
        e = np.asarray(e)
        out = np.empty(e.shape, self._store.layout[name][0])
        for ei in np.unique(e):
            sel = e == ei
            out[sel] = self.field_at(name, int(ei))[row[sel], col[sel]]
        return out

    def mask_array(self) -> np.ndarray:
        """(E, H, W) bool, every position's compared pixels at once (E x H x W bytes)."""
        return np.stack([self.mask_at(e) for e in range(self.e_n)]) if self.e_n else np.zeros((0, *self.shape), bool)


class ErrorMaps:
    """A ``(2, E, H, W)`` float32 error map (mm) that stays in :class:`HeldOutMaps`' file.

    :meth:`position` reads one held-out position; ``np.asarray(maps)`` and
    indexing (``maps[0, e]``) build the whole array, for small sensors and tests.

    Parameters
    ----------
    maps : HeldOutMaps
    prefix : str
        A method (``"ptp"``, ...: method minus measured) or ``"truth"`` (measured minus truth).
    """

    dtype = np.dtype(np.float32)
    ndim = 4

    def __init__(self, maps: HeldOutMaps, prefix: str):
        self.maps = maps
        self.prefix = prefix

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return (2, self.maps.e_n, *self.maps.shape)

    def __len__(self) -> int:
        return 2

    def position(self, e: int) -> np.ndarray:
        """(2, H, W) float32, mm: dX, dY at held-out position ``e``; NaN outside the mask."""
        return np.stack([self.maps.field_at(f"{self.prefix}.{a}", e) for a in "xy"])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        whole = np.stack([self.position(e) for e in range(self.maps.e_n)], axis=1)
        return whole if dtype is None else whole.astype(dtype)

    def __getitem__(self, key):
        return np.asarray(self)[key]


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
    maps : HeldOutMaps
        The per-position error maps and compared pixels, in a temporary file
        (read one held-out position at a time: :meth:`errors_at`). The
        properties below build whole arrays from it on request.
    mask : (E, H, W) bool (property)
        Compared pixels (:meth:`HeldOutMaps.mask_at` for one position).
    error_vs_measured : dict of str to ErrorMaps (property)
        Per method, ``(dX, dY)`` = method minus measured sample, ``(2, E, H, W)``
        float32, mm; NaN outside ``mask``. ``ErrorMaps.position(e)`` reads one
        position, ``np.asarray`` the whole array.
    measured_minus_truth : ErrorMaps or None (property)
        The held-out samples' own error against the truth, ``(2, E, H, W)``
        float32, mm (NaN outside ``mask``).
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
    corrections : dict
        What was removed from the samples before every method's fit
        (``SampleStack.corrections``: the cover glass, a measured flatness and
        a refined stage pose, each with its median and max per-pixel shift, µm).
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
    maps: HeldOutMaps
    coverage: Coverage
    pairs: dict
    references: dict = field(default_factory=dict)
    reference_noise: CoordinateStats | None = None
    methods: tuple = METHODS
    smooth_degree: int | None = None
    notes: list = field(default_factory=list)
    corrections: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the camera."""
        return self.maps.shape

    @property
    def mask(self) -> np.ndarray:
        """(E, H, W) bool: the compared pixels, built from the file on each access."""
        return self.maps.mask_array()

    @property
    def error_vs_measured(self) -> dict:
        """Per method an :class:`ErrorMaps` ``(2, E, H, W)`` float32, mm: method minus measured."""
        return {m: ErrorMaps(self.maps, m) for m in self.methods}

    @property
    def measured_minus_truth(self) -> ErrorMaps | None:
        """:class:`ErrorMaps` ``(2, E, H, W)`` float32, mm: measured minus truth; None without a truth."""
        return ErrorMaps(self.maps, "truth") if self.maps.with_truth else None

    @property
    def pinhole(self) -> PinholeFit:
        """The 3DSTC fit of the first fold (the only one for ``alternate``)."""
        return self.folds[0].pinhole

    def errors_at(self, method: str, reference: str, e: int) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel coordinate errors at held-out position ``e`` (index into :attr:`held_positions`).

        Returns
        -------
        dx, dy : (H, W) float64, mm
            Method minus reference; NaN outside ``mask[e]``.

        Raises
        ------
        ValueError
            Unknown method or reference, or ``"truth"`` without a truth.
        """
        self._check_errors(method, reference)
        dx = self.maps.field_at(f"{method}.x", e).astype(np.float64)
        dy = self.maps.field_at(f"{method}.y", e).astype(np.float64)
        if reference == "truth":  # (method - measured) + (measured - truth), in float64 as the sum always was
            dx += self.maps.field_at("truth.x", e)
            dy += self.maps.field_at("truth.y", e)
        return dx, dy

    def errors(self, method: str, reference: str) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel coordinate errors at every held-out position at once (small sensors, tests).

        Parameters
        ----------
        method : one of :attr:`methods` ({"ptp", "smooth", "3dstc"})
        reference : {"measured", "truth"}

        Returns
        -------
        dx, dy : (E, H, W) float64, mm
            Method minus reference; NaN outside :attr:`mask`. Error heatmaps
            are ``np.hypot(dx, dy)``. 16 bytes per pixel and position: for big
            sensors read one position at a time with :meth:`errors_at`.
        """
        self._check_errors(method, reference)
        both = [self.errors_at(method, reference, e) for e in range(len(self.held_positions))]
        if not both:
            return np.zeros((0, *self.shape)), np.zeros((0, *self.shape))
        return np.stack([b[0] for b in both]), np.stack([b[1] for b in both])

    def _check_errors(self, method: str, reference: str) -> None:
        if method not in self.methods:
            raise ValueError(f"method must be one of {self.methods}, got {method!r}")
        if reference not in REFERENCES:
            raise ValueError(f"reference must be one of {REFERENCES}, got {reference!r}")
        if reference == "truth" and not self.maps.with_truth:
            raise ValueError("no truth was given to compare(): only the 'measured' reference exists")

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
                       "smooth_valid_fraction": jsonable(f.smooth_valid_fraction),
                       "smooth_scale_px": jsonable(f.smooth_scale_px), "lut_degree": f.lut_degree}
                      for f in self.folds],
            "coverage": {k: v.tolist() for k, v in self.coverage.__dict__.items() if v is not None},
            "pairs": {k: {"n": len(p), "edges_mm": jsonable(p.edges_mm)} for k, p in self.pairs.items()},
            "reference_noise": None if self.reference_noise is None else self.reference_noise.to_json_dict(),
            "notes": list(self.notes),
            "corrections": self.corrections,
            "references": {},
        }
        for ref, rr in self.references.items():
            r = {"verdict": {k: jsonable(v) for k, v in rr.verdict.__dict__.items()}}
            for m, mr in rr.methods.items():
                r[m] = {
                    "coordinate": mr.coordinate.to_json_dict(),
                    "per_position": [dict(position=int(k), z_mm=float(z), **s.to_json_dict())
                                     for k, z, s in zip(self.held_positions, self.z_held, mr.per_position)],
                    "distance": {kind: {"stats": d.stats.to_json_dict(), "curve": d.curve.to_json_dict()}
                                 for kind, d in mr.distance.items()},
                    "heatmap": {"block_px": block, "rms_um": jsonable(block_rms(mr.heatmap_mm, block) * 1e3)},
                }
            out["references"][ref] = r
        return out


def _pinhole_json(fit: PinholeFit) -> dict:
    d = fit.model.to_dict()
    d.update(param_names=list(fit.param_names), param_values=fit.param_values.tolist(),
             param_std=jsonable(fit.param_std), reprojection_rms_px=fit.reprojection_rms_px,
             n_points=fit.n_points)
    return d


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
    if result.lut_model == "auto":
        chosen = ", ".join(str(f.lut_degree) for f in result.folds)
        lut = (f"auto: poly degree {chosen} (the most accurate of degrees 1-3 at positions held out of the"
               f" calibration positions{', per fold' if len(result.folds) > 1 else ''})")
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
    for msg in describe_corrections(result.corrections):
        lines.append(f"  correction          {msg}")
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

        row("vector error |(dX, dY)|", lambda mr: mr.coordinate)
        cells = [f"{rr.methods[m].coordinate.rms_x_um:.3g} / {rr.methods[m].coordinate.rms_y_um:.3g}" for m in ms]
        lines.append(f"    {'  per axis, RMS X / Y':<26}" + "".join(f"{c:^25}" for c in cells))
        row("distance, same height", lambda mr: mr.distance["same_height"].stats)
        row("distance, across heights", lambda mr: mr.distance["across_heights"].stats)
        per = "; ".join(f"{position_label(k, z)}: " + "/".join(f"{rr.methods[m].per_position[i].rms_um:.3g}"
                                                             for m in ms)
                        for i, (k, z) in enumerate(zip(result.held_positions, result.z_held)))
        lines.append(f"    vector error RMS per position, {'/'.join(METHOD_LABELS[m] for m in ms)}: {per}")
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
