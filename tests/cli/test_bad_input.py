"""Bad input through the CLI: one clear line naming the culprit, nothing computed lost.

Every case runs ``ptp calibrate`` (in process, stderr captured at the file
descriptor so C-library chatter would show too) on a broken copy of a tiny
simulated dataset, with ``--out`` pointing at an existing LUT and
``--session`` at a new session file. Each must end with exit code 2 and
exactly one stderr line that names the file or key, leave the LUT byte for
byte unchanged and write no session file and no stray temporary file.
"""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
import tomli_w

from ptpcore.cli import main
from ptpcore.io import validate_dataset
from ptpcore.errors import DatasetError
from ptpcore.rig import Camera, rig_to_toml
from ptpcore.run import load_session, new_session, save_session
from ptpcore.simulate import preset, simulate_dataset

FIRST = "z000/x_T4096_n00.png"  # an image every case can break


@pytest.fixture(scope="module")
def dataset_template(tmp_path_factory):
    """A valid 64x48 8-bit dataset (3 positions, 120 images) and a LUT calibrated from it."""
    root = tmp_path_factory.mktemp("bad-input")
    rig, settings = preset("ideal")
    rig = dataclasses.replace(rig, camera=Camera(64, 48, 8)).with_z([0.0, 10.0, 20.0])
    ds = simulate_dataset(root / "ds", rig, settings, seed=5)
    lut = root / "previous.lut.h5"
    assert main(["calibrate", str(ds), "--out", str(lut), "--degree", "1", "-q"]) == 0
    return ds, lut


@pytest.fixture
def case(dataset_template, tmp_path):
    """A fresh copy of the dataset plus an existing LUT in an output folder."""
    src, lut = dataset_template
    ds = tmp_path / "ds"
    shutil.copytree(src, ds)
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(lut, out / "calib.lut.h5")
    return ds, out


def _edit_rig(ds: Path, edit) -> None:
    doc = tomllib.loads((ds / "rig.toml").read_text())
    edit(doc)
    (ds / "rig.toml").write_text(tomli_w.dumps(doc))


def _run_bad(capfd, ds: Path, out: Path, *culprits: str) -> str:
    """Run a calibration expected to fail; check the contract; return the message."""
    lut = out / "calib.lut.h5"
    before = lut.read_bytes()
    capfd.readouterr()
    code = main(["calibrate", str(ds), "--out", str(lut), "--session", str(out / "s.ptps.h5"), "--force",
                 "--degree", "1", "-q"])
    captured = capfd.readouterr()
    err = captured.err
    assert code == 2, err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("ptp: error: ")
    assert "Traceback" not in err and captured.out == ""
    for culprit in culprits:
        assert culprit in lines[0], (culprit, lines[0])
    assert lut.read_bytes() == before  # the previous LUT is untouched
    assert sorted(p.name for p in out.iterdir()) == ["calib.lut.h5"]  # no session, no temp file
    return lines[0]


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


# --------------------------------------------------------------------------- images

def test_zero_byte_image(case, capfd):
    ds, out = case
    (ds / FIRST).write_bytes(b"")
    msg = _run_bad(capfd, ds, out, FIRST, "empty")
    assert "1 of 120 images" in msg


