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


@pytest.mark.parametrize("shape, dtype", [((3, 2, 517, 333), np.float32), ((3, 517, 333), np.uint16)])
def test_a_slab_is_stored_as_h5py_stores_it(tmp_path, shape, dtype):
    """write_compressed(dset, i, x) leaves the same chunks as ``dset[i] = x`` (byte for byte where the
    chunk is whole: a ragged edge chunk's padding is zeros here, the fill value in h5py's); unwritten
    slabs keep the fill."""
    rng = np.random.default_rng(2)
    data = (rng.standard_normal(shape) * 100).astype(dtype)
    chunks = (1,) * (len(shape) - 2) + (50, shape[-1])  # ragged last chunk of rows
    with h5py.File(tmp_path / "s.h5", "w") as f:
        ours, theirs = (f.create_dataset(n, shape, dtype, chunks=chunks, compression="gzip",
                                         compression_opts=h5chunks.GZIP_LEVEL, shuffle=True, fillvalue=7)
                        for n in ("ours", "theirs"))
        for i in range(shape[0] - 1):
            h5chunks.write_compressed(ours, i, data[i])
            theirs[i] = data[i]
    with h5py.File(tmp_path / "s.h5", "r") as f:
        np.testing.assert_array_equal(f["ours"][:-1], data[:-1])
        assert (f["ours"][-1] == 7).all()
        a, b = f["ours"].id, f["theirs"].id
        assert a.get_num_chunks() == b.get_num_chunks()
        for n in range(a.get_num_chunks()):
            ca, cb = a.get_chunk_info(n), b.get_chunk_info(n)
            assert ca.chunk_offset == cb.chunk_offset
            if ca.chunk_offset[-2] + chunks[-2] <= shape[-2]:
                assert a.read_direct_chunk(ca.chunk_offset)[1] == b.read_direct_chunk(cb.chunk_offset)[1]


def test_other_datasets_are_written_the_plain_way(tmp_path):
    data = np.arange(60.0).reshape(6, 10)
    with h5py.File(tmp_path / "p.h5", "w") as f:
        d = f.create_dataset("lzf", (2, 6, 10), np.float64, chunks=(1, 3, 10), compression="lzf")
        h5chunks.write_compressed(d, 1, data)
        np.testing.assert_array_equal(d[1], data)
