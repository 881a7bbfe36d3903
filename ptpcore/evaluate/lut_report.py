"""What a LUT says about itself, read once: the typed report ``ptp calibrate``, ``resume`` and ``inspect``
print and the wizard's Calibrate page shows.

:meth:`LutReport.of` reads a :class:`~ptpcore.io.lutfile.Lut` whole: its model, validity and positions
per pixel, the statistics of its quality maps (fit residual, leave-one-out, predicted sigma with its noise
and model parts), and every ``/provenance`` record (docs/formats.md): ``corrections``, the stage pose,
``model_choice``, ``robust``, ``drift``, ``fit_settings`` and ``decode_options``, and the scanner's
``/height``. This module is the one place their JSON is parsed; a record that cannot be read becomes a
note of the report (:attr:`LutReport.notes`), never an exception.

:meth:`LutReport.lines` is the command line's text, every line at most ``width`` columns (a longer one
continues on indented lines); the wizard formats the fields as HTML itself.
"""

from __future__ import annotations

import json
import re
import textwrap
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from ptpcore.decode.options import DECODE_OPTIONS_KEY, decode_options_from_json
from ptpcore.decode.phase import DecodeOptions
from ptpcore.fit.choice import ModelChoice
from ptpcore.fit.glass import describe_corrections
from ptpcore.fit.models import describe_lut
from ptpcore.fit.settings import FIT_SETTINGS_KEY, FitSettings
from ptpcore.fit.sigma import sigma_parts
from ptpcore.fit.stage_pose import describe_stage_pose
from ptpcore.rig.naming import lut_stage_z, position_label

__all__ = ["LutReport", "Spread", "AxisSigma", "Suspect", "RobustFit", "DriftRepeat", "DriftRecord",
           "HeightSummary", "WIDTH", "fit_width"]

WIDTH = 100
"""The terminal width :meth:`LutReport.lines` fits by default (columns)."""

LABEL = 20
"""Width of the label column of the printed lines (``"  valid pixels        2409 (78.4 %)"``)."""

NOT_RECORDED = "not recorded (the LUT was written before ptp recorded it in /provenance {key})"
"""What :meth:`LutReport.lines` says of a settings record the LUT does not hold."""


# --------------------------------------------------------------------------- parts

@dataclass(frozen=True)
class Spread:
    """A per-pixel map over the valid pixels: median and 95th percentile, µm."""

    median_um: float
    p95_um: float

    @classmethod
    def of(cls, values_mm, where) -> "Spread | None":
        """The spread of ``values_mm[where]`` (finite values only), None for none or no map."""
        if values_mm is None:
            return None
        a = values_mm[where]
        a = a[np.isfinite(a)]
        if not a.size:
            return None
        return cls(1e3 * float(np.median(a)), 1e3 * float(np.percentile(a, 95)))

    def text(self) -> str:
        return f"median {self.median_um:.2f} µm, 95th percentile {self.p95_um:.2f} µm"


@dataclass(frozen=True)
class AxisSigma:
    """The predicted 1-sigma along one axis; ``noise`` and ``model`` when the fit estimated the model's part."""

    axis: str
    total: Spread
    noise: Spread | None = None
    model: Spread | None = None


@dataclass(frozen=True)
class Suspect:
    """A position the robust fit named suspect: ``fraction`` of its samples were left out."""

    position: int
    z_mm: float | None
    fraction: float

    @property
    def label(self) -> str:
        return position_label(self.position, self.z_mm)


@dataclass(frozen=True)
class RobustFit:
    """What the robust fit left out (``/provenance`` ``robust``, ``/quality/n_rejected``)."""

    n_rejected: int
    n_pixels: int
    k_sigma: float
    noise_scale: float
    suspects: tuple[Suspect, ...] = ()

    @classmethod
    def from_json(cls, text: str, z_mm=(), n_pixels: int = 0) -> "RobustFit":
        """The record's JSON; ``z_mm`` the stage readings that name the suspects' heights.

        Raises ValueError when it cannot be read.
        """
        d = _object(text)
        fractions = d.get("rejected_fraction", {}) or {}
        suspects = tuple(Suspect(int(k), float(z_mm[k]) if 0 <= int(k) < len(z_mm) else None,
                                 float(fractions.get(str(k), 1.0)))
                         for k in d.get("suspect_positions", []))
        return cls(int(d.get("n_rejected", 0)), int(n_pixels), float(d.get("k_sigma", 0)),
                   float(d.get("noise_scale", 1)), suspects)


