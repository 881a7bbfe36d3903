"""The fast paths (docs/performance.md) give the reference results.

Tiled, threaded N-step sums, unwrapping, classification, LUT fitting and
evaluation, direct TIFF reads and spilled sample stacks, each against a plain
reference: the straightforward implementation kept here, the frame-by-frame
:class:`PhaseAccumulator`, OpenCV's reader, or the in-memory stack. Images are
wide enough (4096 px: 8 rows per tile) that every path crosses tile borders.
"""


import cv2
import os

import numpy as np
import pytest
from scipy import ndimage

from ptpcore.io import DatasetSource, SimulatedSource
from ptpcore.io import SpillStore, read_block, read_into
from ptpcore.io.lutfile import _horner
from ptpcore.fit import fit_lut
from ptpcore.io import SampleStack
from ptpcore.decode.phase import (DecodeOptions, PhaseAccumulator, Reason, _nstep_chain, decode_direction,
    finish_position, unwrap_hierarchical, wrapped_phase)
from ptpcore.parallel import row_tiles, run_tiles
from ptpcore.run import collect_samples, decode_position
from ptpcore.rig import save_rig
from ptpcore.simulate import VirtualRig, scaled_preset


def _stack(rng, n, shape, dtype, level=255):
    phi = rng.uniform(-np.pi, np.pi, shape)
    a = rng.uniform(0.3, 0.6, shape) * level
    b = rng.uniform(0.05, 0.3, shape) * level
    f = np.stack([a + b * np.cos(phi + 2 * np.pi * k / n) + rng.normal(0, 0.01 * level, shape) for k in range(n)])
    if np.dtype(dtype).kind == "u":
        f = np.clip(np.rint(f), 0, level).astype(dtype)
    return f.astype(dtype)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float64])
@pytest.mark.parametrize("n", [3, 4, 5, 8])
def test_tiled_nstep_equals_the_frame_by_frame_accumulator(dtype, n):
    rng = np.random.default_rng(n)
    level = 4095 if dtype == np.uint16 else 255
    frames = _stack(rng, n, (40, 4096), dtype, level)
    assert len(row_tiles(40, 4096)) > 1
    acc = PhaseAccumulator(frames.shape[1:], n, level * 0.99)
    for k in range(n):
        acc.add(frames[k], k)
    ref = acc.result()
    got = wrapped_phase(frames, level * 0.99)
    dphi = np.angle(np.exp(1j * (got.phase.astype(float) - ref.phase)))
    assert np.max(np.abs(dphi)) < 1e-5  # float32 rounding of the sums (|S|, |C| ~ 100 levels)
    np.testing.assert_allclose(got.modulation, ref.modulation, rtol=1e-5, atol=1e-4 * level / 255)
    np.testing.assert_array_equal(got.background, ref.background)
    np.testing.assert_array_equal(got.saturated, ref.saturated)
    if n > 3:
        # The residual variance, against float64 arithmetic on the frames as both
        # implementations see them (float32 samples).
        f64 = frames.astype(np.float32).astype(np.float64)
        a = f64.mean(axis=0)
        d = 2 * np.pi * np.arange(n) / n
        s = np.tensordot(np.sin(d), f64, 1)
        c = np.tensordot(np.cos(d), f64, 1)
        b = 2 / n * np.hypot(s, c)
        fit = a + b * np.cos(np.arctan2(-s, c)[None] + d[:, None, None])
        exact = ((f64 - fit) ** 2).sum(axis=0) / (n - 3)
        scale = (0.01 * level) ** 2
        # Integer frames: the sums of I and I^2 are exact; float frames: float32 sums.
        tol = 1e-3 if np.dtype(dtype).kind == "u" else 1e-2
        assert np.max(np.abs(got.residual_var - exact)) < tol * scale + 2e-4 * exact.max()
        assert np.max(np.abs(ref.residual_var - exact)) < 2e-2 * scale + 1e-3 * exact.max()
    else:
        assert got.residual_var is None and ref.residual_var is None
    lean = wrapped_phase(frames, level * 0.99, photometry=False)
    np.testing.assert_array_equal(lean.phase, got.phase)
    assert lean.background is None and lean.residual_var is None


