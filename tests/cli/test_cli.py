"""The ptp command line: a new user's path and one-line errors."""

import subprocess
import sys

import numpy as np
import pytest

from ptpcore.cli import main
from ptpcore.io import load_lut


def test_simulate_calibrate_inspect(tmp_path, capsys):
    data = tmp_path / "data"
    assert main(["simulate", str(data), "--preset", "realistic", "--width", "80", "--positions", "4", "-q"]) == 0
    out = tmp_path / "cal.lut.h5"
    assert main(["calibrate", str(data), "--out", str(out), "--model", "poly", "--degree", "1", "-q"]) == 0
    lut = load_lut(out)
    assert lut.kind == "poly" and lut.degree == 1 and lut.shape == (60, 80)
    assert lut.valid.mean() > 0.5
    assert main(["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert "valid pixels" in text and "leave-one-out RMS X" in text
    assert main(["calibrate", str(data), "--out", str(tmp_path / "t.lut.h5"), "--model", "pchip", "-q"]) == 0
    assert np.isfinite(load_lut(tmp_path / "t.lut.h5").evaluate(1.0).x).any()


def test_calibrate_smooth_and_inspect(tmp_path, capsys):
    """`--model smooth` writes poly coefficients (scanners read it unchanged) plus predicted sigma maps."""
    data = tmp_path / "data"
    assert main(["simulate", str(data), "--preset", "rough", "--width", "80", "--positions", "5", "-q"]) == 0
    out = tmp_path / "smooth.lut.h5"
    assert main(["calibrate", str(data), "--out", str(out), "--model", "smooth", "--degree", "1", "-q"]) == 0
    lut = load_lut(out)
    assert lut.kind == "poly" and lut.degree == 1 and lut.extra_attrs["method"] == "smooth"
    scale = float(lut.extra_attrs["smoothing_scale_px"])
    assert lut.sigma_x is not None and np.all(np.isfinite(lut.sigma_x[lut.valid]))
    capsys.readouterr()
    assert main(["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"smooth, poly degree 1, smoothing scale {scale:g} px" in text or "not smoothed" in text
    assert "predicted sigma X" in text and "predicted sigma Y" in text
    # a plain poly LUT gets its sigma maps too
    plain = tmp_path / "plain.lut.h5"
    assert main(["calibrate", str(data), "--out", str(plain), "--model", "poly", "--degree", "1", "-q"]) == 0
    assert load_lut(plain).sigma_x is not None and "method" not in load_lut(plain).extra_attrs
    text = capsys.readouterr().out
    assert "predicted sigma X" in text
    # the robust fit's report and the residual diagnostics, worst first
    assert "robust fit" in text and "worst positions (residual RMS over X and Y): " in text and "worst pixels" in text
    # the stage's reading error enters the sigma maps only; the corrections move the coefficients
    staged = tmp_path / "staged.lut.h5"
    assert main(["calibrate", str(data), "--out", str(staged), "--model", "smooth", "--degree", "1",
                 "--stage-sigma-um", "2", "-q"]) == 0
    st = load_lut(staged)
    np.testing.assert_array_equal(st.x, lut.x)
    v = lut.valid
    # Here (rough lens, 80 px) the leave-one-out resolves a model error of about 10 um: the data fix the
    # total, and a declared stage error explains part of that excess instead of adding to it
    # (fit/smooth._model_error); the plain LUT below shows it adding.
    assert abs(np.mean(st.sigma_x[v] ** 2) / np.mean(lut.sigma_x[v] ** 2) - 1) < 0.01
    raw = tmp_path / "raw.lut.h5"
    assert main(["calibrate", str(data), "--out", str(raw), "--model", "smooth", "--degree", "1",
                 "--no-level-bias", "--no-footprint", "-q"]) == 0
    assert not np.array_equal(load_lut(raw).x, lut.x)
    plain_st = tmp_path / "plain_staged.lut.h5"
    assert main(["calibrate", str(data), "--out", str(plain_st), "--model", "poly", "--degree", "1",
                 "--stage-sigma-um", "2", "-q"]) == 0
    a, b = load_lut(plain), load_lut(plain_st)
    assert np.all(b.sigma_x[a.valid] >= a.sigma_x[a.valid]) and np.mean(b.sigma_x[a.valid]) > np.mean(a.sigma_x[a.valid])
    capsys.readouterr()
    assert main(["calibrate", str(data), "--out", str(tmp_path / "bad.lut.h5"), "--stage-sigma-um", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "stage sigma" in err[0] and "--stage-sigma-um -1" in err[0]


def test_bad_input_is_one_line_and_exit_code_2(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "ptpcore.cli", "calibrate", str(tmp_path / "nope"), "--out",
                           str(tmp_path / "x.lut.h5")], capture_output=True, text=True)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "nope" in lines[0] and "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "ptpcore.cli", "inspect", str(tmp_path / "missing.lut.h5")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "missing.lut.h5" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_help_everywhere():
    for cmd in (["--help"], ["simulate", "--help"], ["calibrate", "--help"], ["inspect", "--help"], ["demo", "--help"]):
        proc = subprocess.run([sys.executable, "-m", "ptpcore.cli", *cmd], capture_output=True, text=True)
        assert proc.returncode == 0 and "usage: ptp" in proc.stdout


@pytest.mark.slow  # ~70 s; the README's main command, also run by the bundle and wheel tests
def test_demo_runs_end_to_end_and_leaves_no_temporary_folder(capsys, tmp_path, monkeypatch):
    """The README's main job, for real (not a stub): simulate, decode, fit, report against the truth."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    assert main(["demo", "--preset", "mild", "--no-compare", "-q"]) == 0
    out = capsys.readouterr().out
    assert "held-out accuracy" in out and "observed / predicted" in out
    assert list(tmp_path.iterdir()) == []