@dataclass(frozen=True)
class DriftRepeat:
    """One repeat position against its sweep position; ``rms_um`` None when it was not judged."""

    z_mm: float
    position: int
    rms_um: float | None
    predicted_rms_um: float | None
    mean_um: tuple[float, float] | None

    def text(self) -> str:
        """``drift at z = 0 mm (position 0 again): RMS ... µm (noise predicts ... µm), mean (...) µm``."""
        if self.position < 0:
            return f"drift at z = {self.z_mm:g} mm: no sweep position at that reading, not judged"
        head = f"drift at z = {self.z_mm:g} mm ({position_label(self.position)} again)"
        if self.rms_um is None:
            return head + ": no pixel valid in both, not judged"
        pred = f" (noise predicts {self.predicted_rms_um:.3f} µm)" if self.predicted_rms_um is not None else ""
        m = self.mean_um or (float("nan"), float("nan"))
        return head + f": RMS {self.rms_um:.3f} µm{pred}, mean ({m[0]:+.3f}, {m[1]:+.3f}) µm"


@dataclass(frozen=True)
class DriftRecord:
    """The drift of the sweep's repeat positions (``/provenance`` ``drift``), warnings first."""

    warnings: tuple[str, ...]
    repeats: tuple[DriftRepeat, ...]

    @classmethod
    def from_json(cls, text: str) -> "DriftRecord":
        """The record's JSON (:meth:`ptpcore.fit.drift.Drift.to_json`); ValueError when it cannot be read."""
        d = _object(text)

        def num(v):
            return None if v is None else float(v)

        repeats = []
        for r in d.get("repeats", []):
            mean = r.get("mean_um")
            repeats.append(DriftRepeat(float(r["z_mm"]), int(r.get("position", -1)), num(r.get("rms_um")),
                                       num(r.get("predicted_rms_um")),
                                       (float("nan") if mean[0] is None else float(mean[0]),
                                        float("nan") if mean[1] is None else float(mean[1])) if mean else None))
        return cls(tuple(str(w) for w in d.get("warnings", [])), tuple(repeats))

    def lines(self) -> list[str]:
        return [f"DRIFT WARNING: {w}" for w in self.warnings] + [r.text() for r in self.repeats]


@dataclass(frozen=True)
class HeightSummary:
    """The scanner's height map ``u_p -> Z`` (``/height``)."""

    degree: int
    chosen_by: str
    direction: str
    design_size: tuple[Any, Any]
    periods_px: tuple[float, ...]
    n_valid: int
    n_pixels: int
    positions: tuple[int, int, int] | None
    rms_z: Spread | None
    loo_z: Spread | None
    sigma_z: Spread | None
    sigma_model_z: Spread | None
    degree_choice_um: tuple[tuple[str, float], ...]
    n_rejected: int

    @classmethod
    def of(cls, hm) -> "HeightSummary":
        v = hm.valid
        d = hm.design or {}
        choice = (hm.provenance or {}).get("degree_choice", {}) or {}
        held = choice.get("held_out_rms_mm", {}) if isinstance(choice, dict) else {}
        return cls(int(hm.degree), str(hm.chosen_by or ""), str(hm.direction),
                   (d.get("width"), d.get("height")), tuple(float(t) for t in d.get("periods_px", [])),
                   int(v.sum()), int(v.size), _counts(hm.n_positions, v),
                   Spread.of(hm.rms_z, v), Spread.of(hm.loo_z, v), Spread.of(hm.sigma_z, v),
                   Spread.of(hm.sigma_model_z, v),
                   tuple((str(k), 1e3 * float(val)) for k, val in (held or {}).items()),
                   int(hm.n_rejected.sum()) if hm.n_rejected is not None else 0)

    @property
    def fraction(self) -> float:
        return self.n_valid / self.n_pixels if self.n_pixels else 0.0


# --------------------------------------------------------------------------- the report

