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
    assert f.lines()[0].startswith(f"worst positions (residual RMS over X and Y): position {k}, z = {f.z[k]:g} mm")
    png = tmp_path / "res.png"
    residual_png(f, k, png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_arguments(mild):
    vr, samples = mild
    lut = fit_model(samples, vr.rig, "poly", 1)
    with pytest.raises(ValueError):
        residual_field(lut, samples, block=0)


def _whole_image_field(lut, samples, block):
    """The residual field as one whole-image pass (the formula before row bands), for comparison."""
    from ptpcore.evaluate.residuals import _block_mean

    k_all, (h, w) = samples.z.size, samples.shape
    dx, dy, sq, cnt, rms = [], [], np.zeros((h, w)), np.zeros((h, w)), []
    for k in range(k_all):
        ev = lut.evaluate(float(samples.z[k]))
        sx, sy = samples.absolute(k)
        ok = (samples.reasons[k] == 0) & ev.in_range & lut.valid & np.isfinite(sx)
        rx, ry = np.where(ok, sx - ev.x, np.nan), np.where(ok, sy - ev.y, np.nan)
        r2 = rx * rx + ry * ry
        rms.append(np.sqrt(np.mean(r2[ok])) * 1e3 if ok.any() else np.nan)
        dx.append(_block_mean(rx, block))
        dy.append(_block_mean(ry, block))
        sq += np.where(ok, r2, 0.0)
        cnt += ok
    with np.errstate(invalid="ignore", divide="ignore"):
        pix = np.where(cnt > 0, np.sqrt(sq / cnt) * 1e3, np.nan)
    return np.array(rms), np.array(dx), np.array(dy), pix


@pytest.mark.parametrize("band_pixels", [16 * 160, 48 * 160, 1 << 19])
def test_row_bands_give_the_whole_image_field(mild, monkeypatch, band_pixels):
    """Row bands of 16 and 48 rows (7 and 3 bands, the last one partial) and one band: the arrows,
    the per-pixel RMS and the worst pixels are bit-identical to the whole-image formula; each
    position's RMS, a sum over bands, agrees to 1e-12 relative (the summation order changes)."""
    from ptpcore.evaluate import residuals

    vr, samples = mild
    lut = fit_model(samples, vr.rig, "poly", 2, positions=list(range(0, samples.z.size, 2)))
    monkeypatch.setattr(residuals, "BAND_PIXELS", band_pixels)
    f = residual_field(lut, samples, block=16)
    rms, dx, dy, pix = _whole_image_field(lut, samples, 16)
    np.testing.assert_array_equal(f.dx, dx)
    np.testing.assert_array_equal(f.dy, dy)
    np.testing.assert_array_equal(f.pixel_rms_um, pix)
    np.testing.assert_allclose(f.rms_um, rms, rtol=1e-12)
    flat = np.where(np.isfinite(pix), pix, -1.0).ravel()
    np.testing.assert_array_equal(f.worst_pixels, np.stack(np.unravel_index(np.argsort(flat)[::-1][:20], pix.shape), 1))


def test_merged_blocks_are_the_mean_of_their_blocks(mild):
    """Merging 3 x 3 blocks (the panel's coarser arrows on a big sensor): each merged residual is the
    mean of its blocks' residuals that have one, at the mean of their centres; the edge groups are
    partial; the per-position and per-pixel numbers are the field's own."""
    vr, samples = mild
    lut = fit_model(samples, vr.rig, "poly", 3)
    f = residual_field(lut, samples, block=8)
    assert f.merged(1) is f
    m = f.merged(3)
    k = 4
    gy, gx = f.dx.shape[1:]
    assert m.dx.shape == (samples.z.size, -(-gy // 3), -(-gx // 3)) and m.block == 24
    for i, j in [(0, 0), (1, 2), (m.dx.shape[1] - 1, m.dx.shape[2] - 1)]:
        rows, cols = slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3)
        np.testing.assert_allclose(m.dx[k, i, j], np.nanmean(f.dx[k, rows, cols]), rtol=1e-12)
        np.testing.assert_allclose(m.dy[k, i, j], np.nanmean(f.dy[k, rows, cols]), rtol=1e-12)
        assert m.rows[i] == np.mean(f.rows[rows]) and m.cols[j] == np.mean(f.cols[cols])
    assert m.rms_um is f.rms_um and m.pixel_rms_um is f.pixel_rms_um
    with pytest.raises(ValueError, match="group"):
        f.merged(0)