def test_truncated_png(case, capfd):
    ds, out = case
    data = (ds / FIRST).read_bytes()
    (ds / FIRST).write_bytes(data[: len(data) // 2])
    _run_bad(capfd, ds, out, FIRST, "truncated")


def test_png_cut_just_before_its_end_chunk(case, capfd):
    ds, out = case
    data = (ds / FIRST).read_bytes()
    (ds / FIRST).write_bytes(data[:-12])  # every pixel is there, IEND is not
    _run_bad(capfd, ds, out, FIRST, "truncated")


def test_missing_image(case, capfd):
    ds, out = case
    (ds / FIRST).unlink()
    _run_bad(capfd, ds, out, FIRST, "missing")


def test_wrong_size(case, capfd):
    ds, out = case
    (ds / FIRST).write_bytes(_png(np.zeros((24, 32), np.uint8)))
    _run_bad(capfd, ds, out, FIRST, "32x24", "64x48")


def test_wrong_bit_depth_16_in_8(case, capfd):
    ds, out = case
    (ds / FIRST).write_bytes(_png(np.zeros((48, 64), np.uint16)))
    _run_bad(capfd, ds, out, FIRST, "16-bit", "bit_depth = 8")


def test_wrong_bit_depth_8_in_12(case, capfd):
    ds, out = case
    _edit_rig(ds, lambda d: d["camera"].update(bit_depth=12))
    msg = _run_bad(capfd, ds, out, FIRST, "8-bit", "bit_depth = 12")
    assert "120 of 120" in msg and "... and 110 more" in msg  # listing capped, all counted


def test_every_problem_is_reported_in_one_pass(case, capfd):
    ds, out = case
    names = sorted(str(p.relative_to(ds)) for p in ds.rglob("*.png"))
    (ds / names[0]).write_bytes(b"")
    (ds / names[1]).unlink()
    (ds / names[2]).write_bytes((ds / names[2]).read_bytes()[:100])
    (ds / names[3]).write_bytes(_png(np.zeros((10, 10), np.uint8)))
    (ds / names[4]).write_bytes(_png(np.zeros((48, 64), np.uint16)))
    msg = _run_bad(capfd, ds, out, *names[:5])
    assert "5 of 120 images unusable" in msg
    for kind in ("1 empty", "1 missing", "1 truncated", "1 wrong size", "1 wrong bit depth"):
        assert kind in msg


def test_listing_is_capped_with_a_count(case):
    ds, _ = case
    for p in sorted(ds.rglob("z001/*.png")):
        p.unlink()
    with pytest.raises(DatasetError) as err:
        validate_dataset(ds, max_listed=3)
    msg = str(err.value)
    assert "40 of 120 images unusable (40 missing)" in msg
    assert msg.count("image missing") == 3 and "... and 37 more" in msg


def test_not_an_image(case, capfd):
    ds, out = case
    (ds / FIRST).write_text("hello")
    _run_bad(capfd, ds, out, FIRST, "not a PNG or TIFF")


# --------------------------------------------------------------------------- rig.toml

def test_rig_wrong_type(case, capfd):
    ds, out = case
    _edit_rig(ds, lambda d: d["camera"].update(width="64"))
    _run_bad(capfd, ds, out, "rig.toml", "camera.width", "integer")


def test_rig_unknown_key(case, capfd):
    ds, out = case
    _edit_rig(ds, lambda d: d["camera"].update(colour=True))
    _run_bad(capfd, ds, out, "rig.toml", "camera.colour", "unknown key")


def test_rig_missing_section(case, capfd):
    ds, out = case
    _edit_rig(ds, lambda d: d.pop("lcd"))
    _run_bad(capfd, ds, out, "rig.toml", "[lcd]")


def test_rig_not_toml(case, capfd):
    ds, out = case
    (ds / "rig.toml").write_text("[camera\nwidth = 64\n")
    _run_bad(capfd, ds, out, "rig.toml", "not valid TOML")


def test_rig_missing(case, capfd):
    ds, out = case
    (ds / "rig.toml").unlink()
    _run_bad(capfd, ds, out, "rig.toml", "not found")


def test_rig_non_monotonic_z(case, capfd):
    ds, out = case
    _edit_rig(ds, lambda d: d["stage"].update(z_mm=[0.0, 20.0, 10.0]))
    _run_bad(capfd, ds, out, "rig.toml", "stage.z_mm", "monotonic")


def test_rig_duplicate_positions(case, capfd):
    ds, out = case
    _edit_rig(ds, lambda d: d["stage"].update(z_mm=[0.0, 10.0, 10.0]))
    _run_bad(capfd, ds, out, "rig.toml", "stage.z_mm", "duplicate position")


def test_ambiguous_period_list(case, capfd):
    ds, out = case
    # 512 px cannot cover a 3840 px LCD: the coarse phase would wrap several times.
    _edit_rig(ds, lambda d: d["fringes"].update(periods_px=[512, 128, 32], steps=[4, 4, 8]))
    _run_bad(capfd, ds, out, "rig.toml", "fringes.periods_px", "ambiguous")


def test_carrier_makes_period_list_ambiguous(case, capfd):
    ds, out = case
    # 3840 px + 20 mm * 20 px/mm = 4240 px > 4096 px.
    _edit_rig(ds, lambda d: d["fringes"].update(carrier_px_per_mm=[20.0, 0.0]))
    _run_bad(capfd, ds, out, "rig.toml", "fringes.periods_px", "ambiguous", "direction x")


@pytest.mark.parametrize("template", ["z{pos.__class__}/{dir}_T{period}_n{step:02d}.png",
                                      "z{pos:03d}/{dir[0]}_T{period}_n{step:02d}.png",
                                      "z{pos!r}/{dir}_T{period}_n{step}.png",
                                      "z{pos:{dir}}/{dir}_T{period}_n{step}.png",
                                      "../z{pos}/{dir}_T{period}_n{step}.png"])
def test_template_reaching_into_objects_or_out_of_the_folder(case, capfd, template):
    ds, out = case
    _edit_rig(ds, lambda d: d["images"].update(template=template))
    _run_bad(capfd, ds, out, "rig.toml", "images.template")


# --------------------------------------------------------------------------- sessions

def test_existing_session_is_never_overwritten(case, capfd):
    ds, out = case
    session = out / "s.ptps.h5"
    s = new_session(ds, degree=1)
    save_session(s, session)
    before = session.read_bytes()
    capfd.readouterr()
    code = main(["calibrate", str(ds), "--out", str(out / "calib.lut.h5"), "--session", str(session), "-q"])
    err = capfd.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1 and str(session) in err and "ptp resume" in err
    assert session.read_bytes() == before


def test_resume_with_a_dataset_broken_since_keeps_the_session(case, capfd):
    ds, out = case
    session = out / "s.ptps.h5"
    save_session(new_session(ds, degree=1, out=out / "calib.lut.h5"), session)
    before = session.read_bytes(), (out / "calib.lut.h5").read_bytes()
    (ds / FIRST).write_bytes(b"")
    capfd.readouterr()
    code = main(["resume", str(session), "-q"])
    captured = capfd.readouterr()
    assert code == 2 and len(captured.err.splitlines()) == 1 and FIRST in captured.err
    assert (session.read_bytes(), (out / "calib.lut.h5").read_bytes()) == before
    assert load_session(session).stage == "new"


def test_resume_refuses_a_dataset_whose_rig_changed(case, capfd):
    ds, out = case
    session = out / "s.ptps.h5"
    save_session(new_session(ds, degree=1, out=out / "calib.lut.h5"), session)
    _edit_rig(ds, lambda d: d["fringes"].update(offset=120.0))
    capfd.readouterr()
    assert main(["resume", str(session), "-q"]) == 2
    err = capfd.readouterr().err
    assert len(err.splitlines()) == 1 and "rig.toml" in err and "differs" in err


def test_resume_of_a_lut_file_says_what_it_is(dataset_template, capfd):
    _, lut = dataset_template
    capfd.readouterr()
    assert main(["resume", str(lut), "-q"]) == 2
    err = capfd.readouterr().err
    assert len(err.splitlines()) == 1 and str(lut) in err and "a LUT file" in err


# --------------------------------------------------------------------------- good odd input

def test_colour_images_pass_with_one_warning(case):
    ds, _ = case
    for p in sorted(ds.rglob("z000/y_*.png")):
        grey = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        p.write_bytes(_png(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)))
    with pytest.warns(UserWarning, match="20 colour images will be decoded from their BT.601 luminance") as rec:
        report = validate_dataset(ds)
    assert len(rec) == 1 and len(report.colour) == 20


def test_colour_dataset_calibrates_with_one_warning_line(case, capfd):
    ds, out = case
    for p in sorted(ds.rglob("*/x_T32_*.png")):
        grey = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        p.write_bytes(_png(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGRA)))
    capfd.readouterr()
    assert main(["calibrate", str(ds), "--out", str(out / "c.lut.h5"), "--degree", "1", "-q"]) == 0
    err = capfd.readouterr().err.splitlines()
    assert err == [f"ptp: warning: {ds}: 24 colour images will be decoded from their BT.601 luminance (e.g. z000/x_T32_n00.png)"]