@dataclass(frozen=True)
class LutReport:
    """Everything ``ptp inspect`` says of a LUT (module docstring); made by :meth:`of`.

    Attributes
    ----------
    name : str
        What the first line names (the file).
    model : str
        :func:`ptpcore.fit.models.describe_lut` (``"smooth, poly degree 2, ..., chosen by ..."``).
    width, height : int
        Pixels.
    z_min, z_max : float
        The calibrated range (mm).
    n_valid, n_pixels : int
    positions : (min, max, median) of the positions per valid pixel, or None
    rms, loo : dict axis -> Spread
        Fit residual RMS and leave-one-position-out RMS.
    sigma : tuple of AxisSigma
    corrections : tuple of str
        What was removed from the samples before fitting, one sentence each.
    stage_pose : tuple of str or None
        The refined stage pose, one line per position (``--refine-stage``), None without.
    choice : ModelChoice or None
        The table behind an ``auto`` LUT.
    robust : RobustFit or None
    drift : DriftRecord or None
    height : HeightSummary or None
    fit_settings : FitSettings or None
        The settings the LUT was fitted with (None: not recorded, or unreadable: see ``notes``).
    decode_options : DecodeOptions or None
    notes : tuple of str
        Records that could not be read, each with why.
    """

    name: str
    model: str
    width: int
    height: int
    z_min: float
    z_max: float
    n_valid: int
    n_pixels: int
    positions: tuple[int, int, int] | None = None
    rms: dict = None
    loo: dict = None
    sigma: tuple[AxisSigma, ...] = ()
    corrections: tuple[str, ...] = ()
    stage_pose: tuple[str, ...] | None = None
    choice: ModelChoice | None = None
    robust: RobustFit | None = None
    drift: DriftRecord | None = None
    height_map: HeightSummary | None = None
    fit_settings: FitSettings | None = None
    decode_options: DecodeOptions | None = None
    notes: tuple[str, ...] = ()

    @property
    def fraction(self) -> float:
        """Valid pixels over all."""
        return self.n_valid / self.n_pixels if self.n_pixels else 0.0

    @classmethod
    def of(cls, lut, name: str = "LUT") -> "LutReport":
        """Read ``lut`` (a :class:`~ptpcore.io.lutfile.Lut`) whole; ``name`` heads the printed lines."""
        prov = dict(lut.provenance or {})
        notes: list[str] = []
        v = lut.valid
        h, w = lut.shape
        rms, loo, sigma = {}, {}, []
        if v.any():
            for a in "xy":
                for out, arr in ((rms, getattr(lut, f"rms_{a}")), (loo, getattr(lut, f"loo_{a}"))):
                    s = Spread.of(arr, v)
                    if s is not None:
                        out[a] = s
                total, noise, model = sigma_parts(lut, a)
                t = Spread.of(total, v)
                if t is not None:
                    sigma.append(AxisSigma(a, t, Spread.of(noise, v), Spread.of(model, v)))
        z = lut_stage_z(lut)
        corrections = _read(prov, "corrections", _corrections, notes, ())
        choice = _read(prov, "model_choice", ModelChoice.from_json, notes)
        n_pix = int((lut.n_rejected > 0).sum()) if lut.n_rejected is not None else 0
        robust = _read(prov, "robust", lambda t: RobustFit.from_json(t, z, n_pix), notes)
        drift = _read(prov, "drift", DriftRecord.from_json, notes)
        settings = _read(prov, FIT_SETTINGS_KEY, lambda t: FitSettings.from_json(t, f"/provenance {FIT_SETTINGS_KEY}"),
                         notes)
        options = _read(prov, DECODE_OPTIONS_KEY,
                        lambda t: decode_options_from_json(t, f"/provenance {DECODE_OPTIONS_KEY}"), notes)
        return cls(str(name), describe_lut(lut), int(w), int(h), float(lut.z_min), float(lut.z_max), int(v.sum()),
                   int(v.size), _counts(lut.n_positions, v), rms, loo, tuple(sigma), corrections,
                   _stage_pose(lut, z), choice, robust, drift,
                   HeightSummary.of(lut.height) if getattr(lut, "height", None) is not None else None,
                   settings, options, tuple(notes))

    # ---- text ---------------------------------------------------------------------------
    def lines(self, width: int = WIDTH) -> list[str]:
        """The report as ``ptp inspect`` prints it, every line at most ``width`` columns (longer ones continue
        on lines indented under their text; a single word longer than that, a long path, stays whole)."""
        rows: list[tuple[str, int]] = [
            (f"{self.name}: ptp-lut/1, {self.width}x{self.height} px, z {self.z_min:g} .. {self.z_max:g} mm", 2),
            _row("model", self.model),
            _row("valid pixels", f"{self.n_valid} ({100 * self.fraction:.1f} %)")]
        if self.positions is not None:
            lo, hi, med = self.positions
            rows.append(_row("positions per pixel", f"{lo} .. {hi} (median {med})"))
        for label, stats in (("fit residual RMS", self.rms), ("leave-one-out RMS", self.loo)):
            rows += [_row(f"{label} {a.upper()}", s.text()) for a, s in (stats or {}).items()]
        noise_words = "(phase noise; stage pose and glass tolerances when given)"
        for s in self.sigma:
            a = s.axis.upper()
            if s.model is None:
                rows.append(_row(f"predicted sigma {a}", f"{s.total.text()} {noise_words}"))
                continue
            rows.append(_row(f"predicted sigma {a}", f"{s.total.text()} (noise and model in quadrature)"))
            if s.noise is not None:
                rows.append(_row(f"  noise part {a}", f"{s.noise.text()} {noise_words}"))
            rows.append(_row(f"  model part {a}", f"{s.model.text()} (the model's own error, estimated from"
                                                   " held-out positions: /provenance model_error)"))
        rows += [_row("correction", c) for c in self.corrections]
        if self.stage_pose is not None:
            rows.append(("  stage pose refined  per position (µm, µrad; up to a common offset, scale and linear"
                         " trend):", 4))
            rows += [(f"    {line}", 4 + line.index(": ") + 2 if ": " in line else 6) for line in self.stage_pose]
        rows += self._choice_rows()
        if self.robust is not None:
            r = self.robust
            rows += [_row("SUSPECT", f"{s.label}: {100 * s.fraction:.0f} % of its samples far from the curve of"
                                     " the others (wrong images? a stage glitch?); left out everywhere")
                     for s in r.suspects]
            rows.append(_row("robust fit", f"{r.n_rejected} samples left out at {r.n_pixels} pixels (beyond"
                                           f" {r.k_sigma:g} x {r.noise_scale:.2f} predicted sigma)"))
        if self.drift is not None:
            rows += [(f"  {line}", 4) for line in self.drift.lines()]
        rows += self._height_rows()
        rows += self._settings_rows()
        rows += [_row("note", n) for n in self.notes]
        return [out for text, hang in rows for out in fit_width(text, width, hang)]

    def text(self, width: int = WIDTH) -> str:
        """:meth:`lines` joined."""
        return "\n".join(self.lines(width))

    def choice_lines(self, width: int = WIDTH) -> list[str]:
        """The model-choice table of an ``auto`` LUT as :meth:`lines` prints it (none for a fixed model)."""
        return [out for text, hang in self._choice_rows() for out in fit_width(text, width, hang)]

    def _choice_rows(self) -> list[tuple[str, int]]:
        c = self.choice
        if c is None:
            return []
        rows = [(f"  model chosen by its error at held-out {_folds(c.held_out)} ({c.rule}):", 4)]
        rows += [(f"    {row}", 6) for row in c.table()]
        if np.isfinite(c.noise_rms_um):
            rows.append((f"    (predicted noise of the held-out samples {c.noise_rms_um:.3f} µm RMS; model error"
                         " = held-out RMS with it taken out)", 5))
        return rows

    def _height_rows(self) -> list[tuple[str, int]]:
        hm = self.height_map
        if hm is None:
            return []
        rows = [_row("height map", f"rational, numerator degree {hm.degree} ({hm.chosen_by}), u_p from projector"
                                   f" direction {hm.direction}, {hm.design_size[0]}x{hm.design_size[1]} px, periods"
                                   f" {', '.join(f'{t:g}' for t in hm.periods_px)} px"),
                _row("  valid pixels", f"{hm.n_valid} ({100 * hm.fraction:.1f} %)")]
        if hm.positions is None:
            return rows
        lo, hi, med = hm.positions
        rows.append(_row("  heights per pixel", f"{lo} .. {hi} (median {med})"))
        for label, s in (("fit residual RMS Z", hm.rms_z), ("leave-one-out RMS Z", hm.loo_z),
                         ("predicted sigma Z", hm.sigma_z), ("  model part Z", hm.sigma_model_z)):
            if s is not None:
                rows.append(_row("  " + label, s.text(), LABEL + 2))
        if hm.degree_choice_um:
            rows.append(_row("  degree choice", "held-out RMS " + ", ".join(f"D={k}: {val:.2f} µm"
                                                                          for k, val in hm.degree_choice_um)))
        if hm.n_rejected:
            rows.append(_row("  robust fit", f"{hm.n_rejected} samples left out"))
        return rows

    def _settings_rows(self) -> list[tuple[str, int]]:
        rows = []
        for label, key, record in (("fit settings", FIT_SETTINGS_KEY, self.fit_settings),
                                   ("decode options", DECODE_OPTIONS_KEY, self.decode_options)):
            if record is not None:
                rows.append(_row(label, ", ".join(f"{f.name} {_value(getattr(record, f.name))}"
                                                  for f in fields(record))))
            elif not any(n.startswith(f"/provenance {key}") for n in self.notes):
                rows.append(_row(label, NOT_RECORDED.format(key=key)))
        return rows


