"""Never silent: what a decode or calibration reports about each position (docs/method.md section 4).

- A position that keeps less than :data:`MIN_VALID_FRACTION` of its pixels is
  reported with its dominant reason; a run that keeps no pixel at all fails.
- A wrong ``phase_origin_rad`` or ``shift_sign`` is recognised from the data:
  the wrapped phases are unwrapped again under other conventions on a sample
  of well-modulated pixels. The conventions the design cannot tell apart
  (docs/method.md section 4, :func:`ptpcore.decode.patterns.equivalent_conventions`)
  are all scored; those that agree as well (unwrapping consistent, residuals as
  small, coordinates on the LCD) form a set, never narrowed to one by taste:
  one member is the fix, several are listed with why the data cannot tell.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ptpcore.decode.patterns import blind_origin_shifts, equivalent_conventions
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


def check_valid_fractions(samples, positions=None, min_fraction: float = MIN_VALID_FRACTION,
                          warn: bool = True) -> list[str]:
    """Warn about every position of a sample stack that keeps too few pixels (``warn``: as warnings too).

    Returns
    -------
    list of str
        One line per position that keeps too few.

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
    if warn:
        for line in lines:
            warnings.warn(line, stacklevel=2)
    return lines


class ConventionFinding:
    """What the data say of the configured phase convention of one direction.

    Attributes
    ----------
    direction : str
    settings : list of str
        ``rig.toml`` lines of the first candidate (``"shift_sign = -1"``, ``"phase_origin_rad = 3.14159"``).
    score_configured, score_best : float
        Fraction of the sampled pixels that decode consistently each way.
    candidates : list of list of str
        The settings of every convention that decodes as consistently as the best (one: the fix).
    conventions : list of (int, float)
        Those conventions as ``(shift_sign, phase_origin_rad)``.
    fatal : bool
        True when the configured convention decodes worse than the candidates (an error);
        False when it is one of several the data cannot tell apart (a warning).
    why : str
        Why the data cannot tell the candidates apart and which design would (several candidates).
    residuals : (float, float) or None
        Median unwrapping residual (radians, summed over the levels) of the configured
        convention and of the candidates.
    """

    def __init__(self, direction: str, settings: list[str], score_configured: float, score_best: float,
                 candidates: list[list[str]] | None = None, conventions: list | None = None,
                 fatal: bool = True, why: str = "", residuals: tuple[float, float] | None = None):
        self.direction = direction
        self.settings = settings
        self.score_configured = score_configured
        self.score_best = score_best
        self.candidates = candidates if candidates is not None else [settings]
        self.conventions = conventions or []
        self.fatal = fatal
        self.why = why
        self.residuals = residuals

    def message(self, source: str = "rig.toml") -> str:
        table = "[fringes]" if self.direction is None else f"[fringes] (or [fringes.{self.direction}])"
        res = ("", "")
        if self.residuals is not None and self.score_best - self.score_configured < 0.2:
            # As many pixels either way: the residuals tell (an origin wrong within the tolerance).
            res = tuple(f" (median unwrapping residual {r:.2f} rad)" for r in self.residuals)
        if len(self.candidates) == 1 and self.fatal:
            fix = " and ".join(f"`{s}`" for s in self.settings)
            return (f"{source}: direction {self.direction} decodes consistently on {100 * self.score_configured:.0f} %"
                    f" of well-modulated pixels with its phase convention{res[0]}, on {100 * self.score_best:.0f} %"
                    f" with {fix}{res[1]} in {table}: set it")
        listed = "; ".join(f"({i + 1}) " + (" and ".join(f"`{s}`" for s in c) if c else "the configured one")
                           for i, c in enumerate(self.candidates))
        head = (f"{source}: direction {self.direction} decodes consistently on {100 * self.score_configured:.0f} %"
                f" of well-modulated pixels with its phase convention{res[0]}; {len(self.candidates)} conventions"
                f" decode as consistently ({100 * self.score_best:.0f} %{res[1]}): {listed} in {table}")
        if not self.fatal:
            head = (f"{source}: direction {self.direction}: {len(self.candidates)} phase conventions decode"
                    f" equally consistently ({100 * self.score_best:.0f} % of well-modulated pixels): {listed}")
        return (f"{head}. The data cannot tell them apart ({self.why}); set the one of the pattern generator,"
                " or capture with a design that tells them apart")


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


RESIDUAL_SLACK = (1.5, 0.05)
"""Two conventions are as consistent when their median unwrapping residuals (radians, summed over
the levels) agree within ``1.5 x + 0.05``: noise gives both the same; an origin wrong by ``e``
inside the unwrapping tolerance adds ``(r_j - 1) e`` at every level."""


def _as_good(score: float, resid: float, top: float, best_resid: float) -> bool:
    """A convention decodes as consistently as the best: as many pixels, residuals as small."""
    return score >= top - 0.01 and resid <= RESIDUAL_SLACK[0] * best_resid + RESIDUAL_SLACK[1]


