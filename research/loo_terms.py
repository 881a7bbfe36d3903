"""The smooth LUT's leave-one-out excess, term by term, against the exact rays (issue 30's diagnosis).

    python -m research.loo_terms OUT_DIR [--kind symmetric] [--seed 1] [--sweep noisy|noiseless|white]
                                   [--degree 2] [--scale 2]

Renders sweep A of the harness's draw (:func:`research.rigs.sweep_folder`, the folder
:mod:`research.trust_split` names ``KIND-SEED-a``; ``noiseless``: no image noise, no stage errors) and
fits it as ``ptp calibrate --model smooth`` does at one fixed degree and smoothing scale. ``white``
replaces the noisy sweep's values by the exact rays plus white noise of each sample's predicted sigma (no
model error exists there; no level-bias, footprint or glass correction). At every interior position ``k``
the model error's estimate is ``x = r^2 - own - v`` (:func:`ptpcore.fit.smooth.leave_one_out.model_error`):
``r`` the left-out residual, ``own`` the sample's noise from its pixel's own fit, ``v`` the left-out fit's
predicted variance. Beside each, what it estimates, from the truth ``T`` (the exact ray at the position's
true height): ``(s - T)^2`` for ``own`` (``s`` the corrected sample) and ``(p - T)^2`` for ``v`` (``p`` the
left-out prediction). Also the correlation of ``s - T`` between neighbouring positions (independent noise:
0 within about 0.002), and the LUT's error at 7 heights over each pixel's range against its sigma maps
(RMS(z), per decile of sigma, the noise and model parts). Pixels 3 px or more inside the image.
"""

from __future__ import annotations

import argparse
import json
import sys
from functools import partial
from pathlib import Path

import numpy as np

from research.rigs import RIG_TYPES, drawn_rig, sweep_folder
from research.scoring import FRACTIONS, deciles, fit_leverage, fit_weights, stage_terms, weighted_stage_terms

EDGE_PX = 3


class TermCatcher:
    """Wraps the leave-one-out's accumulation: per interior position and axis, the excess's terms and
    what they estimate, from the truth."""

    def __init__(self, truth, white: bool):
        import ptpcore.fit.smooth.leave_one_out as loo

        self.loo, self.truth, self.white = loo, truth, white
        self.rows, self.errors, self.pred_errors = [], {"x": {}, "y": {}}, {"x": {}, "y": {}}
        self.original = loo.accumulate_left_out

    def __enter__(self):
        self.loo.accumulate_left_out = self.accumulate
        return self

    def __exit__(self, *exc):
        self.loo.accumulate_left_out = self.original

    def accumulate(self, s, k, coef, valid, sums, grow, own_noise, kept, odd=False):
        self.original(s, k, coef, valid, sums, grow, own_noise, kept, odd)
        if own_noise is None:
            return
        h, w = s.samples.shape
        t_k = (s.z[k] - s.z_norm[0]) / s.z_norm[1]
        powers = t_k ** np.arange(s.degree + 1)
        values = kept.row_block(0, h).reshape(3, h, w)
        own = own_noise.row_block(0, h).reshape(own_noise.shape[0], h, w)
        z_true = s.z[k] if self.white else self.truth.z_true[s.sel[k]]
        exact = self.truth.xy(np.full((h, w), z_true))
        inner = np.zeros((h, w), bool)
        inner[EDGE_PX:-EDGE_PX, EDGE_PX:-EDGE_PX] = True
        for i, a in enumerate("xy"):
            pred = np.einsum("j,jhw->hw", powers, coef[a])
            v = self.loo.left_out_variance(s, sums, a, 0, h, t_k, own[2].ravel(), grow).reshape(h, w)
            se, pe, r = values[i] - exact[i], pred - exact[i], values[i] - pred
            ok = (values[2] > 0) & valid & np.isfinite(r) & np.isfinite(own[i]) & inner
            self.rows.append({"k": int(k), "axis": a, "r2": _um2(r * r, ok), "own": _um2(own[i], ok),
                              "v": _um2(v, ok), "s_T2": _um2(se * se, ok), "p_T2": _um2(pe * pe, ok)})
            self.errors[a][int(k)] = np.where(ok, se, np.nan).astype(np.float32)
            self.pred_errors[a][int(k)] = np.where(ok, pe, np.nan).astype(np.float32)

    def left_out_noise(self, other: "TermCatcher", axis: str) -> dict:
        """Per interior position, the left-out fits' realised noise variance (um^2): half the mean square
        difference of this fit's and ``other``'s predictions, two fits of the same rig with independent
        noise (what they share, the model error, cancels)."""
        out = {}
        for k, pe in self.pred_errors[axis].items():
            d = (pe - other.pred_errors[axis][k]).astype(np.float64)
            out[k] = float(np.nanmean(d * d)) / 2 * 1e6
        return out

    def neighbour_correlations(self, axis: str) -> list[float]:
        """Correlation over the pixels of ``s - T`` between neighbouring interior positions (each
        position's mean over the image removed)."""
        ks = sorted(self.errors[axis])
        stack = np.stack([self.errors[axis][k] for k in ks])
        ok = np.isfinite(stack).all(axis=0)
        e = stack[:, ok].astype(np.float64)
        e -= e.mean(axis=1, keepdims=True)
        c = np.corrcoef(e)
        return [round(float(c[i, i + 1]), 4) for i in range(len(ks) - 1)]


