"""``--model auto``: the LUT model chosen by its error at held-out positions.

Every candidate (:data:`AUTO_CANDIDATES`: plain ``poly`` degrees 1 to 3 and
``smooth``) is fitted on some of the calibration positions and judged at the
others (interior positions, so nothing extrapolates), against the samples
measured there. The chosen model is then refitted on all positions.

What is judged. A held-out sample differs from the candidate's prediction by
the candidate's own error ``e`` plus the sample's noise ``n`` (independent of
the fit, which never saw the sample): ``E[d^2] = E[e^2] + E[n^2]``. The noise
term is the same for every candidate, so the ranking is that of the measured
RMS ``d``; the model error itself, ``sqrt(max(d^2 - n^2, 0))`` with ``n`` the
predicted sample noise (:func:`ptpcore.fit.smooth.sample_sigma_from_noise`, plus
the stage readings' error through each pixel's slope), is what the tie rule
compares: a simpler candidate whose model error is within :data:`TIE_FRACTION`
of the best one's is taken (judged on the difference of the measured mean squares,
in which the noise cancels: ``d_i^2 - d_best^2 <= (1.05^2 - 1) (d_best^2 - n^2)``;
a noise prediction above the measured ``d_best^2`` leaves no allowance, so a
wrong noise prediction can cost a tie but never choose a worse model) (with a few thousand held-out samples the RMS itself
is known to far better than 5 %; what is not known better is how far the
held-out positions, fitted from half the positions, speak for the full fit).

The smooth candidate is judged as ``--model smooth`` writes it: its smoothing scale is chosen
first by the smooth fit's own cross-validation on all calibration positions, and the fold's fit
keeps that scale (a fold with half the positions would choose a smaller one: 2 px where all
positions choose 16 px on a glass rig, issue 30).

The candidates are compared over the pixels every one of them covers; a
candidate covering less than :data:`MIN_COVERAGE` of the best covered pixels
(e.g. ``poly`` degree 3 with too few positions in a fold) is left out, with a
note.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from ptpcore.fit.kinds import fit_kind
from ptpcore.fit.smooth import position_sigma_from_noise
from ptpcore.io.lutfile import Lut
from ptpcore.io.samples import SampleStack
from ptpcore.progress import Progress, sub_progress
from ptpcore.rig.rigfile import Rig
from ptpcore.store import release_free_memory

__all__ = ["AUTO", "AUTO_CANDIDATES", "TIE_FRACTION", "MIN_COVERAGE", "CandidateError", "ModelChoice", "SmoothGlobalFits",
           "choice_folds", "choose_model", "fit_auto"]

AUTO = "auto"
SMOOTH_DEGREE = 3
"""``ptp calibrate --model smooth``'s degree (its ``--degree`` default)."""

AUTO_CANDIDATES: tuple[tuple[str, int], ...] = (("poly", 1), ("poly", 2), ("poly", 3), ("smooth", 2),
                                                ("smooth", SMOOTH_DEGREE))
"""``(model, degree)`` in order of simplicity (ties go to the earlier one). Each smooth candidate is
the LUT ``--model smooth --degree D`` writes, its smoothing scale chosen on all positions
(:func:`choose_model`), so the choice judges the LUT it would then write: degree 3, the command's
default, and degree 2 (0.34 against 0.43 um on a drawn realistic rig with 1.1 mm glass, where both
choose 2 px: issue 30's harness, half A)."""

TIE_FRACTION = 0.05
"""A simpler candidate whose model error is within this fraction of the best one's is chosen."""

MIN_COVERAGE = 0.5
"""Fraction of the best candidate's pixels a candidate must cover to be judged."""

JUDGE_BAND_PIXELS = 1 << 20
"""Pixels per band of rows in which a candidate is evaluated at a held-out position (8 MB a float64 map)."""


@dataclass
class CandidateError:
    """One candidate's error at the held-out positions.

    Attributes
    ----------
    model : str
    degree : int
    held_out_rms_um : float
        RMS over X and Y of (prediction - held-out sample), µm; NaN if not judged.
    model_error_um : float
        The same with the predicted sample noise taken out (µm); NaN if unknown.
    coverage : float
        Fraction of the best covered candidate's held-out samples this one predicts.
    note : str
        Why it was not judged (empty if it was).
    smoothing_scale_px : float
        ``smooth`` only: the scale ``--model smooth`` chooses on all positions, which each fold's fit
        kept and the final fit reuses (NaN for the other models, or when it could not be chosen).
    """

    model: str
    degree: int
    held_out_rms_um: float
    model_error_um: float
    coverage: float
    note: str = ""
    smoothing_scale_px: float = float("nan")

    @property
    def name(self) -> str:
        if self.model == "poly":
            return f"poly degree {self.degree}"
        at = f", {self.smoothing_scale_px:g} px" if np.isfinite(self.smoothing_scale_px) else ""
        return f"{self.model} (degree {self.degree}{at})"


