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


def _halves(rng, b2, n_even=5, n_odd=4, noise_var=1.0):
    """:func:`_excess` split as the fits split their interior positions: the sums over all of them,
    their count, the sums of squares, and ``(sums, count)`` over the ``n_odd`` of odd rank."""
    x = rng.standard_normal((n_even + n_odd,) + b2.shape) ** 2 * (noise_var + b2) - noise_var
    n = np.full(b2.shape, n_even + n_odd)
    return x.sum(axis=0), n, (x * x).sum(axis=0), (x[n_even:].sum(axis=0), np.full(b2.shape, n_odd))


def test_model_variance_map_follows_a_smooth_field():
    """A model variance rising linearly across the image from 0 to 2 (noise variance 1, 9 held-out samples
    per pixel, 4 of them of odd rank): the map follows it within 0.15 RMS (a kernel regression's
    statistical error at 8 px is about sqrt(2 * 2^2 / (9 * 4 pi 8^2)) = 0.03, the posterior's pull toward
    the prior adds to it), its mean is the data's level within 2 standard errors, and it is positive
    everywhere: the posterior mean never puts a pixel at nothing."""
    rng = np.random.default_rng(2)
    h, w = 120, 160
    b2 = np.tile(np.linspace(0.0, 2.0, w), (h, 1))
    e, n, e2, odd = _halves(rng, b2)
    var, scale, info = model_variance_map(e, n, excess_sq_sum=e2, odd=odd)
    assert info["spatial"] and info["resolved"] and scale in info["cv"]
    assert np.sqrt(np.mean((var - b2) ** 2)) < 0.15
    assert abs(var.mean() - info["mean"]) < info["limit"] and var.min() > 0


def test_the_split_half_validation_picks_a_scale_the_field_has():
    """A field that changes over 20 px gets a small kernel; a uniform one the largest, and its map is flat
    at the level (its spread is the map's noise, which the posterior takes out)."""
    rng = np.random.default_rng(5)
    h, w = 160, 200
    cols = np.arange(w)
    wavy = np.tile(1.0 + 0.9 * np.sin(2 * np.pi * cols / 40.0), (h, 1))
    e, n, e2, odd = _halves(rng, wavy, noise_var=0.3)
    assert model_variance_map(e, n, excess_sq_sum=e2, odd=odd)[1] <= 8.0
    e, n, e2, odd = _halves(rng, np.full((h, w), 0.05))
    flat, scale, info = model_variance_map(e, n, excess_sq_sum=e2, odd=odd)
    assert scale >= 64.0 and flat.max() - flat.min() < 0.05 * info["mean"]
    assert abs(info["mean"] - 0.05) < 1.5 * info["limit"]


def test_the_map_is_calibrated_per_decile_of_itself():
    """What issue 30 judges the sigma maps by: within each decile of the map, the true model variance's
    mean over the map's. A log-normal field (smooth over 12 px, 2.2x spread) under noise 3x its level:
    the posterior map is within the issue's bound for RMS(z), [0.7, 1.4], in every decile (three fields;
    measured 0.83-1.06). The kernel map floored at 0 under-predicted its lowest decile by 1.22-1.63x
    on the same data."""
    from ptpcore.fit.sigma import gaussian_blur

    for seed in range(3):
        rng = np.random.default_rng(10 + seed)
        f = gaussian_blur(rng.standard_normal((240, 320)), 12.0)
        b2 = 0.3 * np.exp(0.8 * f / f.std())
        e, n, e2, odd = _halves(rng, b2)
        var, scale, _ = model_variance_map(e, n, excess_sq_sum=e2, odd=odd)
        edges = np.quantile(var, np.linspace(0, 1, 11))
        dec = np.clip(np.searchsorted(edges, var, side="right") - 1, 0, 9)
        ratio = [b2[dec == q].mean() / var[dec == q].mean() for q in range(10)]
        assert 0.7 <= min(ratio) and max(ratio) <= 1.4, (seed, scale, np.round(ratio, 2))


def test_without_halves_or_with_nothing_resolved_the_map_is_uniform_or_zero():
    """Without the odd-rank sums (the height map) or with ``spatial=False`` the level everywhere; with no
    model error the image-wide mean is within its 2 standard errors and the map is 0."""
    rng = np.random.default_rng(3)
    b2 = np.tile(np.linspace(0.0, 2.0, 50), (40, 1))
    e, n, e2, odd = _halves(rng, b2)
    for kwargs in ({}, {"odd": odd, "spatial": False}):
        var, scale, info = model_variance_map(e, n, excess_sq_sum=e2, **kwargs)
        assert info["resolved"] and not info["spatial"] and np.isnan(scale)
        np.testing.assert_array_equal(var, np.full((40, 50), e.sum() / n.sum()))
    e, n, e2, odd = _halves(rng, 0.0 * b2)
    none, _, info = model_variance_map(e, n, excess_sq_sum=e2, odd=odd)
    assert (not info["resolved"]) == (info["mean"] <= info["limit"]) and (info["resolved"] or not none.any())


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
