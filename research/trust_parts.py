"""What the error two sweeps share is made of (issue 30): the realised stage errors, the panel's bow, the rest.

    python -m research.trust_parts SPLIT_DIR --kind real [--seed 1] [--model auto]

Reads the two sweeps and LUTs that :mod:`research.trust_split` wrote (``SPLIT_DIR/KIND-SEED-a``, ``-b``,
``MODEL.lut.h5``) and the simulator's truth. At :data:`research.scoring.FRACTIONS` of each pixel's
range, the error the two LUTs share, ``(e_A + e_B) / 2``, is regressed on two fields known exactly from
the truth, which no per-pixel residual can show:

- the realised stage term: the simulator's height errors (``z_true`` - readings) projected onto the
  LUT's polynomial degree in z (what a per-pixel fit of that degree passes on), times the ray's slope
  against the travel direction; beside it what sigma expects of it, ``sigma_stage * sqrt(leverage)``
  times the same slope;
- the bow term: the drawn panel bow ``w(u, v)`` (:class:`ptpcore.simulate.lcd_physics.LcdPhysics`) at
  the point the ray meets, times the slope (0 on rigs without a bow).

Printed per axis: RMS of the shared error, of each term and its regression coefficient (1 if the LUT
carries it as is), of what is left; the same per decile of the LUT's sigma. A diagnosis: nothing is
fitted to the product.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from research.scoring import FRACTIONS, lut_degree, stage_terms


def shared_fields(folder_a: Path, folder_b: Path, model: str) -> tuple[dict, dict]:
    """Per axis, over valid pixels and :data:`FRACTIONS`: the shared error, the realised stage and bow
    terms, the stage term sigma expects, and the LUT's sigma (flat arrays, mm); and the rig's numbers."""
    from ptpcore.fit.sigma import sigma_parts
    from ptpcore.io.lutfile import load_lut
    from ptpcore.rig.rigfile import load_rig
    from ptpcore.simulate import load_truth
    from ptpcore.simulate.lcd_physics import LcdPhysics

    truth, s, _ = load_truth(folder_a)
    rig = load_rig(folder_a / "rig.toml")
    a, b = load_lut(folder_a / f"{model}.lut.h5"), load_lut(folder_b / f"{model}.lut.h5")
    degree = lut_degree(folder_a / f"{model}.lut.h5")
    readings = np.asarray(rig.stage.z_mm, float)
    panel = LcdPhysics(bow_mm=s.bow_um * 1e-3, size_mm=((rig.lcd.width - 1) * rig.lcd.pitch_mm[0],
                                                       (rig.lcd.height - 1) * rig.lcd.pitch_mm[1]))
    sigma = {ax: sigma_parts(a, ax)[0].astype(float) for ax in "xy"}
    ok = a.valid.astype(bool) & b.valid.astype(bool)
    lo, hi = a.pixel_z_min, a.pixel_z_max
    out = {ax: {k: [] for k in ("shared", "stage", "stage_expected", "bow", "sigma")} for ax in "xy"}
    for f in FRACTIONS:
        z = np.where(ok, lo + f * (hi - lo), 0.0)
        true_xy = truth.xy(z)
        ea, eb = a.evaluate(z), b.evaluate(z)
        dz, leverage = stage_terms(readings, truth.z_true, degree, z)
        bow = panel.bow(*true_xy)
        for i, ax in enumerate("xy"):
            slope = (truth.sx, truth.sy)[i]
            rel = slope - rig.stage.direction[i]
            shared = ((getattr(ea, ax) - true_xy[i]) + (getattr(eb, ax) - true_xy[i])) / 2
            m = ok & np.isfinite(shared)
            o = out[ax]
            o["shared"].append(shared[m])
            o["stage"].append((rel * dz)[m])
            o["stage_expected"].append((np.abs(rel) * s.stage_error_um * 1e-3 * np.sqrt(leverage))[m])
            o["bow"].append((slope * bow)[m])
            o["sigma"].append(sigma[ax][m])
    info = {"degree": degree, "stage_declared_um": s.stage_error_um,
            "stage_realised_um": float(np.sqrt(np.mean(np.square(truth.z_true - readings))) * 1e3),
            "bow_um": s.bow_um}
    return {ax: {k: np.concatenate(v) for k, v in o.items()} for ax, o in out.items()}, info


def _um(v) -> float:
    return float(np.sqrt(np.mean(np.square(v))) * 1e3)


def explain(o: dict) -> dict:
    """Regress the shared error on the stage and bow terms; RMS (um) of each part, overall and per decile."""
    terms = [o["stage"]] + ([o["bow"]] if np.any(o["bow"]) else [])
    coef = np.linalg.lstsq(np.stack(terms, 1), o["shared"], rcond=None)[0]
    rest = o["shared"] - np.stack(terms, 1) @ coef
    edges = np.quantile(o["sigma"], np.linspace(0, 1, 11))
    decile = np.clip(np.searchsorted(edges, o["sigma"], side="right") - 1, 0, 9)
    per = [{k: round(_um(v[decile == q]), 4) for k, v in
            (("shared", o["shared"]), ("stage", o["stage"]), ("stage_expected", o["stage_expected"]),
             ("bow", o["bow"]), ("rest", rest))} for q in range(10)]
    return {"shared_um": _um(o["shared"]), "stage_um": _um(o["stage"]), "stage_expected_um": _um(o["stage_expected"]),
            "stage_coef": float(coef[0]), "bow_um": _um(o["bow"]),
            "bow_coef": float(coef[1]) if len(coef) > 1 else None, "rest_um": _um(rest), "deciles": per}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("split_dir")
    ap.add_argument("--kind", default="realistic")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--model", default="auto")
    args = ap.parse_args(argv)
    base = Path(args.split_dir)
    fields, info = shared_fields(base / f"{args.kind}-{args.seed}-a", base / f"{args.kind}-{args.seed}-b", args.model)
    print(f"{args.kind}#{args.seed} {args.model}: degree {info['degree']}; stage sigma declared"
          f" {info['stage_declared_um']:.3f} um, realised RMS {info['stage_realised_um']:.3f} um; bow {info['bow_um']:.2f} um")
    result = {"info": info}
    for ax in "xy":
        r = result[ax] = explain(fields[ax])
        bow = f"; bow {r['bow_um']:.3f} (coef {r['bow_coef']:.2f})" if r["bow_coef"] is not None else ""
        print(f" {ax}: shared {r['shared_um']:.3f} um; stage realised {r['stage_um']:.3f} (coef {r['stage_coef']:.2f},"
              f" expected {r['stage_expected_um']:.3f}){bow}; rest {r['rest_um']:.3f} um")
        print("   per decile of sigma, shared / stage realised / stage expected / rest (um): "
              + "  ".join(f"{p['shared']:.3f}/{p['stage']:.3f}/{p['stage_expected']:.3f}/{p['rest']:.3f}"
                          for p in r["deciles"]))
    (base / f"parts-{args.kind}-{args.seed}-{args.model}.json").write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
