"""Robust per-pixel fits (issue 16): outliers left out and counted, a wrong position named suspect."""

import json
from dataclasses import replace

import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.evaluate import held_out_accuracy
from ptpcore.fit import fit_model
from ptpcore.fit.robust import K_SIGMA, fit_robust, screen_samples
from ptpcore.fit.smooth import sample_sigma_from_noise
from ptpcore.io import load_lut, save_lut


@pytest.fixture(scope="module")
def mild(mild_21_positions):
    return mild_21_positions  # shared with test_choice.py (tests/fit/conftest.py)


def _copy(samples):
    return replace(samples, x=samples.x.copy(), y=samples.y.copy(), reasons=samples.reasons.copy(),
                   modulation=samples.modulation.copy(), background=samples.background.copy())


def test_a_clean_dataset_loses_almost_nothing(mild):
    vr, samples = mild
    rep = screen_samples(samples, vr.rig)
    n_valid = int(samples.valid.sum())
    # Gaussian noise beyond 5 sigma (either axis, after the fit): ~1e-6 of the samples
    assert rep.n_outliers <= 1e-4 * n_valid and not rep.suspect
    assert 1.0 <= rep.noise_scale < 1.2  # the noise model holds on the simulator


def test_one_dusty_sample_is_left_out_and_counted(mild, tmp_path):
    vr, samples = mild
    bad = _copy(samples)
    sig = sample_sigma_from_noise(samples, vr.rig)
    r, c, k = 40, 70, 8
    bad.x[k, r, c] += 30 * sig[k, r, c]  # a speck of dust: 30 predicted sigmas off in X
    lut, rep = fit_robust(bad, vr.rig, "poly", 3)
    assert rep.rejected_at(k)[r, c] and lut.n_rejected[r, c] == 1  # every position screened: index k
    assert bad.reasons[k, r, c] == 0  # the caller's samples are left alone; the fit saw Reason.OUTLIER
    assert rep.n_outliers <= 1e-4 * samples.valid.sum() + 1 and not rep.suspect
    clean = fit_model(samples, vr.rig, "poly", 3)
    ref = fit_model(samples, vr.rig, "poly", 3, positions=[i for i in range(21) if i != k])
    # the pixel's curve is the one fitted without the sample, not the one pulled by it
    np.testing.assert_allclose(lut.x[:, r, c], ref.x[:, r, c], rtol=0, atol=1e-9)
    assert abs(clean.x[0, r, c] - lut.x[0, r, c]) < 3 * sig[k, r, c]
    path = tmp_path / "r.lut.h5"
    save_lut(lut, path)
    back = load_lut(path)
    assert back.n_rejected[r, c] == 1 and json.loads(back.provenance["robust"])["k_sigma"] == K_SIGMA


def test_a_position_with_another_positions_images_is_named_suspect(mild, tmp_path, capsys):
    """Must show (issue 16): position 11's images replaced by position 13's (both calibration positions):
    position 11 is named suspect, and the default LUT's error at held-out heights stays within 1.2x
    of the clean dataset's."""
    vr, samples = mild
    bad = _copy(samples)
    for name in ("x", "y", "reasons", "modulation", "background"):
        getattr(bad, name)[10] = getattr(samples, name)[12]
    truth, z = vr.truth(), vr.rig.stage.z_mm
    cal, held = list(range(0, 21, 2)), list(range(1, 21, 2))
    clean = held_out_accuracy(fit_model(samples, vr.rig, "auto", positions=cal, robust=True), truth, z, held)
    lut, rep = fit_robust(bad, vr.rig, "auto", positions=cal)
    assert rep.suspect == [10]
    robust = held_out_accuracy(lut, truth, z, held)
    plain = held_out_accuracy(fit_model(bad, vr.rig, "poly", 3, positions=cal), truth, z, held)
    print(f"held-out RMS clean {clean.rms_um:.3f} um, robust {robust.rms_um:.3f} um,"
          f" without the robust fit (poly 3) {plain.rms_um:.3f} um")
    assert robust.rms_um <= 1.2 * clean.rms_um
    assert plain.rms_um > 5 * clean.rms_um  # the damage the robust fit undoes
    path = tmp_path / "bad.lut.h5"
    save_lut(lut, path)
    assert main(["inspect", str(path)]) == 0
    assert "SUSPECT             position 10, z = " in capsys.readouterr().out


def test_k_sigma_must_be_positive(mild):
    vr, samples = mild
    with pytest.raises(ValueError):
        screen_samples(samples, vr.rig, k_sigma=0)


def test_the_calibrate_page_names_a_suspect_position():
    pytest.importorskip("PySide6")
    from ptp_studio.pages.calibrate import robust_text
    from ptpcore.evaluate import RobustFit

    record = json.dumps({"n_rejected": 120, "k_sigma": 5.0, "suspect_positions": [3],
                         "rejected_fraction": {"3": 0.97}})
    text = robust_text(RobustFit.from_json(record))
    assert "120 samples left out" in text and "SUSPECT position 3" in text and "97 %" in text


def test_without_outliers_of_a_spilled_stack_stays_spilled(rough_rig):
    """Issue 15: a spilled stack's flagged copy of ``reasons`` goes to a spill file of its own (read
    block by block, not held), with the same flags as the in-memory copy."""
    from dataclasses import replace

    from ptpcore.fit.robust import screen_samples, without_outliers
    from ptpcore.store import SpillStore, read_block

    vr, samples = rough_rig
    rep = screen_samples(samples, vr.rig, positions=list(range(1, samples.z.size)))
    for i in range(len(rep.positions)):  # some flags for sure
        mask = rep.rejected_at(i)
        mask[10:12, 20:25] = True
        rep.set_rejected(i, mask)
    store = SpillStore(samples.z.size, samples.shape, {"reasons": np.uint8}, {})
    for k in range(samples.z.size):
        store.write("reasons", k, np.asarray(samples.reasons[k]))
    spilled = replace(samples, reasons=store.arrays()["reasons"])
    want = without_outliers(samples, rep).reasons
    got = without_outliers(spilled, rep).reasons
    assert isinstance(got, np.memmap) and got is not spilled.reasons
    h, w = samples.shape
    np.testing.assert_array_equal(read_block(got, 0, h * w).reshape(want.shape), want)
