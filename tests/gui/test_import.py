"""Importing a ptp-dataset/1 folder: its rig.toml fills the form (read-only) and the acquisition reads it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from gui_helpers import run_job

from ptpcore.rig import Camera
from ptpcore.simulate import preset, simulate_dataset


def test_import_a_dataset_folder(wizard, qtbot, tmp_path):
    rig, settings = preset("mild")
    rig = replace(rig, camera=Camera(64, 48, rig.camera.bit_depth)).with_z(np.linspace(0, 40, 5))
    folder = simulate_dataset(tmp_path / "ds", rig, settings, seed=3)

    page = wizard.page_by_key["rig"]
    page.import_folder(folder)
    s = wizard.model.session
    assert wizard.next_blocker() is None
    assert s.source_kind == "folder"
    assert (s.rig.camera, s.rig.stage, s.rig.fringes) == (rig.camera, rig.stage, rig.fringes)
    assert page.cam_w.value() == 64 and not page.cam_w.isEnabled()  # a dataset's rig is what it says
    assert not page.sim_box.isEnabled()
    wizard.next()
    fr = wizard.page_by_key["fringes"]
    assert not fr.periods.isEnabled() and fr.report is not None
    wizard.next()
    acq = wizard.page_by_key["acquire"]
    assert "dataset folder" in acq.source_label.text()
    assert not acq.write_check.isVisible()
    assert run_job(qtbot, acq.start()) == "finished"
    assert s.samples.x.shape == (5, 48, 64)
    assert s.truth is not None  # truth.h5 beside the images
    assert wizard.next_blocker() is None