@dataclass
class ModelChoice:
    """The candidates' held-out errors and the pick.

    Attributes
    ----------
    candidates : list of CandidateError
    chosen : int
        Index into ``candidates``.
    held_out : list of list of int
        Held-out positions of each fold.
    noise_rms_um : float
        Predicted RMS noise of the held-out samples (µm), NaN without a noise model.
    n_samples : int
        Held-out X and Y values every judged candidate was compared on.
    rule : str
    """

    candidates: list
    chosen: int
    held_out: list
    noise_rms_um: float
    n_samples: int
    rule: str = field(default=f"lowest held-out error; within {TIE_FRACTION:.0%} of it, the simplest")

    @property
    def model(self) -> str:
        return self.candidates[self.chosen].model

    @property
    def degree(self) -> int:
        return self.candidates[self.chosen].degree

    def to_json(self) -> str:
        """The ``/provenance`` attribute ``model_choice`` (FORMATS.md)."""
        c = self.candidates[self.chosen]
        return json.dumps({
            "chosen": {"model": c.model, "degree": c.degree},
            "rule": self.rule, "held_out_positions": self.held_out,
            "noise_rms_um": _num(self.noise_rms_um), "n_samples": int(self.n_samples),
            "candidates": [{"model": k.model, "degree": k.degree, "held_out_rms_um": _num(k.held_out_rms_um),
                            "model_error_um": _num(k.model_error_um), "coverage": _num(k.coverage),
                            "note": k.note,
                            **({"smoothing_scale_px": _num(k.smoothing_scale_px)} if k.model == "smooth" else {})}
                           for k in self.candidates],
        })

    @classmethod
    def from_json(cls, text: str) -> "ModelChoice":
        """Read back :meth:`to_json` (missing numbers come back as NaN)."""
        d = json.loads(text)
        cands = [CandidateError(k["model"], int(k["degree"]), _flt(k.get("held_out_rms_um")),
                                _flt(k.get("model_error_um")), _flt(k.get("coverage")), k.get("note", ""),
                                _flt(k.get("smoothing_scale_px")))
                 for k in d["candidates"]]
        pick = d["chosen"]
        chosen = next(i for i, k in enumerate(cands) if (k.model, k.degree) == (pick["model"], pick["degree"]))
        return cls(cands, chosen, d.get("held_out_positions", []), _flt(d.get("noise_rms_um")),
                   int(d.get("n_samples", 0)), d.get("rule", ""))

    def table(self) -> list[str]:
        """The candidates as text lines (the chosen one marked), for summaries."""
        lines = [f"{'model':<22} {'held-out RMS':>13} {'model error':>12}"]
        for i, c in enumerate(self.candidates):
            mark = "  <- chosen" if i == self.chosen else ""
            if c.note:
                lines.append(f"{c.name:<22} {'-':>13} {'-':>12}  ({c.note})")
            else:
                lines.append(f"{c.name:<22} {c.held_out_rms_um:>10.3f} µm {c.model_error_um:>9.3f} µm{mark}")
        return lines


def _num(v):
    return None if v is None or not np.isfinite(v) else round(float(v), 6)


def _flt(v) -> float:
    return float("nan") if v is None else float(v)


def choice_folds(n_positions: int, min_fit: int = 5) -> list[tuple[np.ndarray, np.ndarray]]:
    """Fit / held-out folds of ``n_positions`` calibration positions for the choice.

    One fold holding out every second interior position (1, 3, ..., as
    :func:`ptpcore.evaluate.split_positions` does) when at least ``min_fit``
    positions are left to fit; otherwise leave-one-interior-position-out folds.

    Returns
    -------
    list of (fit (Kf,) int64, held (Kh,) int64)
        Indices into the calibration positions.

    Raises
    ------
    ValueError
        Fewer than 3 positions.
    """
    k = int(n_positions)
    if k < 3:
        raise ValueError(f"choosing a model needs at least 3 positions, got {k}")
    allk = np.arange(k)
    held = np.arange(1, k - 1, 2)
    if k - held.size >= min_fit:
        return [(np.setdiff1d(allk, held), held)]
    return [(np.setdiff1d(allk, [i]), np.array([i])) for i in range(1, k - 1)]


