"""The per-pixel height map u_p -> Z (METHOD.md section 9) against the simulator's exact truth."""

from dataclasses import replace

import h5py
import numpy as np
import pytest

from ptpcore.errors import FileFormatError
from ptpcore.evaluate.scanner import height_map_accuracy
from ptpcore.fit.height import Q_MAX, fit_height_map
from ptpcore.io.lutfile import Lut, load_lut, save_lut
from ptpcore.run.scanner import decode_projector
from ptpcore.simulate.scanner import HeightSweepSource, ProjectorSettings, ScannerRig, scanner_preset

HONEST = (0.8, 1.25)  # the trust issue's band for RMS(error / sigma)


def _rig(name="scanner-mild", width=96, heights=11, seed=2, **projector):
    rig, sim, sc = scanner_preset(name, width, heights=heights)
    if projector:
        sc = replace(sc, projector=replace(sc.projector, **projector))
    return ScannerRig(rig, sim, sc, seed)


def _true_sweep(sr):
    """The exact u_p of every pixel at every height of the sweep (no noise), (K, H, W)."""
    return np.stack([sr.true_up(z) for z in sr.rig.height.z_mm])


@pytest.fixture(scope="module")
def mild_sweep():
    sr = _rig()
    return sr, decode_projector(HeightSweepSource(sr))


def test_pinhole_projector_is_exactly_rational_of_degree_1():
    """Without distortion, Z(u_p) along a ray is a linear fraction: degree 1 reproduces the truth
    at heights it never saw to rounding (exact data, no noise)."""
    sr = _rig(dist=(0.0, 0.0, 0.0, 0.0, 0.0))
    z = np.asarray(sr.rig.height.z_mm)
    u = _true_sweep(sr)
    hm = fit_height_map(u, np.full(u.shape, 0.05), z, degree=1, positions=np.arange(0, z.size, 2))
    acc = height_map_accuracy(hm, sr, z[1::2])
    assert acc.coverage == 1.0 and acc.max_um < 1e-6
    assert np.all(np.abs(hm.q[0]) < Q_MAX)


def test_degree_follows_the_bend_beyond_the_noise():
    """Exact data of the rough projector (its distortion and field bend Z(u_p)) need a degree above 1;
    the same bend under the camera's noise does not show, and degree 1 is kept."""
    sr = _rig("scanner-rough")
    z = np.asarray(sr.rig.height.z_mm)
    u = _true_sweep(sr)
    rng = np.random.default_rng(0)
    tiny = 1e-4
    exact = fit_height_map(u + rng.normal(0, tiny, u.shape), np.full(u.shape, tiny), z)
    assert exact.degree > 1, exact.provenance
    noisy = fit_height_map(u + rng.normal(0, 0.1, u.shape), np.full(u.shape, 0.1), z)
    assert noisy.degree == 1, noisy.provenance


def test_held_out_heights_within_the_predicted_sigma(mild_sweep):
    """Fitted on every second height of a decoded sweep; at the others, the map read at the true u_p
    errs by its predicted sigma: RMS(error / sigma_z) in the honesty band."""
    sr, dec = mild_sweep
    z = dec.z_mm
    hm = fit_height_map(dec.u, dec.sigma_u, z, positions=np.arange(0, z.size, 2))
    acc = height_map_accuracy(hm, sr, z[1::2])
    assert acc.coverage > 0.99
    assert HONEST[0] <= acc.rms_z <= HONEST[1], acc


def test_model_error_enters_sigma_when_the_degree_cannot_follow():
    """Degree 1 forced on the rough projector's nearly exact data: held-out positions show the bend,
    the model part carries it, and the sigma stays honest (not the noise part alone, far below)."""
    sr = _rig("scanner-rough", heights=21)
    z = np.asarray(sr.rig.height.z_mm)
    u = _true_sweep(sr)
    sig = 0.002
    u = u + np.random.default_rng(1).normal(0, sig, u.shape)
    hm = fit_height_map(u, np.full(u.shape, sig), z, degree=1, positions=np.arange(0, z.size, 2))
    assert hm.provenance["model_error"]["resolved"]
    assert np.nanmedian(hm.sigma_model_z) > 2 * np.nanmedian(np.sqrt(hm.sigma_z ** 2 - hm.sigma_model_z ** 2))
    acc = height_map_accuracy(hm, sr, z[1::2])
    assert HONEST[0] <= acc.rms_z <= HONEST[1], acc


