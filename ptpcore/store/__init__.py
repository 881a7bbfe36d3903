"""Where big arrays live while a run works on them: one mechanism below every stage.

A stage computes on in-memory blocks of rows; this package decides whether the whole array is in
memory or in a temporary file, and gives memory back between steps. Every stage uses it the same way:

- :mod:`.rows` — image-shaped float64 maps ``(*lead, H, W)`` by row ranges (the smooth fit's pixel
  fits, rays, sums and weights): :func:`row_store`, :func:`park`, :func:`load`; methods ``store[..., r0:r1] = v``,
  ``rows``, ``row_block``, ``plane``, ``plane_rows``, ``add_rows``, ``load``;
- :mod:`.positions` — per-position arrays ``(K, H, W)`` (the decoder's sample stack, the comparison's
  blocks, the model choice's predictions, the leave-one-out's noise estimates): :class:`SpillStore`
  (``write_rows``, ``read``, ``arrays``), :class:`MemoryPositions`, :func:`position_store`,
  :func:`read_block` (pixel ranges of a stack, file reads when it is spilled);
- :mod:`.release` — :func:`release_free_memory` (mapped pages of spilled stacks, then the C heap).

Files go to ``PTP_SPILL_DIR`` (default the system's temporary folder). May import
:mod:`ptpcore.atomic` and :mod:`ptpcore.parallel` only.
"""

from .release import release_free_memory, on_release
from .positions import (SpillStore, MemoryPositions, position_store, read_block, release_mapped_pages,
                        remove_orphaned_spill_files)
from .rows import SPILL_PIXELS, FileRows, MemoryRows, PlaneRows, row_store, park, load, spills

__all__ = [
    "release_free_memory",
    "on_release",
    "SpillStore",
    "remove_orphaned_spill_files",
    "MemoryPositions",
    "position_store",
    "read_block",
    "release_mapped_pages",
    "SPILL_PIXELS",
    "FileRows",
    "MemoryRows",
    "PlaneRows",
    "row_store",
    "park",
    "load",
    "spills",
]