def test_extra_files_are_ignored(case):
    ds, _ = case
    (ds / "notes.txt").write_text("captured on a Tuesday")
    (ds / "z000" / "preview.png").write_bytes(b"junk")
    (ds / "z000" / "x_T4096_n00.png.bak").write_bytes(b"")
    report = validate_dataset(ds)
    assert report.n_images == 120 and report.formats == {"png": 120}


def test_tiff_dataset_truncation_and_bit_depth(tmp_path):
    rig, settings = preset("ideal")
    rig = dataclasses.replace(rig, camera=Camera(64, 48, 12)).with_z([0.0, 20.0])
    ds = simulate_dataset(tmp_path / "tif", rig, settings, seed=2, image_ext=".tif")
    report = validate_dataset(ds)
    assert report.formats == {"tiff": 80}
    first = "z000/x_T4096_n00.tif"
    data = (ds / first).read_bytes()
    (ds / first).write_bytes(data[: len(data) - 100])
    ok, buf = cv2.imencode(".tif", np.zeros((48, 64), np.uint8))
    (ds / "z001/y_T32_n07.tif").write_bytes(buf.tobytes())
    with pytest.raises(DatasetError) as err:
        validate_dataset(ds)
    msg = str(err.value)
    assert "2 of 80" in msg and first in msg and "truncated TIFF" in msg
    assert "z001/y_T32_n07.tif: 8-bit unsigned image" in msg