def test_outliers_are_left_out(mild_sweep):
    """Samples 40 sigma off (dust, a bad frame) are rejected, one per corrupted pixel, and the map is
    the one fitted without them, to 0.1 % of its sigma (the rational form does not depend on the
    normalisation; the reweighting, a fixed number of passes, starts elsewhere)."""
    sr, dec = mild_sweep
    clean = fit_height_map(dec.u, dec.sigma_u, dec.z_mm, degree=1)
    u = dec.u.copy()
    without = dec.u.copy()
    rng = np.random.default_rng(3)
    h, w = u.shape[1:]
    cells = {(int(r), int(c)) for r, c in zip(rng.integers(0, h, 40), rng.integers(0, w, 40))}
    for r, c in cells:
        u[5, r, c] += 40 * dec.sigma_u[5, r, c]
        without[5, r, c] = np.nan
    dirty = fit_height_map(u, dec.sigma_u, dec.z_mm, degree=1)
    assert int(dirty.n_rejected.sum()) - int(clean.n_rejected.sum()) == len(cells)
    test_u = sr.true_up(17.0)
    ref = fit_height_map(without, dec.sigma_u, dec.z_mm, degree=1).evaluate(test_u).z
    assert np.nanmax(np.abs(dirty.evaluate(test_u).z - ref) / clean.sigma_z) < 1e-3
    assert np.nanmax(np.abs(clean.evaluate(test_u).z - ref) / clean.sigma_z) > 1e-2  # the sample mattered


def test_outside_the_calibrated_range_is_flagged_not_extrapolated(mild_sweep):
    sr, dec = mild_sweep
    hm = fit_height_map(dec.u, dec.sigma_u, dec.z_mm, degree=1)
    beyond = sr.true_up(max(dec.z_mm) + 3.0)
    ev = hm.evaluate(beyond)
    assert not ev.in_range.any() and np.all(np.isnan(ev.z))
    inside = hm.evaluate(sr.true_up(10.0))
    assert inside.in_range.mean() > 0.99


def test_lut_file_round_trip_and_damaged_height(mild_sweep, tmp_path):
    _sr, dec = mild_sweep
    hm = fit_height_map(dec.u, dec.sigma_u, dec.z_mm, design={"width": 1280, "height": 800,
                                                              "periods_px": [1280.0, 320.0, 80.0],
                                                              "steps": [4, 4, 8], "phase_origin_rad": 0.0,
                                                              "shift_sign": 1, "unwrap": "periods"})
    h, w = hm.shape
    nan = np.full((h, w), np.nan, np.float32)
    lut = Lut("poly", 1, 20.0, 20.0, 0.0, 40.0, np.zeros((2, h, w)), np.zeros((2, h, w)), None,
              np.ones((h, w), bool), np.full((h, w), 11, np.uint16), np.zeros((h, w), np.float32),
              np.full((h, w), 40.0, np.float32), nan, nan, nan, nan, height=hm)
    path = tmp_path / "scanner.lut.h5"
    save_lut(lut, path)
    back = load_lut(path).height
    assert back.degree == hm.degree and back.design["periods_px"] == [1280.0, 320.0, 80.0]
    for name in ("p", "q", "u_center", "u_scale", "valid", "sigma_z", "u_min", "u_max"):
        np.testing.assert_array_equal(getattr(back, name), getattr(hm, name))
    with h5py.File(path, "r+") as f:
        f["height/q"][0, 3, 4] = 1.5
    with pytest.raises(FileFormatError, match="/height/q"):
        load_lut(path)
    save_lut(lut, path)
    with h5py.File(path, "r+") as f:
        del f["height/quality/sigma_z"]
    with pytest.raises(FileFormatError, match="/height/quality/sigma_z"):
        load_lut(path)


def test_diff_of_two_sweeps_is_consistent_and_sees_a_shift():
    """Two sweeps of one scanner (another noise draw): their height maps differ by their predicted
    sigma (observed / predicted in the honesty band, consistent); 5 sigma added to one is seen."""
    from ptpcore.evaluate.scanner import diff_height_maps

    maps = []
    for seed in (6, 7):  # the mild scanner's geometry does not depend on the seed; its noise does
        sr = _rig(seed=seed)
        dec = decode_projector(HeightSweepSource(sr))
        maps.append(fit_height_map(dec.u, dec.sigma_u, dec.z_mm, degree=1))
    a, b = maps
    r = diff_height_maps(a, b)
    assert r.consistent and HONEST[0] <= r.ratio <= HONEST[1], r.summary()
    shifted = replace(b, p=b.p + np.array([5.0, 0.0])[:, None, None] * np.sqrt(a.sigma_z ** 2 + b.sigma_z ** 2))
    assert not diff_height_maps(a, shifted).consistent
