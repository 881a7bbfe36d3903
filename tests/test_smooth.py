"""The smooth LUT (issue 8): beats 3DSTC on a Brown lens and the plain LUT on a rough one.

All comparisons are against the simulator's exact rays at held-out heights.
"""

import warnings

import numpy as np
import pytest

from ptpcore.accuracy import held_out_accuracy
from ptpcore.lut import fit_lut
from ptpcore.pinhole import fit_pinhole
from ptpcore.smooth import fit_smooth_lut, local_linear_smooth, poly_sigma_maps


def _split(samples):
    k = samples.z.size
    return list(range(0, k, 2)), list(range(1, k, 2))


def _threedstc_rms_um(vr, samples, cal, held, mask, n_points=2000, seed=0):
    """The paper's 3DSTC: pinhole + Brown from 2000 random feature points of the calibration positions."""
    rng = np.random.default_rng(seed)
    h, w = samples.shape
    pts, pix = [], []
    for k in cal:
        idx = np.flatnonzero(samples.valid[k].ravel())
        pick = rng.choice(idx, n_points // len(cal), replace=False)
        x, y = samples.absolute(k)
        r, c = np.divmod(pick, w)
        pts.append(np.stack([x.ravel()[pick], y.ravel()[pick], np.full(pick.size, samples.z[k])], 1))
        pix.append(np.stack([c, r], 1).astype(float))
    model = fit_pinhole(np.concatenate(pts), np.concatenate(pix)).model
    truth = vr.truth()
    rr, cc = np.mgrid[0:h, 0:w]
    errs = []
    for k in held:
        z = vr.rig.stage.z_mm[k]
        x, y = model.pixel_to_world_at_z(cc, rr, z)
        tx, ty = truth.xy(z)
        m = mask[k]
        errs.append(np.concatenate([(x - tx)[m], (y - ty)[m]]))
    e = np.concatenate(errs)
    return float(np.sqrt(np.mean(e * e)) * 1e3)


def test_local_linear_smoothing_keeps_linear_trends_and_predicts_its_noise():
    rng = np.random.default_rng(1)
    h, w = 80, 100
    rr, cc = np.mgrid[0:h, 0:w]
    trend = 0.3 + 0.01 * cc - 0.02 * rr
    weights = np.where(rng.random((h, w)) < 0.7, 4.0, 0.0)  # sigma 0.5 where present
    out, var = local_linear_smooth(trend, weights, 6.0)
    assert np.nanmax(np.abs(out - trend)) < 1e-9  # exact for a plane, edges included
    noisy = trend + rng.normal(0, 0.5, (h, w))
    est = np.stack([local_linear_smooth(trend + rng.normal(0, 0.5, (h, w)), weights, 6.0)[0] for _ in range(40)])
    spread = est.std(axis=0)
    inner = (slice(15, -15), slice(15, -15))
    ratio = spread[inner].mean() / np.sqrt(var[inner]).mean()
    assert 0.85 < ratio < 1.15  # 40 draws: the spread is known to ~ +-11 % (3 sigma)
    assert np.all(np.isfinite(local_linear_smooth(noisy, weights, 6.0)[0]))


def test_smooth_beats_3dstc_on_a_brown_lens(mild_rig):
    vr, samples = mild_rig
    cal, held = _split(samples)
    lut, info = fit_smooth_lut(samples, vr.rig, 1, cal)
    acc = held_out_accuracy(lut, vr.truth(), vr.rig.stage.z_mm, held)
    mask = {k: np.isfinite(acc.error_x[i]) for i, k in enumerate(held)}
    stc = _threedstc_rms_um(vr, samples, cal, held, mask)
    plain = held_out_accuracy(fit_lut(samples, "poly", 1, positions=cal), vr.truth(), vr.rig.stage.z_mm, held)
    assert acc.rms_um * 1.25 <= stc, (acc.rms_um, stc)
    assert stc < plain.rms_um  # the reason the smooth kind exists: plain loses to 3DSTC here
    assert info.scale_px >= 16  # a Brown lens needs almost no local correction


def test_smooth_beats_the_plain_lut_on_the_rough_preset(rough_rig):
    vr, samples = rough_rig
    cal, held = _split(samples)
    truth = vr.truth()
    lut, info = fit_smooth_lut(samples, vr.rig, 1, cal)
    smooth = held_out_accuracy(lut, truth, vr.rig.stage.z_mm, held)
    plain = held_out_accuracy(fit_lut(samples, "poly", 1, positions=cal), truth, vr.rig.stage.z_mm, held)
    assert smooth.rms_um * 1.25 <= plain.rms_um, (smooth.rms_um, plain.rms_um)
    assert lut.kind == "poly" and lut.extra_attrs["method"] == "smooth"
    # It still follows the non-parametric lens field that a pinhole model misses.
    mask = {k: np.isfinite(smooth.error_x[i]) for i, k in enumerate(held)}
    assert smooth.rms_um * 10 < _threedstc_rms_um(vr, samples, cal, held, mask)
    # The predicted sigma map explains the observed error over the image.
    m = np.isfinite(smooth.error_x[0]) & np.isfinite(lut.sigma_x)
    ratio = smooth.rms_um / (np.sqrt(np.mean(lut.sigma_x[m].astype(float) ** 2)) * 1e3)
    assert 0.7 <= ratio <= 1.4, ratio


def test_plain_lut_sigma_maps_agree_with_observed_errors_everywhere(rough_rig):
    """Observed RMS / predicted sigma within [0.7, 1.4] in every tile of a 4x4 grid."""
    vr, samples = rough_rig
    cal, held = _split(samples)
    lut = fit_lut(samples, "poly", 2, positions=cal)
    sx, sy = poly_sigma_maps(samples, vr.rig, lut, cal)
    acc = held_out_accuracy(lut, vr.truth(), vr.rig.stage.z_mm, held)
    with warnings.catch_warnings():  # pixels never in range are all-NaN: they stay NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        e2 = np.nanmean(np.concatenate([acc.error_x ** 2, acc.error_y ** 2]), axis=0)
    h, w = e2.shape
    ratios = []
    for i in range(4):
        for j in range(4):
            tile = (slice(i * h // 4, (i + 1) * h // 4), slice(j * w // 4, (j + 1) * w // 4))
            m = np.isfinite(e2[tile]) & np.isfinite(sx[tile])
            if m.sum() > 200:
                ratios.append(np.sqrt(e2[tile][m].mean()) / np.sqrt(np.mean(sx[tile][m].astype(float) ** 2)))
    assert len(ratios) >= 12
    assert 0.7 <= min(ratios) and max(ratios) <= 1.4, ratios


def test_binned_smoothing_keeps_linear_trends_and_follows_the_per_pixel_one():
    """The large-image path (bins of b x b px, interpolated back) is exact for planes, close otherwise."""
    from ptpcore.smooth import _smooth_binned

    rng = np.random.default_rng(2)
    h, w = 96, 130  # not multiples of the bin
    rr, cc = np.mgrid[0:h, 0:w]
    trend = 0.3 + 0.01 * cc - 0.02 * rr
    weights = np.where(rng.random((h, w)) < 0.7, rng.uniform(1.0, 8.0, (h, w)), 0.0)
    weights[:, :9] = 0.0  # an edge of the valid region that cuts through bins
    out, var = _smooth_binned(trend, weights, 16.0, 4)
    m = np.isfinite(out)
    assert m[:, 9:].all() and np.nanmax(np.abs(out - trend)) < 1e-9
    field = np.sin(cc / 25.0) + np.cos(rr / 30.0) + rng.normal(0, 0.5, (h, w))
    ref, ref_var = local_linear_smooth(field, weights, 16.0)
    got, got_var = _smooth_binned(field, weights, 16.0, 4)
    inner = (slice(10, -10), slice(20, -10))
    # A slightly different smoother (each pixel weighted by the Gaussian at its bin's centre):
    # the two estimates differ by a fraction of their own noise, not by a bias.
    diff = (got - ref)[inner] / np.sqrt(ref_var[inner])
    assert np.sqrt(np.mean(diff ** 2)) < 0.15 and np.max(np.abs(diff)) < 0.4 and abs(np.mean(diff)) < 0.04
    assert np.allclose(got_var[inner], ref_var[inner], rtol=0.1)


@pytest.mark.parametrize("which", ["rough", "mild"])
def test_binned_cross_validation_chooses_the_same_scale(which, rough_rig, mild_rig, monkeypatch):
    """Large images cross-validate large scales on bins and small ones per pixel in strips of rows:
    forced onto the 320x240 presets (2 and 4 px bins, strips of 40 rows) it picks the same scale, and
    the per-pixel scales score exactly as on the whole image."""
    import ptpcore.smooth as smooth

    vr, samples = rough_rig if which == "rough" else mild_rig
    cal, _ = _split(samples)
    _, ref = fit_smooth_lut(samples, vr.rig, 1, cal)
    monkeypatch.setattr(smooth, "_STRIP_ROWS", 40)
    for b in (2, 4):
        _, info = fit_smooth_lut(samples, vr.rig, 1, cal, cv_bin=b)
        assert info.scale_px == ref.scale_px, (b, info.cv_rms_mm, ref.cv_rms_mm)
        fine = ref.scales_px < 4 * b
        np.testing.assert_allclose(info.cv_rms_mm[fine], ref.cv_rms_mm[fine], rtol=1e-9)