def _best_origin(raw, periods, sign, shift, extent, tol, o0):
    """The origin that decodes most pixels under ``sign``, with the smallest residuals.

    Of an arc of equal scores (the tolerance admits one), the origin of the smallest
    median unwrapping residual, refined to 0.05 degree; the configured origin ``o0`` when
    it is as good (:func:`_as_good`); else a multiple of 15 degrees (real generators use
    0, pi, 2 pi / 3 ...) when within 3 degrees and as good.
    """
    grid = np.radians(np.arange(360.0))
    scores, resid = _score(raw, periods, sign, grid, shift, extent, tol)
    top = float(scores.max())
    near = np.flatnonzero(scores >= top - 0.01)
    o = float(grid[near[np.argmin(resid[near])]])
    fine = o + np.radians(np.linspace(-1.0, 1.0, 41))
    fs, fr = _score(raw, periods, sign, fine, shift, extent, tol)
    i = int(np.argmin(np.where(fs >= top - 0.01, fr, np.inf)))
    o, r = float(fine[i]), float(fr[i])
    snap = math.radians(15.0) * round(math.degrees(o) / 15.0)
    for alt in (o0, snap):
        if alt == snap and abs(math.remainder(o - snap, 2 * math.pi)) >= math.radians(3.0):
            continue
        sa, ra = _score(raw, periods, sign, np.array([alt]), shift, extent, tol)
        if _as_good(float(sa[0]), float(ra[0]), top, r):
            return float(alt), top
    return o, top


def _settings(sign: int, origin: float, s0: int, o0: float) -> list[str]:
    """The ``rig.toml`` lines that turn ``(s0, o0)`` into ``(sign, origin)``."""
    out = []
    if sign != s0:
        out.append(f"shift_sign = {sign}")
    if abs(math.remainder(origin - o0, 2 * math.pi)) > math.radians(0.5):
        out.append(f"phase_origin_rad = {_format_origin(origin)}")
    return out


def _why(periods, kept: list[tuple[int, float]]) -> str:
    """Why the members of a convention set decode alike, and the design change that tells them apart."""
    ratios = ", ".join(f"{a / b:.4g}" for a, b in zip(periods, periods[1:]))
    parts = []
    if any(sum(1 for s, _o in kept if s == sign) > 1 for sign in (1, -1)):
        nonzero = sorted({round(math.degrees(e) % 360.0, 4) % 360.0 for e in blind_origin_shifts(periods)} - {0.0})
        hidden = f" by {', '.join(f'{x:g}' for x in nonzero)} degrees" if nonzero else ""
        parts.append(f"an origin wrong{hidden} unwraps as consistently (period ratios {ratios}; docs/method.md section 4):"
                     " a level whose period ratio to the coarser one is 2 reveals every wrong origin")
    if len({s for s, _o in kept}) > 1:
        parts.append("the other shift sign (with another origin) mirrors the map without an unwrapping disagreement"
                     " and keeps this view on the LCD: a camera that sees more of the LCD (up to its edges) tells"
                     " a mirrored map")
    return "; ".join(parts)


def _same(a: tuple[int, float], b: tuple[int, float]) -> bool:
    return a[0] == b[0] and abs(math.remainder(a[1] - b[1], 2 * math.pi)) < math.radians(0.5)


def _direction_finding(d: str, raw, periods, s0: int, o0: float, shift: float, extent: float,
                       tol: float) -> ConventionFinding | None:
    """The finding of one direction from its sampled plain N-step phases ``raw`` (per level)."""
    # The design's equivalence class of each sign's best origin (docs/method.md section 4), each
    # member then scored on the data: what stays as consistent on the LCD is the set.
    members: list[tuple[int, float]] = [(s0, o0)]
    for sign in (s0, -s0):
        o, _sc = _best_origin(raw, periods, sign, shift, extent, tol, o0)
        for m in equivalent_conventions(periods, sign, o):
            if not any(_same(m, x) for x in members):
                members.append(m)
    scored = [_score(raw, periods, s, np.array([o]), shift, extent, tol) for s, o in members]
    scores = [float(sc[0]) for sc, _r in scored]
    resids = [float(r[0]) for _sc, r in scored]
    top = max(scores)
    best_resid = min(r for sc, r in zip(scores, resids) if sc >= top - 0.01)
    kept = [m for m, sc, r in zip(members, scores, resids) if _as_good(sc, r, top, best_resid)]
    # Listed: the configured origin first, then round ones (real generators use 0, pi, 2 pi / 3 ...).
    kept.sort(key=lambda m: (abs(math.remainder(m[1] - o0, 2 * math.pi)) > math.radians(0.5),
                             abs(math.remainder(m[1], math.radians(15.0))) > math.radians(0.01)))
    if _as_good(scores[0], resids[0], top, best_resid):  # members[0] is the configured convention
        if len(kept) == 1:
            return None
        fatal = False
    elif top >= 0.5:
        fatal = True
    else:
        return None
    cands = [_settings(s, o, s0, o0) for s, o in kept]
    return ConventionFinding(d, cands[0], scores[0], top, cands, kept, fatal,
                             _why(periods, kept) if len(kept) > 1 else "", (resids[0], best_resid))


def convention_check(rig: Rig, pos: DecodedPosition, options: DecodeOptions = DecodeOptions(),
                     seed: int = 0) -> list[ConventionFinding]:
    """Findings of a wrong or undecidable phase convention at one decoded position
    (unwrapping by periods with two or more levels).

    Each sign's best origin (1-degree scan, refined) and every convention the design
    makes as consistent (:func:`ptpcore.decode.patterns.equivalent_conventions`) unwrap a
    sample of well-modulated pixels; those as consistent as the best (within one
    percentage point of its pixels decoded onto the LCD, residuals as small:
    :data:`RESIDUAL_SLACK`) form the set. When the configured convention is not in it
    (and the set decodes at least half the pixels), a fatal finding lists the set
    whole (one member: the fix); a set of several that includes the configured
    convention is a warning.
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
        if len(periods) < 2:
            continue  # no unwrapping: only the LCD's edges would tell (the design check says so)
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
        finding = _direction_finding(d, raw, periods, s0, o0, f.carrier(d) * pos.z_mm, extent,
                                     options.unwrap_tolerance)
        if finding is not None:
            findings.append(finding)
    return findings
