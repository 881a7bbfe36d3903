"""The `real` rig's sigma with and without its panel bow declared (issue 30).

    python -m research.real_bow OUT_DIR [--seed 1] [--grid 17]

Sweep A of the harness's draw of ``real`` (:func:`research.rigs.sweep_folder`, the folder
``real-SEED-a`` that :mod:`research.trust_split` also renders), calibrated as ``ptp calibrate`` does
(:func:`research.rigs.calibrate`: auto, the drawn stage sigma declared) twice: as the preset is
(``asis.lut.h5``: the bow undeclared), and with the drawn bow declared as a measured map
(``bow.lut.h5``: ``[lcd] flatness_*`` on a ``--grid`` x ``--grid`` grid of the simulator's own bow,
which the existing flatness correction applies). Existing LUTs are scored again, not refitted. Scored
at 3 heights per pixel drawn uniformly over its range against the exact rays: the error, the median
sigma and its noise and model parts, RMS(z) and RMS(z) per decile of sigma (the harness's deciles).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from research.rigs import calibrate, drawn_rig, sweep_folder
from research.scoring import deciles


def bow_declared(rig, bow_um: float, n: int):
    """``rig`` declaring the simulator's bow ``w = bow (1 - xn^2)(1 - yn^2)`` as an ``n`` x ``n`` flatness grid."""
    u = np.linspace(0.0, rig.lcd.width - 1.0, n)
    v = np.linspace(0.0, rig.lcd.height - 1.0, n)
    xn, yn = 2 * u / (rig.lcd.width - 1) - 1, 2 * v / (rig.lcd.height - 1) - 1
    grid = bow_um * (1 - yn[:, None] ** 2) * (1 - xn[None, :] ** 2)
    return replace(rig, lcd=replace(rig.lcd, flatness_u_px=tuple(u), flatness_v_px=tuple(v),
                                    flatness_um=tuple(tuple(float(x) for x in row) for row in grid)))


def score(path: Path, truth, seed: int = 1) -> list[str]:
    """One line per axis for the LUT at ``path``."""
    from ptpcore.fit.sigma import sigma_parts
    from ptpcore.io.lutfile import load_lut

    lut = load_lut(path)
    valid = lut.valid.astype(bool)
    lo, hi = np.where(valid, lut.pixel_z_min, 0.0), np.where(valid, lut.pixel_z_max, 0.0)
    fractions = np.random.default_rng(seed).uniform(size=(3,) + valid.shape)
    lines = []
    for i, a in enumerate("xy"):
        err = np.array([getattr(lut.evaluate(lo + f * (hi - lo)), a) - truth.xy(lo + f * (hi - lo))[i]
                        for f in fractions])
        total, noise, model = sigma_parts(lut, a)
        ok = valid & np.isfinite(err).all(axis=0) & np.isfinite(total)
        rms_z, per_decile, beyond = deciles(err, total.astype(float), ok)
        med = lambda m: 1e3 * float(np.median(m[ok])) if m is not None else 0.0  # noqa: E731
        lines.append(f"  {a}: error {1e3 * np.sqrt(np.mean(err[:, ok] ** 2)):.3f} um; median sigma {med(total):.3f}"
                     f" (noise part {med(noise):.3f}, model part {med(model):.3f}); RMS(z) {rms_z:.2f};"
                     f" deciles {np.round(per_decile, 2).tolist()}; |z|>3 {100 * beyond:.2f} %")
    return lines


def main(argv=None) -> int:
    from ptpcore.rig.rigfile import load_rig
    from ptpcore.simulate import load_truth

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--grid", type=int, default=17, help="flatness grid points per side")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    folder = sweep_folder(out, "real", args.seed, False)
    _, settings = drawn_rig("real", args.seed)
    rig = load_rig(folder / "rig.toml")
    fits = {"asis": (rig, "as the preset is (bow undeclared)"),
            "bow": (bow_declared(rig, settings.bow_um, args.grid),
                    f"the drawn {settings.bow_um:.2f} um bow declared ({args.grid} x {args.grid} grid)")}
    missing = [(name, "auto", 3, r) for name, (r, _) in fits.items() if not (folder / f"{name}.lut.h5").exists()]
    if missing:
        calibrate(folder, missing, settings.stage_error_um)
    truth = load_truth(folder)[0]
    print(f"real#{args.seed}: stage sigma {settings.stage_error_um:.2f} um, tilt {settings.tilt_urad:.1f} urad,"
          f" run-out {settings.runout_um:.2f} um (undeclared), bow {settings.bow_um:.2f} um")
    for name, (_, label) in fits.items():
        print(label)
        print("\n".join(score(folder / f"{name}.lut.h5", truth)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
