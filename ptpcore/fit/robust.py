"""Robust per-pixel fits: samples far outside their pixel's curve are left out, and counted.

A sample hit by dust, a reflection or a stage glitch at one position lies far from
the curve its pixel's other samples follow. Every pixel's samples are screened
before any model is fitted (so the screening serves every model, ``auto`` included):

1. A weighted polynomial of degree :data:`SCREEN_DEGREE` (lower with few positions)
   is fitted to each pixel's valid samples, weights ``1 / sigma_k^2`` with ``sigma_k``
   the sample's predicted noise (:func:`ptpcore.fit.smooth.sample_sigma_from_noise`:
   phase noise, plus the stage readings' error through the pixel's slope).
2. Each residual is studentized, ``r_k / (sigma_k sqrt(1 - h_kk))`` (``h`` the hat
   matrix's diagonal), which is N(0, 1) for a sample that follows the curve. The
   spread actually seen in a block of pixels (median of the larger of the X and Y
   values / 1.0518, its median under N(0, 1)) scales the threshold when it is above 1:
   a noise model that is too optimistic does not turn good samples into outliers.
3. A pixel's worst sample is rejected when it is beyond :data:`K_SIGMA` of that
   spread; the pixel is refitted and screened again, at most :data:`MAX_PER_PIXEL`
   times, and never below ``degree + 2`` samples.
4. A position whose valid samples are rejected at more than :data:`SUSPECT_FRACTION`
   of the pixels (wrong images, a stage glitch) is named suspect and left out at
   every pixel.

Without a camera noise model every ``sigma_k`` is 1 and the threshold is K_SIGMA
times the residuals' robust spread alone. The rejected samples are flagged
:attr:`ptpcore.decode.phase.Reason.OUTLIER` in a copy of the ``reasons`` array (the
coordinates are shared, not copied); ``n_rejected`` per pixel goes to the LUT's
``/quality/n_rejected`` and the report to ``/provenance`` ``robust`` (FORMATS.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import numpy as np

from ptpcore.decode.phase import Reason
from ptpcore.fit.choice import fit_auto
from ptpcore.fit.kinds import fit_kind
from ptpcore.fit.smooth import phase_sigma_mm
from ptpcore.io.samples import SampleStack
from ptpcore.parallel import map_in_order
from ptpcore.rig.naming import position_label
from ptpcore.rig.rigfile import Rig
from ptpcore.store import read_block, release_free_memory

__all__ = ["K_SIGMA", "SCREEN_DEGREE", "MAX_PER_PIXEL", "SUSPECT_FRACTION", "RobustReport", "screen_samples",
           "without_outliers", "fit_robust"]

K_SIGMA = 5.0
"""A sample beyond this many (scaled) predicted sigmas of its pixel's curve is rejected."""

SCREEN_DEGREE = 3
"""Degree of the screening polynomial (lowered to ``n_positions - 4`` with few positions)."""

MAX_PER_PIXEL = 3
"""Samples rejected per pixel at most (before suspect positions)."""

SUSPECT_FRACTION = 0.5
"""A position rejected at more than this fraction of its valid samples is suspect."""

_MEDIAN_MAX_ABS_N01 = 1.0518
"""Median of max(|a|, |b|) for independent a, b ~ N(0, 1): (2 Phi(m) - 1)^2 = 1/2."""

_BLOCK = 1 << 15


