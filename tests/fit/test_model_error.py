"""The model's own part of the sigma maps (issue 30): mapped from held-out residuals' excess over noise."""

import json

import numpy as np
import pytest

from ptpcore.fit.sigma import model_variance_map


def _excess(rng, b2, n, noise_var=1.0, squares=False):
    """Per-pixel sums of ``n`` held-out samples' ``x = e^2 - noise_var`` with ``e ~ N(0, noise_var + b2)``:
    unbiased for ``b2``, as the fits' excess is (and the sums of ``x^2`` with ``squares``)."""
    x = rng.standard_normal((n,) + b2.shape) ** 2 * (noise_var + b2) - noise_var
    return (x.sum(axis=0), (x * x).sum(axis=0)) if squares else x.sum(axis=0)


def test_model_variance_map_follows_a_smooth_field_and_is_zero_without_one():
    """A model variance rising linearly across the image from 0 to 2 (noise variance 1, 9 held-out samples
    per pixel): the map follows it (RMS error below 0.15 where the field spans 2; the kernel regression's
    statistical error at the chosen scale is about sqrt(2 * 3^2 / (9 * 4 pi s^2))) and is >= 0.
    Without any model error the map's mean is within 0.05 of 0 (the image-wide mean's standard error
    is 1.4 / sqrt(9 * 19100) = 0.005)."""
    rng = np.random.default_rng(2)
    h, w, n = 120, 160, 9
    b2 = np.tile(np.linspace(0.0, 2.0, w), (h, 1))
    count = np.full((h, w), n)
    count[:10, :10] = 0  # a corner without held-out samples
    sums = np.where(count > 0, _excess(rng, b2, n), 0.0)
    var, scale, info = model_variance_map(sums, count, spatial=True)
    assert np.all(var >= 0) and scale in info["cv"] and info["radius_px"] == 3
    err = np.sqrt(np.mean((var - b2)[count > 0] ** 2))
    assert err < 0.15, (err, scale, info)
    flat, _, _ = model_variance_map(np.where(count > 0, _excess(rng, 0 * b2, n), 0.0), count, spatial=True)
    assert abs(flat[count > 0].mean()) < 0.05, flat.mean()
    # The map's mean is the data's mean excess (the floor at 0 does not lift it).
    np.testing.assert_allclose(np.sum(var * count) / count.sum(), sums.sum() / count.sum(), rtol=1e-9)
    # With the squares the data's resolution is judged: nothing to resolve, the map is 0; a small
    # uniform model error (0.05 of the noise variance, 20 standard errors here) is kept.
    e, e2 = _excess(rng, 0 * b2, n, squares=True)
    none, _, info = model_variance_map(e, np.full((h, w), n), excess_sq_sum=e2, spatial=True)
    assert (not info["resolved"]) == (info["mean"] <= info["limit"]) and (info["resolved"] or not none.any())
    e, e2 = _excess(rng, 0 * b2 + 0.05, n, squares=True)
    small, _, info = model_variance_map(e, np.full((h, w), n), excess_sq_sum=e2, spatial=True)
    assert info["resolved"] and abs(small.mean() - 0.05) < 3 * info["limit"] / 2


def test_correlated_neighbours_are_left_out_of_the_cross_validation():
    """The radius left out grows with the LUT's smoothing scale: 3 correlation lengths (sqrt(2) s + 1)."""
    count = np.ones((40, 40))
    for s, want in ((0.0, 3), (2.0, 12), (16.0, 71)):
        assert model_variance_map(np.zeros((40, 40)), count, s, scales_px=(4.0,), spatial=True)[2]["radius_px"] == want


@pytest.fixture(scope="module")
def realistic_96():
    from ptpcore.io import SimulatedSource
    from ptpcore.run import collect_samples
    from ptpcore.simulate import VirtualRig, scaled_preset

    rig, s = scaled_preset("realistic", 96)
    v = VirtualRig(rig, s, 1)
    return v, collect_samples(SimulatedSource(v))


@pytest.mark.parametrize("model,degree", [("poly", 2), pytest.param("smooth", 2, marks=pytest.mark.slow)])
def test_lut_carries_its_model_part_and_says_how(realistic_96, model, degree, tmp_path, capsys):
    """poly and smooth LUTs write /quality/sigma_model_x, _y, within the total sigma (noise and model in
    quadrature), /provenance model_error says how; ``ptp inspect`` prints both parts; the file keeps them."""
    from ptpcore.cli import main
    from ptpcore.fit import fit_model
    from ptpcore.io import load_lut, save_lut

    v, samples = realistic_96
    lut = fit_model(samples, v.rig, model, degree)
    m = lut.valid
    for a in "xy":
        total, part = getattr(lut, f"sigma_{a}")[m], getattr(lut, f"sigma_model_{a}")[m]
        assert np.all(np.isfinite(part)) and np.all(part >= 0) and np.all(part <= total * (1 + 1e-6))
    how = json.loads(lut.provenance["model_error"])
    assert "leave-one-position-out" in how["method"] and set(how["scale_px"]) == {"x", "y"}
    p = tmp_path / "l.lut.h5"
    save_lut(lut, p)
    back = load_lut(p)
    np.testing.assert_array_equal(back.sigma_model_y, lut.sigma_model_y)
    assert main(["inspect", str(p)]) == 0
    out = capsys.readouterr().out
    assert "noise part X" in out and "model part Y" in out


def test_an_unresolved_map_falls_back_to_the_level_not_to_zero():
    """A uniform model variance (0.05 of the noise variance): the kernel map's pixel-to-pixel spread is
    sampling noise, so the shrinkage (tau^2 = spread beyond the standard errors, about 0) puts every
    pixel at the image-wide level, where flooring the raw map would leave some near 0. The level is
    within 3 standard errors of 0.05."""
    rng = np.random.default_rng(7)
    h, w, n = 120, 160, 9
    e, e2 = _excess(rng, np.full((h, w), 0.05), n, squares=True)
    count = np.full((h, w), n)
    raw, _, _ = model_variance_map(e, count, excess_sq_sum=e2, shrink=False, scales_px=(4.0,), spatial=True)
    shrunk, _, info = model_variance_map(e, count, excess_sq_sum=e2, scales_px=(4.0,), spatial=True)
    assert raw.min() < 0.5 * info["mean"]  # the raw map at 4 px is noisy
    assert shrunk.max() - shrunk.min() < 0.2 * info["mean"], (shrunk.min(), shrunk.max())
    assert abs(info["mean"] - 0.05) < 1.5 * info["limit"]


def test_the_default_map_is_the_uniform_level():
    """MODEL_MAP_SPATIAL off (the harness's verdict, issue 30): the level everywhere when resolved."""
    from ptpcore.fit.sigma import MODEL_MAP_SPATIAL

    rng = np.random.default_rng(3)
    e, e2 = _excess(rng, np.tile(np.linspace(0.0, 2.0, 50), (40, 1)), 9, squares=True)
    var, scale, info = model_variance_map(e, np.full((40, 50), 9), excess_sq_sum=e2)
    assert not MODEL_MAP_SPATIAL and info["resolved"] and np.isnan(scale)
    np.testing.assert_array_equal(var, np.full((40, 50), e.sum() / (9 * 2000)))