def test_subprocess_end_to_end_no_traceback(case):
    ds, out = case
    (ds / FIRST).write_bytes(b"")
    before = (out / "calib.lut.h5").read_bytes()
    proc = subprocess.run([sys.executable, "-m", "ptpcore.cli", "calibrate", str(ds), "--out",
                           str(out / "calib.lut.h5"), "--session", str(out / "s.ptps.h5"), "--force",
                           "--degree", "1"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and FIRST in proc.stderr and "Traceback" not in proc.stderr
    assert (out / "calib.lut.h5").read_bytes() == before
    assert not (out / "s.ptps.h5").exists()


def test_rig_toml_in_session_matches_dataset(case):
    ds, _ = case
    s = new_session(ds, degree=1)
    assert rig_to_toml(s.rig) == (ds / "rig.toml").read_text()


def test_full_check_also_decodes_pixels(case):
    """Corrupt compressed data inside an intact PNG structure: only ``full=True`` sees it."""
    ds, _ = case
    data = bytearray((ds / FIRST).read_bytes())
    start = data.index(b"IDAT") + 4
    data[start + 2:start + 40] = bytes(38)  # inside the zlib stream; chunk lengths untouched
    (ds / FIRST).write_bytes(bytes(data))
    assert validate_dataset(ds).n_images == 120  # headers and structure are fine
    with pytest.raises(DatasetError, match=f"1 of 120 images unusable .*{FIRST}: corrupt PNG"):
        validate_dataset(ds, full=True)


def test_corrupt_pixels_found_while_decoding_still_give_one_line(case, capfd):
    """Found only when decoding: one line (our checksum check runs before libpng can print),
    and the session saved before the decode stays at its stage for `ptp resume`."""
    ds, out = case
    last = "z002/y_T32_n07.png"
    data = bytearray((ds / last).read_bytes())
    start = data.index(b"IDAT") + 4
    data[start + 2:start + 40] = bytes(38)
    (ds / last).write_bytes(bytes(data))
    before = (out / "calib.lut.h5").read_bytes()
    capfd.readouterr()
    code = main(["calibrate", str(ds), "--out", str(out / "calib.lut.h5"), "--session", str(out / "s.ptps.h5"),
                 "--force", "--degree", "1", "-q"])
    err = capfd.readouterr().err
    assert code == 2 and err.count("\n") == 1 and last in err and "corrupt PNG" in err, err
    assert (out / "calib.lut.h5").read_bytes() == before
    assert load_session(out / "s.ptps.h5").stage == "new"
    assert sorted(p.name for p in out.iterdir()) == ["calib.lut.h5", "s.ptps.h5"]
