"""The footprint correction against the shift the simulator makes (issue 30).

    python -m research.footprint_truth OUT_DIR [--kind fisheye] [--seed 1]

Renders the harness's draw (:func:`research.rigs.drawn_rig`) without noise and without stage
errors, decodes it as ``ptp calibrate`` does, and takes each sample's X and Y (less the display's
level bias) minus the exact ray at the position's true height: what the decoder hands the fit besides
noise, mostly the footprint's shift where the lens bends. Beside it, what
:func:`ptpcore.fit.smooth.footprint_bias` subtracts (from the global model and the decoded contrast).
Printed per axis, over pixels 3 px or more inside the image: the RMS of both, their correlation and
regression coefficient, and the RMS of what the correction leaves (a constant, the LCD frame's offset,
removed first).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from research.rigs import RIG_TYPES, drawn_rig, simulate, simulator_seed

EDGE_PX = 3


def decoded(out: Path, kind: str, seed: int):
    """The noise-free, stage-error-free render of draw ``seed`` of ``kind`` (once) and its decoded session."""
    from ptpcore.run import new_session, run_session

    rig, s = drawn_rig(kind, seed)
    folder = out / f"{kind}-{seed}-noiseless"
    if not (folder / "rig.toml").exists():
        sim = simulator_seed(kind, seed)
        simulate(folder, rig, replace(s, noise=False, stage_error_um=0.0), sim, sim)
    session = new_session(folder, model="smooth")
    run_session(session, stop_after="samples", validate=False)
    return folder, session


def _decoded_lcd_shift(samples, axis: int):
    """The samples' LCD shift along ``axis`` per pixel, flat (0.0 when the decoder recorded none): what the
    smooth fit's level-bias removal is given."""
    shift = getattr(samples, "lcd_shift", None)
    return 0.0 if shift is None else np.asarray(shift[axis]).reshape(-1)


def compare(folder: Path, session) -> dict:
    """Per axis: the decoded samples' shift from the exact rays and the product's correction (um)."""
    from ptpcore.fit.smooth.global_model import (GlobalRays, footprint_bias, global_pinhole,
                                                 remove_level_bias)
    from ptpcore.simulate import load_truth
    from ptpcore.store import read_block

    truth, _, _ = load_truth(folder)
    sm, rig = session.samples, session.rig
    h, w = sm.shape
    sel = list(range(len(sm.z)))
    rays = GlobalRays(global_pinhole(sm, sel, rig=rig), sm.shape)
    near, lo = rays.window(0, h)
    mod = read_block(sm.modulation, 0, h * w, sel).astype(float)
    bg = read_block(sm.background, 0, h * w, sel).astype(float)
    correction = footprint_bias(near, rig, np.asarray(sm.z), mod, bg, -lo, h - lo)
    keep = read_block(sm.reasons, 0, h * w, sel) == 0
    inner = np.zeros((h, w), bool)
    inner[EDGE_PX:-EDGE_PX, EDGE_PX:-EDGE_PX] = True
    keep &= inner.ravel()[None]
    exact_xy = [truth.xy(np.full((h, w), zt)) for zt in truth.z_true]  # (K,) of both axes' (H, W) maps
    out = {}
    for i, ax in enumerate("xy"):
        values = getattr(sm, f"{ax}_ref").reshape(-1)[None] + read_block(getattr(sm, ax), 0, h * w, sel).astype(float)
        remove_level_bias(values, rig, ax, np.asarray(sm.z), _decoded_lcd_shift(sm, i))
        exact = np.stack([xy[i].ravel() for xy in exact_xy])
        ok = keep & np.isfinite(values)
        shift = (values - exact)[ok]
        shift -= np.median(shift)
        corr = correction[i][ok]
        um = lambda v: float(np.sqrt(np.mean(np.square(v))) * 1e3)  # noqa: E731
        out[ax] = {"shift_um": um(shift), "correction_um": um(corr),
                   "correlation": float(np.corrcoef(shift, corr)[0, 1]),
                   "coefficient": float(np.dot(shift, corr) / np.dot(corr, corr)), "left_um": um(shift - corr)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--kind", default="fisheye", choices=RIG_TYPES)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = compare(*decoded(out, args.kind, args.seed))
    for ax, r in result.items():
        print(f"{args.kind}#{args.seed} {ax}: decoded shift {r['shift_um']:.3f} um RMS; correction {r['correction_um']:.3f};"
              f" correlation {r['correlation']:.2f}, coefficient {r['coefficient']:.2f}; left {r['left_um']:.3f} um")
    return 0


if __name__ == "__main__":
    sys.exit(main())
