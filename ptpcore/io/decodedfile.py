"""``ptp-decoded/1``: the decoded LCD coordinates of some positions (FORMATS.md).

Arrays ``[K, H, W]`` (``[K, 2, H, W]`` per direction x, y) for K positions in
``rig.toml`` order; NaN where invalid or the direction is absent.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass

import h5py
import numpy as np

from ptpcore import __version__
from ptpcore.atomic import atomic_path

__all__ = ["DECODED_FORMAT", "Decoded", "save_decoded", "load_decoded"]

DECODED_FORMAT = "ptp-decoded/1"

_OPTS = dict(chunks=True, compression="gzip", compression_opts=1, shuffle=True)


@dataclass
class Decoded:
    """The content of a ``ptp-decoded/1`` file.

    Attributes
    ----------
    positions : (K,) int32
        Index of each decoded position in the dataset.
    z_mm : (K,) float64
    u, v : (K, H, W) float32
        LCD coordinates (px, carrier removed); NaN where invalid or the direction is absent.
    modulation, background : (K, 2, H, W) float32
        At the finest level, per direction (x, y), camera DN.
    reasons : (K, 2, H, W) uint16
        Per direction: 0 valid, else bit flags named by ``reason_bits``.
    reason_bits : dict of str -> int
    rig_toml : str
    """

    positions: np.ndarray
    z_mm: np.ndarray
    u: np.ndarray
    v: np.ndarray
    modulation: np.ndarray
    background: np.ndarray
    reasons: np.ndarray
    reason_bits: dict
    rig_toml: str


def save_decoded(path, dec: Decoded) -> None:
    """Write a ``ptp-decoded/1`` file atomically."""
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = DECODED_FORMAT
            f.attrs["software"] = f"ptpcore {__version__}"
            f.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
            f.create_group("rig").attrs["toml"] = dec.rig_toml
            f["positions"] = np.asarray(dec.positions, np.int32)
            f["z_mm"] = np.asarray(dec.z_mm, np.float64)
            for name in ("u", "v", "modulation", "background"):
                f.create_dataset(name, data=np.asarray(getattr(dec, name), np.float32), **_OPTS)
            r = f.create_dataset("reasons", data=np.asarray(dec.reasons, np.uint16), **_OPTS)
            for key, bit in dec.reason_bits.items():
                r.attrs[key] = np.uint16(bit)


def load_decoded(path) -> Decoded:
    """Read a ``ptp-decoded/1`` file."""
    with h5py.File(path, "r") as f:
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode()
        if fmt != DECODED_FORMAT:
            raise ValueError(f"{path}: not a {DECODED_FORMAT} file (format {fmt!r})")
        toml = f["rig"].attrs["toml"]
        return Decoded(f["positions"][()], f["z_mm"][()], f["u"][()], f["v"][()], f["modulation"][()],
                       f["background"][()], f["reasons"][()], {k: int(v) for k, v in f["reasons"].attrs.items()},
                       toml.decode() if isinstance(toml, bytes) else str(toml))
