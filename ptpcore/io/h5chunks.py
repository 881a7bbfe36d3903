"""HDF5 datasets whose chunks are compressed on all cores.

h5py compresses a dataset's chunks one after the other on the calling thread: a 5 MP poly
LUT (320 MB of coefficients, 480 MB in all) took 3.5 s of a single core to write, the
largest single step after the fit. Here each chunk goes through the same filters HDF5 would
apply (its byte shuffle, then zlib's deflate, which releases the GIL) on the tile pool, and
is stored with ``write_direct_chunk``: the file is an ordinary gzip + shuffle dataset that
any HDF5 reader (h5py, the C library, HDFView) decodes with its built-in filters. No library
offers parallel HDF5 compression (h5py and libhdf5 have none, hdf5plugin's threaded
compressors need the plugin on every reader), hence these few lines.
"""

from __future__ import annotations

import itertools
import zlib

import numpy as np

from ptpcore.parallel import map_in_order

__all__ = ["create_compressed", "write_compressed", "chunk_shape", "GZIP_LEVEL"]

GZIP_LEVEL = 1
CHUNK_BYTES = 1 << 20
"""About this many bytes a chunk (the HDF5 chunk cache's default size): whole image rows."""
BATCH = 64
"""Chunks compressed ahead of the writes (bounds the compressed bytes held at once)."""


def chunk_shape(shape: tuple, itemsize: int) -> tuple:
    """Chunks of whole rows of the last two axes, about :data:`CHUNK_BYTES`; 1 along leading axes."""
    h, w = shape[-2:]
    rows = max(1, min(h, CHUNK_BYTES // max(1, w * itemsize)))
    return (1,) * (len(shape) - 2) + (rows, w)


def _encoded(data: np.ndarray, chunks: tuple, start: tuple, deflate: bool = True) -> bytes:
    """One chunk as HDF5's shuffle + deflate filters would store it, or without ``deflate`` as HDF5 stores
    a chunk without filters (its raw bytes); edge chunks zero-padded to full size."""
    src = data[tuple(slice(s, s + c) for s, c in zip(start, chunks))]
    if src.shape == chunks:
        block = np.ascontiguousarray(src)
    else:
        block = np.zeros(chunks, data.dtype)
        block[tuple(slice(0, n) for n in src.shape)] = src
    raw = block.reshape(-1).view(np.uint8)
    if not deflate:
        return raw.tobytes()
    if data.dtype.itemsize > 1:  # the shuffle filter: byte 0 of every element, then byte 1, ...
        raw = np.ascontiguousarray(raw.reshape(-1, data.dtype.itemsize).T)
    return zlib.compress(raw, GZIP_LEVEL)


def create_compressed(group, name: str, data):
    """``group.create_dataset(name, data=data, compression="gzip", compression_opts=1, shuffle=True)``,
    the chunks compressed on the tile pool.

    Parameters
    ----------
    group : h5py.Group
    name : str
    data : array_like
        Any numeric array of at least 2 dimensions (smaller ones are written the plain way).

    Returns
    -------
    h5py.Dataset
    """
    data = np.asarray(data)
    if data.ndim < 2 or data.size == 0 or data.dtype.kind not in "biuf":
        return group.create_dataset(name, data=data, chunks=True if data.size else None,
                                    compression="gzip" if data.size else None,
                                    compression_opts=GZIP_LEVEL if data.size else None, shuffle=bool(data.size))
    chunks = chunk_shape(data.shape, data.dtype.itemsize)
    dset = group.create_dataset(name, shape=data.shape, dtype=data.dtype, chunks=chunks, compression="gzip",
                                compression_opts=GZIP_LEVEL, shuffle=True)
    _write_chunks(dset, data, chunks, ())
    return dset


def _write_chunks(dset, data: np.ndarray, chunks: tuple, lead: tuple, deflate: bool = True) -> None:
    """Every chunk of ``data`` compressed on the tile pool (or as raw bytes without ``deflate``), in
    batches, stored at ``lead + its start``."""
    starts = list(itertools.product(*(range(0, n, c) for n, c in zip(data.shape, chunks))))
    for b in range(0, len(starts), BATCH):
        batch = starts[b:b + BATCH]
        payloads = map_in_order(lambda s: _encoded(data, chunks, s, deflate), batch) if deflate else \
            (_encoded(data, chunks, s, False) for s in batch)
        for start, payload in zip(batch, payloads):
            dset.id.write_direct_chunk(lead + start, payload)


def write_compressed(dset, index: int, data) -> None:
    """``dset[index] = data``, its chunks compressed on the tile pool.

    For a dataset written one leading index at a time (a position of a ``ptp-decoded/1``
    file): chunked ``(1, ...)`` along its first axis, gzip at :data:`GZIP_LEVEL` with the
    shuffle filter, or without any filter (each chunk's bytes stored as they are, one HDF5
    call a chunk: a whole position in one call held the GIL for its whole write). Any other
    dataset is written the plain way.

    Parameters
    ----------
    dset : h5py.Dataset
    index : int
        Along the first axis.
    data : array_like
        Shape ``dset.shape[1:]``, converted to ``dset.dtype``.
    """
    data = np.ascontiguousarray(data, dtype=dset.dtype)
    plain = dset.chunks is not None and dset.chunks[0] == 1 and not dset.fletcher32 and dset.scaleoffset is None
    deflate = dset.compression == "gzip" and dset.compression_opts == GZIP_LEVEL and dset.shuffle
    raw = dset.compression is None and not dset.shuffle
    if not (plain and (deflate or raw) and data.ndim >= 2) or data.shape != dset.shape[1:]:
        dset[index] = data
        return
    _write_chunks(dset, data, dset.chunks[1:], (index,), deflate)
