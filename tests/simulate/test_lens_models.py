"""Lens models beyond Brown plus a smooth field, and rigs drawn per seed (issue 30).

The truth rays of every new lens are checked against an independent forward
projection (:func:`ptpcore.simulate.lens_models.project_world`: ray -> pixel,
the simulator's rays being pixel -> ray) at several heights; the inverse maps
round-trip; the existing presets go through exactly the code path they did
before (rays equal to the pre-existing Brown formula bit for bit, settings
records without the new keys).
"""

import json
from dataclasses import replace

import numpy as np
import pytest

from ptpcore.errors import ConfigError
from ptpcore.pinhole.lens import undistort_normalised
from ptpcore.simulate import (LENS_MODELS, PRESETS, VirtualRig, base_rig, draw_rig, lens_model_rig, preset,
                              scaled_preset)
from ptpcore.simulate import lens_models
from ptpcore.simulate.virtual_rig import _settings_json, settings_from_json


def _pixels(rig, step=37):
    """A grid of pixel centres over the whole image, corners included."""
    h, w = rig.camera.shape
    rows = np.unique(np.r_[np.arange(0, h, step), h - 1])
    cols = np.unique(np.r_[np.arange(0, w, step), w - 1])
    return np.meshgrid(rows, cols, indexing="ij")


def _combined():
    """Every term at once: equidistant, prism, ripple, the smooth field and a non-central pupil."""
    rig, s = lens_model_rig("fisheye")
    lens = replace(s.lens, prism=(1.5e-3, -8e-4, -1e-3, 6e-4), ripple_px=0.08, ripple_wavelength_px=30.0,
                   field_amplitude_px=0.6, pupil_shift_mm=0.8)
    return rig, replace(s, name="combined", lens=lens)


def _true_xy(vr, rows, cols, z, truth=None):
    """True X, Y (mm) of pixels at height z: from ``truth`` (``vr.truth()``, the whole image as
    truth.h5 holds it) or from the same rays on the given pixels only (faster)."""
    if truth is not None:
        x, y = truth.xy(z)
        return x[rows, cols], y[rows, cols]
    o, d = vr.rays(cols.astype(float), rows.astype(float))
    t = (z - o[..., 2]) / d[..., 2]
    return o[..., 0] + t * d[..., 0], o[..., 1] + t * d[..., 1]


@pytest.mark.parametrize("name", [*LENS_MODELS, "combined"])
def test_truth_rays_project_back_to_their_pixels(name):
    """At four heights, each pixel's true ray meets the plane at a point the forward map sends back
    to that pixel (within 1e-7 px: the Newton inverse and the fixed points converge fully). The
    lens with every term is checked on ``truth()`` itself, the others on the rays it is made of."""
    rig, s = _combined() if name == "combined" else lens_model_rig(name)
    vr = VirtualRig(rig, s, seed=5)
    rows, cols = _pixels(rig)
    truth = vr.truth() if name == "combined" else None
    for z in (-3.0, 0.0, 17.3, 40.0):
        x, y = _true_xy(vr, rows, cols, z, truth)
        pts = np.stack([x, y, np.full(rows.shape, z)], axis=-1)
        pc, pr = lens_models.project_world(vr, pts)
        assert np.max(np.abs(pc - cols)) < 1e-7, (name, z)
        assert np.max(np.abs(pr - rows)) < 1e-7, (name, z)


def test_each_lens_model_leaves_the_brown_family_where_it_says():
    """The new terms move the rays: the fisheye's corners by many pixels against a pinhole of the
    same focal length, the prism's by about its size, the ripple's by about its amplitude at a short
    scale (it changes sign within a few tens of pixels)."""
    out = {}
    for name in LENS_MODELS:
        rig, s = lens_model_rig(name)
        plain = replace(s.lens, projection="perspective", prism=(0.0, 0.0, 0.0, 0.0), ripple_px=0.0)
        rows, cols = _pixels(rig, step=8)
        a = VirtualRig(rig, s, seed=2).rays(cols, rows)[1]
        b = VirtualRig(rig, replace(s, lens=plain), seed=2).rays(cols, rows)[1]
        tx = a[..., 0] / a[..., 2] - b[..., 0] / b[..., 2]  # tangent difference x
        out[name] = tx * s.lens.focal_px  # ~ px
    assert np.max(np.abs(out["fisheye"])) > 20.0
    assert 0.1 < np.max(np.abs(out["prism"])) < 2.0
    ripple = out["ripple"]
    assert 0.02 < np.sqrt(np.mean(ripple ** 2)) < 0.2
    # Short scale: neighbours 8 px apart already decorrelate well below the whole-image field.
    c = np.corrcoef(ripple[:, :-2].ravel(), ripple[:, 2:].ravel())[0, 1]
    assert c < 0.5


