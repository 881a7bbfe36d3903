"""What the smooth LUT's leave-one-out excess sees of its real error (issue 30): a diagnosis.

    python -m research.trust_excess SPLIT_DIR [--kind realistic] [--seed 1] [--scales 8,16,32,64,128]

``SPLIT_DIR`` holds the two sweeps of one drawn rig that :mod:`research.trust_split` renders
(``KIND-SEED-a``, ``KIND-SEED-b``: same rig, independent image noise). Each is fitted again as
``ptp calibrate --model smooth --degree 3`` fits it, keeping the per-pixel sums of the leave-one-out
excess ``x = r^2 - r_own^2 / (1 - h) - sigma_fit^2`` (:func:`ptpcore.fit.smooth.leave_one_out.model_error`
reads them; they are caught on their way there). Against the exact rays at 7 heights over each
pixel's range it reports, per axis:

- the shared error of the two sweeps (:func:`research.trust_split.errors`) and the excess, pooled per
  block of a 4 x 4 and 8 x 8 grid (their correlation and ratio);
- the excess mapped by Gaussian kernel regression at each scale (count-weighted, scaled to the
  image-wide level, floored at 0: the map before the posterior), and the product's posterior map
  (:func:`ptpcore.fit.sigma.model_variance_map`): RMS(z) of sweep A's LUT with that map as its model
  part, per decile of the predicted total (the issue's bound: each in [0.7, 1.4]), and |z| > 3;
- how the two sweeps' maps agree (independent noise: what they share is the rig's), and in the
  lowest tenth of the 16 px map, the map's value against the shared error there.

No constant is fitted: this is a diagnosis of the estimator, not a choice of its scale.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from research import trust_split
from research.rigs import RIG_TYPES, drawn_rig
from research.scoring import deciles, gauss_blur


def fit_with_excess(folder: Path, stage_sigma_um: float) -> tuple:
    """``ptp calibrate FOLDER --model smooth --degree 3``'s LUT, and its leave-one-out excess sums
    ``{"x": (sum x, sum x^2, sum x over odd ranks), "y": ..., "n": count, "n_odd": count of odd ranks}``
    ((H, W) each, mm^2, mm^4)."""
    import ptpcore.fit.smooth.leave_one_out as loo
    from ptpcore.run import new_session, run_session

    caught = {}
    original = loo.model_error

    def catch(sums):
        caught.update({a: (sums.get("excess", a).copy(), sums.get("excess_sq", a).copy(),
                           sums.get("excess_odd", a).copy()) for a in "xy"})
        caught["n"] = sums.n_model.astype(np.float64)
        caught["n_odd"] = sums.n_odd.astype(np.float64)
        return original(sums)

    loo.model_error = catch
    try:
        session = new_session(folder, model="smooth", degree=3, stage_sigma_um=stage_sigma_um)
        run_session(session, validate=False)
    finally:
        loo.model_error = original
    return session.lut, caught


def kernel_map(excess: np.ndarray, n: np.ndarray, scale: float) -> np.ndarray:
    """The count-weighted Gaussian kernel regression of the per-sample excess (mm^2), floored at 0 and
    scaled to the image-wide mean: the map :func:`ptpcore.fit.sigma.model_variance_map` drew before
    issue 30's posterior map (without its shrinkage)."""
    have = n > 0
    local = np.maximum(gauss_blur(excess, scale) / np.maximum(gauss_blur(n, scale), 1e-300), 0.0)
    level = excess.sum() / n.sum()
    return local * level / (np.sum(local[have] * n[have]) / n[have].sum())


