"""The wizard's writing actions pass the engine's output guard (issue 41): Export (the LUT, the report,
the plots, rig.toml and the session file), Save point cloud and Save acceptance report.

Each action is driven through its file dialog, monkeypatched to answer a bad path: a file the session
reads (its dataset), a file of another kind (by content, under the name the action writes), a missing
folder, a folder that does not take files (the guard's write probe made to fail: as root a chmod does
not stop a write), a file where a folder is due. Each must show one line naming the path, start no
job, ask no question and write nothing. A good path then writes (the guard refuses nothing more).
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from gui_helpers import lut_on_export, run_job
from PySide6.QtWidgets import QFileDialog

import ptpcore.io.outputs as outputs
from ptpcore.io.lutfile import Lut, save_lut
from ptpcore.simulate import preset, simulate_dataset
from ptpcore.rig import Camera
from ptp_studio.pages.export import LUT_NAME, SESSION_NAME
from ptp_studio.widgets.acceptance import AcceptancePanel
from ptp_studio.widgets.pointcloud import PointCloudPanel


def _random_lut(h: int = 6, w: int = 8) -> Lut:
    rng = np.random.default_rng(0)
    f32 = lambda: rng.random((h, w), dtype=np.float32)  # noqa: E731
    return Lut("poly", 3, 20.0, 20.0, 0.0, 40.0, rng.random((4, h, w)), rng.random((4, h, w)), None,
               np.ones((h, w), bool), np.full((h, w), 3, np.uint16), np.zeros((h, w), np.float32),
               np.full((h, w), 40.0, np.float32), f32(), f32(), f32(), f32())


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A tiny dataset folder (the session's input in these tests) and a LUT file beside it."""
    import dataclasses

    root = tmp_path_factory.mktemp("gui-guard")
    rig, settings = preset("ideal")
    rig = dataclasses.replace(rig, camera=Camera(32, 24, 8)).with_z([0.0, 20.0])
    ds = simulate_dataset(root / "DS", rig, settings, seed=1)
    save_lut(_random_lut(), root / "other.lut.h5")
    return ds


def _snapshot(folder: Path):
    return sorted((str(p.relative_to(folder)), p.read_bytes() if p.is_file() else None)
                  for p in folder.rglob("*")) if folder.is_dir() else None


def _fail_probe_in(monkeypatch, folder: Path) -> None:
    """The guard's write probe fails in ``folder`` as in a full or read-only one (no read-only mount in
    a GUI test: mounting needs a subprocess per case)."""
    probe = outputs.probe_writable

    def refuse(where):
        if Path(where) != folder:
            return probe(where)
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(Path(where) / ".ptp-write-test-xyz"))

    monkeypatch.setattr(outputs, "probe_writable", refuse)


def _refused(jobs, started, watched: list[Path], before, questions, *words: str) -> str:
    """No job, no question, nothing written, one line naming the path."""
    assert started is None
    text = jobs.error.text()
    assert text and "\n" not in text and "Errno" not in text and ".ptp-write-test" not in text, text
    for word in words:
        assert word in text, (word, text)
    assert [_snapshot(f) for f in watched] == before
    assert questions.asked == []
    return text


def _dialog(monkeypatch, name: str, answer) -> None:
    if name == "getSaveFileName":
        monkeypatch.setattr(QFileDialog, name, lambda *a, **k: (str(answer), ""))
    else:
        monkeypatch.setattr(QFileDialog, name, lambda *a, **k: str(answer))


# --------------------------------------------------------------------------- Export, and the session file