class SmoothGlobalFits:
    """The smooth fit's global model per set of positions, fitted once and shared by the smooth
    candidates of every degree (it depends on neither degree nor scale), the scale pre-passes and
    the final fit (:func:`ptpcore.fit.smooth.smooth_global_fit`; 3.5 s of CPU each).
    """

    def __init__(self, samples: SampleStack, rig: Rig, level_bias: bool):
        self._args = (samples, rig)
        self._level_bias = level_bias
        self._fits = {}

    def __call__(self, positions):
        from ptpcore.fit.smooth import smooth_global_fit

        key = tuple(int(k) for k in positions)
        if key not in self._fits:
            self._fits[key] = smooth_global_fit(*self._args, key, self._level_bias)
        return self._fits[key]


def _fit_candidate(samples, rig, model, degree, positions, stage_sigma_mm, level_bias, footprint,
                   smooth_scale_px=None, global_fits=None, progress=None) -> Lut | None:
    smooth = {}
    if model == "smooth":
        smooth = {"smooth_scales_px": None if smooth_scale_px is None else (smooth_scale_px,),
                  "smooth_global_fit": None if global_fits is None else global_fits(positions)}
    try:
        return fit_kind(samples, rig, model, degree, positions=positions, progress=progress,
                        stage_sigma_mm=stage_sigma_mm, level_bias=level_bias, footprint=footprint,
                        uncertainty=False, **smooth)  # judged by its predictions only
    except ValueError:
        return None


def _smooth_scale_on_all(samples, rig, degree, positions, stage_sigma_mm, level_bias, footprint,
                         global_fits) -> float | None:
    """The smoothing scale (px) ``--model smooth`` chooses on all ``positions`` (its own cross-validation;
    None when it cannot be fitted: the candidate then chooses on its fold)."""
    from ptpcore.fit.smooth import fit_smooth_lut

    try:
        _lut, info = fit_smooth_lut(samples, rig, degree, list(positions), stage_sigma_mm=stage_sigma_mm,
                                    level_bias=level_bias, footprint=footprint, uncertainty=False,
                                    global_fit=global_fits(positions))
    except ValueError:
        return None
    return float(info.scale_px)


