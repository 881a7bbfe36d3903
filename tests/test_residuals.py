"""Residual diagnostics (issue 16): per position the residual field as arrows and its RMS, worst first."""

from dataclasses import replace

import numpy as np
import pytest

from ptpcore.evaluate.residuals import residual_field, residual_png
from ptpcore.fit import fit_model
from ptpcore.io import SimulatedSource
from ptpcore.run import collect_samples
from ptpcore.simulate import VirtualRig, scaled_preset


@pytest.fixture(scope="module")
def mild():
    rig, settings = scaled_preset("mild", 160, positions=11)
    vr = VirtualRig(rig, settings, 2)
    return vr, collect_samples(SimulatedSource(vr))


def test_a_sideways_stage_move_shows_as_parallel_arrows(mild, tmp_path):
    """Position 6 held out of the fit and moved 50 um in +X (the stage slipped sideways): its arrows
    are the clean ones plus exactly that shift, it is listed first, and the other positions are unchanged."""
    vr, samples = mild
    k, shift = 5, 0.050
    moved = replace(samples, x=samples.x.copy())
    moved.x[k] += np.float32(shift)
    fit_on = [i for i in range(samples.z.size) if i != k]
    lut = fit_model(moved, vr.rig, "poly", 3, positions=fit_on)
    f = residual_field(lut, moved, fit_on, block=16)
    clean = residual_field(lut, samples, fit_on, block=16)
    assert f.worst_positions[0] == k and not f.used[k] and f.used[fit_on].all()
    ok = np.isfinite(f.dx[k])
    assert ok.sum() > 0.8 * ok.size
    np.testing.assert_allclose(f.dx[k][ok] - clean.dx[k][ok], shift, atol=1e-5)  # float32 samples: nm
    np.testing.assert_allclose(f.dy[k][ok], clean.dy[k][ok], atol=1e-9)
    np.testing.assert_allclose(np.delete(f.rms_um, k), np.delete(clean.rms_um, k), rtol=1e-9)
    assert f.rms_um[k] > 0.9 * shift * 1e3 > 2 * np.max(np.delete(f.rms_um, k))
    # the worst pixels are real pixels ranked by their RMS over positions
    r, c = f.worst_pixels[0]
    assert f.pixel_rms_um[r, c] == np.nanmax(f.pixel_rms_um)
    assert f.lines()[0].startswith(f"worst positions (residual RMS): {k + 1} ")
    png = tmp_path / "res.png"
    residual_png(f, k, png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_arguments(mild):
    vr, samples = mild
    lut = fit_model(samples, vr.rig, "poly", 1)
    with pytest.raises(ValueError):
        residual_field(lut, samples, block=0)