def test_export_refuses_bad_folders_before_writing(wizard, qtbot, tmp_path, dataset, monkeypatch, questions):
    ex = lut_on_export(wizard, qtbot)
    ds = tmp_path / "DS"
    shutil.copytree(dataset, ds)
    wizard.model.session.dataset_folder = ds  # the session's input
    other_kind = tmp_path / "json-lut"
    other_kind.mkdir()
    (other_kind / LUT_NAME).write_text('{"not": "a LUT"}\n')
    session_kind = tmp_path / "lut-session"
    session_kind.mkdir()
    shutil.copy(dataset.parent / "other.lut.h5", session_kind / SESSION_NAME)
    unwritable = tmp_path / "full"
    unwritable.mkdir()
    _fail_probe_in(monkeypatch, unwritable)
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    cases = [(ds, ("rig.toml", "input")), (other_kind, (LUT_NAME, "is a JSON report, not a ptp-lut/1 file")),
             (session_kind, (SESSION_NAME, "ptp-lut/1 file, not a ptp-session/1 file")),
             (tmp_path / "missing" / "out", ("does not exist",)), (unwritable, ("cannot write", str(unwritable))),
             (a_file, ("not a folder",))]
    watched = [tmp_path]
    for folder, words in cases:
        _dialog(monkeypatch, "getExistingDirectory", folder)
        ex._browse()
        assert ex.folder.text() == str(folder)
        before = [_snapshot(f) for f in watched]
        _refused(ex.jobs, ex.export(), watched, before, questions, "Nothing written", *words)
    assert ex.files == [] and ex.blocker() is not None

    good = tmp_path / "good"
    _dialog(monkeypatch, "getExistingDirectory", good)
    ex._browse()
    assert run_job(qtbot, ex.export()) == "finished"
    assert (good / LUT_NAME).is_file() and not ex.jobs.error.isVisible()
    with h5py.File(good / SESSION_NAME, "r") as f:
        assert str(f.attrs["format"]).startswith("ptp-session/")


# --------------------------------------------------------------------------- Save point cloud

def test_save_point_cloud_refuses_bad_paths(qtbot, tmp_path, dataset, monkeypatch, questions):
    lut = _random_lut()
    panel = PointCloudPanel(lambda: lut, lambda: tmp_path)
    qtbot.addWidget(panel)
    panel.cloud = lut.points(20.0)
    assert panel.cloud.n_points > 0
    heights = tmp_path / "heights.npy"
    np.save(heights, np.full(lut.shape, 20.0))
    panel.set_height_file(heights)  # read by the action: never written
    (tmp_path / "text.ply").write_text("not a point cloud\n")
    (tmp_path / "lut.ply").write_bytes((dataset.parent / "other.lut.h5").read_bytes())
    unwritable = tmp_path / "full"
    unwritable.mkdir()
    _fail_probe_in(monkeypatch, unwritable)
    cases = [(heights, ("input",)), (tmp_path / "text.ply", ("another kind",)),
             (tmp_path / "lut.ply", ("ptp-lut/1",)), (tmp_path / "missing" / "c.ply", ("does not exist",)),
             (unwritable / "c.ply", ("cannot write",)), (tmp_path, ("is a folder",))]
    for path, words in cases:
        _dialog(monkeypatch, "getSaveFileName", path)
        before = [_snapshot(tmp_path)]
        panel._save_dialog()
        _refused(panel.jobs, panel.jobs.job if panel.jobs.busy else None, [tmp_path], before, questions,
                 "Nothing saved", *words)
    good = tmp_path / "cloud.ply"
    _dialog(monkeypatch, "getSaveFileName", good)
    panel._save_dialog()
    assert run_job(qtbot, panel.jobs.job) == "finished"
    assert good.read_bytes().startswith(b"ply\n")


# --------------------------------------------------------------------------- Save acceptance report

def test_save_acceptance_report_refuses_bad_paths(qtbot, tmp_path, dataset, monkeypatch, questions):
    ds = tmp_path / "DS"
    shutil.copytree(dataset, ds)
    scans = tmp_path / "scans"
    scans.mkdir()
    (scans / "scan.toml").write_text("# a scan\n")
    panel = AcceptancePanel(lambda: None, lambda: ds, lambda: tmp_path)
    qtbot.addWidget(panel)
    panel.set_scans(scans)
    panel.report, panel.page, panel._counts = object(), np.zeros((4, 4, 3), np.uint8), {}  # never reached
    (tmp_path / "r.json").write_text("{}\n")
    shutil.copy(dataset.parent / "other.lut.h5", tmp_path / "r.png")  # the page's name, a LUT inside
    unwritable = tmp_path / "full"
    unwritable.mkdir()
    _fail_probe_in(monkeypatch, unwritable)
    cases = [(ds / "rig.toml", ("input",)), (scans / "scan.toml", ("input",)),
             (tmp_path / "r.json", ("r.png", "ptp-lut/1")), (tmp_path / "page.png", ("the same file",)),
             (tmp_path / "missing" / "a.json", ("does not exist",)), (unwritable / "a.json", ("cannot write",))]
    for path, words in cases:
        _dialog(monkeypatch, "getSaveFileName", path)
        before = [_snapshot(tmp_path)]
        panel._save_dialog()
        _refused(panel.jobs, panel.jobs.job if panel.jobs.busy else None, [tmp_path], before, questions,
                 "Nothing saved", *words)
