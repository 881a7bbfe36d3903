"""Chunks compressed on the tile pool read back through HDF5's own filters (ptpcore.io.h5chunks)."""

import h5py
import numpy as np
import pytest

from ptpcore.io import h5chunks


@pytest.mark.parametrize("shape, dtype", [((3, 301, 257), np.float64), ((130, 77), np.float32),
                                          ((65, 1100), np.uint16), ((5, 3), np.uint8), ((2, 1, 9000), np.float64)])
def test_datasets_read_back_through_hdf5s_filters(tmp_path, monkeypatch, shape, dtype):
    monkeypatch.setattr(h5chunks, "CHUNK_BYTES", 4096)  # many chunks, ragged edges
    rng = np.random.default_rng(1)
    data = (rng.standard_normal(shape) * 1e3).astype(dtype)
    if data.dtype.kind == "f":
        data.flat[::7] = np.nan
    path = tmp_path / "c.h5"
    with h5py.File(path, "w") as f:
        h5chunks.create_compressed(f, "a", data)
    with h5py.File(path, "r") as f:
        ds = f["a"]
        assert ds.compression == "gzip" and ds.compression_opts == h5chunks.GZIP_LEVEL and ds.shuffle
        assert ds.chunks == h5chunks.chunk_shape(shape, data.dtype.itemsize)
        np.testing.assert_array_equal(ds[()], data)
        assert ds.dtype == data.dtype
        # a part read through the chunk index, as a scanner's reader does
        np.testing.assert_array_equal(ds[..., 1:4, 2:5], data[..., 1:4, 2:5])


def test_compression_matches_h5pys_own(tmp_path):
    """The same filters at the same level: about the same stored size as h5py's own writer."""
    rng = np.random.default_rng(2)
    data = np.cumsum(rng.standard_normal((400, 600)), axis=1).astype(np.float32)
    with h5py.File(tmp_path / "c.h5", "w") as f:
        ours = h5chunks.create_compressed(f, "a", data).id.get_storage_size()
        ref = f.create_dataset("b", data=data, chunks=h5chunks.chunk_shape(data.shape, 4), compression="gzip",
                               compression_opts=1, shuffle=True).id.get_storage_size()
    assert abs(ours - ref) <= 0.01 * ref


def test_small_and_empty_arrays_are_written_the_plain_way(tmp_path):
    with h5py.File(tmp_path / "c.h5", "w") as f:
        h5chunks.create_compressed(f, "v", np.arange(5.0))
        h5chunks.create_compressed(f, "e", np.zeros((0, 4)))
    with h5py.File(tmp_path / "c.h5", "r") as f:
        np.testing.assert_array_equal(f["v"][()], np.arange(5.0))
        assert f["e"].shape == (0, 4)
