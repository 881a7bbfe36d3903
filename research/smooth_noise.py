"""Is the smooth LUT's predicted noise part right for its own fit? (issue 30's diagnosis)

    python -m research.smooth_noise SWEEP_DIR [--scale 16] [--degree 2]

On a simulated sweep (a ``ptp simulate`` folder with its ``truth.h5``), the decoded samples keep
their masks, heights and predicted sigmas, but their values are replaced by the exact rays plus
white Gaussian noise of exactly each sample's predicted sigma, twice (two seeds). Both are fitted
with ``fit_smooth_lut`` at one fixed scale (no level-bias or footprint correction, no model part);
``(LUT_1 - LUT_2) / sqrt(2)`` at 7 heights over each pixel's range is the fit's own noise, which its
sigma maps must predict. Reported over the inner 80 % of the image and its border, beside the two
forms of the prediction :func:`ptpcore.fit.smooth.uncertainty.smooth_sigma_maps` can make: each
coefficient's smoothed variance alone ("diagonal", an upper bound when the coefficients of a pixel
are anti-correlated) and scaled by the pixel's own ratio of full to diagonal variance ("ratio",
what the product writes).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

FRACTIONS = np.linspace(0.05, 0.95, 7)


def predictions(fits, zc: float, zs: float, degree: int, noise_scale: float) -> dict:
    """Both forms of the smoothed noise prediction, (H, W) mm: ``diagonal`` and ``ratio``."""
    from ptpcore.fit.smooth.pixel_fits import range_moments

    h, w = fits.pz_min.shape
    mom = range_moments(((fits.pz_min - zc) / zs).astype(np.float64), ((fits.pz_max - zc) / zs).astype(np.float64),
                        2 * degree)
    diag = np.einsum("jhw,jhw->hw", fits.var.row_block(0, h), mom[2 * np.arange(degree + 1)])
    with np.errstate(all="ignore"):
        return {"diagonal": noise_scale * np.sqrt(diag),
                "ratio": noise_scale * np.sqrt(diag * fits.own_var / fits.own_diag)}


def main(argv=None) -> int:
    import ptpcore.fit.smooth.estimator as estimator
    from ptpcore.fit.smooth import fit_smooth_lut
    from ptpcore.run import new_session, run_session
    from ptpcore.simulate import load_truth
    from ptpcore.simulate.synthetic import white_noise_samples

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep")
    ap.add_argument("--scale", type=float, default=16.0)
    ap.add_argument("--degree", type=int, default=2)
    args = ap.parse_args(argv)
    session = new_session(Path(args.sweep), model="poly")
    run_session(session, stop_after="samples", validate=False)
    truth, _settings, _seed = load_truth(Path(args.sweep))
    seen = {}
    real = estimator.smooth_sigma_maps

    def keep(fits, zc, zs, degree, noise_scale, stage_var):  # the fit's own maps, before they are released
        if "pred" not in seen:
            seen["pred"] = predictions(fits, zc, zs, degree, noise_scale)
        return real(fits, zc, zs, degree, noise_scale, stage_var)

    estimator.smooth_sigma_maps = keep
    try:
        luts = [fit_smooth_lut(white_noise_samples(session.samples, session.rig, truth, seed), session.rig, args.degree,
                               scales_px=(args.scale,), uncertainty=False, level_bias=False, footprint=False)[0]
                for seed in (1, 2)]
    finally:
        estimator.smooth_sigma_maps = real
    a, b = luts
    valid = a.valid.astype(bool) & b.valid.astype(bool)
    lo = np.where(valid, a.pixel_z_min, 0.0).astype(float)
    hi = np.where(valid, a.pixel_z_max, 0.0).astype(float)
    h, w = valid.shape
    inner = np.zeros_like(valid)
    inner[h // 10: h - h // 10, w // 10: w - w // 10] = True
    for axis in "xy":
        d = np.array([getattr(a.evaluate(lo + f * (hi - lo)), axis) - getattr(b.evaluate(lo + f * (hi - lo)), axis)
                      for f in FRACTIONS]) / np.sqrt(2)
        ok = valid & np.isfinite(d).all(0) & np.isfinite(seen["pred"]["ratio"])
        for name, m in (("inner", ok & inner), ("border", ok & ~inner)):
            rms = lambda v: 1e3 * float(np.sqrt(np.mean(v)))  # noqa: E731
            print(f"{axis} {name:<6} measured {rms(d[:, m] ** 2):.4f} um; predicted: written"
                  f" {rms(getattr(a, f'sigma_{axis}')[m] ** 2):.4f}, ratio {rms(seen['pred']['ratio'][m] ** 2):.4f},"
                  f" diagonal {rms(seen['pred']['diagonal'][m] ** 2):.4f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
