"""A LUT's report (issue 41): its provenance read once, what ``ptp calibrate`` / ``inspect`` print and the
wizard's Calibrate summary builds from, every printed line within 100 columns."""

from __future__ import annotations

import contextlib
import io
import json
import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.decode.phase import DecodeOptions
from ptpcore.evaluate import LutReport
from ptpcore.evaluate.lut_report import NOT_RECORDED, fit_width
from ptpcore.fit.choice import ModelChoice
from ptpcore.fit.settings import FitSettings
from ptpcore.io.lutfile import load_lut

WIDTH = 100


def _run(argv) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(argv) == 0
    return out.getvalue()


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """`real` (its cover glass declared) with a repeat that moved 10 µm, calibrated with the defaults (auto,
    robust): a model choice, a robust record, drift with a warning and a cover glass. About 10 s."""
    tmp = tmp_path_factory.mktemp("report")
    data, lut = tmp / "real", tmp / "real.lut.h5"
    _run(["simulate", str(data), "--preset", "real", "--width", "48", "--positions", "6", "--repeat",
          "--drift-um", "10", "0", "-q"])
    said = _run(["calibrate", str(data), "--out", str(lut), "-q"])
    return lut, said, _run(["inspect", str(lut)])


def _too_wide(text: str) -> list[str]:
    return [line for line in text.splitlines() if len(line) > WIDTH]


def test_calibrate_and_inspect_print_the_report_within_100_columns(calibrated):
    path, said, inspected = calibrated
    assert not _too_wide(said) and not _too_wide(inspected)
    for text in (said, inspected):
        assert "model chosen by its error at held-out positions" in text and "<- chosen" in text
        assert "robust fit          " in text and "cover glass 1.1 mm, n 1.52 removed" in text
        assert "DRIFT WARNING" in text and "drift at z = 0 mm (position 0 again): RMS" in text
        assert "fit settings        model auto, degree 3, stage_sigma_um 0," in text
        assert "decode options      min_modulation" in text
        assert "noise part X" in text and "leave-one-out RMS Y" in text
    # calibrate adds the residual diagnostics (wrapped too); the report itself is the same lines
    assert "worst pixels" in said and said.startswith(inspected)
    assert inspected.rstrip("\n") == LutReport.of(load_lut(path), str(path)).text()


def test_the_report_holds_every_record_typed(calibrated):
    lut = load_lut(calibrated[0])
    r = LutReport.of(lut)
    assert isinstance(r.choice, ModelChoice) and r.model.endswith("chosen by held-out positions")
    assert r.fit_settings == FitSettings() and isinstance(r.decode_options, DecodeOptions)
    assert r.robust is not None and r.robust.n_rejected >= 0 and r.robust.suspects == ()
    assert r.drift is not None and r.drift.warnings and r.drift.repeats[0].position == 0
    assert any(c.startswith("cover glass 1.1 mm") for c in r.corrections) and r.notes == ()
    assert r.n_valid == int(lut.valid.sum()) and r.positions[1] <= 6 and r.height_map is None
    v = lut.valid
    assert r.rms["x"].median_um == pytest.approx(1e3 * float(np.median(lut.rms_x[v])))
    assert [s.axis for s in r.sigma] == ["x", "y"] and all(s.model is not None for s in r.sigma)


def test_unreadable_records_become_notes(calibrated):
    lut = load_lut(calibrated[0])
    for key in ("corrections", "model_choice", "robust", "drift", "fit_settings", "decode_options"):
        lut.provenance[key] = "{not json"
    lut.provenance["fit_settings"] = json.dumps({"model": "auto", "warp": 9})  # a newer version's key
    r = LutReport.of(lut)
    assert (r.choice, r.robust, r.drift, r.fit_settings, r.decode_options, r.corrections) == \
        (None, None, None, None, None, ())
    assert len(r.notes) == 6 and "unknown fit setting 'warp'" in r.notes[-2]
    text = r.text()
    assert not _too_wide(text) and "not recorded" not in text
    assert text.count("  note                /provenance ") == 6


def test_a_lut_written_before_the_settings_record_says_so(calibrated):
    lut = load_lut(calibrated[0])
    del lut.provenance["fit_settings"], lut.provenance["decode_options"]
    text = LutReport.of(lut).text()
    assert f"fit settings        {NOT_RECORDED.format(key='fit_settings')}" in text.replace("\n" + " " * 22, " ")
    assert "decode options      not recorded" in text and not _too_wide(text)


def test_stage_pose_and_long_lines_wrap_under_their_text(calibrated):
    lut = load_lut(calibrated[0])
    k = int(lut.n_positions.max())
    lut.stage_pose = np.random.default_rng(1).normal(0, 30, (k, 6))
    lut.stage_pose_sigma = np.abs(lut.stage_pose) / 7
    lines = LutReport.of(lut, "/a/rather/long/folder/name/for/the/lut/file/to/start/the/line/" + "x" * 30
                         + ".lut.h5").lines()
    assert all(len(line) <= WIDTH for line in lines)
    pose = [line for line in lines if line.startswith("    z=")]
    assert len(pose) == k and all(line.count("±") >= 4 for line in pose)
    assert fit_width("a " * 80, 20, 3)[1].startswith("   a") and fit_width("short") == ["short"]
    assert fit_width("x" * 120) == ["x" * 120]  # one word: left whole
    assert fit_width("w" * 90 + " z = 12.5 mm and more") == ["w" * 90, "    z = 12.5 mm and more"]


def test_the_wizard_summary_builds_from_the_report(calibrated):
    pytest.importorskip("PySide6")
    from ptp_studio.pages.calibrate import _stats_text

    lut = load_lut(calibrated[0])
    r = LutReport.of(lut)
    text = _stats_text(r)
    assert "chosen by held-out positions" in text and f"{r.n_valid} of {r.n_pixels} pixels valid" in text
    x = r.sigma[0]
    assert f"X {x.total.median_um:.2f} µm (noise {x.noise.median_um:.2f}, model {x.model.median_um:.2f})" in text
    assert "Cover glass 1.1 mm" in text and "Robust fit: " in text
    assert "DRIFT WARNING" in text and "Drift at z = 0 mm (position 0 again): RMS" in text
    lut.provenance["robust"] = "[]"
    assert "Note: /provenance robust unreadable" in _stats_text(LutReport.of(lut))
