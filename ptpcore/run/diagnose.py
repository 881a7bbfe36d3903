"""Never silent: what a decode or calibration reports about each position (METHOD.md section 4).

- A position that keeps less than :data:`MIN_VALID_FRACTION` of its pixels is
  reported with its dominant reason; a run that keeps no pixel at all fails.
- A wrong ``phase_origin_rad`` or ``shift_sign`` is recognised from the data:
  the wrapped phases are unwrapped again under other conventions on a sample
  of well-modulated pixels, and a convention that agrees (unwrapping
  consistent, coordinates on the LCD) where the configured one does not is
  named as the setting that fixes it.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ptpcore.decode.phase import REASON_NAMES, DecodedPosition, DecodeOptions
from ptpcore.errors import DatasetError
from ptpcore.rig.rigfile import Rig

__all__ = ["MIN_VALID_FRACTION", "dominant_reason", "position_report", "check_valid_fractions",
           "convention_check", "ConventionFinding"]

MIN_VALID_FRACTION = 0.1
"""A position keeping fewer of its pixels than this is reported."""

CHECK_PIXELS = 4000
"""Well-modulated pixels the convention check unwraps under each candidate convention."""


def dominant_reason(reasons: np.ndarray) -> tuple[str, float]:
    """The reason flagged on most invalid pixels, and the fraction of all pixels it is on."""
    reasons = np.asarray(reasons)
    n = reasons.size
    best, frac = "none", 0.0
    for bit, name in REASON_NAMES.items():
        c = np.count_nonzero(reasons & bit) / max(n, 1)
        if c > frac:
            best, frac = name, c
    return best, frac


def position_report(label: str, reasons: np.ndarray, min_fraction: float = MIN_VALID_FRACTION) -> str | None:
    """One line when ``reasons`` (a position's, or one direction's) keep less than ``min_fraction``."""
    valid = float(np.mean(np.asarray(reasons) == 0)) if np.size(reasons) else 0.0
    if valid >= min_fraction:
        return None
    name, frac = dominant_reason(reasons)
    return (f"{label} keeps {100 * valid:.1f} % of its pixels (less than {100 * min_fraction:g} %);"
            f" dominant reason: {name} ({100 * frac:.1f} % of pixels)")


def check_valid_fractions(samples, positions=None, min_fraction: float = MIN_VALID_FRACTION) -> list[str]:
    """Warn about every position of a sample stack that keeps too few pixels.

    Raises
    ------
    DatasetError
        No pixel is valid at any position (one line, with the dominant reason).
    """
    ks = range(len(samples.z)) if positions is None else positions
    lines = []
    any_valid = False
    for k in ks:
        r = samples.plane("reasons", k)  # a file read of a spilled stack, not its memory map
        any_valid |= bool(np.any(r == 0))
        line = position_report(f"position {k} (z = {samples.z[k]:g} mm)", r, min_fraction)
        if line:
            lines.append(line)
    if not any_valid:
        name, frac = dominant_reason(np.stack([samples.plane("reasons", k) for k in ks]))
        raise DatasetError(f"no pixel is valid at any position; dominant reason: {name}"
                           f" ({100 * frac:.1f} % of pixels)")
    for line in lines:
        warnings.warn(line, stacklevel=2)
    return lines


class ConventionFinding:
    """A convention that fits the data better than the configured one.

    Attributes
    ----------
    direction : str
    settings : list of str
        ``rig.toml`` lines that fix it (``"shift_sign = -1"``, ``"phase_origin_rad = 3.14159"``).
    score_configured, score_best : float
        Fraction of the sampled pixels that decode consistently each way.
    """

    def __init__(self, direction: str, settings: list[str], score_configured: float, score_best: float):
        self.direction = direction
        self.settings = settings
        self.score_configured = score_configured
        self.score_best = score_best

    def message(self, source: str = "rig.toml") -> str:
        fix = " and ".join(f"`{s}`" for s in self.settings)
        table = "[fringes]" if self.direction is None else f"[fringes] (or [fringes.{self.direction}])"
        return (f"{source}: direction {self.direction} decodes consistently on {100 * self.score_configured:.0f} %"
                f" of well-modulated pixels with its phase convention, on {100 * self.score_best:.0f} % with"
                f" {fix} in {table}: set it")


def _format_origin(rad: float) -> str:
    rad = math.remainder(rad, 2 * math.pi)
    if abs(rad + math.pi) < 1e-9:
        rad = math.pi
    return f"{rad:.5f}"


def _score(raw: list[np.ndarray], periods, sign: int, origins: np.ndarray, shift: float, extent: float,
           tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """For each candidate origin: the fraction of pixels whose phases (``raw``: the plain N-step
    phases, per level) unwrap without disagreement onto the LCD under ``(sign, origin)``, and
    the median absolute unwrapping residual (radians) over those pixels."""
    two_pi = 2 * np.pi
    o = np.asarray(origins, np.float64)[:, None]
    phases = [np.mod(sign * r[None, :] - o, two_pi) for r in raw]
    un = phases[0]
    ok = np.ones(un.shape, bool)
    resid = np.zeros(un.shape)
    for j in range(1, len(periods)):
        pred = un * (periods[j - 1] / periods[j])
        un = phases[j] + two_pi * np.rint((pred - phases[j]) / two_pi)
        dev = np.abs(un - pred)
        ok &= dev <= two_pi * tolerance
        resid += dev
    coord = un * periods[-1] / two_pi - shift
    ok &= (coord >= -0.5) & (coord <= extent - 0.5)
    frac = ok.mean(axis=1)
    r = np.sort(np.where(ok, resid, np.inf), axis=1)
    n = ok.sum(axis=1)
    median = np.where(n > 0, r[np.arange(r.shape[0]), np.maximum(n - 1, 0) // 2], np.inf)
    return frac, median


def convention_check(rig: Rig, pos: DecodedPosition, options: DecodeOptions = DecodeOptions(),
                     seed: int = 0) -> list[ConventionFinding]:
    """Findings of a wrong phase convention at one decoded position (periods unwrapping only).

    Every candidate ``(shift_sign, phase_origin_rad)`` (both signs, origins in
    1-degree steps) unwraps a sample of well-modulated pixels; a candidate that
    decodes at least 20 percentage points more of them consistently, and at
    least half of them, is reported.
    """
    f = rig.fringes
    if f.unwrap != "periods":
        return []
    options = options.for_rig(rig)
    findings = []
    min_mod = options.min_modulation * rig.camera.max_level
    rng = np.random.default_rng(seed)
    for d, dec in pos.directions.items():
        periods = [float(t) for t in f.periods(d)]
        if len(periods) < 1:
            continue
        good = np.ones(dec.coord.shape, bool)
        for wp in dec.wrapped:
            good &= (wp.modulation >= min_mod) & ~wp.saturated
        idx = np.flatnonzero(good)
        if idx.size < 20:
            continue
        if idx.size > CHECK_PIXELS:
            idx = rng.choice(idx, CHECK_PIXELS, replace=False)
        s0, o0 = f.sign(d), f.origin(d)
        # Back to the plain N-step phase (before the configured convention).
        raw = [s0 * (wp.phase.ravel()[idx].astype(np.float64) + o0) for wp in dec.wrapped]
        extent = float(rig.lcd.width if d == "x" else rig.lcd.height)
        shift = f.carrier(d) * pos.z_mm
        tol = options.unwrap_tolerance
        conf_score, conf_resid = _score(raw, periods, s0, np.array([o0]), shift, extent, tol)
        configured = float(conf_score[0])
        grid = np.radians(np.arange(360.0))
        cands = []
        for sign in (s0, -s0):
            scores, resid = _score(raw, periods, sign, grid, shift, extent, tol)
            top = scores.max()
            # Of the origins that decode as many pixels (a whole arc does, within the
            # tolerance), the one with the smallest unwrapping residuals; snapped to 15
            # degrees when close.
            at_o0, r_o0 = _score(raw, periods, sign, np.array([o0]), shift, extent, tol)
            if at_o0[0] >= top - 0.01:
                # The configured origin decodes as many: keep it (a fix of the sign alone is the
                # simplest; over a wide arc of equal scores the smallest residual is noise's choice).
                cands.append((float(top), sign, o0, float(r_o0[0]), True))
                continue
            near = np.flatnonzero(scores >= top - 0.01)
            o = float(grid[near[np.argmin(resid[near])]])
            fine = o + np.radians(np.linspace(-1.0, 1.0, 41))
            fs, fr = _score(raw, periods, sign, fine, shift, extent, tol)
            i = int(np.argmin(np.where(fs >= top - 0.01, fr, np.inf)))
            o, r = float(fine[i]), float(fr[i])
            snap = math.radians(15.0) * round(math.degrees(o) / 15.0)
            round_ = abs(math.remainder(o - snap, 2 * math.pi)) < math.radians(3.0)
            cands.append((float(top), sign, snap if round_ else o, r, round_))
        # A clearly higher score wins. Between nearly equal ones (a mirrored map can decode
        # as consistently as the true one, e.g. when the periods are the screen over
        # n - 0.1 cycles), the round origin (real generators use 0, pi, 2 pi / 3, ...),
        # then the smaller unwrapping residuals.
        top = max(c[0] for c in cands)
        pick = min((c for c in cands if c[0] >= top - 0.01), key=lambda c: (not c[4], c[3]))
        best = (pick[0], pick[1], pick[2], pick[3])
        sc, sign, o, _r = best
        if sc >= 0.5 and sc >= configured + 0.2:
            settings = []
            if sign != s0:
                settings.append(f"shift_sign = {sign}")
            if abs(math.remainder(o - o0, 2 * math.pi)) > math.radians(0.5):
                settings.append(f"phase_origin_rad = {_format_origin(o)}")
            findings.append(ConventionFinding(d, settings, configured, sc))
    return findings
