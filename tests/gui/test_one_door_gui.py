"""The wizard is a door like the others (issue 41): its Acquire and Calibrate jobs and its Export write
the LUT ``ptp calibrate`` writes, dataset by dataset and attribute by attribute (the time of writing and
the program's version aside), on the same datasets and settings as tests/run/test_one_door.py."""

from __future__ import annotations

import pytest

from ptpcore.cli import main
from ptpcore.evaluate.lutcompare import compare_lut_files
from ptpcore.fit.settings import FitSettings

from gui_helpers import run_job

SETTINGS = {"defaults": ([], FitSettings()),
            "smooth-refined": (["--model", "smooth", "--refine-stage", "--stage-sigma-um", "1"],
                               FitSettings(model="smooth", refine_stage=True, stage_sigma_um=1.0))}
FAST = {("realistic", "defaults")}
CASES = [pytest.param(kind, settings, marks=() if (kind, settings) in FAST else pytest.mark.slow)
         for kind in ("realistic", "real", "scanner") for settings in SETTINGS]


@pytest.mark.parametrize("kind, settings", CASES)
def test_the_wizard_writes_the_lut_ptp_calibrate_writes(wizard, qtbot, tmp_path, kind, settings, door_dataset):
    from ptp_studio.pages.export import LUT_NAME

    flags, fit = SETTINGS[settings]
    ds = door_dataset(kind, tmp_path / "ds")
    cli = tmp_path / "cli.lut.h5"
    assert main(["calibrate", str(ds), "--out", str(cli), "-q", *flags]) == 0
    wizard.page_by_key["rig"].import_folder(ds)
    wizard.go_to("acquire")
    assert run_job(qtbot, wizard.page_by_key["acquire"].start(), timeout=120000) == "finished"
    wizard.go_to("calibrate")
    cal = wizard.page_by_key["calibrate"]
    cal.configure(fit)
    assert cal.fit_settings() == fit
    assert run_job(qtbot, cal.fit(), timeout=180000) == "finished"
    wizard.go_to("export")
    ex = wizard.page_by_key["export"]
    ex.set_folder(tmp_path / "out")
    assert run_job(qtbot, ex.export(), timeout=120000) == "finished"
    same = compare_lut_files(cli, tmp_path / "out" / LUT_NAME)
    assert same.equal, "\n".join(same.lines())
