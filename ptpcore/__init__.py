"""ptpcore: the headless engine of PTP Studio (point-to-point camera calibration).

Layers, bottom up:

- :mod:`ptpcore.rig` — the rig description and ``rig.toml`` (``ptp-dataset/1``);
- :mod:`ptpcore.patterns` — the LCD's fringe patterns and the design check;
- :mod:`ptpcore.simulate` — a virtual rig with exact ground truth;
- :mod:`ptpcore.dataset` — reading image folders;
- :mod:`ptpcore.phase` — phase retrieval, unwrapping, LCD coordinates, validity;
- :mod:`ptpcore.lut` — per-pixel LUTs and ``ptp-lut/1`` files;
- :mod:`ptpcore.pipeline` — the streaming calibration from images to LUT;
- :mod:`ptpcore.pinhole`, :mod:`ptpcore.compare` — the 3DSTC baseline and the comparison;
- :mod:`ptpcore.cli` — the ``ptp`` command line.

The engine never imports Qt: the GUI (``ptp_studio``) sits on top of it.
"""

__version__ = "0.1.0"
