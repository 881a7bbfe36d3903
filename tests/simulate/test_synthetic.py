"""``ptpcore.simulate.synthetic``: analytic samples with known truth, and decoded samples made white.

The samples' noise is what the product predicts for them, so a fit of them can be judged against the
truth with tolerances from the noise alone."""

from __future__ import annotations

import numpy as np

from ptpcore.fit.smooth.noise import position_sigma_from_noise
from ptpcore.simulate.synthetic import synthetic_photometric_samples, white_noise_samples


def test_photometric_samples_are_the_rays_plus_their_predicted_noise():
    """Every valid sample is its pixel's true ray at the reading plus noise whose sigma the product
    predicts from the sample's modulation and background (``z = error / sigma``: mean 0, SD 1 within
    3 standard errors of ~60 k values); invalid samples are NaN, in bands that move with z."""
    samples, rig, truth = synthetic_photometric_samples(0.01, 5, seed=3, spill=False)
    assert samples.shape == rig.camera.shape == (96, 112) and samples.z.tolist() == [0.0, 3.0, 6.0, 9.0, 12.0]
    z = []
    for k in range(samples.z.size):
        tx, ty = truth.xy(samples.z[k])
        ok = samples.reasons[k] == 0
        assert np.isnan(samples.x[k][~ok]).all() and np.isfinite(samples.x[k][ok]).all()
        sig = position_sigma_from_noise(samples, rig, k)
        for axis, t in (("x", tx), ("y", ty)):
            err = samples.x_ref + samples.x[k] - t if axis == "x" else samples.y_ref + samples.y[k] - t
            z.append((err / sig)[ok])
    z = np.concatenate(z)
    assert z.size > 90_000
    assert abs(np.mean(z)) < 4 / np.sqrt(z.size) and abs(np.std(z) - 1) < 4 / np.sqrt(2 * z.size)
    assert (samples.reasons[0] != 0).sum() < (samples.reasons[4] != 0).sum()  # the bands grow with z
    again = synthetic_photometric_samples(0.01, 5, seed=3, spill=True)[0]
    assert isinstance(again.x, np.memmap)
    np.testing.assert_array_equal(np.asarray(again.x), samples.x)


def test_white_noise_samples_are_the_truth_plus_noise_of_each_samples_predicted_sigma():
    """On a simulated sweep's decoded samples: the replaced samples are the truth plus noise of exactly
    their predicted sigma, on the real samples' masks (``z`` of ~28 k values: mean 0 and SD 1, each within
    4 of its standard errors); without a seed, the truth itself at the given heights (to float32 rounding:
    values of a few mm); the input is not modified."""
    from ptpcore.io import SimulatedSource
    from ptpcore.run import collect_samples
    from ptpcore.simulate import VirtualRig, scaled_preset

    rig, settings = scaled_preset("mild", 96, positions=5)
    vr = VirtualRig(rig, settings, 3)
    samples = collect_samples(SimulatedSource(vr))
    before = samples.x.copy()
    fake = white_noise_samples(samples, rig, vr.truth(), seed=1)
    exact = white_noise_samples(samples, rig, vr.truth(), seed=None, heights=vr.truth().z_true)
    np.testing.assert_array_equal(samples.x, before)
    z = []
    for k in range(samples.z.size):
        tx, _ty = vr.truth().xy(np.full(samples.shape, samples.z[k]))
        x = fake.x_ref + fake.x[k]
        assert np.array_equal(np.isfinite(fake.x[k]), np.isfinite(samples.x[k]))
        ok = np.isfinite(x)
        z.append(((x - tx) / position_sigma_from_noise(samples, rig, k))[ok])
        tx_true, _ = vr.truth().xy(np.full(samples.shape, vr.truth().z_true[k]))
        np.testing.assert_allclose((exact.x_ref + exact.x[k])[ok], tx_true[ok], rtol=0, atol=1e-5)
    z = np.concatenate(z)
    assert z.size > 25_000
    assert abs(np.mean(z)) < 4 / np.sqrt(z.size) and abs(np.std(z) - 1) < 4 / np.sqrt(2 * z.size)
