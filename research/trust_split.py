"""Where a LUT's error comes from (issue 30): two sweeps of one drawn rig, the error split into its parts.

    python -m research.trust_split OUT_DIR [--kind realistic] [--seed 1] [--model auto] [--degree 3]

Two sweeps of the same drawn rig (:func:`research.rigs.drawn_rig`: same lens, field, glass,
stage errors and poses; the simulator's seed :func:`research.rigs.simulator_seed`) with
independent image noise (noise seeds that seed and it + 1000) are
calibrated as ``ptp calibrate --model M`` writes them; both LUTs are evaluated at 7 heights over each
pixel's calibrated range and compared with the exact rays. What the two sweeps share cancels in
their difference, so per pixel and height

- ``(e_A - e_B) / sqrt(2)`` is the error from the image noise alone: its RMS is what the LUT's noise
  part of sigma (``sigma_parts``: the total less the model part, less the stage term, which the sweeps
  share: declared stage sigma x |ray slope - travel direction| x sqrt(the LUT's leverage)) must predict;
- ``(e_A + e_B) / 2`` holds the shared error (model, stage errors, LCD) plus half the noise's
  variance: the common part ``sqrt(mean((e_A + e_B)^2 / 4) - mean(noise^2) / 2)``.

Reported (stdout and ``OUT_DIR/split.json``): per axis the measured and predicted noise part and the
common part against the model part and the stage term, over the image's inner 80 % and its border; per decile of the
predicted total sigma; per block of a 4 x 4 grid; and the noise part's RMS after a Gaussian low-pass
of 2 to 96 px (the scale at which the noise differs). No constant is fitted: this is a diagnosis.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from research.rigs import RIG_TYPES, calibrate, drawn_rig, simulate, simulator_seed
from research.scoring import FRACTIONS, fit_leverage, lut_degree


def sweeps(out: Path, kind: str, seed: int, model: str, degree: int) -> tuple[Path, Path]:
    """Simulate (once) and calibrate the two sweeps; the folders of LUTs ``NAME.lut.h5``."""
    rig, settings = drawn_rig(kind, seed)
    folders = []
    sim = simulator_seed(kind, seed)
    for tag, noise_seed in (("a", sim), ("b", sim + 1000)):
        folder = out / f"{kind}-{seed}-{tag}"
        if not (folder / "rig.toml").exists():
            simulate(folder, rig, settings, sim, noise_seed)
        if not (folder / f"{model}.lut.h5").exists():
            calibrate(folder, [(model, model, degree)], settings.stage_error_um)
        folders.append(folder)
    return folders[0], folders[1]


def load(folder_a: Path, folder_b: Path, model: str) -> tuple:
    """The two sweeps' LUTs, the rig's truth, and what sigma's stage term is made of: ``(readings (K,) mm,
    travel direction (3,), declared stage sigma mm, the LUT's degree)`` (read once for both axes)."""
    from ptpcore.io.lutfile import load_lut
    from ptpcore.rig.rigfile import load_rig
    from ptpcore.simulate import load_truth

    truth, s, _ = load_truth(folder_a)
    rig = load_rig(folder_a / "rig.toml")
    stage = (np.asarray(rig.stage.z_mm, float), rig.stage.direction, s.stage_error_um * 1e-3,
             lut_degree(folder_a / f"{model}.lut.h5"))
    return load_lut(folder_a / f"{model}.lut.h5"), load_lut(folder_b / f"{model}.lut.h5"), truth, stage


def errors(a, b, truth, stage, axis: str) -> dict:
    """Both LUTs' errors (mm) at :data:`FRACTIONS` of each pixel's range, and the first one's sigma parts:
    the model part, the stage term (declared sigma, the LUT's leverage at those heights, the exact ray's
    slope against the travel direction) and the noise part (what is left of sigma)."""
    from ptpcore.fit.sigma import sigma_parts

    valid = a.valid.astype(bool) & b.valid.astype(bool)
    lo = np.where(valid, a.pixel_z_min, 0.0).astype(float)
    hi = np.where(valid, a.pixel_z_max, 0.0).astype(float)
    ea, eb = [], []
    for f in FRACTIONS:
        z = lo + f * (hi - lo)
        t = truth.xy(z)["xy".index(axis)]
        ea.append(getattr(a.evaluate(z), axis) - t)
        eb.append(getattr(b.evaluate(z), axis) - t)
    ea, eb = np.array(ea), np.array(eb)
    total, noise, model_part = sigma_parts(a, axis)
    if noise is None:  # no model part: the total is the noise alone
        noise, model_part = total.astype(np.float64), np.zeros(total.shape)
    readings, direction, sigma_mm, degree = stage
    i = "xy".index(axis)
    leverage = np.mean([fit_leverage(readings, degree, lo + f * (hi - lo)) for f in FRACTIONS], axis=0)
    stage_part = np.abs((truth.sx, truth.sy)[i] - direction[i]) * sigma_mm * np.sqrt(leverage)
    # sigma's "noise" (total less model) holds the stage term; the two sweeps share the stage errors.
    noise = np.sqrt(np.maximum(np.square(noise) - np.square(stage_part), 0.0))
    ok = valid & np.isfinite(ea).all(0) & np.isfinite(eb).all(0) & np.isfinite(total)
    return {"noise": (ea - eb) / np.sqrt(2), "mean": (ea + eb) / 2, "err_a": ea, "ok": ok,
            "total": total.astype(float), "noise_pred": noise, "model_pred": model_part.astype(float),
            "stage_pred": stage_part}