@dataclass
class RobustReport:
    """What the screening left out.

    Attributes
    ----------
    positions : (Kp,) int64
        The screened positions (indices into the stack).
    rejected_bits : (Kp, ceil(H * W / 8)) uint8
        Samples left out (suspect positions included), a bit per pixel (``numpy.packbits`` of
        each position's flat mask: a big sensor's ``(Kp, H, W)`` bool would grow with the
        positions); :meth:`rejected_at` unpacks one position.
    n_rejected : (H, W) uint16
        Samples left out per pixel.
    fraction : (Kp,) float64
        Fraction of each position's valid samples rejected as outliers (before suspects are dropped).
    suspect : list of int
        Suspect positions (stack indices), left out everywhere.
    k_sigma : float
    degree : int
        Degree of the screening polynomial.
    noise_scale : float
        Median over blocks of the residual spread in predicted sigmas (the threshold's factor).
    noise_model : bool
        Whether the samples' predicted noise was used.
    """

    positions: np.ndarray
    rejected_bits: np.ndarray
    n_rejected: np.ndarray
    fraction: np.ndarray
    suspect: list
    k_sigma: float
    degree: int
    noise_scale: float
    noise_model: bool

    @property
    def n_outliers(self) -> int:
        return int(self.n_rejected.sum(dtype=np.int64))

    def rejected_at(self, i: int) -> np.ndarray:
        """``(H, W)`` bool: the samples of screened position ``positions[i]`` left out."""
        h, w = self.n_rejected.shape
        return np.unpackbits(self.rejected_bits[i], count=h * w).view(bool).reshape(h, w)

    def set_rejected(self, i: int, mask: np.ndarray) -> None:
        """Replace position ``positions[i]``'s left-out samples by ``mask`` ((H, W) bool); ``n_rejected`` follows."""
        old = self.rejected_at(i)
        new = np.asarray(mask, bool)
        self.n_rejected = (self.n_rejected.astype(np.int64) + new - old).astype(np.uint16)
        self.rejected_bits[i] = np.packbits(new.ravel())

    def to_json(self) -> str:
        """The ``/provenance`` attribute ``robust`` (FORMATS.md)."""
        return json.dumps({"k_sigma": self.k_sigma, "screen_degree": self.degree,
                           "noise_scale": round(float(self.noise_scale), 4), "noise_model": self.noise_model,
                           "n_rejected": self.n_outliers, "suspect_positions": [int(k) for k in self.suspect],
                           "rejected_fraction": {str(int(k)): round(float(f), 5)
                                                 for k, f in zip(self.positions, self.fraction)}})

    def lines(self, z=None) -> list[str]:
        """The report in words, for summaries (``z``: the stage readings, to name positions)."""
        out = [f"robust fit: {self.n_outliers} samples left out (beyond {self.k_sigma:g} x"
               f" {self.noise_scale:.2f} predicted sigma), at {int((self.n_rejected > 0).sum())} pixels"]
        for k in self.suspect:
            i = int(np.flatnonzero(self.positions == k)[0])
            name = position_label(k, None if z is None else z[k])
            out.append(f"SUSPECT {name}: {100 * self.fraction[i]:.0f} % of its samples are far"
                       " from the curve of the others (wrong images? a stage glitch?); left out everywhere")
        return out


def _sigma_block(samples: SampleStack, rig: Rig, start: int, stop: int, idx, valid) -> np.ndarray:
    """(Kp, n) predicted phase-noise sigma (mm) of a block of pixels; 1 without a noise model."""
    if samples.noise is None or samples.modulation is None or samples.background is None:
        return np.where(valid, 1.0, np.nan)
    bg = read_block(samples.background, start, stop, idx).astype(float)
    mod = read_block(samples.modulation, start, stop, idx).astype(float)
    s = phase_sigma_mm(samples, rig, bg, mod)
    return np.where(valid & np.isfinite(s) & (s > 0), s, np.nan)


def _studentized(t: np.ndarray, vx, vy, sigma, use, degree: int):
    """Weighted per-pixel polynomial fit and studentized residuals.

    Parameters
    ----------
    t : (Kp,) float, normalised z
    vx, vy : (Kp, n) float, mm (anything where not ``use``)
    sigma : (Kp, n) float, mm
    use : (Kp, n) bool
    degree : int

    Returns
    -------
    z : (Kp, n) float
        max(|studentized X|, |studentized Y|); NaN where not used or the pixel has no fit.
    slope : (Kp, n) float
        |d(X, Y)/dt| of the fit at each position (normalised z units), for the stage term.
    """
    d1 = degree + 1
    v = np.vander(t, d1, increasing=True)  # (Kp, D)
    vv = (v[:, :, None] * v[:, None, :]).reshape(v.shape[0], d1 * d1)  # (Kp, D*D): v_ki v_kj
    w = np.where(use, 1.0 / np.where(use, sigma, 1.0) ** 2, 0.0)
    # Sums over the positions as matrix products (BLAS): numpy's einsum of three or four operands
    # runs one naive loop over every index, 210 s of CPU at 5 MP x 21 positions.
    a = (w.T @ vv).reshape(-1, d1, d1)  # (n, D, D) normal matrices
    n_used = use.sum(axis=0)
    ok = n_used >= degree + 2
    a[~ok] = np.eye(d1)
    ainv = np.linalg.inv(a)
    out = []
    for vals in (vx, vy):
        vals = np.where(use, vals, 0.0)
        c = np.einsum("pij,pj->pi", ainv, (w * vals).T @ v)
        out.append((vals - v @ c.T, c))
    h = (vv @ ainv.reshape(-1, d1 * d1).T) * w
    with np.errstate(invalid="ignore", divide="ignore"):
        den = sigma * np.sqrt(np.clip(1.0 - h, 1e-6, None))
        z = np.fmax(np.abs(out[0][0]) / den, np.abs(out[1][0]) / den)
    z = np.where(use & ok[None, :], z, np.nan)
    dv = np.vander(t, degree, increasing=True) * np.arange(1, degree + 1)  # d/dt of each power
    slope = np.hypot(dv @ out[0][1][:, 1:].T, dv @ out[1][1][:, 1:].T)
    return z, slope


