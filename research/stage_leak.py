"""How the smooth LUT passes a sweep's stage height errors on (issue 30's diagnosis of the mild preset).

    python -m research.stage_leak OUT_DIR [--kind mild] [--seed 3] [--scale 64] [--degree 2]

Sweep A of the harness's draw (:func:`research.rigs.sweep_folder`), its masks and predicted sigmas kept,
its values replaced by the exact rays at each position's TRUE height (the sweep's stage errors), alone ("stage
alone") and plus white noise of each sample's predicted sigma ("stage + white noise"), fitted smooth at one
degree and scale without level-bias or footprint correction, with the declared stage sigma. Scored by
:func:`research.loo_terms.score`: the LUT's error beside the realised stage errors' first-order part (their
degree-D fit, weighted per pixel as the LUT's fit in z is, times the exact ray's slope against the travel
direction), sigma's stage term, and the error left without that first-order part against the noise part.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from research import loo_terms
from research.rigs import RIG_TYPES, drawn_rig, sweep_folder
from research.scoring import fit_weights


def main(argv=None) -> int:
    from ptpcore.fit.smooth.estimator import fit_smooth_lut
    from ptpcore.rig.rigfile import load_rig
    from ptpcore.run import new_session, run_session
    from ptpcore.simulate import load_truth
    from ptpcore.simulate.synthetic import white_noise_samples

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--kind", default="mild", choices=RIG_TYPES)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--degree", type=int, default=2)
    ap.add_argument("--scale", type=float, default=64.0, help="smoothing scale, px (fixed)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    folder = sweep_folder(out, args.kind, args.seed, False)
    truth, _, _ = load_truth(folder)
    rig = load_rig(folder / "rig.toml")
    stage_um = drawn_rig(args.kind, args.seed)[1].stage_error_um
    session = new_session(folder, model="smooth", validate=False)
    run_session(session, stop_after="samples", validate=False)
    weights = fit_weights(session.samples, rig)
    for label, noise_seed in (("stage alone", None), ("stage + white noise", 5)):
        samples = white_noise_samples(session.samples, rig, truth, noise_seed, heights=truth.z_true)
        lut = fit_smooth_lut(samples, rig, args.degree, scales_px=(args.scale,), level_bias=False, footprint=False,
                             stage_sigma_mm=stage_um * 1e-3)[0]
        scores = loo_terms.score(lut, truth, rig, args.degree, stage_um, weights)
        for a in "xy":
            s = scores[a]
            print(f"{label}, {a}: error {s['error_um']:.4f} um; realised stage, first order {s['stage_realised_um']:.4f}"
                  f" (sigma's stage term {s['stage_predicted_um']:.4f}); without it {s['error_less_stage_um']:.4f}"
                  f" against a noise part of {s['noise_less_stage_um']:.4f}; RMS(z) {s['rms_z']:.3f}, deciles {s['deciles']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
