"""Files and the data structures that cross them: dataset folders, samples, LUT files,
fast readers and spill stores.

- :mod:`.dataset` — frame sources (dataset folders, the virtual rig) and one-pass validation;
- :mod:`.images` — grey PNG/TIFF decoded into a caller's buffer (tifffile, imagecodecs);
- :mod:`.fastio` — page-cache mapped frame reads (the spill store for big sensors is
  :mod:`ptpcore.store`'s; ``SpillStore`` and ``read_block`` are re-exported here);
- :mod:`.readahead` — a position's sets of frames from any source, read ahead from a folder;
- :mod:`.samples` — :class:`SampleStack`, every pixel's samples over all positions;
- :mod:`.sample_store` — each decoded position's world coordinates into the stack, in memory or spilled;
- :mod:`.lutfile` — :class:`Lut`, its evaluation and ``ptp-lut/1`` files;
- :mod:`.pointcloud` — :class:`PointCloud` (what ``Lut.points`` returns), height maps, PLY/.npy/.h5 writers.

May import :mod:`ptpcore.decode`, :mod:`ptpcore.rig`, :mod:`ptpcore.store` and the base modules.
"""

from .dataset import (FrameSource, DatasetSource, SimulatedSource, ImageHeader, DatasetReport,
    read_image, read_header, validate_dataset, check_calibration_design, open_source)
from .fastio import read_into, map_frame, tiff_layout
from ptpcore.store import SpillStore, read_block
from .samples import SampleStack
from .readahead import READ_AHEAD_BYTES, DatasetReader, source_sets
from .sample_store import SampleWriter, world_xy
from .lutfile import LUT_FORMAT, Lut, LutEvaluation, save_lut, load_lut, MODELS
from .pointcloud import PointCloud, read_height_map, write_point_cloud
from .outputs import PLAIN_FOLDER, Output, guard_outputs

__all__ = [
    "FrameSource",
    "DatasetSource",
    "SimulatedSource",
    "ImageHeader",
    "DatasetReport",
    "read_image",
    "read_header",
    "validate_dataset",
    "check_calibration_design",
    "open_source",
    "read_into",
    "map_frame",
    "tiff_layout",
    "SpillStore",
    "read_block",
    "SampleStack",
    "READ_AHEAD_BYTES",
    "DatasetReader",
    "source_sets",
    "SampleWriter",
    "world_xy",
    "LUT_FORMAT",
    "Lut",
    "LutEvaluation",
    "save_lut",
    "load_lut",
    "MODELS",
    "PointCloud",
    "read_height_map",
    "write_point_cloud",
    "PLAIN_FOLDER",
    "Output",
    "guard_outputs",
]