def _noise_scale(t, vx, vy, sigma, use, z, degree: int, noise_model: bool) -> float:
    """The residuals' spread in predicted sigmas, with every pixel's worst sample left out.

    Leaving the worst out first keeps one bad position (which drags every pixel's curve,
    and so every residual) from inflating the threshold that is to find it. At least 1
    with a noise model (the prediction is a floor, never lowered).
    """
    zf = np.where(np.isfinite(z), z, -1.0)
    cols = np.arange(zf.shape[1])
    worst = np.argmax(zf, axis=0)
    trim = use.sum(axis=0) > degree + 2
    use2 = use.copy()
    use2[worst[trim], cols[trim]] = False
    z2, _slope = _studentized(t, vx, vy, sigma, use2, degree)
    med = np.nanmedian(z2) if np.isfinite(z2).any() else np.nan
    scale = med / _MEDIAN_MAX_ABS_N01 if np.isfinite(med) and med > 0 else 1.0
    return max(scale, 1.0) if noise_model else scale


def _screen_block(samples, rig, start, stop, idx, t, degree, k_sigma, stage_t_sigma):
    """Reject the outliers of pixels ``[start, stop)``; returns (Kp, n) bool and the block's noise scale."""
    valid = read_block(samples.reasons, start, stop, idx) == 0
    vx = read_block(samples.x, start, stop, idx).astype(float)
    vy = read_block(samples.y, start, stop, idx).astype(float)
    valid &= np.isfinite(vx) & np.isfinite(vy)
    sigma = _sigma_block(samples, rig, start, stop, idx, valid)
    use = valid & np.isfinite(sigma)
    rejected = np.zeros_like(use)
    z, slope = _studentized(t, vx, vy, sigma, use, degree)
    if stage_t_sigma > 0:  # the stage reading's error moves the sample along its ray
        sigma = np.sqrt(sigma ** 2 + (slope * stage_t_sigma) ** 2)
        z, slope = _studentized(t, vx, vy, sigma, use, degree)
    scale = _noise_scale(t, vx, vy, sigma, use, z, degree, samples.noise is not None)
    # Only the pixels that just lost a sample are refitted: every other pixel's data, and so its
    # verdict, is unchanged (a few thousand pixels of 5 MP have an outlier).
    cols = np.arange(use.shape[1])
    for it in range(MAX_PER_PIXEL):
        zf = np.where(np.isfinite(z), z, -1.0)
        worst = np.argmax(zf, axis=0)
        bad = (zf[worst, np.arange(cols.size)] > k_sigma * scale) & (use[:, cols].sum(axis=0) > degree + 2)
        if not bad.any():
            break
        cols, worst = cols[bad], worst[bad]
        use[worst, cols] = False
        rejected[worst, cols] = True
        if it + 1 < MAX_PER_PIXEL:
            z, _slope = _studentized(t, vx[:, cols], vy[:, cols], sigma[:, cols], use[:, cols], degree)
    return rejected, valid, scale