@pytest.mark.parametrize("n", [3, 4, 6, 8, 12, 16])
def test_accumulate_weighted_chain_makes_the_weighted_sums(n):
    d = 2 * np.pi * np.arange(n) / n
    for kind, wts in (("s", -np.sin(d)), ("c", np.cos(d))):
        steps, lam = _nstep_chain(n, kind)
        coef = np.zeros(n)
        for i, alpha in steps:  # the chain on unit impulses, in float64
            coef *= 1 - alpha
            coef[i] += alpha
        np.testing.assert_allclose(coef / lam, wts, atol=1e-12)


def _unwrap_reference(phases, periods):
    two_pi = 2.0 * np.pi
    unwrapped = np.mod(np.asarray(phases[0], dtype=np.float64), two_pi)
    dis = np.zeros(unwrapped.shape, bool)
    for j in range(1, len(periods)):
        predicted = unwrapped * (periods[j - 1] / periods[j])
        phi = np.asarray(phases[j], dtype=np.float64)
        order = np.rint((predicted - phi) / two_pi)
        unwrapped = phi + two_pi * order
        dis |= np.abs(unwrapped - predicted) > (np.pi / 2)
    return unwrapped * (periods[-1] / two_pi), dis


def test_tiled_unwrapping_equals_the_reference_exactly():
    rng = np.random.default_rng(0)
    periods = [4096, 256, 16]
    u = np.linspace(0, 4000, 4096)[None, :] + rng.uniform(0, 50, (40, 1))
    phases = [np.angle(np.exp(2j * np.pi * u / t) * np.exp(1j * rng.normal(0, 0.3, u.shape))).astype(np.float32)
              for t in periods]
    coord, dis = unwrap_hierarchical(phases, periods)
    rc, rd = _unwrap_reference(phases, periods)
    np.testing.assert_array_equal(coord, rc)
    np.testing.assert_array_equal(dis, rd)
    assert dis.any() and not dis.all()
    # Phases outside [-2pi, 2pi) take np.mod itself.
    shifted = [phases[0] + np.float32(7.0)] + phases[1:]
    np.testing.assert_array_equal(unwrap_hierarchical(shifted, periods)[0], _unwrap_reference(shifted, periods)[0])


def _finish_reference(rig, decoded, options=DecodeOptions()):
    shape = rig.camera.shape
    reasons = np.zeros(shape, np.uint8)
    min_mod = options.min_modulation * rig.camera.max_level
    for d, dec in decoded.items():
        extent = rig.lcd.width if d == "x" else rig.lcd.height
        for w in dec.wrapped:
            reasons[w.modulation < min_mod] |= Reason.LOW_MODULATION
            reasons[w.saturated] |= Reason.SATURATED
        reasons[dec.disagreement] |= Reason.UNWRAP
        outside = ~((dec.coord >= -0.5) & (dec.coord <= extent - 0.5))
        reasons[outside] |= Reason.OUTSIDE_LCD
        with np.errstate(invalid="ignore"):
            gr, gc = np.gradient(dec.coord)
            reach = options.border_margin_px * np.hypot(gr, gc)
            near_edge = (dec.coord < -0.5 + reach) | (dec.coord > extent - 0.5 - reach)
        reasons[near_edge & ~outside] |= Reason.BORDER
    m = options.border_margin_px
    bezel = (reasons & (Reason.OUTSIDE_LCD | Reason.LOW_MODULATION)) != 0
    near = ndimage.binary_dilation(bezel, structure=np.ones((2 * m + 1, 2 * m + 1), bool))
    reasons[near & ~bezel] |= Reason.BORDER
    return reasons


@pytest.fixture(scope="module")
def realistic():
    rig, settings = scaled_preset("realistic", 320)
    return VirtualRig(rig, settings, seed=4)


def test_tiled_classification_equals_the_reference(realistic):
    rig = realistic.rig
    f = rig.fringes
    for k in (0, rig.stage.n_positions - 1):
        frames = {}
        for (d, j, _t, n, big_n), img in realistic.frames(k):
            frames.setdefault((d, j), [None] * big_n)[n] = img
        decoded = {d: decode_direction([wrapped_phase(np.stack(frames[(d, j)]), rig.camera.max_level)
                                        for j in range(len(f.periods_px))], f.periods_px,
                                       f.carrier(d) * rig.stage.z_mm[k]) for d in f.directions}
        got = finish_position(rig, k, decoded).reasons
        ref = _finish_reference(rig, decoded)
        np.testing.assert_array_equal(got, ref)
        assert (got & Reason.BORDER).any() and (got == 0).mean() > 0.5


