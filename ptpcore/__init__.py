"""ptpcore: the headless engine of PTP Studio (point-to-point camera calibration).

Rooms by stage of the run, bottom up (the order is an import-linter ``layers``
contract in ``pyproject.toml``; a room imports only rooms below it):

- :mod:`ptpcore.rig` — the rig description and ``rig.toml``;
- :mod:`ptpcore.decode` — fringe patterns, phase retrieval, unwrapping, masks, noise;
- :mod:`ptpcore.io` — dataset folders, samples, LUT files, fast readers, spill stores;
- :mod:`ptpcore.pinhole` — the pinhole + Brown lens model and its calibration;
- :mod:`ptpcore.fit` — per-pixel and smooth LUTs, their sigma maps, the model entry point;
- :mod:`ptpcore.simulate` — a virtual rig with exact ground truth;
- :mod:`ptpcore.run` / :mod:`ptpcore.evaluate` / :mod:`ptpcore.capture` — running a
  calibration (pipeline, sessions), judging it (3DSTC comparison, accuracy, views),
  driving a rig (capture sequence, devices);
- :mod:`ptpcore.cli` — the ``ptp`` command line.

Below them all: :mod:`ptpcore.errors`, :mod:`ptpcore.atomic` (atomic writes) and
:mod:`ptpcore.parallel` (the row-tile thread pool).

The names a user needs are re-exported here (``from ptpcore import calibrate,
load_lut``), imported on first use so that ``import ptpcore`` stays cheap.
The engine never imports Qt: the GUI (``ptp_studio``) sits on top of it.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# name -> module that defines it (loaded on first access, PEP 562)
_PUBLIC = {
    # rig
    "Rig": "ptpcore.rig", "Camera": "ptpcore.rig", "Lcd": "ptpcore.rig", "Stage": "ptpcore.rig",
    "FringeDesign": "ptpcore.rig", "load_rig": "ptpcore.rig", "save_rig": "ptpcore.rig",
    "rig_from_toml": "ptpcore.rig", "rig_to_toml": "ptpcore.rig",
    # decode
    "design_check": "ptpcore.decode", "Reason": "ptpcore.decode", "REASON_NAMES": "ptpcore.decode",
    "DecodeOptions": "ptpcore.decode",
    # io
    "Lut": "ptpcore.io", "LutEvaluation": "ptpcore.io", "load_lut": "ptpcore.io", "save_lut": "ptpcore.io",
    "SampleStack": "ptpcore.io", "DatasetSource": "ptpcore.io", "SimulatedSource": "ptpcore.io",
    "validate_dataset": "ptpcore.io", "read_image": "ptpcore.io",
    "PointCloud": "ptpcore.io", "read_height_map": "ptpcore.io", "write_point_cloud": "ptpcore.io",
    # pinhole
    "PinholeModel": "ptpcore.pinhole", "fit_pinhole": "ptpcore.pinhole",
    # fit
    "fit_lut": "ptpcore.fit", "fit_smooth_lut": "ptpcore.fit", "fit_model": "ptpcore.fit",
    "LUT_MODELS": "ptpcore.fit",
    # simulate
    "VirtualRig": "ptpcore.simulate", "preset": "ptpcore.simulate", "scaled_preset": "ptpcore.simulate",
    "simulate_dataset": "ptpcore.simulate", "load_truth": "ptpcore.simulate", "PRESETS": "ptpcore.simulate",
    # run
    "decode_position": "ptpcore.run", "collect_samples": "ptpcore.run", "calibrate": "ptpcore.run",
    "calibrate_session": "ptpcore.run", "Calibration": "ptpcore.run", "FitSettings": "ptpcore.fit",
    "Session": "ptpcore.run", "new_session": "ptpcore.run", "load_session": "ptpcore.run",
    "save_session": "ptpcore.run", "run_session": "ptpcore.run",
    # evaluate
    "compare": "ptpcore.evaluate", "CompareResult": "ptpcore.evaluate", "format_summary": "ptpcore.evaluate",
    "held_out_accuracy": "ptpcore.evaluate",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name: str):
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'ptpcore' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(__all__)