# --------------------------------------------------------------------------- helpers

def fit_width(text: str, width: int = WIDTH, hang: int = 4) -> list[str]:
    """``text`` cut at spaces into lines of at most ``width`` columns; each continuation indented ``hang``
    columns. The text's own indent and inner spacing stay; a word longer than the width stays whole."""
    if len(text) <= width:
        return [text]
    glued = _KEEP.sub(lambda m: m.group(0).replace(" ", _GLUE), text)  # "12.3 µm", "z = 8", "(3, 39)" stay whole
    lines = textwrap.wrap(glued, width, subsequent_indent=" " * hang, break_long_words=False,
                          break_on_hyphens=False)
    return [line.replace(_GLUE, " ") for line in lines] or [text]


_GLUE = "\x00"
"""Holds a number and its unit together while :func:`fit_width` cuts (textwrap cuts at whitespace only)."""
_KEEP = re.compile(r"\w = [-+]?[\d.]+(?: (?:µm|mm|px|µrad|%)(?!\w))?|\d (?:µm|mm|px|µrad|%)(?!\w)|\(\d+, \d+\)|[a-z]+ [-+]\S+±")
"""What :func:`fit_width` never cuts: a number and its unit, ``z = 8``, a pixel's ``(row, col)``, a stage pose
estimate (``dx +1.20±0.30``)."""


