"""Sample storage: each decoded position's world coordinates into the sample stack, row tile by row tile.

:class:`SampleWriter` holds the stack a streaming decode fills (:class:`~ptpcore.io.samples.SampleStack`
in memory, or its ``(K, H, W)`` arrays in a temporary file, :class:`ptpcore.store.SpillStore`, so
memory stays flat however many positions there are); each row tile of a position computes
:func:`world_xy` relative to the pixel's first valid position and writes its rows as soon as it
has stored them (:func:`store_rows`, or :func:`store_rows_fused` with the numba kernels, bit-equal).
"""

from __future__ import annotations

import numpy as np

from ptpcore.decode.phase import DecodedPosition, WrappedPhase, fused_kernels
from ptpcore.io.samples import SampleStack
from ptpcore.parallel import KERNEL_TILE_PIXELS, TILE_PIXELS, run_tiles
from ptpcore.rig import Rig
from ptpcore.store import SpillStore

__all__ = ["world_xy", "SampleWriter", "store_rows", "store_rows_fused"]


def world_xy(rig: Rig, pos: DecodedPosition) -> tuple[np.ndarray, np.ndarray]:
    """World X, Y (mm) of a decoded position: ``X = u*pitch_x + a*z`` (docs/method.md section 2)."""
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    x = pos.u * px + a * pos.z_mm if pos.u is not None else None
    y = pos.v * py + b * pos.z_mm if pos.v is not None else None
    return x, y


class SampleWriter:
    """The sample stack a streaming decode fills, position by position: in memory or spilled to a file.

    Parameters
    ----------
    rig : Rig
        Its stage gives the K positions, its camera the ``(H, W)`` shape.
    spill : bool
        Keep the ``(K, H, W)`` arrays in a temporary file (:class:`ptpcore.store.SpillStore`,
        ``numpy.memmap`` once finished) instead of memory.
    spill_dir : path, optional
        Folder of that file (default: the system's temporary folder).

    Notes
    -----
    Positions never put stay invalid (x, y NaN, reasons 0xFF, modulation and background 0).
    """

    def __init__(self, rig: Rig, spill: bool, spill_dir=None):
        self.rig = rig
        shape = rig.camera.shape
        self.z_all = np.asarray(rig.stage.z_mm, dtype=float)
        self.store = self.spill_maps = None
        if spill:
            self.store = SpillStore(rig.stage.n_positions, shape,
                                    {"x": np.float32, "y": np.float32, "reasons": np.uint8,
                                     "modulation": np.float32, "background": np.float32},
                                    {"x": np.nan, "y": np.nan, "reasons": 0xFF, "modulation": 0, "background": 0},
                                    spill_dir)
            self.samples = SampleStack(self.z_all, np.empty((0, *shape), np.float32),
                                       np.empty((0, *shape), np.float32), np.full(shape, np.nan),
                                       np.full(shape, np.nan), np.empty((0, *shape), np.uint8))
            # Whole position maps only for the numpy path (_store_position).
            self.spill_maps = (None if fused_kernels() else
                               {name: np.empty(shape, dt) for name, (dt, _off) in self.store.layout.items()})
        else:
            self.samples = SampleStack.empty(rig.stage.z_mm, shape)

    @property
    def spilled(self) -> bool:
        """True when the samples go to a temporary file."""
        return self.store is not None

    def put(self, pos: DecodedPosition, k: int) -> None:
        """Store position ``k``'s samples (``pos``, both directions decoded)."""
        _store_position(self.rig, pos, k, self.samples, self.store, self.spill_maps)

    def finish(self) -> SampleStack:
        """The filled stack (spilled: its arrays mapped from the file, no noise model yet)."""
        if self.store is None:
            return self.samples
        self.store.finish()
        arrays = self.store.arrays()
        return SampleStack(self.z_all, arrays["x"], arrays["y"], self.samples.x_ref, self.samples.y_ref,
                           arrays["reasons"], arrays["modulation"], arrays["background"])