def screen_samples(samples: SampleStack, rig: Rig, positions=None, *, k_sigma: float = K_SIGMA,
                   degree: int = SCREEN_DEGREE, stage_sigma_mm: float = 0.0) -> RobustReport:
    """Find the samples far outside their pixel's curve, and the suspect positions (module docstring).

    Parameters
    ----------
    samples : SampleStack
    rig : Rig
    positions : sequence of int, optional
        Positions to screen (default all); the others are left alone.
    k_sigma : float
        Threshold in (scaled) predicted sigmas.
    degree : int
        Screening polynomial degree, lowered to ``len(positions) - 4`` (at least 1).
    stage_sigma_mm : float
        1-sigma error of the stage readings (mm).

    Returns
    -------
    RobustReport

    Raises
    ------
    ValueError
        ``k_sigma`` not positive.
    """
    if not k_sigma > 0:
        raise ValueError(f"k_sigma must be > 0, got {k_sigma}")
    idx = np.arange(samples.z.size) if positions is None else np.asarray(positions, dtype=np.int64)
    h, w = samples.shape
    deg = int(max(1, min(degree, idx.size - 4)))
    z = np.asarray(samples.z, float)[idx]
    zc, zs = 0.5 * (z.max() + z.min()), max(0.5 * (z.max() - z.min()), 1e-9)
    t = (z - zc) / zs
    # Packed bits (blocks are multiples of 8 pixels): 1/8 of a (K, H, W) bool stack.
    bits = np.zeros((idx.size, -(-h * w // 8)), np.uint8)
    n_rej = np.zeros(h * w, np.int64)
    n_valid, n_out = np.zeros(idx.size, np.int64), np.zeros(idx.size, np.int64)
    scales = []
    if idx.size >= 5:  # fewer: nothing to judge a sample against
        starts = range(0, h * w, _BLOCK)

        def screen(start):
            stop = min(start + _BLOCK, h * w)
            return (start, stop) + _screen_block(samples, rig, start, stop, idx, t, deg, k_sigma, stage_sigma_mm / zs)

        for start, stop, rej, valid, scale in map_in_order(screen, starts):
            bits[:, start // 8:-(-stop // 8)] = np.packbits(rej, axis=1)
            n_rej[start:stop] = rej.sum(axis=0)
            n_out += rej.sum(axis=1)
            n_valid += valid.sum(axis=1)
            scales.append(scale)
    fraction = n_out / np.maximum(n_valid, 1)
    suspect = [int(k) for k, f in zip(idx, fraction) if f > SUSPECT_FRACTION]
    report = RobustReport(idx, bits, np.minimum(n_rej, 65535).astype(np.uint16).reshape(h, w), fraction, suspect,
                          float(k_sigma), deg, float(np.nanmedian(scales)) if scales else 1.0,
                          samples.noise is not None and samples.modulation is not None)
    for k in suspect:  # left out everywhere it was valid
        i = int(np.flatnonzero(idx == k)[0])
        report.set_rejected(i, report.rejected_at(i) | (samples.plane("reasons", k) == 0))
    return report


def without_outliers(samples: SampleStack, report: RobustReport) -> SampleStack:
    """The stack with the rejected samples flagged :attr:`Reason.OUTLIER` (a copy of ``reasons`` only).

    A spilled stack's copy goes to a spill file of its own, a position at a time (at 5 MP x 21
    positions the ``(K, H, W)`` uint8 copy and its temporaries are 210-315 MB).
    """
    if isinstance(samples.reasons, np.memmap):
        from ptpcore.store import SpillStore

        h, w = samples.shape
        store = SpillStore(samples.z.size, (h, w), {"reasons": np.uint8}, {})
        row_of = {int(k): i for i, k in enumerate(report.positions)}
        for k in range(samples.z.size):
            r = read_block(samples.reasons, 0, h * w, [k])[0].reshape(h, w)
            if k in row_of:
                r[report.rejected_at(row_of[k])] |= np.uint8(Reason.OUTLIER)
            store.write("reasons", k, r)
        return replace(samples, reasons=store.arrays()["reasons"])
    reasons = np.array(samples.reasons, copy=True)
    for i, k in enumerate(report.positions):
        reasons[k][report.rejected_at(i)] |= np.uint8(Reason.OUTLIER)
    return replace(samples, reasons=reasons)


def fit_robust(samples: SampleStack, rig: Rig, model: str = "auto", degree: int = 3, positions=None, *,
               k_sigma: float = K_SIGMA, stage_sigma_mm: float = 0.0, progress=None, **kwargs):
    """Screen the samples (:func:`screen_samples`), then fit ``model`` without the outliers.

    Parameters
    ----------
    samples, rig, model, degree, positions, stage_sigma_mm, progress, **kwargs
        As for :func:`ptpcore.fit.models.fit_model` (``level_bias``, ``footprint``).
    k_sigma : float

    Returns
    -------
    lut : Lut
        With ``n_rejected`` (H, W) and ``provenance["robust"]`` (:meth:`RobustReport.to_json`).
    report : RobustReport
    """
    if progress:
        progress(0.0, "screening the samples for outliers")
    report = screen_samples(samples, rig, positions, k_sigma=k_sigma, stage_sigma_mm=stage_sigma_mm)
    clean = without_outliers(samples, report) if report.n_outliers else samples
    release_free_memory()  # the screening's blocks, before the fit's
    sub = None if progress is None else (lambda f, msg: progress(0.05 + 0.95 * f, msg))
    if model == "auto":
        lut = fit_auto(clean, rig, positions, stage_sigma_mm=stage_sigma_mm, progress=sub, **kwargs)[0]
    else:
        lut = fit_kind(clean, rig, model, degree, positions, sub, stage_sigma_mm=stage_sigma_mm, **kwargs)
    lut.n_rejected = report.n_rejected
    lut.provenance["robust"] = report.to_json()
    return lut, report