class _HeldOutJudge:
    """One fold's candidates judged at its held-out positions, one candidate LUT in memory at a time.

    Each candidate is evaluated at every held-out position as soon as it is fitted: the
    pixels it predicts (bits in memory) and its squared difference ``(X - x)^2 + (Y - y)^2``
    per pixel (float64, to a temporary file, :class:`ptpcore.store.SpillStore`), then its
    LUT is dropped. :meth:`errors` sums them over the pixels every kept candidate predicts,
    the same numbers in the same order as evaluating all the LUTs side by side (a big sensor's
    four candidate LUTs would take about 1 GB at 5 MP).

    Parameters
    ----------
    samples : SampleStack
    held : (E,) int
        The held-out positions.
    n_candidates : int
    stage_sigma_mm : float
        With a stage error, each candidate's squared slope ``|dXY/dz|^2`` is kept too
        (:func:`_noise_variance_sum` takes the first kept candidate's).
    """

    def __init__(self, samples: SampleStack, held, n_candidates: int, stage_sigma_mm: float):
        from ptpcore.store import SpillStore

        self.samples, self.held, self.stage_sigma_mm = samples, [int(k) for k in held], stage_sigma_mm
        self.n_valid = np.zeros(n_candidates, dtype=np.int64)
        self.in_range: list = [None] * n_candidates  # (E, ceil(H*W/8)) uint8 packed bits, per candidate
        self.ok = [self._usable(k) for k in self.held]
        fields = {"e2": np.float64, **({"slope2": np.float64} if stage_sigma_mm else {})}
        self.store = SpillStore(n_candidates * len(self.held), samples.shape, fields, {name: np.nan for name in fields})

    def _usable(self, k: int) -> np.ndarray:
        """Position ``k``'s usable samples (the robust fit's outliers left out too), as packed bits of the flat mask."""
        sx, sy = self.samples.absolute(k)
        return np.packbits((np.isfinite(sx) & np.isfinite(sy) & (self.samples.plane("reasons", k) == 0)).ravel())

    def add(self, ci: int, lut: Lut) -> None:
        """Evaluate candidate ``ci``'s ``lut`` at every held-out position (then it may be dropped).

        In bands of image rows (:data:`JUDGE_BAND_PIXELS`): each pixel's prediction depends on
        its own coefficients only, so the numbers are those of evaluating the whole image,
        without its float64 X, Y maps beside the candidate LUT (the 12 MP wizard's peak).
        """
        self.n_valid[ci] = int(lut.valid.sum())
        from ptpcore.parallel import row_tiles

        h, w = self.samples.shape
        bits = []
        for e, k in enumerate(self.held):
            slot, z = ci * len(self.held) + e, float(self.samples.z[k])
            in_range = np.empty((h, w), bool)
            for r0, r1 in row_tiles(h, w, JUDGE_BAND_PIXELS):
                band = lut.row_band(r0, r1)
                ev = band.evaluate(z)
                in_range[r0:r1] = ev.in_range
                self.store.write_rows("e2", slot, r0, self._squared_difference(ev, k, r0, r1))
                if self.stage_sigma_mm:
                    self.store.write_rows("slope2", slot, r0, _squared_slope(band, z))
            for name in self.store.layout:
                self.store.mark_written(name, slot)
            bits.append(np.packbits(in_range.ravel()))
        self.in_range[ci] = np.stack(bits)

    def _squared_difference(self, ev, k: int, r0: int, r1: int) -> np.ndarray:
        """``(X - x)^2 + (Y - y)^2`` of rows ``[r0, r1)`` at position ``k``, in ``ev``'s own maps (float64)."""
        from ptpcore.store import read_block

        w = self.samples.shape[1]
        for diff, axis in ((ev.x, "x"), (ev.y, "y")):
            sample = read_block(getattr(self.samples, axis), r0 * w, r1 * w, [k]).reshape(r1 - r0, w)
            diff -= getattr(self.samples, f"{axis}_ref")[r0:r1] + sample
            np.square(diff, out=diff)
        ev.x += ev.y
        return ev.x

    def drop(self, ci: int) -> None:
        """Leave candidate ``ci`` out of the comparison (too few pixels)."""
        self.in_range[ci] = None

    def _plane(self, name: str, ci: int, e: int) -> np.ndarray:
        n = self.store.pixels
        return self.store.read(name, 0, n, [ci * len(self.held) + e])[0]

    def errors(self, rig: Rig):
        """Squared held-out differences of every kept candidate, over the samples all of them predict.

        Returns
        -------
        sums : (C,) float, mm^2
            Sum over X and Y of (prediction - sample)^2 on the common samples.
        counts : (C,) int
            Samples each candidate predicts (for its coverage).
        n_common : int
            X and Y values in the common set (2 per sample).
        noise_sum : float, mm^2
            Sum of the predicted noise variance over the common set (NaN without a noise model).
        """
        kept = [ci for ci, bits in enumerate(self.in_range) if bits is not None]
        sums = np.zeros(len(self.in_range))
        counts = np.zeros(len(self.in_range), dtype=np.int64)
        n_common, noise_sum = 0, 0.0
        n = self.store.pixels
        for e, k in enumerate(self.held):
            ok = np.unpackbits(self.ok[e], count=n).view(bool)
            common = ok.copy()
            for ci in kept:
                in_range = np.unpackbits(self.in_range[ci][e], count=n).view(bool)
                counts[ci] += int((ok & in_range).sum())
                common &= in_range
            for ci in kept:
                sums[ci] += float(np.sum(self._plane("e2", ci, e)[common]))
            n_common += 2 * int(common.sum())
            slope2 = self._plane("slope2", kept[0], e) if self.stage_sigma_mm and kept else None
            noise_sum += _noise_variance_sum(self.samples, rig, k, common.reshape(self.samples.shape), slope2,
                                             self.stage_sigma_mm, position_sigma_from_noise)
        return sums, counts, n_common, noise_sum


def _squared_slope(lut: Lut, z: float) -> np.ndarray:
    """``|dXY/dz|^2`` of every pixel of ``lut`` at ``z`` (mm^2/mm^2), by a central difference over 0.1 mm."""
    h = 0.05
    hi, lo = lut.evaluate(z + h, extrapolate=True), lut.evaluate(z - h, extrapolate=True)
    return ((hi.x - lo.x) / (2 * h)) ** 2 + ((hi.y - lo.y) / (2 * h)) ** 2