def test_nested_tiles_run_serially():
    out = np.zeros((64, 64), int)

    def outer(r0, r1):
        run_tiles(lambda a, b: out[r0:r1].__setitem__(slice(None), out[r0:r1] + 1), 8, 64, tile_pixels=64)

    run_tiles(outer, 64, 64, tile_pixels=64 * 8)
    assert (out == 8).all()  # 8 inner tiles per outer tile, no deadlock


# ---------------------------------------------------------------------------- files


@pytest.mark.parametrize("depth", [8, 16])
def test_read_into_reads_grey_png_and_tiff_and_declines_the_rest(tmp_path, depth):
    rng = np.random.default_rng(depth)
    dtype = np.uint8 if depth == 8 else np.uint16
    img = rng.integers(0, 1 << depth, (37, 53), dtype=dtype)
    plain = tmp_path / "plain.tif"
    cv2.imwrite(str(plain), img, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    lzw = tmp_path / "lzw.tif"
    cv2.imwrite(str(lzw), img, [cv2.IMWRITE_TIFF_COMPRESSION, 5])
    png = tmp_path / "img.png"
    cv2.imwrite(str(png), img)
    for path in (plain, lzw, png):
        out = np.zeros_like(img)
        assert read_into(path, out), path
        np.testing.assert_array_equal(out, img)
    colour = tmp_path / "colour.png"
    cv2.imwrite(str(colour), np.dstack([img] * 3))
    assert not read_into(colour, out)
    assert not read_into(plain, np.empty((37, 52), dtype))  # wrong size
    assert not read_into(plain, np.empty((37, 53), np.uint16 if depth == 8 else np.uint8))  # wrong depth
    assert not read_into(tmp_path / "missing.tif", out)
    for path in (plain, lzw, png):
        cut = tmp_path / f"cut{path.suffix}"
        cut.write_bytes(path.read_bytes()[:200])
        assert not read_into(cut, out), path


def _dataset(tmp_path, vr, ext):
    rig = vr.rig
    from dataclasses import replace

    rig = replace(rig, template="z{pos:02d}/{dir}_{period}_{step}" + ext)
    save_rig(rig, tmp_path / "rig.toml")
    params = [cv2.IMWRITE_TIFF_COMPRESSION, 1] if ext == ".tif" else []
    for k in range(rig.stage.n_positions):
        for (d, _j, t, n, big_n), img in vr.frames(k):
            p = tmp_path / rig.image_name(k, d, t, n, big_n)
            p.parent.mkdir(exist_ok=True)
            cv2.imwrite(str(p), img, params)
    return DatasetSource(tmp_path)


@pytest.fixture(scope="module")
def small_rig():
    rig, settings = scaled_preset("realistic", 160)
    return VirtualRig(rig.with_z(rig.stage.z_mm[:6]), settings, seed=2)


@pytest.mark.parametrize("ext", [".tif", ".png"])
def test_folder_decoding_equals_the_frame_source(tmp_path, small_rig, ext):
    src = _dataset(tmp_path, small_rig, ext)
    ref = decode_position(SimulatedSource(small_rig), 3)
    got = decode_position(src, 3)
    # Same frames; OpenCV's SIMD sums may round differently in other buffers (float32 level).
    np.testing.assert_array_equal(got.reasons, ref.reasons)
    np.testing.assert_allclose(got.u, ref.u, rtol=0, atol=1e-5)
    for d in "xy":
        for a, b in zip(got.directions[d].wrapped, ref.directions[d].wrapped):
            np.testing.assert_allclose(a.modulation, b.modulation, rtol=1e-5)
            # (a difference of large sums: float32 rounding of S, C shows at 1e-3 here)
            np.testing.assert_allclose(a.residual_var, b.residual_var, rtol=5e-3, atol=0.05)


def test_spilled_samples_equal_samples_in_memory(tmp_path, small_rig):
    src = _dataset(tmp_path, small_rig, ".tif")
    mem = collect_samples(src, spill=False)
    seen = []
    spilled = collect_samples(src, spill=True, spill_dir=tmp_path, on_position=lambda p: seen.append(p.index))
    assert seen == list(range(6))
    assert isinstance(spilled.x, np.memmap)
    # Bit for bit where no float32 sum is involved; OpenCV's SIMD sums can round
    # a last bit differently in other buffers (modulation: 1e-7 relative).
    for name in ("reasons", "background"):
        np.testing.assert_array_equal(getattr(spilled, name), getattr(mem, name), err_msg=name)
    for name in ("x", "y", "x_ref", "y_ref"):  # mm; 1e-9 mm is far below float32 phase rounding
        np.testing.assert_allclose(getattr(spilled, name), getattr(mem, name), rtol=0, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(spilled.modulation, mem.modulation, rtol=1e-6)
    assert spilled.noise.read_var == pytest.approx(mem.noise.read_var, rel=1e-3, abs=1e-6)
    assert spilled.noise.gain == pytest.approx(mem.noise.gain, rel=1e-3)
    part = collect_samples(src, spill=True, spill_dir=tmp_path, positions=[1, 4])
    assert (part.reasons[[0, 2, 3, 5]] == 0xFF).all()
    np.testing.assert_array_equal(part.reasons[1], mem.reasons[1])
    for model, positions in (("poly", None), ("poly", [0, 1, 2, 3, 5]), ("linear", [0, 2, 4])):
        a = fit_lut(mem, model, 2, positions=positions)
        b = fit_lut(spilled, model, 2, positions=positions)
        for field in ("x", "y", "valid", "rms_x", "loo_y", "pixel_z_min", "n_positions"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=f"{model} {field}")


def test_spill_store_blocks_and_cleanup(tmp_path):
    st = SpillStore(3, (4, 5), {"x": np.float32, "r": np.uint8}, {"x": np.nan, "r": 0xFF}, tmp_path)
    st.write("x", 1, np.arange(20, dtype=np.float32).reshape(4, 5))
    st.finish()
    arrays = st.arrays()
    path = st.path
    del st
    np.testing.assert_array_equal(read_block(arrays["x"], 3, 7), arrays["x"].reshape(3, -1)[:, 3:7])
    np.testing.assert_array_equal(read_block(arrays["x"], 3, 7, [1]), [[3, 4, 5, 6]])
    assert (arrays["r"] == 0xFF).all()
    assert path.exists() == (os.name != "posix")  # POSIX: unlinked at creation, the maps keep the file
    del arrays
    import gc

    gc.collect()
    assert not path.exists()


# ---------------------------------------------------------------------------- LUT


def test_tiled_evaluation_equals_horner():
    rng = np.random.default_rng(0)
    h, w = 40, 4096
    samples = SampleStack.empty(np.arange(6) * 2.0, (h, w), with_photometry=False)
    x0, sx = rng.uniform(0, 100, (h, w)), rng.uniform(-0.3, 0.3, (h, w))
    for k, z in enumerate(samples.z):
        reasons = (rng.random((h, w)) < 0.1).astype(np.uint8)
        samples.set_position(k, x0 + sx * z + 1e-3 * z * z, x0 - sx * z, reasons)
    lut = fit_lut(samples, "poly", 2)
    zmap = rng.uniform(-1, 11, (h, w))
    for z in (4.0, zmap):
        for extrapolate in (False, True):
            ev = lut.evaluate(z, extrapolate=extrapolate)
            zz = np.asarray(z, float)
            in_range = lut.valid & (zz >= lut.pixel_z_min - 1e-9) & (zz <= lut.pixel_z_max + 1e-9)
            keep = lut.valid if extrapolate else in_range
            t = (zz - lut.z_center) / lut.z_scale
            np.testing.assert_array_equal(ev.in_range, in_range)
            np.testing.assert_array_equal(ev.x, np.where(keep, _horner(lut.x, t), np.nan))
            np.testing.assert_array_equal(ev.y, np.where(keep, _horner(lut.y, t), np.nan))


# ---------------------------------------------------------------------------- numba kernels
# The optional fused kernels (ptpcore.decode._fused, `pip install ".[fast]"`) against the numpy/OpenCV
# path on the same inputs: N-step sums to float32 rounding, unwrapping, classification and
# the stored samples bit for bit.


@pytest.fixture
def kernels(monkeypatch):
    """The numba kernels, switched on (skips without numba)."""
    pytest.importorskip("numba")
    from ptpcore.decode.phase import fused_kernels

    monkeypatch.delenv("PTP_NO_NUMBA", raising=False)
    kern = fused_kernels()
    assert kern is not None
    return kern


@pytest.fixture
def numpy_path(monkeypatch):
    """A context switch: ``with numpy_path():`` runs the numpy/OpenCV path."""
    import contextlib

    @contextlib.contextmanager
    def use():
        with monkeypatch.context() as m:
            m.setenv("PTP_NO_NUMBA", "1")
            yield

    return use


def test_numba_can_be_switched_off(monkeypatch):
    from ptpcore.decode.phase import fused_kernels

    monkeypatch.setenv("PTP_NO_NUMBA", "1")
    assert fused_kernels() is None


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("n", [3, 4, 5, 8])
def test_numba_nstep_matches_the_numpy_path(dtype, n, kernels, numpy_path):
    rng = np.random.default_rng(10 + n)
    level = 4095 if dtype == np.uint16 else 255
    frames = _stack(rng, n, (40, 4096), dtype, level)
    frames[:, :3] = level  # saturated rows
    frames[:, 5, :100] = 7  # constant pixels: S = C = 0 up to rounding
    for sat in (level * 0.99, None, level):
        for photometry in (True, False):
            got = wrapped_phase(frames, sat, photometry=photometry)
            with numpy_path():
                ref = wrapped_phase(frames, sat, photometry=photometry)
            np.testing.assert_array_equal(got.saturated, ref.saturated)
            np.testing.assert_allclose(got.modulation, ref.modulation, rtol=2e-6, atol=2e-4 * level / 255)
            sure = ref.modulation > 1e-3 * level  # the phase of a zero vector is rounding noise
            dphi = np.angle(np.exp(1j * (got.phase.astype(float) - ref.phase)))
            assert np.max(np.abs(dphi[sure])) < 1e-5
            if photometry:
                np.testing.assert_array_equal(got.background, ref.background)
                if n > 3:
                    scale = (0.01 * level) ** 2
                    np.testing.assert_allclose(got.residual_var, ref.residual_var, rtol=0,
                                               atol=2e-3 * scale + 1e-4 * float(ref.residual_var.max()))
                else:
                    assert got.residual_var is None
            else:
                assert got.background is None and got.residual_var is None


def _wrapped_levels(vr, k):
    rig = vr.rig
    f = rig.fringes
    frames = {}
    for (d, j, _t, n, big_n), img in vr.frames(k):
        frames.setdefault((d, j), [None] * big_n)[n] = img
    return {d: [wrapped_phase(np.stack(frames[(d, j)]), rig.camera.max_level) for j in range(len(f.periods_px))]
            for d in f.directions}


def test_numba_unwrap_and_classification_equal_the_numpy_path_exactly(realistic, kernels):
    from ptpcore.decode.phase import decode_and_finish

    rig = realistic.rig
    f = rig.fringes
    for k in (0, rig.stage.n_positions - 1):
        levels = _wrapped_levels(realistic, k)
        for opts in (DecodeOptions(), DecodeOptions(0.1, 0), DecodeOptions(0.01, 5)):
            got = decode_and_finish(rig, k, levels, opts)
            dec = {d: decode_direction(levels[d], f.periods_px, f.carrier(d) * rig.stage.z_mm[k]) for d in levels}
            ref = finish_position(rig, k, dec, opts)
            np.testing.assert_array_equal(got.reasons, ref.reasons)
            np.testing.assert_array_equal(got.u, ref.u)
            np.testing.assert_array_equal(got.v, ref.v)
            for d in levels:
                np.testing.assert_array_equal(got.directions[d].disagreement, dec[d].disagreement)
            assert got.z_mm == ref.z_mm
        assert (got.reasons & Reason.BORDER).any() and (got.reasons == 0).mean() > 0.5


def test_numba_unwrapping_of_odd_phases_equals_the_reference(kernels):
    unwrap_classify_rows = kernels.unwrap_classify_rows

    rng = np.random.default_rng(3)
    periods = [4096, 256, 16]
    u = np.linspace(0, 4000, 4096)[None, :] + rng.uniform(0, 50, (40, 1))
    phases = [np.angle(np.exp(2j * np.pi * u / t) * np.exp(1j * rng.normal(0, 0.3, u.shape))).astype(np.float32)
              for t in periods]
    phases[0][3, 7:20] += np.float32(7.0)  # outside [-2pi, 2pi): np.mod
    phases[0][4, 1] = np.nan
    phases[1][5, 2] = np.nan
    phases[0][6, :5] = [-0.0, 0.0, -2 * np.pi, np.float32(2 * np.pi), -1e-30]
    ref_coord, ref_dis = _unwrap_reference(phases, periods)
    ref_coord -= 1.25
    coord = np.empty(u.shape)
    dis = np.empty(u.shape, bool)
    reasons = np.zeros(u.shape, np.uint8)
    mods = tuple(np.ones(u.shape, np.float32) for _ in periods)
    sats = tuple(np.zeros(u.shape, bool) for _ in periods)
    unwrap_classify_rows(0, 40, tuple(phases), np.array([1.0, 16.0, 16.0]), 16 / (2 * np.pi), 1.25, mods, sats,
                         np.float32(0.5), 3840.0, coord, dis, reasons)
    np.testing.assert_array_equal(coord, ref_coord)
    np.testing.assert_array_equal(dis, ref_dis)


def test_numba_store_equals_the_numpy_path_exactly(realistic, kernels):
    from ptpcore.io.sample_store import store_rows, store_rows_fused

    rig = realistic.rig
    f = rig.fringes
    shape = rig.camera.shape
    stacks = [SampleStack.empty(rig.stage.z_mm, shape) for _ in range(2)]
    for k in (0, 3, rig.stage.n_positions - 1):
        levels = _wrapped_levels(realistic, k)
        dec = {d: decode_direction(levels[d], f.periods_px, f.carrier(d) * rig.stage.z_mm[k]) for d in levels}
        pos = finish_position(rig, k, dec)
        fx, fy = levels["x"][-1], levels["y"][-1]
        for s, fused in zip(stacks, (False, True)):
            dest = {"x": s.x[k], "y": s.y[k], "reasons": s.reasons[k], "modulation": s.modulation[k],
                    "background": s.background[k]}
            if fused:  # into each tile's rows (as a spilled run does, into a scratch of the tile)
                run_tiles(lambda r0, r1: store_rows_fused(kernels, rig, pos, fx, fy, s,
                                                          {n: a[r0:r1] for n, a in dest.items()}, r0, r1), *shape)
            else:
                run_tiles(lambda r0, r1: store_rows(rig, pos, fx, fy, s, dest, r0, r1), *shape)
    for name in ("x", "y", "x_ref", "y_ref", "reasons", "modulation", "background"):
        np.testing.assert_array_equal(getattr(stacks[1], name), getattr(stacks[0], name), err_msg=name)


def test_numba_calibration_matches_the_numpy_path(tmp_path, small_rig, kernels, numpy_path):
    src = _dataset(tmp_path, small_rig, ".tif")
    got = collect_samples(src, spill=True, spill_dir=tmp_path)
    with numpy_path():
        ref = collect_samples(src, spill=False)
    # The N-step sums agree to float32 rounding, and a pixel's class follows that rounding
    # only where a phase is undefined (no modulation: its coordinate is noise) or a
    # coordinate sits on a threshold (the coarse level's 0/2pi seam, the border test).
    low = ((got.reasons | ref.reasons) & Reason.LOW_MODULATION) != 0
    same = got.reasons == ref.reasons
    assert (~same & ~low).mean() < 1e-3
    assert ((got.reasons == 0) != (ref.reasons == 0)).mean() < 1e-3
    both = same & (ref.reasons == 0)
    for name in ("x", "y"):  # mm, absolute: x_ref, the first valid position, may differ
        a = getattr(got, name) + getattr(got, name + "_ref")
        b = getattr(ref, name) + getattr(ref, name + "_ref")
        np.testing.assert_allclose(a[both], b[both], rtol=0, atol=5e-6)  # float32 of tens of mm
    np.testing.assert_array_equal(got.background, ref.background)
    np.testing.assert_allclose(got.modulation, ref.modulation, rtol=2e-6, atol=1e-4)
    assert got.noise.read_var == pytest.approx(ref.noise.read_var, rel=1e-2, abs=1e-5)
    assert got.noise.gain == pytest.approx(ref.noise.gain, rel=1e-2)


@pytest.mark.parametrize("positions", [None, [0, 2, 3, 5, 6, 8], [8, 1, 4, 2, 6, 0]])
def test_numba_poly_fit_equals_the_numpy_path(positions, kernels, numpy_path):
    """The compiled all-valid-pattern fit (and the z range by argmax) give the numpy path's LUT."""
    rng = np.random.default_rng(1)
    k, h, w = 9, 30, 900
    z = np.linspace(0, 8, k)
    x = (rng.normal(size=(k, h, w)) * 0.01 + z[:, None, None] * 0.3).astype(np.float32)
    y = (rng.normal(size=(k, h, w)) * 0.01 - z[:, None, None] * 0.2).astype(np.float32)
    reasons = np.zeros((k, h, w), np.uint8)
    reasons[rng.random((k, h, w)) < 0.03] = 1
    x[reasons != 0] = np.nan
    y[reasons != 0] = np.nan
    s = SampleStack(z, x, y, np.zeros((h, w)), np.ones((h, w)), reasons)
    fast = fit_lut(s, "poly", 3, positions=positions)
    with numpy_path():
        ref = fit_lut(s, "poly", 3, positions=positions)
    for name in ("x", "y", "rms_x", "rms_y", "loo_x", "loo_y", "pixel_z_min", "pixel_z_max", "valid",
                 "n_positions"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(ref, name), err_msg=name)


def test_frames_tapped_and_full_maps_for_chosen_positions(tmp_path, small_rig):
    """on_frame sees every frame of the dataset reader's sets; with full_positions only those
    positions reach on_position with every level's maps; the samples do not change."""
    src = _dataset(tmp_path, small_rig, ".tif")
    plain = collect_samples(src, spill=True, spill_dir=tmp_path)
    frames, full = [], {}

    def on_frame(k, spec, img):
        assert img.shape == small_rig.rig.camera.shape
        frames.append((k, spec[0], spec[1], spec[3]))

    def on_position(pos):  # whether a coarse level kept its background map
        full[pos.index] = pos.directions["x"].wrapped[0].background is not None

    tapped = collect_samples(src, spill=True, spill_dir=tmp_path, on_frame=on_frame, on_position=on_position,
                             full_positions=[5])
    per_position = small_rig.rig.fringes.frames_per_position
    assert len(frames) == 6 * per_position and len(set(frames)) == len(frames)
    assert [k for k, *_ in frames] == sorted(k for k, *_ in frames)  # position by position
    assert full == {0: False, 1: False, 2: False, 3: False, 4: False, 5: True}
    for name in ("x", "y", "reasons", "modulation", "background"):
        np.testing.assert_array_equal(getattr(tapped, name), getattr(plain, name), err_msg=name)


@pytest.mark.parametrize("spatial", [True, False])
def test_positions_decoded_in_a_row_equal_one_by_one(tmp_path, small_rig, spatial):
    """decode_positions (one reader, reused maps; ptp decode) gives decode_position's coordinates and
    reasons, without the spatial flags when asked (ptp decode checks each direction alone)."""
    from ptpcore.run.pipeline import decode_positions

    src = _dataset(tmp_path, small_rig, ".tif")
    rig = src.rig
    t, n = rig.fringes.periods("x")[-1], rig.fringes.steps_of("x")[-1]
    for step, change in ((0, 40), (1, -40)):  # a 2 x 2 px blemish at position 1: spatial outliers there
        path = tmp_path / rig.image_name(1, "x", t, step, n)
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        img[60:62, 80:82] = np.clip(img[60:62, 80:82].astype(int) + change, 0, 255)
        cv2.imwrite(str(path), img, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    src = DatasetSource(tmp_path)
    assert (decode_position(src, 1).reasons[60:62, 80:82] & Reason.SPATIAL).all()
    seen = []
    for pos in decode_positions(src, [4, 1, 2], spatial=spatial):
        ref = decode_position(src, pos.index)
        want = ref.reasons if spatial else ref.reasons & np.uint8(~Reason.SPATIAL & 0xFF)
        np.testing.assert_array_equal(pos.reasons, want)
        for d in "xy":
            np.testing.assert_array_equal(pos.directions[d].coord, ref.directions[d].coord)
            np.testing.assert_array_equal(pos.directions[d].wrapped[-1].background, ref.directions[d].wrapped[-1].background)
        seen.append(pos.index)
    assert seen == [4, 1, 2]