def _store_position(rig: Rig, pos: DecodedPosition, k: int, samples: SampleStack, store,
                    spill_maps: dict | None) -> None:
    """Position ``k``'s samples (``pos``) into ``samples`` (in memory) or the spill ``store``, row tile by row tile.

    Each tile writes its rows to the file as soon as it has stored them (while they are in the
    cache; positional writes from the tile pool): with the kernels from a scratch of the tile's
    rows, else from ``spill_maps``, one set of whole maps.
    """
    shape = rig.camera.shape
    fine_x, fine_y = pos.directions["x"].wrapped[-1], pos.directions["y"].wrapped[-1]
    if store is None:
        dest = {"x": samples.x[k], "y": samples.y[k], "reasons": samples.reasons[k],
                "modulation": samples.modulation[k], "background": samples.background[k]}
    else:
        dest = spill_maps
    kern = fused_kernels()

    def rows(r0: int, r1: int) -> None:
        if kern is None:
            store_rows(rig, pos, fine_x, fine_y, samples, dest, r0, r1)
            tile = {name: a[r0:r1] for name, a in dest.items()}
        else:
            tile = ({name: a[r0:r1] for name, a in dest.items()} if dest is not None else
                    {name: np.empty((r1 - r0, shape[1]), dt) for name, (dt, _off) in store.layout.items()})
            store_rows_fused(kern, rig, pos, fine_x, fine_y, samples, tile, r0, r1)
        if store is not None:
            for name, a in tile.items():
                store.write_rows(name, k, r0, a)

    run_tiles(rows, *shape, TILE_PIXELS if kern is None else KERNEL_TILE_PIXELS)
    if store is not None:
        for name in store.layout:
            store.mark_written(name, k)


def store_rows(rig: Rig, pos: DecodedPosition, fine_x: WrappedPhase, fine_y: WrappedPhase,
                samples: SampleStack, dest: dict, r0: int, r1: int) -> None:
    """:func:`world_xy` and :meth:`SampleStack.set_position` of rows ``[r0, r1)``, into ``dest``.

    Same arithmetic as those two, tile by tile (``dest`` holds the ``(H, W)``
    maps of position ``pos.index``: x, y, reasons, modulation, background).
    """
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    z = pos.z_mm
    rs = pos.reasons[r0:r1]
    valid = rs == 0
    invalid = ~valid
    for name, coord, pitch, slope, ref in (("x", pos.u, px, a, samples.x_ref), ("y", pos.v, py, b, samples.y_ref)):
        w = coord[r0:r1] * pitch
        w += slope * z
        rf = ref[r0:r1]
        new_ref = valid & np.isnan(rf)
        np.copyto(rf, w, where=new_ref)
        w -= rf
        w[invalid] = np.nan
        dest[name][r0:r1] = w
    dest["reasons"][r0:r1] = rs
    np.minimum(fine_x.modulation[r0:r1], fine_y.modulation[r0:r1], out=dest["modulation"][r0:r1])
    bg = dest["background"][r0:r1]
    np.add(fine_x.background[r0:r1], fine_y.background[r0:r1], out=bg)
    bg *= 0.5


def store_rows_fused(kern, rig: Rig, pos: DecodedPosition, fine_x: WrappedPhase, fine_y: WrappedPhase,
                      samples: SampleStack, tile: dict, r0: int, r1: int) -> None:
    """:func:`store_rows` with the numba kernel :func:`ptpcore.decode._fused.store_rows` (bit-equal),
    into ``tile``: the ``(r1 - r0, W)`` rows of each map (views of whole maps, or a tile's scratch)."""
    a, b, _ = rig.stage.direction
    px, py = rig.lcd.pitch_mm
    z = pos.z_mm
    with_bg = fine_x.background is not None and fine_y.background is not None
    bgx = fine_x.background if with_bg else fine_x.modulation
    bgy = fine_y.background if with_bg else fine_y.modulation
    rows = slice(r0, r1)
    kern.store_rows(0, r1 - r0, pos.reasons[rows], pos.u[rows], pos.v[rows], float(px), float(py), float(a * z),
                    float(b * z), samples.x_ref[rows], samples.y_ref[rows], fine_x.modulation[rows],
                    fine_y.modulation[rows], bgx[rows], bgy[rows], with_bg,
                    tile["x"], tile["y"], tile["reasons"], tile["modulation"], tile["background"])