def _noise_variance_sum(samples, rig, k, common, slope2, stage_sigma_mm, sigma_fn) -> float:
    """Sum over X and Y of the predicted noise variance of position ``k``'s samples on ``common`` (mm^2).

    The phase noise of each sample, plus (``stage_sigma_mm``) the stage reading's error, which
    moves the sample along its pixel's ray: ``dX/dz * dz`` (``slope2``: the squared slope of the
    first kept candidate LUT, flat ``(H*W,)``, by a central difference over 0.1 mm).
    """
    if samples.noise is None or samples.modulation is None:
        return float("nan")
    s = sigma_fn(samples, rig, k)[common]
    total = 2.0 * float(np.sum(s * s))
    if stage_sigma_mm and slope2 is not None:
        total += float(np.nansum(slope2[common.ravel()])) * stage_sigma_mm ** 2
    return total


def choose_model(samples: SampleStack, rig: Rig, positions=None, *, candidates=AUTO_CANDIDATES,
                 stage_sigma_mm: float = 0.0, level_bias: bool = True, footprint: bool = True,
                 progress: Progress | None = None, global_fits: SmoothGlobalFits | None = None) -> ModelChoice:
    """Judge every candidate at held-out positions (see the module docstring).

    Parameters
    ----------
    samples : SampleStack
    rig : Rig
    positions : sequence of int, optional
        The calibration positions (default all); folds are taken among them.
    candidates : sequence of (model, degree)
        In order of simplicity.
    stage_sigma_mm, level_bias, footprint
        As for :func:`ptpcore.fit.models.fit_model`.
    progress : callable, optional
    global_fits : SmoothGlobalFits, optional
        Shared with the caller's final fit (:func:`fit_auto`); a new one by default.

    Returns
    -------
    ModelChoice

    Raises
    ------
    ValueError
        Fewer than 3 positions, or no candidate could be fitted and judged.
    """
    pos = np.arange(samples.z.size) if positions is None else np.asarray(positions)
    folds = choice_folds(pos.size)
    cands = list(candidates)
    global_fits = global_fits or SmoothGlobalFits(samples, rig, level_bias)
    scales = {d: _smooth_scale_on_all(samples, rig, d, pos, stage_sigma_mm, level_bias, footprint, global_fits)
              for m, d in cands if m == "smooth"}
    sums = np.zeros(len(cands))
    counts = np.zeros(len(cands), dtype=np.int64)
    fitted = np.ones(len(cands), dtype=bool)
    notes = ["could not be fitted"] * len(cands)
    n_common, noise_sum = 0, 0.0
    steps = len(folds) * len(cands)
    for fi, (fit_i, held_i) in enumerate(folds):
        judge = _HeldOutJudge(samples, pos[held_i], len(cands), stage_sigma_mm)
        for ci, (model, degree) in enumerate(cands):
            if progress:
                progress((fi * len(cands) + ci) / steps, f"choosing the model: fitting {model} {degree}")
            lut = _fit_candidate(samples, rig, model, degree, pos[fit_i], stage_sigma_mm, level_bias, footprint,
                                 scales.get(degree) if model == "smooth" else None, global_fits) \
                if fitted[ci] else None
            fitted[ci] &= lut is not None
            if fitted[ci]:
                judge.add(ci, lut)
            del lut  # one candidate LUT in memory at a time
            release_free_memory()
        n_valid = np.where(fitted, judge.n_valid, 0)
        for ci in np.nonzero(fitted & (n_valid < MIN_COVERAGE * max(n_valid.max(), 1)))[0]:
            judge.drop(ci)  # too few pixels: it would shrink the common set for all
            fitted[ci] = False
            notes[ci] = f"fits only {n_valid[ci] / max(n_valid.max(), 1):.0%} of the pixels on {fit_i.size} positions"
        s, c, n, ns = judge.errors(rig)
        del judge  # its temporary file with it
        sums, counts, n_common, noise_sum = sums + s, counts + c, n_common + n, noise_sum + ns
    choice = _pick(cands, fitted, notes, sums, counts, n_common, noise_sum, [pos[h].tolist() for _, h in folds])
    for c in choice.candidates:
        if c.model == "smooth" and scales.get(c.degree) is not None:
            c.smoothing_scale_px = scales[c.degree]
    return choice