def _um2(values: np.ndarray, ok: np.ndarray) -> float:
    return float(np.mean(values[ok])) * 1e6


def fit(folder: Path, sweep: str, degree: int, scale: float, stage_sigma_um: float, truth, footprint: bool = True):
    """The LUT (``degree``, smoothing ``scale`` px fixed), the caught terms (:class:`TermCatcher`) and the
    samples' fit weights (:func:`fit_weights`)."""
    import ptpcore.fit.kinds as kinds
    from ptpcore.fit.corrected import fit_corrected
    from ptpcore.fit.settings import FitSettings
    from ptpcore.fit.smooth.estimator import fit_smooth_lut
    from ptpcore.run import new_session, run_session

    session = new_session(folder, model="smooth", validate=False)
    run_session(session, stop_after="samples", validate=False)
    with TermCatcher(truth, sweep == "white") as caught:
        if sweep == "white":
            from ptpcore.simulate.synthetic import white_noise_samples

            samples = white_noise_samples(session.samples, session.rig, truth, seed=7)
            lut = fit_smooth_lut(samples, session.rig, degree, scales_px=(scale,), level_bias=False,
                                 footprint=False)[0]
        else:
            original = kinds.fit_smooth_lut
            kinds.fit_smooth_lut = partial(original, scales_px=(scale,))
            try:
                lut = fit_corrected(session.samples, session.rig,
                                    FitSettings(model="smooth", degree=degree, stage_sigma_um=stage_sigma_um,
                                                footprint=footprint)).lut
            finally:
                kinds.fit_smooth_lut = original
    return lut, caught, fit_weights(session.samples, session.rig)


def score(lut, truth, rig=None, degree: int = 2, stage_sigma_um: float = 0.0, weights=None) -> dict:
    """Per axis: the LUT's error (um) at :data:`FRACTIONS` of each pixel's range, its sigma parts (um, RMS
    over the pixels), RMS(z) and RMS(z) per decile of sigma. With the ``rig``, also the part of the error
    that is this sweep's realised stage height errors (:func:`research.scoring.stage_terms`: the
    degree-``degree`` fit of them, times the exact ray's slope against the travel direction), and the
    error without it, and sigma's stage term (the declared ``stage_sigma_um``, the fit's leverage) and
    what is left of its noise part without it. ``weights`` ((K, H, W), :func:`fit_weights`): the realised
    part through each pixel's weighted fit, as the LUT passes it on
    (:func:`research.scoring.weighted_stage_terms`); without, the unweighted fit's."""
    from ptpcore.fit.sigma import sigma_parts

    valid = lut.valid.astype(bool)
    lo, hi = np.where(valid, lut.pixel_z_min, 0.0), np.where(valid, lut.pixel_z_max, 0.0)
    inner = np.zeros(valid.shape, bool)
    inner[EDGE_PX:-EDGE_PX, EDGE_PX:-EDGE_PX] = True
    heights = lo + FRACTIONS[:, None, None] * (hi - lo)  # (F, H, W) mm
    if rig is not None:  # the stage's part in heights: the same for both axes, each pixel's fit solved once
        readings = np.asarray(rig.stage.z_mm, float)
        z_true = np.asarray(truth.z_true, float)[:readings.size]
        stage_z = (stage_terms(readings, z_true, degree, heights)[0] if weights is None
                   else weighted_stage_terms(readings, z_true, degree, heights, weights))
        lev = np.mean(fit_leverage(readings, degree, heights), axis=0)
    out = {}
    for i, a in enumerate("xy"):
        err = np.array([getattr(lut.evaluate(z), a) - truth.xy(z)[i] for z in heights])
        total, noise, model = sigma_parts(lut, a)
        ok = valid & inner & np.isfinite(err).all(axis=0) & np.isfinite(total)
        um = lambda v: round(1e3 * float(np.sqrt(np.mean(np.square(v)))), 4)  # noqa: E731
        rms_z, per_decile, _beyond = deciles(err, total, ok)
        if rig is not None:
            slope = np.abs((truth.sx, truth.sy)[i] - rig.stage.direction[i])
            stage = stage_z * ((truth.sx, truth.sy)[i] - rig.stage.direction[i])
            predicted = slope * stage_sigma_um * 1e-3 * np.sqrt(lev)
            rest = np.sqrt(np.maximum(np.square(noise if noise is not None else total) - predicted ** 2, 0))
            extra = {"stage_realised_um": um(stage[:, ok]), "error_less_stage_um": um((err - stage)[:, ok]),
                     "stage_predicted_um": um(predicted[ok]), "noise_less_stage_um": um(rest[ok]),
                     "rms_z_less_stage": round(float(np.sqrt(np.mean(((err - stage)[:, ok] / np.hypot(
                         rest, model if model is not None else 0)[ok]) ** 2))), 3)}
        else:
            extra = {}
        out[a] = {**extra, "error_um": um(err[:, ok]), "sigma_um": um(total[ok]),
                  "noise_part_um": um(noise[ok]) if noise is not None else um(total[ok]),
                  "model_part_um": um(model[ok]) if model is not None else 0.0,
                  "rms_z": round(rms_z, 3), "deciles": [round(v, 2) for v in per_decile]}
    return out