@pytest.mark.parametrize("name", [*LENS_MODELS, "combined"])
def test_inverse_maps_round_trip(name):
    """tangent -> image -> tangent and image -> tangent -> image to 1e-13 (normalised)."""
    _rig, s = _combined() if name == "combined" else lens_model_rig(name)
    lens, dist = s.lens, np.asarray(s.lens.dist)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.9, 0.9, (2, 2000))
    xd, yd = lens_models.tangent_to_image(x, y, lens, dist)
    x2, y2 = lens_models.image_to_tangent(xd, yd, lens, dist)
    assert np.max(np.abs(x2 - x)) < 1e-13 and np.max(np.abs(y2 - y)) < 1e-13
    a, b = rng.uniform(-0.6, 0.6, (2, 2000))
    xt, yt = lens_models.image_to_tangent(a, b, lens, dist)
    a2, b2 = lens_models.tangent_to_image(xt, yt, lens, dist)
    assert np.max(np.abs(a2 - a)) < 1e-13 and np.max(np.abs(b2 - b)) < 1e-13


def test_a_lens_without_the_new_terms_takes_the_brown_path_bit_for_bit():
    """Existing presets: rays as the Brown formula gives them (same function, same arguments), and
    settings records without the new keys (truth.h5 byte-identical), read back equal."""
    rng = np.random.default_rng(1)
    xd, yd = rng.uniform(-0.5, 0.5, (2, 500))
    for name in PRESETS:
        rig, s = preset(name)
        assert not lens_models.uses_extensions(s.lens)
        got = lens_models.image_to_tangent(xd, yd, s.lens, np.asarray(s.lens.dist))
        want = undistort_normalised(xd, yd, np.asarray(s.lens.dist))
        assert all(np.array_equal(g, w) for g, w in zip(got, want)), name
        record = json.loads(_settings_json(s, 3))
        assert not set(lens_models.NEW_LENS_KEYS) & set(record["lens"]), name
        assert settings_from_json(_settings_json(s, 3)) == (s, 3)
    rig, s = scaled_preset("rough", 96)
    vr = VirtualRig(rig, s, seed=4)
    rows, cols = _pixels(rig, step=5)
    o, d = vr.rays(cols, rows)
    fx, fy = vr.distortion_field(cols.astype(float), rows.astype(float))
    x, y = undistort_normalised((cols - fx - vr.K[0, 2]) / vr.K[0, 0], (rows - fy - vr.K[1, 2]) / vr.K[1, 1], vr.dist)
    assert np.array_equal(d[..., 0], (np.stack([x, y, np.ones_like(x)], -1) @ vr.R)[..., 0])


def test_new_lens_settings_round_trip_through_the_truth_record():
    for name in LENS_MODELS:
        _rig, s = lens_model_rig(name)
        assert lens_models.uses_extensions(s.lens)
        assert settings_from_json(_settings_json(s, 9)) == (s, 9)


def test_a_folding_ripple_is_refused():
    with pytest.raises(ConfigError, match="folds"):
        lens_models.RippleField(2.0, 8.0, np.random.default_rng(0))


@pytest.mark.parametrize("name", ["mild", "realistic", "rough", "real", "fisheye", "ripple"])
def test_rig_draws_are_seeded_new_rigs(name):
    """Same seed, same rig; another seed, another lens, pose and stage; glass drawn (and declared)
    only where the base has one; the drawn lens invertible over the whole image."""
    base = base_rig(name)
    a, b, c = draw_rig(base, name, 1), draw_rig(base, name, 1), draw_rig(base, name, 2)
    assert a == b and a != c
    (rig_a, s_a), (_rig_c, s_c) = a, c
    assert s_a.lens.focal_px != s_c.lens.focal_px and s_a.lens.dist != s_c.lens.dist
    assert s_a.tilt_deg != s_c.tilt_deg and s_a.stage_error_um != s_c.stage_error_um
    assert s_a.name == f"{name}#1" and rig_a.camera == base[0].camera and rig_a.stage.z_mm == base[0].stage.z_mm
    assert tuple(rig_a.stage.direction[:2]) == s_a.skew  # the rig declares its true travel
    if base[1].cover_glass_mm > 0:
        assert s_a.cover_glass_mm != base[1].cover_glass_mm and rig_a.lcd.cover_glass_mm == s_a.cover_glass_mm
    else:
        assert s_a.cover_glass_mm == 0.0
    rows, cols = _pixels(rig_a, step=16)
    _o, d = VirtualRig(rig_a, s_a, seed=1).rays(cols, rows)
    assert np.isfinite(d).all()


def test_another_sweep_of_the_same_rig_has_its_own_noise_only():
    """``noise_seed``: the same rays, stage errors and poses, other noise; equal to ``seed`` it is
    the rig as before."""
    rig, s = scaled_preset("real", 64, positions=3)
    a, b, same = VirtualRig(rig, s, 5), VirtualRig(rig, s, 5, noise_seed=6), VirtualRig(rig, s, 5, noise_seed=5)
    ta, tb = a.truth(), b.truth()
    assert all(np.array_equal(getattr(ta, n), getattr(tb, n)) for n in ("x0", "y0", "sx", "sy", "z_true", "stage_pose"))
    frame = (1, "x", rig.fringes.periods_px[-1], 1, rig.fringes.steps[-1])
    assert not np.array_equal(a.render(*frame), b.render(*frame))
    assert np.array_equal(a.render(*frame), same.render(*frame))
    assert json.loads(_settings_json(s, 5, 6))["noise_seed"] == 6 and "noise_seed" not in _settings_json(s, 5, 5)
    assert settings_from_json(_settings_json(s, 5, 6)) == (s, 5)