def blocks(values: np.ndarray, weights: np.ndarray, ok: np.ndarray, g: int) -> np.ndarray:
    """Weighted means of ``values`` over the ``g x g`` blocks of the image (NaN for an empty block)."""
    h, w = ok.shape
    out = np.full(g * g, np.nan)
    for i in range(g):
        for j in range(g):
            m = np.zeros_like(ok)
            m[i * h // g:(i + 1) * h // g, j * w // g:(j + 1) * w // g] = True
            m &= ok
            if weights[m].sum() > 0:
                out[i * g + j] = np.sum(values[m] * weights[m]) / weights[m].sum()
    return out


def report_axis(axis: str, lut_a, lut_b, truth, stage: tuple, sums_a: dict, sums_b: dict, scales) -> list[str]:
    """The diagnosis lines of one axis (``stage``: what sigma's stage term is made of, as
    :func:`research.trust_split.load` gives it)."""
    e = trust_split.errors(lut_a, lut_b, truth, stage, axis)
    ok = e["ok"]
    shared2 = np.mean(e["mean"] ** 2, axis=0) - np.mean(e["noise"] ** 2, axis=0) / 2  # (H, W) mm^2
    ex, n = sums_a[axis][0], sums_a["n"]
    um = lambda v: 1e3 * np.sqrt(max(float(v), 0.0))  # noqa: E731
    lines = [f"axis {axis}: shared error {um(np.mean(shared2[ok])):.3f} um; excess level {um(ex.sum() / n.sum()):.3f} um"]
    for g in (4, 8):
        s_b = blocks(shared2, np.ones_like(shared2), ok, g)
        x_b = blocks(ex / np.maximum(n, 1), n, ok & (n > 0), g)
        fin = np.isfinite(s_b) & np.isfinite(x_b)
        ratio = x_b[fin] / s_b[fin]
        lines.append(f"  {g}x{g} blocks: corr(excess, shared) {np.corrcoef(s_b[fin], x_b[fin])[0, 1]:.2f};"
                     f" excess / shared median {np.median(ratio):.2f}, range {ratio.min():.2f} .. {ratio.max():.2f}")
    noise2 = e["noise_pred"] ** 2
    for s in scales:
        rz, per, tail = deciles(e["err_a"], np.sqrt(noise2 + kernel_map(ex, n, s)), ok)
        lines.append(f"  map at {s:>5g} px: RMS(z) {rz:.2f}; deciles " + " ".join(f"{v:.2f}" for v in per)
                     + f"; |z| > 3: {100 * tail:.2f} %")
    from ptpcore.fit.sigma import model_variance_map

    post, s_post, _ = model_variance_map(ex, n, excess_sq_sum=sums_a[axis][1], odd=(sums_a[axis][2], sums_a["n_odd"]),
                                         spatial=True)
    rz, per, tail = deciles(e["err_a"], np.sqrt(noise2 + post), ok)
    lines.append(f"  the product's posterior map (scale {s_post:g} px): RMS(z) {rz:.2f}; deciles "
                 + " ".join(f"{v:.2f}" for v in per) + f"; |z| > 3: {100 * tail:.2f} %")
    inner = np.zeros_like(ok)
    h, w = ok.shape
    inner[h // 8:h - h // 8, w // 8:w - w // 8] = True
    m = inner & ok & (n > 0) & (sums_b["n"] > 0)
    for s in (16, 64):
        ma = gauss_blur(ex, s) / np.maximum(gauss_blur(n, s), 1e-300)
        mb = gauss_blur(sums_b[axis][0], s) / np.maximum(gauss_blur(sums_b["n"], s), 1e-300)
        sh = gauss_blur(np.where(ok, shared2, 0.0), s) / np.maximum(gauss_blur(ok.astype(float), s), 1e-12)
        low = m & (ma < np.quantile(ma[m], 0.1))
        lines.append(f"  {s} px maps of the two sweeps (inner image): corr {np.corrcoef(ma[m], mb[m])[0, 1]:.2f};"
                     f" below 0 {100 * np.mean(ma[m] < 0):.1f} %; in A's lowest tenth: map {1e6 * ma[low].mean():+.3f},"
                     f" shared {1e6 * sh[low].mean():.3f} um^2 (upper half: map {1e6 * ma[m & (ma > np.median(ma[m]))].mean():.3f},"
                     f" shared {1e6 * sh[m & (ma > np.median(ma[m]))].mean():.3f})")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("split_dir")
    ap.add_argument("--kind", default="realistic", choices=RIG_TYPES)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--scales", default="8,16,32,64,128", help="kernel scales (px), comma-separated")
    args = ap.parse_args(argv)
    root = Path(args.split_dir)
    folder_a, folder_b = (root / f"{args.kind}-{args.seed}-{t}" for t in "ab")
    for f in (folder_a, folder_b):
        if not (f / "rig.toml").exists():
            ap.error(f"{f}: no sweep there (render both with python -m research.trust_split {root})")
    stage_um = drawn_rig(args.kind, args.seed)[1].stage_error_um
    lut_a, sums_a = fit_with_excess(folder_a, stage_um)
    lut_b, sums_b = fit_with_excess(folder_b, stage_um)
    from ptpcore.rig import load_rig
    from ptpcore.simulate import load_truth

    truth = load_truth(folder_a)[0]
    rig = load_rig(folder_a / "rig.toml")
    stage = (np.asarray(rig.stage.z_mm, float), rig.stage.direction, stage_um * 1e-3, 3)  # degree 3, as fitted
    scales = [float(v) for v in args.scales.split(",")]
    with np.errstate(all="ignore"):
        for axis in "xy":
            print("\n".join(report_axis(axis, lut_a, lut_b, truth, stage, sums_a, sums_b, scales)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