def report(caught: TermCatcher, scores: dict) -> list[str]:
    """Text lines: the terms per position and axis, their means, the correlations and the LUT's score."""
    lines = ["k axis |      r^2      own  (s-T)^2 |        v  (p-T)^2 |   excess   [um^2]"]
    for r in caught.rows:
        lines.append(f"{r['k']:2d} {r['axis']}    | {r['r2']:8.4f} {r['own']:8.4f} {r['s_T2']:8.4f} |"
                     f" {r['v']:8.4f} {r['p_T2']:8.4f} | {r['r2'] - r['own'] - r['v']:8.4f}")
    for a in "xy":
        m = {key: np.mean([r[key] for r in caught.rows if r["axis"] == a]) for key in ("r2", "own", "s_T2", "v", "p_T2")}
        lines.append(f"mean {a}: r^2 {m['r2']:.4f}, own {m['own']:.4f} against (s-T)^2 {m['s_T2']:.4f},"
                     f" v {m['v']:.4f} against (p-T)^2 {m['p_T2']:.4f}; excess {m['r2'] - m['own'] - m['v']:.4f} um^2")
        lines.append(f"  correlation of s - T between neighbouring positions: {caught.neighbour_correlations(a)}")
        sc = scores[a]
        if "stage_realised_um" in sc:
            lines.append(f"  the sweep's realised stage errors pass on {sc['stage_realised_um']:.4f} um (sigma's stage term"
                         f" {sc['stage_predicted_um']:.4f}); without them the LUT's error is {sc['error_less_stage_um']:.4f} um"
                         f" against {sc['noise_less_stage_um']:.4f} of noise part: RMS(z) {sc['rms_z_less_stage']:.3f}")
        lines.append(f"  LUT: error {sc['error_um']:.4f} um, sigma {sc['sigma_um']:.4f} (noise part {sc['noise_part_um']:.4f},"
                     f" model part {sc['model_part_um']:.4f}); RMS(z) {sc['rms_z']:.3f}, per decile {sc['deciles']}")
    return lines


def main(argv=None) -> int:
    from ptpcore.simulate import load_truth

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--kind", default="symmetric", choices=RIG_TYPES)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sweep", default="noisy", choices=["noisy", "noiseless", "white"])
    ap.add_argument("--degree", type=int, default=2)
    ap.add_argument("--scale", type=float, default=2.0, help="smoothing scale, px (fixed)")
    ap.add_argument("--no-footprint", action="store_true", help="fit without the footprint correction")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    folder = sweep_folder(out, args.kind, args.seed, args.sweep == "noiseless")
    truth, _, _ = load_truth(folder)
    stage_um = 0.0 if args.sweep != "noisy" else drawn_rig(args.kind, args.seed)[1].stage_error_um
    lut, caught, weights = fit(folder, args.sweep, args.degree, args.scale, stage_um, truth, not args.no_footprint)
    from ptpcore.rig.rigfile import load_rig

    scores = score(lut, truth, load_rig(folder / "rig.toml"), args.degree, stage_um, weights)
    print(f"{args.kind}#{args.seed}, sweep {args.sweep}: smooth degree {args.degree} at {args.scale:g} px")
    print("\n".join(report(caught, scores)))
    (out / f"loo_terms-{args.kind}-{args.seed}-{args.sweep}.json").write_text(
        json.dumps({"rows": caught.rows, "scores": scores}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