def _folds(held_out) -> str:
    """``positions 1, 3, 5`` (one fold), ``positions 1, 2, 3 one at a time`` (single-position folds), else
    the folds separated by ``;`` (positions counted from 0, as everywhere)."""
    folds = [list(f) for f in held_out]
    if len(folds) > 1 and all(len(f) == 1 for f in folds):
        return "positions " + ", ".join(str(f[0]) for f in folds) + " one at a time"
    return "positions " + "; ".join(", ".join(str(k) for k in f) for f in folds)


def _row(label: str, text: str, width: int = LABEL) -> tuple[str, int]:
    """A labelled line, ``"  label<padded to width>text"``, and its continuation indent (under the text)."""
    return f"  {label:<{width}}{text}", 2 + width


def _counts(n, where) -> tuple[int, int, int] | None:
    """(min, max, median) of an integer map over ``where``; None for no pixel."""
    if not where.any():
        return None
    a = n[where]
    return int(a.min()), int(a.max()), int(np.median(a))


def _object(text: str) -> dict:
    """A JSON object from ``text``; ValueError for anything else."""
    d = json.loads(text)
    if not isinstance(d, dict):
        raise ValueError(f"expected a JSON object, got {type(d).__name__}")
    return d


def _corrections(text: str) -> tuple[str, ...]:
    """The ``corrections`` record in words; a raw stage-refinement record is left to the stage pose lines."""
    return tuple(line for line in describe_corrections(_object(text)) if not line.startswith("stage_refinement"))


def _read(prov: dict, key: str, parse, notes: list, missing=None):
    """``parse(prov[key])``, ``missing`` without the record; an unreadable one is noted and read as ``missing``."""
    text = prov.get(key)
    if not text:
        return missing
    try:
        return parse(text)
    except (ValueError, KeyError, TypeError, IndexError, StopIteration, AttributeError) as exc:
        why = str(exc).removeprefix(f"/provenance {key}: ") or type(exc).__name__
        notes.append(f"/provenance {key} unreadable ({why}); left out")
        return missing


def _stage_pose(lut, z) -> tuple[str, ...] | None:
    """The refined stage pose, one line per position (by index when the rig's readings do not match)."""
    if lut.stage_pose is None:
        return None
    if len(z) != len(lut.stage_pose):
        z = np.arange(len(lut.stage_pose), dtype=float)
    sig = lut.stage_pose_sigma if lut.stage_pose_sigma is not None else np.full_like(lut.stage_pose, np.nan)
    return tuple(describe_stage_pose(lut.stage_pose, sig, z))


def _value(v) -> str:
    if isinstance(v, bool):
        return "on" if v else "off"
    if v is None:
        return "none"
    return f"{v:g}" if isinstance(v, float) else str(v)
