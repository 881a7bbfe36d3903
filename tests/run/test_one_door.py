"""One door to a calibration (issue 41): every front end writes the same LUT.

``ptpcore.calibrate``, ``ptp calibrate`` and ``ptp resume`` (of a session stopped after the decode) on
the same dataset and settings write LUT files equal dataset by dataset and attribute by attribute
(:func:`ptpcore.evaluate.lutcompare.compare_lut_files`; the time of writing and the program's
version aside). The wizard's Calibrate job is the fourth door (tests/gui/test_one_door_gui.py).
The presets: ``realistic``; ``real`` (its cover glass declared, so the glass correction runs);
a scanner (its height sweep, so ``/height`` is fitted). The settings: the defaults (auto), and
smooth with the stage refined and a stage sigma declared.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.evaluate.lutcompare import compare_lut_files
from ptpcore.fit.settings import FitSettings
from ptpcore.io.lutfile import load_lut, save_lut
from ptpcore.run import calibrate, calibrate_session, load_session, new_session

FAST = {("realistic", "defaults"), ("scanner", "smooth-refined")}
SETTINGS = {"defaults": ([], FitSettings()),
            "smooth-refined": (["--model", "smooth", "--refine-stage", "--stage-sigma-um", "1"],
                               FitSettings(model="smooth", refine_stage=True, stage_sigma_um=1.0))}


@pytest.fixture(scope="module")
def datasets(tmp_path_factory, door_dataset):
    root = tmp_path_factory.mktemp("doors")
    return {kind: door_dataset(kind, root / kind) for kind in ("realistic", "real", "scanner")}


def _equal(a: Path, b: Path) -> None:
    result = compare_lut_files(a, b)
    assert result.equal, "\n".join(result.lines())


def _doors(ds: Path, flags: list[str], settings: FitSettings, tmp: Path) -> dict[str, Path]:
    """The LUT of each engine door, as files."""
    out = {"cli": tmp / "cli.lut.h5", "python": tmp / "python.lut.h5", "resume": tmp / "resume.lut.h5"}
    assert main(["calibrate", str(ds), "--out", str(out["cli"]), "-q", *flags]) == 0
    save_lut(calibrate(ds, settings), out["python"])
    session = tmp / "s.ptps.h5"
    calibrate_session(new_session(ds, settings), session, stop_after="samples")
    assert load_session(session).stage == "samples"
    assert main(["resume", str(session), "--out", str(out["resume"]), "-q"]) == 0
    return out


CASES = [pytest.param(kind, settings, marks=() if (kind, settings) in FAST else pytest.mark.slow)
         for kind in ("realistic", "real", "scanner") for settings in SETTINGS]
"""Every preset with both settings; the default tier runs two of them, the slow tier the rest."""


@pytest.mark.parametrize("kind, settings", CASES)
def test_every_engine_door_writes_the_same_lut(datasets, kind, settings, tmp_path):
    flags, fs = SETTINGS[settings]
    out = _doors(datasets[kind], flags, fs, tmp_path)
    _equal(out["cli"], out["python"])
    _equal(out["cli"], out["resume"])
    lut = load_lut(out["cli"])
    assert FitSettings.from_json(lut.provenance["fit_settings"]) == fs  # the settings recorded whole
    assert (lut.height is not None) == (kind == "scanner")
    glass = json.loads(lut.provenance["corrections"])["cover_glass"]["t_mm"]
    assert (glass > 0) == (kind == "real")  # the real preset declares its cover glass


def test_a_failed_height_map_writes_the_xy_lut_and_exits_3(datasets, tmp_path, capsys):
    """The one partial outcome: the height sweep cannot be fitted -> the XY LUT is written, the reason
    printed (one line on stderr), exit 3; ptpcore.calibrate warns with the same words."""
    import shutil
    import warnings

    from ptpcore.errors import DataWarning

    import cv2

    folder = tmp_path / "ds"
    shutil.copytree(datasets["scanner"], folder)
    for frame in sorted(folder.glob("h[0-9]*/*")):  # the plate sweep dark: readable, nothing to decode
        img = cv2.imread(str(frame), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(frame), np.zeros_like(img))
    out = tmp_path / "xy.lut.h5"
    code = main(["calibrate", str(folder), "--out", str(out), "--model", "poly", "--degree", "1", "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 3, err
    assert len(err) == 1 and err[0].startswith("ptp: partial: ") and "height map was not made" in err[0]
    lut = load_lut(out)
    assert lut.height is None and lut.valid.any()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        again = calibrate(folder, FitSettings(model="poly", degree=1))
    words = [str(w.message) for w in caught if issubclass(w.category, DataWarning)]
    assert again.height is None and any(w in err[0] for w in words), (words, err)