def _parts(e: dict, where: np.ndarray) -> dict:
    """Measured and predicted parts (um) over the pixels ``where``."""
    noise2 = float(np.mean(e["noise"][:, where] ** 2))
    common2 = float(np.mean(e["mean"][:, where] ** 2)) - noise2 / 2
    um = lambda v: round(1e3 * float(np.sqrt(max(v, 0.0))), 4)  # noqa: E731
    return {"pixels": int(where.sum()), "noise_measured_um": um(noise2),
            "noise_predicted_um": um(np.mean(e["noise_pred"][where] ** 2)),
            "common_measured_um": um(common2), "model_predicted_um": um(np.mean(e["model_pred"][where] ** 2)),
            "stage_predicted_um": um(np.mean(e["stage_pred"][where] ** 2)),
            "error_um": um(np.mean(e["err_a"][:, where] ** 2)),
            "rms_z": round(float(np.sqrt(np.mean((e["err_a"][:, where] / e["total"][where]) ** 2))), 3)}


def split(e: dict) -> dict:
    """The parts over the inner 80 % and the border, per decile of predicted sigma, per 4 x 4 block,
    and the noise part after low-pass filters."""
    from scipy.ndimage import gaussian_filter

    ok = e["ok"]
    h, w = ok.shape
    inner = np.zeros_like(ok)
    inner[h // 10: h - h // 10, w // 10: w - w // 10] = True
    edges = np.quantile(e["total"][ok], np.linspace(0, 1, 11))
    decile = np.clip(np.searchsorted(edges, e["total"], side="right") - 1, 0, 9)
    blocks = [[_parts(e, ok & _block(h, w, i, j)) for j in range(4)] for i in range(4)]
    middle = np.where(ok, e["noise"][len(FRACTIONS) // 2], 0.0)
    support = ok.astype(float)
    low_pass = {}
    for s in (2, 8, 32, 96):
        lp = gaussian_filter(middle, s) / np.maximum(gaussian_filter(support, s), 1e-12)
        low_pass[f"{s}px"] = round(1e3 * float(np.sqrt(np.mean(lp[ok] ** 2))), 4)
    return {"all": _parts(e, ok), "inner": _parts(e, ok & inner), "border": _parts(e, ok & ~inner),
            "deciles": [_parts(e, ok & (decile == q)) for q in range(10)], "blocks": blocks,
            "noise_low_pass_um": low_pass}


def _block(h: int, w: int, i: int, j: int) -> np.ndarray:
    m = np.zeros((h, w), bool)
    m[i * h // 4:(i + 1) * h // 4, j * w // 4:(j + 1) * w // 4] = True
    return m


def report(axis: str, r: dict) -> list[str]:
    """Text lines of one axis's split."""
    def line(name, p):
        return (f"  {name:<10} noise {p['noise_measured_um']:.3f} measured / {p['noise_predicted_um']:.3f} predicted;"
                f" common {p['common_measured_um']:.3f} / model part {p['model_predicted_um']:.3f}"
                f" + stage {p['stage_predicted_um']:.3f};"
                f" error {p['error_um']:.3f} um, RMS(z) {p['rms_z']:.2f}")
    out = [f"axis {axis}"] + [line(n, r[n]) for n in ("all", "inner", "border")]
    out += [line(f"decile {q}", p) for q, p in enumerate(r["deciles"])]
    out.append("  noise part after a low-pass: " + ", ".join(f"{k} {v:.3f}" for k, v in r["noise_low_pass_um"].items()))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--kind", default="realistic", choices=RIG_TYPES)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--model", default="auto")
    ap.add_argument("--degree", type=int, default=3)
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    luts_and_truth = load(*sweeps(out, args.kind, args.seed, args.model, args.degree), args.model)
    result = {}
    for axis in "xy":
        result[axis] = split(errors(*luts_and_truth, axis))
        print("\n".join(report(axis, result[axis])), flush=True)
    (out / "split.json").write_text(json.dumps({"kind": args.kind, "seed": args.seed, "model": args.model,
                                                "degree": args.degree, **result}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
