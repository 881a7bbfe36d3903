"""``ptp decode``'s file (issue 33): gzip + shuffle or no filter at all, written on a thread of its own
while the next position decodes, the same values either way."""

import threading

import h5py
import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.io import h5chunks
from ptpcore.io.dataset import DatasetSource
from ptpcore.io.decodedfile import BackgroundWriter, load_decoded
from ptpcore.run.decoding import decode_dataset
from ptpcore.simulate import scaled_preset, simulate_dataset

FIELDS = ("positions", "z_mm", "u", "v", "modulation", "background", "reasons")


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    rig, settings = scaled_preset("realistic", 96, positions=3)
    return simulate_dataset(tmp_path_factory.mktemp("ds") / "ds", rig, settings, seed=4)


@pytest.fixture(scope="module")
def in_memory(small_dataset):
    """The small dataset decoded into memory (no file)."""
    return decode_dataset(DatasetSource(small_dataset)).decoded


@pytest.mark.parametrize("compression", ["gzip", "none"])
def test_the_file_holds_the_decoded_maps_with_the_filters_asked_for(small_dataset, in_memory, tmp_path, compression):
    """The file (written in the background, position by position) holds the very values of the decode
    kept in memory, under HDF5's built-in filters: shuffle + deflate, or none."""
    want = in_memory
    out = tmp_path / f"{compression}.decoded.h5"
    assert main(["decode", str(small_dataset), "--out", str(out), "--compression", compression, "-q"]) == 0
    got = load_decoded(out)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    assert got.reason_bits == want.reason_bits
    with h5py.File(out, "r") as f:
        for name in ("u", "v", "modulation", "background", "reasons"):
            d = f[name]
            if compression == "gzip":
                assert (d.compression, d.compression_opts, d.shuffle) == ("gzip", h5chunks.GZIP_LEVEL, True)
            else:
                assert d.compression is None and not d.shuffle


def test_an_unknown_compression_is_refused(small_dataset, tmp_path, capsys):
    assert main(["decode", str(small_dataset), "--out", str(tmp_path / "x.decoded.h5"), "--compression", "lzf"]) == 2
    assert "--compression" in capsys.readouterr().err
    with pytest.raises(ValueError, match="compression"):
        decode_dataset(DatasetSource(small_dataset), [0], out=tmp_path / "y.decoded.h5", compression="lzf")
    assert not (tmp_path / "y.decoded.h5").exists()


def test_raw_chunks_are_stored_as_h5py_stores_them(tmp_path):
    """Without a filter, each chunk's bytes as h5py's own ``dset[i] = x`` stores them."""
    rng = np.random.default_rng(5)
    shape, chunks = (3, 2, 117, 33), (1, 1, 50, 33)
    data = rng.standard_normal(shape).astype(np.float32)
    with h5py.File(tmp_path / "r.h5", "w") as f:
        ours, theirs = (f.create_dataset(n, shape, np.float32, chunks=chunks, fillvalue=np.nan) for n in "ot")
        for i in range(2):
            h5chunks.write_compressed(ours, i, data[i])
            theirs[i] = data[i]
    with h5py.File(tmp_path / "r.h5", "r") as f:
        np.testing.assert_array_equal(f["o"][:2], data[:2])
        assert np.isnan(f["o"][2]).all()
        a, b = f["o"].id, f["t"].id
        assert a.get_num_chunks() == b.get_num_chunks()
        for n in range(a.get_num_chunks()):
            off = a.get_chunk_info(n).chunk_offset
            if off[-2] + chunks[-2] <= shape[-2]:  # a ragged edge chunk's padding may differ
                assert a.read_direct_chunk(off)[1] == b.read_direct_chunk(off)[1]


class _SlowSink:
    def __init__(self, fail_at=None):
        self.release = threading.Event()
        self.written = []
        self.fail_at = fail_at

    def write(self, i, *maps):
        self.release.wait(10)
        if i == self.fail_at:
            raise OSError(f"disk full at {i}")
        self.written.append(i)


def test_the_background_writer_overlaps_and_keeps_one_position_in_flight():
    """``write`` returns while the sink still writes; the next ``write`` waits for it; ``close`` waits
    for the last one."""
    sink = _SlowSink()
    writer = BackgroundWriter(sink)
    writer.write(0, None, None, None, None, None)
    assert sink.written == []  # handed over, not written yet: the caller decodes on meanwhile
    sink.release.set()
    writer.write(1, None, None, None, None, None)
    assert sink.written[0] == 0
    writer.close()
    assert sink.written == [0, 1]


def test_an_error_of_the_writing_thread_reaches_the_caller():
    sink = _SlowSink(fail_at=0)
    sink.release.set()
    writer = BackgroundWriter(sink)
    writer.write(0, None, None, None, None, None)
    with pytest.raises(OSError, match="disk full at 0"):
        writer.close()
    writer = BackgroundWriter(_SlowSink(fail_at=0))
    writer.sink.release.set()
    writer.write(0, None, None, None, None, None)
    writer.close(quiet=True)  # another error on its way: this one is not raised over it
