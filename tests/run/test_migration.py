"""Files written before the fit-settings record still load, and resume to the LUT that code wrote.

The files in tests/data/migration/ were written by commit ea7ada8 (its README says how): each fit
setting one ``/calibration`` attribute, no ``fit_settings`` or ``decode_options`` record.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from ptpcore.cli import main
from ptpcore.decode.phase import DecodeOptions
from ptpcore.evaluate.lutcompare import compare_lut_files
from ptpcore.fit.settings import FitSettings
from ptpcore.io.lutfile import load_lut
from ptpcore.run import calibrate_session, load_session, save_session

DATA = Path(__file__).resolve().parents[1] / "data" / "migration"
NEW_RECORDS = ("created", "software", "/provenance@fit_settings", "/provenance@decode_options")


def test_a_session_stopped_after_the_decode_resumes_to_the_lut_its_own_code_wrote(tmp_path):
    session = load_session(DATA / "samples_stage.ptps.h5")
    assert session.stage == "samples"
    assert session.settings == FitSettings(model="poly", degree=2, stage_sigma_um=0.5, level_bias=False)
    assert session.options == DecodeOptions()
    out = tmp_path / "resumed.lut.h5"
    copy = tmp_path / "s.ptps.h5"
    shutil.copy(DATA / "samples_stage.ptps.h5", copy)
    assert main(["resume", str(copy), "--out", str(out), "-q"]) == 0
    same = compare_lut_files(DATA / "old_poly2.lut.h5", out, ignore=NEW_RECORDS)
    assert same.equal, "\n".join(same.lines())
    lut = load_lut(out)
    assert FitSettings.from_json(lut.provenance["fit_settings"]) == session.settings
    again = load_session(copy)  # saved by today's code: the records, read back whole
    assert again.stage == "lut" and again.settings == session.settings


def test_a_complete_old_session_and_an_old_lut_load(tmp_path):
    session = load_session(DATA / "lut_stage.ptps.h5")
    assert session.stage == "lut" and session.lut is not None
    assert session.settings == FitSettings(model="smooth", degree=3, stage_sigma_um=1.0, footprint=False)
    result = calibrate_session(session)  # nothing left to do but what an older run did not add
    assert result.lut is session.lut and "fit_settings" not in session.lut.provenance
    save_session(session, tmp_path / "re.ptps.h5")
    assert load_session(tmp_path / "re.ptps.h5").settings == session.settings
    old = load_lut(DATA / "old_auto.lut.h5")
    assert old.valid.any() and "fit_settings" not in old.provenance
    assert main(["inspect", str(DATA / "old_auto.lut.h5")]) == 0
