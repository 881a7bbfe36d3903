"""The spilled sample stack written tile by tile (``SpillStore.write_rows``) equals the
stack kept in memory, on both decoding paths (numba kernels and numpy/OpenCV)."""

from __future__ import annotations

import sys
from dataclasses import replace

import cv2
import numpy as np
import pytest

from ptpcore.io import DatasetSource
from ptpcore.fit import fit_lut
from ptpcore.run import collect_samples
from ptpcore.rig import save_rig
from ptpcore.simulate import VirtualRig, scaled_preset


@pytest.fixture(scope="module")
def tiff_folder(tmp_path_factory):
    rig, settings = scaled_preset("realistic", 160)
    vr = VirtualRig(rig.with_z(rig.stage.z_mm[:5]), settings, seed=6)
    rig = replace(vr.rig, template="z{pos:02d}/{dir}_{period}_{step}.tif")
    folder = tmp_path_factory.mktemp("tiffs")
    save_rig(rig, folder / "rig.toml")
    for k in range(rig.stage.n_positions):
        for (d, _j, t, n, big_n), img in vr.frames(k):
            p = folder / rig.image_name(k, d, t, n, big_n)
            p.parent.mkdir(exist_ok=True)
            cv2.imwrite(str(p), img, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    return folder


@pytest.mark.parametrize("numba", [True, False])
def test_spilled_stack_equals_the_one_in_memory(tiff_folder, tmp_path, monkeypatch, numba):
    import ptpcore.decode.phase as phase

    if numba:
        pytest.importorskip("numba")
        monkeypatch.delenv("PTP_NO_NUMBA", raising=False)
    else:
        monkeypatch.setenv("PTP_NO_NUMBA", "1")
    # Small row tiles on the numpy path: many tiles write their rows (157 at 5 MP).
    monkeypatch.setattr(phase, "TILE_PIXELS", 160 * 7)
    monkeypatch.setattr("ptpcore.io.sample_store.TILE_PIXELS", 160 * 7)
    src = DatasetSource(tiff_folder)
    mem = collect_samples(src, spill=False)
    part = collect_samples(src, spill=True, spill_dir=tmp_path, positions=[0, 1, 3, 4])
    assert (part.reasons[2] == 0xFF).all() and np.isnan(part.x[2]).all() and (part.modulation[2] == 0).all()
    np.testing.assert_array_equal(part.reasons[[0, 1, 3, 4]], mem.reasons[[0, 1, 3, 4]])
    del part
    spilled = collect_samples(src, spill=True, spill_dir=tmp_path)
    assert isinstance(spilled.x, np.memmap)
    keep = [0, 1, 2, 3, 4]
    # Bit for bit where no float32 sum is involved; OpenCV's SIMD sums (numpy path) can round
    # a last bit differently in other buffers (modulation: 1e-7 relative, coordinates 1e-9 mm).
    np.testing.assert_array_equal(spilled.reasons[keep], mem.reasons[keep])
    np.testing.assert_array_equal(spilled.background[keep], mem.background[keep])
    exact = numba  # the kernels read the same bytes the same way
    for name in ("x", "y"):
        a, b = getattr(spilled, name)[keep], getattr(mem, name)[keep]
        if exact:
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-9, err_msg=name)
    if exact:
        np.testing.assert_array_equal(spilled.modulation[keep], mem.modulation[keep])
    else:
        np.testing.assert_allclose(spilled.modulation[keep], mem.modulation[keep], rtol=1e-6)
    a = fit_lut(mem, "poly", 2, positions=keep)
    b = fit_lut(spilled, "poly", 2, positions=keep)
    np.testing.assert_array_equal(a.valid, b.valid)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-8)
    assert a.valid.mean() > 0.5


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")
def test_mapped_pages_are_released_in_ranges_and_the_data_stays(monkeypatch):
    """release_mapped_pages drops a spilled map's resident pages (madvise holds the GIL: in ranges of
    _MADVISE_BYTES, here 3 pages, the last range short) and the values read back unchanged."""
    import mmap

    from ptpcore.store import positions as fastio

    def rss_file_mb():
        status = open("/proc/self/status").read()
        return int(status.split("RssFile:")[1].split()[0]) / 1024

    monkeypatch.setattr(fastio, "_MADVISE_BYTES", 3 * mmap.PAGESIZE)
    store = fastio.SpillStore(4, (1000, 2001), {"x": np.float32}, {"x": np.nan})
    x = store.arrays()["x"]
    x[:] = np.arange(2001, dtype=np.float32)  # 32 MB, every page resident
    before = rss_file_mb()
    fastio.release_mapped_pages()
    assert rss_file_mb() < before - 20
    assert np.array_equal(np.asarray(x[3, 999]), np.arange(2001, dtype=np.float32))
