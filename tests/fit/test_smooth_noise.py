"""The smooth LUT's noise part (issue 30): smoothed coefficient covariances and the noise scale's degrees of freedom."""

import numpy as np
import pytest

from ptpcore.fit.smooth.noise import residual_dof_variance
from ptpcore.fit.smooth.smoothing import smooth_on_bins, smoothed_covariance


@pytest.mark.parametrize("b, scale", [(1, 4.0), (2, 8.0)])
def test_two_maps_smoothed_with_their_own_weights_covary_as_predicted(b, scale):
    """Monte Carlo: two maps with per-pixel correlated noise, each smoothed with its own inverse-variance
    weights (other spatial patterns), per pixel and on bins: the empirical covariance of the smoothed
    maps against smoothed_covariance; the map with itself gives smooth_on_bins' own variance."""
    rng = np.random.default_rng(1)
    h, w, n = 80, 120, 400
    yy, xx = np.mgrid[0:h, 0:w]
    sa, sb = 1 + 0.8 * xx / w, 2 - 1.5 * (yy / h) ** 2
    rho = -0.8 + 0.3 * xx / w
    wa, wb = 1 / sa ** 2, 1 / sb ** 2
    wa[:4, :6] = 0.0  # a hole in one map
    a_maps, b_maps = [], []
    for _ in range(n):
        z1, z2 = rng.standard_normal((2, h, w))
        a_maps.append(smooth_on_bins(sa * z1, wa, scale, b, False)[0])
        b_maps.append(smooth_on_bins(sb * (rho * z1 + np.sqrt(1 - rho ** 2) * z2), wb, scale, b, False)[0])
    a_maps, b_maps = np.array(a_maps), np.array(b_maps)
    emp = np.sum((a_maps - a_maps.mean(0)) * (b_maps - b_maps.mean(0)), axis=0) / (n - 1)
    pred = smoothed_covariance(wa, wb, wa * wb * rho * sa * sb, scale, b)
    ok = np.isfinite(pred)
    assert ok.mean() > 0.99
    # The image's mean of the empirical covariance: the smoothed pixels are correlated over the scale,
    # so it averages about n (h w) / (4 pi scale^2) independent pairs, each of relative variance
    # (1 + rho^2) / rho^2; four standard errors allowed (inner part and border strip, each its own area).
    for part in (np.s_[10:-10, 10:-10], np.s_[:, :12]):
        area = ok[part].sum()
        r2 = np.mean(rho[part] ** 2)
        tol = 4 * np.sqrt((1 + r2) / r2 / (n * area / (4 * np.pi * scale ** 2)))
        assert np.mean(emp[part][ok[part]]) / np.mean(pred[part][ok[part]]) == pytest.approx(1.0, abs=tol)
    same = smoothed_covariance(wa, wa, wa, scale, b)
    np.testing.assert_allclose(same, smooth_on_bins(np.zeros((h, w)), wa, scale, b, True)[1], rtol=1e-12)


def test_residual_variance_counts_each_samples_leverage():
    """An unweighted degree-2 fit of samples whose noise grows towards the ends: the expected residual
    sum of squares (Monte Carlo) is sum (1 - h_kk) sigma_k^2, not (n - 3) mean(sigma^2)."""
    rng = np.random.default_rng(2)
    t = np.linspace(-1, 1, 11)
    sig = (1 + 2 * t ** 2)[:, None] * np.ones((1, 3))
    valid = np.ones((11, 3), bool)
    valid[[0, 4], 1] = False  # a pixel without two of its positions
    valid[3:, 2] = False      # one with too few (3 samples, degree 2): NaN
    got = residual_dof_variance(t, valid, sig, 2)
    assert np.isnan(got[2])
    for p in (0, 1):
        k = valid[:, p]
        v = np.vander(t[k], 3, increasing=True)
        noise = rng.standard_normal((20000, k.sum())) * sig[k, p]
        resid = noise - noise @ (v @ np.linalg.pinv(v)).T
        emp = np.mean(np.sum(resid ** 2, axis=1)) / (k.sum() - 3)
        assert got[p] == pytest.approx(emp, rel=0.02)  # 20 000 draws: standard error ~0.5 %
        assert got[p] < 0.95 * np.mean(sig[k, p] ** 2)  # the ends' noise is the less seen
