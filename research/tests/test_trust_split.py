"""research/trust_split.py (issue 30's diagnosis) splits two sweeps' errors into what they share and the noise;
research/scoring.py projects the stage errors through each pixel's weighted fit."""

import numpy as np

from research import trust_split
from research.scoring import stage_terms, weighted_stage_terms


def _errors(noise_um: float, common_um: float, stage_um: float = 0.0, shape=(60, 80), heights=7, seed=0) -> dict:
    """Two sweeps' errors: a shared part and independent noise, with predicted parts to match (the shared
    part predicted as the model part; ``stage_um`` is the stage term's prediction, reported beside it)."""
    rng = np.random.default_rng(seed)
    common = rng.normal(size=(heights, *shape)) * common_um * 1e-3
    ea = common + rng.normal(size=(heights, *shape)) * noise_um * 1e-3
    eb = common + rng.normal(size=(heights, *shape)) * noise_um * 1e-3
    ok = np.ones(shape, bool)
    ok[:3] = False  # invalid pixels stay out
    ea[:, :3] = eb[:, :3] = 1.0
    total = np.hypot(noise_um, common_um) * 1e-3 * (1 + 1e-6 * rng.uniform(size=shape))  # ten deciles
    return {"noise": (ea - eb) / np.sqrt(2), "mean": (ea + eb) / 2, "err_a": ea, "ok": ok, "total": total,
            "noise_pred": np.full(shape, noise_um * 1e-3), "model_pred": np.full(shape, common_um * 1e-3),
            "stage_pred": np.full(shape, stage_um * 1e-3)}


def test_the_split_recovers_the_noise_and_the_shared_part():
    r = trust_split.split(_errors(noise_um=0.1, common_um=0.5, stage_um=0.2))
    for part in ("all", "inner", "border"):
        p = r[part]
        assert abs(p["noise_measured_um"] / 0.1 - 1) < 0.03 and p["noise_predicted_um"] == 0.1
        assert abs(p["common_measured_um"] / 0.5 - 1) < 0.03 and p["model_predicted_um"] == 0.5
        assert abs(p["rms_z"] - 1) < 0.03 and p["stage_predicted_um"] == 0.2
    assert [d["pixels"] > 400 for d in r["deciles"]] == [True] * 10
    assert len(r["deciles"]) == 10 and len(r["blocks"]) == 4 and all(len(row) == 4 for row in r["blocks"])
    assert r["all"]["pixels"] == 57 * 80
    # White noise loses most of its amplitude to a low-pass filter
    assert r["noise_low_pass_um"]["2px"] < 0.5 * r["all"]["noise_measured_um"]
    lines = trust_split.report("x", r)
    assert lines[0] == "axis x" and "measured" in lines[1] and "+ stage 0.200" in lines[1] and "low-pass" in lines[-1]


def test_the_weighted_stage_projection_is_each_pixels_weighted_fit():
    """research.scoring.weighted_stage_terms: with equal weights the unweighted projection; with a pixel's
    own weights, that pixel's weighted least-squares fit (numpy's polyfit, weights sqrt(w)) of the height
    errors at its heights; a pixel without enough samples is NaN."""
    rng = np.random.default_rng(4)
    readings = np.linspace(0.0, 40.0, 11)
    z_true = readings + rng.normal(0.0, 1e-3, 11)
    heights = rng.uniform(0.0, 40.0, (3, 4))
    equal = weighted_stage_terms(readings, z_true, 2, heights, np.ones((11, 3, 4)))
    assert np.allclose(equal, stage_terms(readings, z_true, 2, heights)[0], rtol=1e-9, atol=1e-15)
    weights = rng.uniform(0.2, 3.0, (11, 3, 4))
    weights[:9, 2, 3] = 0.0  # two samples cannot fix a degree-2 fit
    got = weighted_stage_terms(readings, z_true, 2, heights, weights)
    for r, c in [(0, 0), (1, 2), (2, 1)]:
        coef = np.polyfit(readings, z_true - readings, 2, w=np.sqrt(weights[:, r, c]))
        assert np.isclose(got[r, c], np.polyval(coef, heights[r, c]), rtol=1e-7, atol=1e-12)
    assert np.isnan(got[2, 3]) and np.isfinite(got[:2]).all()