def _pick(cands, fitted, notes, sums, counts, n_common, noise_sum, held) -> ModelChoice:
    """Apply the coverage and tie rules to the accumulated errors."""
    best_count = counts[fitted].max() if fitted.any() else 0
    judged = fitted & (counts >= MIN_COVERAGE * max(best_count, 1))
    noise_var = noise_sum / n_common if n_common else float("nan")
    out = []
    for i, (model, degree) in enumerate(cands):
        cov = float(counts[i] / best_count) if best_count else 0.0
        if not fitted[i]:
            out.append(CandidateError(model, degree, np.nan, np.nan, cov, notes[i]))
        elif not judged[i] or n_common == 0:
            out.append(CandidateError(model, degree, np.nan, np.nan, cov, f"covers {cov:.0%} of the pixels"))
        else:
            mse = sums[i] / n_common
            err = np.sqrt(max(mse - noise_var, 0.0)) if np.isfinite(noise_var) else np.sqrt(mse)
            out.append(CandidateError(model, degree, float(np.sqrt(mse) * 1e3), float(err * 1e3), cov))
    ok = [i for i, c in enumerate(out) if not c.note]
    if not ok:
        raise ValueError("no LUT model could be fitted and judged at held-out positions")
    best = min(ok, key=lambda i: out[i].held_out_rms_um)
    mse_best = sums[best] / n_common
    # Differences of the measured MSE are unbiased for differences of the squared model errors
    # (the noise cancels); the allowance, 5 % of the best model error, needs the noise taken out.
    # An overestimated noise leaves no allowance (the best is taken), never a wrong tie.
    err2_best = max(mse_best - noise_var, 0.0) if np.isfinite(noise_var) else mse_best
    allowance = ((1 + TIE_FRACTION) ** 2 - 1) * err2_best
    chosen = next(i for i in ok if sums[i] / n_common - mse_best <= allowance)
    noise_um = float(np.sqrt(noise_var) * 1e3) if np.isfinite(noise_var) else float("nan")
    return ModelChoice(out, chosen, held, noise_um, int(n_common))


def fit_auto(samples: SampleStack, rig: Rig, positions=None, *, stage_sigma_mm: float = 0.0,
             level_bias: bool = True, footprint: bool = True, progress: Progress | None = None,
             candidates=AUTO_CANDIDATES) -> tuple[Lut, ModelChoice]:
    """Choose the model (:func:`choose_model`) and fit it on all ``positions``.

    Returns
    -------
    lut : Lut
        With ``/model`` attribute ``chosen_by = "held-out positions"`` and
        ``provenance["model_choice"]`` (:meth:`ModelChoice.to_json`).
    choice : ModelChoice
        With too few positions to judge any candidate (fewer than 3, or none
        fitted on the folds), ``poly`` degree 1, its ``rule`` saying why.
    """
    global_fits = SmoothGlobalFits(samples, rig, level_bias)
    try:
        choice = choose_model(samples, rig, positions, candidates=candidates, stage_sigma_mm=stage_sigma_mm,
                              level_bias=level_bias, footprint=footprint, progress=sub_progress(progress, 0.0, 0.7),
                              global_fits=global_fits)
    except ValueError as exc:  # too few positions to hold any out: the simplest model, and why
        choice = ModelChoice([CandidateError("poly", 1, np.nan, np.nan, np.nan, "not judged")], 0, [],
                             np.nan, 0, f"poly degree 1 without a choice: {exc}")
    release_free_memory()  # the candidates' freed heap, before the final fit maps its own arrays
    # A smooth pick reuses the scale its pre-pass chose on these same positions (the command's own
    # cross-validation, not run twice): the LUT is the one ``--model smooth`` writes.
    scale = choice.candidates[choice.chosen].smoothing_scale_px
    smooth = {} if choice.model != "smooth" else {
        "smooth_scales_px": (scale,) if np.isfinite(scale) else None,
        "smooth_global_fit": global_fits(np.arange(samples.z.size) if positions is None else positions)}
    lut = fit_kind(samples, rig, choice.model, choice.degree, positions, sub_progress(progress, 0.7, 1.0),
                   stage_sigma_mm=stage_sigma_mm, level_bias=level_bias, footprint=footprint, **smooth)
    lut.extra_attrs["chosen_by"] = "held-out positions"
    lut.provenance["model_choice"] = choice.to_json()
    return lut, choice
