"""Frames mapped from their files and the per-pixel N-step kernel.

- :func:`ptpcore.io.fastio.map_frame` gives a plain TIFF's pixels (as ``read_into`` reads
  them) and declines every other file.
- The numba N-step kernel (pixel by pixel over a tuple of frames) against a float32
  numpy reference with the same operations in the same order: bit for bit.
- ``wrapped_phase`` of separate frames (mapped or not) equals that of the stacked frames.
- A calibration from a TIFF folder whose frames are mapped equals the one read into
  buffers, bit for bit.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ptpcore.io import map_frame, read_into
from ptpcore.decode.phase import WrappedPhase, _nstep_weights, wrapped_phase


@pytest.fixture
def kernels(monkeypatch):
    """The numba kernels, switched on (skips without numba)."""
    pytest.importorskip("numba")
    from ptpcore.decode.phase import fused_kernels

    monkeypatch.delenv("PTP_NO_NUMBA", raising=False)
    kern = fused_kernels()
    assert kern is not None
    return kern


@pytest.mark.parametrize("depth", [8, 16])
def test_map_frame_maps_plain_tiffs_and_declines_the_rest(tmp_path, depth):
    rng = np.random.default_rng(depth)
    dtype = np.uint8 if depth == 8 else np.uint16
    img = rng.integers(0, 1 << depth, (37, 53), dtype=dtype)
    plain = tmp_path / "plain.tif"
    cv2.imwrite(str(plain), img, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    got = map_frame(plain, img.shape, dtype)
    assert got is not None and got.dtype == dtype and not got.flags.writeable
    np.testing.assert_array_equal(got, img)
    read = np.empty_like(img)
    assert read_into(plain, read)
    np.testing.assert_array_equal(got, read)
    del got  # unmapped with its last reference
    lzw = tmp_path / "lzw.tif"
    cv2.imwrite(str(lzw), img, [cv2.IMWRITE_TIFF_COMPRESSION, 5])
    png = tmp_path / "img.png"
    cv2.imwrite(str(png), img)
    assert map_frame(lzw, img.shape, dtype) is None
    assert map_frame(png, img.shape, dtype) is None
    assert map_frame(plain, (37, 52), dtype) is None  # wrong size
    assert map_frame(plain, img.shape, np.uint16 if depth == 8 else np.uint8) is None  # wrong depth
    assert map_frame(plain, img.shape, np.float32) is None
    assert map_frame(tmp_path / "missing.tif", img.shape, dtype) is None
    cut = tmp_path / "cut.tif"
    cut.write_bytes(plain.read_bytes()[:200])
    assert map_frame(cut, img.shape, dtype) is None


def _reference_sums(frames: np.ndarray, sat_thr: int):
    """The row-accumulator arithmetic of the kernel in float32 numpy, frame by frame in order:
    ``-S``, ``C``, modulation, background, saturation (each op rounds to float32 as there)."""
    n = len(frames)
    ws, wc = _nstep_weights(n)
    s = np.zeros(frames.shape[1:], np.float32)
    c = np.zeros_like(s)
    a = np.zeros_like(s)
    for i in range(n):
        v = frames[i].astype(np.float32)
        s += ws[i] * v
        c += wc[i] * v
        a += v
    # sqrt of the float32 sum of squares, rounded to float32 (the kernel takes it in
    # float64 and rounds: the same number, double rounding is exact for sqrt)
    mod = np.sqrt((s * s + c * c).astype(np.float64)).astype(np.float32) * np.float32(2.0 / n)
    return s, c, mod, a / np.float32(n), frames.max(axis=0).astype(np.int64) >= sat_thr


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("n", [3, 4, 5, 8])
def test_nstep_kernel_equals_the_float32_reference_exactly(dtype, n, kernels):
    from ptpcore.decode.phase import _kernel_frames

    rng = np.random.default_rng(n)
    level = 255 if dtype == np.uint8 else 4095
    frames = rng.integers(0, level + 1, (n, 23, 301)).astype(dtype)
    frames[:, 4, :50] = level
    frames[:, 5, :40] = 1
    frames[n - 1, 5, :20] = 0  # black in the last step only
    thr = int(0.98 * level)
    ref = _reference_sums(frames, thr)
    h, w = frames.shape[1:]
    r0, r1 = 3, 19  # a tile inside the image: rows outside it stay untouched
    for photometry in (False, True):
        out = [np.full((h, w), -1, np.float32) for _ in range(5)]
        sat = np.zeros((h, w), bool)
        neg_s, c, mod, bg, rv = out[0][r0:r1], out[1][r0:r1], out[2], out[3], out[4]
        one_w = np.float32(1) if dtype == np.uint8 else np.float64(1)
        black = np.zeros((h, w), bool)
        kernels.nstep_rows(_kernel_frames(frames), r0, r1, *_nstep_weights(n), thr, neg_s, c, mod, sat,
                           photometry, bg, one_w, rv, 0, 0, black, 0)
        rows = slice(r0, r1)
        np.testing.assert_array_equal(black[rows], (frames <= 0).any(axis=0)[rows])
        assert black[5, :20].all() and not black[:r0].any()
        np.testing.assert_array_equal(neg_s, ref[0][rows])
        np.testing.assert_array_equal(c, ref[1][rows])
        np.testing.assert_array_equal(mod[rows], ref[2][rows])
        np.testing.assert_array_equal(sat[rows], ref[4][rows])
        assert (mod[:r0] == -1).all() and (mod[r1:] == -1).all()
        if photometry:
            np.testing.assert_array_equal(bg[rows], ref[3][rows])
            assert (rv[rows] >= 0).all() and (rv[:r0] == -1).all()
        else:
            assert (bg == -1).all() and (rv == -1).all()


def _empty_like_wrapped(shape):
    return WrappedPhase(*(np.empty(shape, np.float32) for _ in range(3)), np.empty(shape, bool),
                        np.empty(shape, np.float32))


@pytest.mark.parametrize("fast", [True, False])
def test_separate_frames_give_the_stack_result(fast, monkeypatch, tmp_path):
    if fast:
        pytest.importorskip("numba")
        monkeypatch.delenv("PTP_NO_NUMBA", raising=False)
    else:
        monkeypatch.setenv("PTP_NO_NUMBA", "1")
    rng = np.random.default_rng(5)
    frames = rng.integers(0, 256, (8, 300, 257)).astype(np.uint8)  # several row tiles
    paths = []
    for i, f in enumerate(frames):
        paths.append(tmp_path / f"f{i}.tif")
        cv2.imwrite(str(paths[i]), f, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    mapped = [map_frame(p, f.shape, np.uint8) for p, f in zip(paths, frames)]
    assert all(m is not None for m in mapped)
    ref = wrapped_phase(frames, 250)
    for seq in ([f.copy() for f in frames], mapped, tuple(mapped)):
        got = wrapped_phase(seq, 250, out=_empty_like_wrapped(frames.shape[1:]))
        for name in ("phase", "modulation", "background", "saturated", "residual_var"):
            a, b = getattr(got, name), getattr(ref, name)
            if fast or name in ("saturated", "background"):
                np.testing.assert_array_equal(a, b, err_msg=name)
            else:  # OpenCV's SIMD sums may round a last bit differently in other buffers
                np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4, err_msg=name)
    with pytest.raises(ValueError, match="one shape and dtype"):
        wrapped_phase([frames[0], frames[1], frames[2].astype(np.uint16)])


def test_mapped_folder_calibration_equals_the_buffered_one(tmp_path, kernels, monkeypatch):
    """Frames mapped from the TIFFs or read into buffers: the same samples, bit for bit."""
    import ptpcore.io.fastio as fastio
    from dataclasses import replace

    from ptpcore.io import DatasetSource
    from ptpcore.run import collect_samples
    from ptpcore.rig import save_rig
    from ptpcore.simulate import VirtualRig, scaled_preset

    rig, settings = scaled_preset("realistic", 160)
    vr = VirtualRig(rig.with_z(rig.stage.z_mm[:4]), settings, seed=4)
    rig = replace(vr.rig, template="z{pos:02d}/{dir}_{period}_{step}.tif")
    save_rig(rig, tmp_path / "rig.toml")
    for k in range(rig.stage.n_positions):
        for (d, _j, t, n, big_n), img in vr.frames(k):
            p = tmp_path / rig.image_name(k, d, t, n, big_n)
            p.parent.mkdir(exist_ok=True)
            cv2.imwrite(str(p), img, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    calls = {"mapped": 0}
    real = fastio.map_frame

    def counting(*args):
        out = real(*args)
        calls["mapped"] += out is not None
        return out

    monkeypatch.setattr(fastio, "map_frame", counting)
    got = collect_samples(DatasetSource(tmp_path), spill=False)
    assert calls["mapped"] == sum(rig.fringes.steps) * 2 * rig.stage.n_positions
    monkeypatch.setattr(fastio, "map_frame", lambda *args: None)  # read into buffers
    ref = collect_samples(DatasetSource(tmp_path), spill=False)
    for name in ("x", "y", "x_ref", "y_ref", "reasons", "modulation", "background"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    assert (got.reasons == 0).mean() > 0.5
    assert got.noise.read_var == ref.noise.read_var and got.noise.gain == ref.noise.gain


def test_spill_rows_written_from_threads_make_the_maps(tmp_path):
    """SpillStore.write_rows: row blocks in any order, from several threads at once."""
    from concurrent.futures import ThreadPoolExecutor

    from ptpcore.io import SpillStore, read_block

    rng = np.random.default_rng(7)
    k, h, w = 3, 50, 37
    want = {"x": rng.normal(size=(k, h, w)).astype(np.float32), "r": rng.integers(0, 9, (k, h, w)).astype(np.uint8)}
    store = SpillStore(k, (h, w), {"x": np.float32, "r": np.uint8}, {"x": np.nan, "r": 0xFF}, tmp_path)
    blocks = [(kk, r0, min(h, r0 + 7)) for kk in (0, 2) for r0 in range(0, h, 7)]
    rng.shuffle(blocks)
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda b: [store.write_rows(n, b[0], b[1], want[n][b[0], b[1]:b[2]]) for n in want], blocks))
    for n in want:
        for kk in (0, 2):
            store.mark_written(n, kk)
    with pytest.raises(ValueError, match="do not fit"):
        store.write_rows("x", 1, h - 2, want["x"][1, :5])
    with pytest.raises(ValueError, match="do not fit"):
        store.write_rows("x", 1, 0, want["x"][1, :5, :-1])
    store.finish()  # position 1 was never written: its fill values
    arrays = store.arrays()
    for n in want:
        np.testing.assert_array_equal(arrays[n][[0, 2]], want[n][[0, 2]])
        np.testing.assert_array_equal(read_block(arrays[n], 10, 400, [2, 0]),  # file reads
                                      want[n][[2, 0]].reshape(2, -1)[:, 10:400])
    assert np.isnan(arrays["x"][1]).all() and (arrays["r"][1] == 0xFF).all()


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_wrapped_phase_black_equals_black_clipped(dtype):
    """The black-clipping test kept beside the N-step sums equals :func:`black_clipped` (both paths)."""
    from ptpcore.decode.phase import WrappedPhase, black_clipped, wrapped_phase

    rng = np.random.default_rng(7)
    frames = rng.integers(0, 40, (8, 37, 53)).astype(dtype)
    got = wrapped_phase(frames, 255, black_level=0.0)
    np.testing.assert_array_equal(got.black, black_clipped(frames))
    np.testing.assert_array_equal(black_clipped(frames), (frames.astype(np.float64) <= 0.0).any(axis=0))
    out = WrappedPhase(*(np.empty((37, 53), np.float32) for _ in range(3)), np.empty((37, 53), bool), None)
    assert wrapped_phase(frames, 255, out=out, black_level=0.0).black is not None
