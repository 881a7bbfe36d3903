"""The smooth LUT's leave-one-position-out without refits (issue 33).

Every pixel's fit without a position is its weighted least-squares fit with one sample less, so it
comes in closed form from the fit through all positions (Sherman-Morrison, METHOD.md section 5);
only the smoothing is redone per left-out position. These tests hold the closed form to the refit it
replaces.
"""

from __future__ import annotations

import numpy as np
import pytest

from ptpcore.fit import smooth as smooth_mod
from ptpcore.fit.smooth import leave_one_out as loo_mod
from ptpcore.fit.smooth.leave_one_out import downdated_fits
from ptpcore.fit.smooth.pixel_fits import SmoothPass, smoothed_coefficients, weighted_poly_fits


def test_downdated_fit_equals_the_fit_without_the_sample():
    """For every pixel: the fit without sample k from the closed form equals the refit with k's weight
    at 0 (coefficients and the inverse normal matrix's diagonal), NaN where fewer than D+1 samples
    remain, unchanged where k was not used."""
    rng = np.random.default_rng(1)
    degree, k_all, p = 3, 9, 400
    t = np.linspace(-1.0, 1.0, k_all)
    weights = rng.uniform(0.5, 4.0, (k_all, p))
    weights[:, :40] *= rng.random((k_all, 40)) < 0.5   # pixels with missing samples
    weights[4:, 40:50] = 0.0                           # exactly D+1 = 4 samples: without one, no fit
    values = [rng.standard_normal((k_all, p)) + 0.3 * t[:, None] ** 2 for _ in range(2)]
    coefs, _v, n, cov = weighted_poly_fits(t, values, weights, degree, full=True)
    for k in (0, 2, 5, 8):
        powers = t[k] ** np.arange(degree + 1)
        got, var, _r, _lev = downdated_fits(coefs, cov, n, weights[k], [v[k] for v in values], powers)
        w_k = weights.copy()
        w_k[k] = 0.0
        want, want_var, _n = weighted_poly_fits(t, values, w_k, degree)
        for g, wnt in zip(got, want):
            np.testing.assert_array_equal(np.isnan(g), np.isnan(wnt))
            np.testing.assert_allclose(g, wnt, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(var, want_var, rtol=1e-9, atol=1e-12)
        assert np.isnan(got[0][:, 40:50]).all() == (k < 4)  # only the pixels that lose one of their 4
        unused = weights[k] == 0
        np.testing.assert_array_equal(got[0][:, unused], coefs[0][:, unused])


_CLOSED_FORM = loo_mod._fit_without


def _refit_without(s, k, own, interior):
    """The leave-one-out before issue 33: every pixel refitted from the samples without position k."""
    keep = np.arange(s.z.size) != k
    run = SmoothPass(s.samples, s.rig, s.sel[keep], s.z[keep], s.z_norm, s.rays, s.degree, [s.scale],
                     s.cv_bin, s.level_bias, s.footprint, cross_validate=False, own=False)
    run.fit_and_cross_validate_fine(lambda f, m: None)
    coef = smoothed_coefficients(run.fits, s.scale, run.b, s.rays, *s.z_norm, variance=False)[0]
    _coef, noise, kept = _CLOSED_FORM(s, k, own, interior)  # the samples' noise and corrections, as before
    return coef, noise, kept


@pytest.fixture(scope="module")
def small_stack():
    """:func:`ptpcore.simulate.synthetic.synthetic_photometric_samples` (exact rays, each sample's own
    predicted noise, invalid regions that move with z) at 112 x 96 px, 9 positions: fast to make and to fit."""
    from ptpcore.simulate.synthetic import synthetic_photometric_samples

    samples, rig, _truth = synthetic_photometric_samples(0.01, 9, spill=False)
    return samples, rig


@pytest.mark.parametrize("cv_bin", [pytest.param(1, marks=pytest.mark.slow), 2])  # each ~10 s
def test_smooth_leave_one_out_in_closed_form_equals_the_refits(small_stack, monkeypatch, cv_bin):
    """The smooth LUT (per pixel, and on 2 x 2 bins as at 5 MP): the closed-form leave-one-out gives the
    refits' leave-one-out and sigma maps to rounding (1e-9 relative); every other map keeps its bits."""
    samples, rig = small_stack
    got, info = smooth_mod.fit_smooth_lut(samples, rig, 2, cv_bin=cv_bin, scales_px=(0.0, 2.0, 8.0))
    monkeypatch.setattr(loo_mod, "_fit_without", _refit_without)
    want, want_info = smooth_mod.fit_smooth_lut(samples, rig, 2, cv_bin=cv_bin, scales_px=(0.0, 2.0, 8.0))
    assert info.scale_px == want_info.scale_px > 0  # a smoothed LUT: the left-out fits are smoothed too
    for name in ("x", "y", "valid", "n_positions", "pixel_z_min", "pixel_z_max", "rms_x", "rms_y"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    for name in ("loo_x", "loo_y", "sigma_x", "sigma_y"):
        g, w = getattr(got, name), getattr(want, name)
        np.testing.assert_array_equal(np.isnan(g), np.isnan(w), err_msg=name)
        np.testing.assert_allclose(g, w, rtol=1e-9, err_msg=name)
    assert np.isfinite(got.loo_x[got.valid]).all()
    assert info.model_sigma_mm == pytest.approx(want_info.model_sigma_mm, rel=1e-9, abs=1e-15)


@pytest.mark.parametrize("b", [1, 2, 4])
def test_shared_weight_smoother_gives_smooth_on_bins_bits(b):
    """The leak variance's smoother (the weights' bins and local systems made once, issue 33) gives
    :func:`smooth_on_bins`'s very bits for every map, and leaves the input alone unless asked."""
    from ptpcore.fit.smooth.smoothing import SharedWeightSmoother, smooth_on_bins
    from ptpcore.store import FileRows

    rng = np.random.default_rng(3)
    h, w = 70, 90  # not multiples of the bins
    weights = np.where(rng.random((h, w)) < 0.8, rng.uniform(1.0, 8.0, (h, w)), 0.0)
    weights[:, :7] = 0.0
    spilled = FileRows((1, h, w))
    spilled[0, 0:h] = weights
    smoother = SharedWeightSmoother(spilled.plane_rows(0), 12.0, b)  # as the leak variance reads them
    for seed in range(3):
        field = np.random.default_rng(seed).standard_normal((h, w)).cumsum(axis=1)
        want = smooth_on_bins(field[None].copy(), weights, 12.0, b, False)[0][0]
        kept = field.copy()
        got = smoother.smooth(field, out=np.empty((h, w)))
        np.testing.assert_array_equal(field, kept)
        np.testing.assert_array_equal(got, want)
        assert smoother.smooth(field, out=field) is field  # in place, as the leak variance smooths
        np.testing.assert_array_equal(field, want)
