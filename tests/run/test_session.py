"""Session files (ptp-session/1): round trip, resume, migrations, too new, damaged files.

Also the checks of the LUT loader (``ptp-lut/1``), which a session reuses for
its ``/lut`` group.
"""

from __future__ import annotations

import dataclasses
import json
import shutil

import h5py
import numpy as np
import pytest

from ptpcore.run import session as sess
from ptpcore.cli import main
from ptpcore.errors import DatasetError, FileFormatError
from ptpcore.io import load_lut, save_lut
from ptpcore.rig import Camera
from ptpcore.run import load_session, new_session, next_step, run_session, save_session
from ptpcore.simulate import preset, simulate_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    rig, settings = preset("mild")
    rig = dataclasses.replace(rig, camera=Camera(64, 48, 12)).with_z([0.0, 8.0, 16.0, 24.0])
    return simulate_dataset(tmp_path_factory.mktemp("session") / "ds", rig, settings, seed=11)


@pytest.fixture(scope="module")
def complete(dataset, tmp_path_factory):
    """A session with every stage done, plus comparison results, saved once."""
    path = tmp_path_factory.mktemp("complete") / "full.ptps.h5"
    s = new_session(dataset, model="poly", degree=2, out=str(path.with_suffix(".lut.h5")))
    run_session(s, path)
    s.comparison = {"ptp": {"rms_um": 1.25, "p95_um": [2.0, 3.5]}, "pinhole": {"rms_um": 7.5}}
    save_session(s, path)
    return s, path


def _same_samples(a, b):
    for name in ("z", "x", "y", "x_ref", "y_ref", "reasons", "modulation", "background"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
    assert getattr(a, "noise", None) == getattr(b, "noise", None)


def _same_lut(a, b):
    for name in ("x", "y", "valid", "n_positions", "pixel_z_min", "pixel_z_max", "rms_x", "rms_y",
                 "loo_x", "loo_y"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
    assert (a.kind, a.degree, a.z_center, a.z_scale, a.z_min, a.z_max, a.rig_toml) == \
           (b.kind, b.degree, b.z_center, b.z_scale, b.z_min, b.z_max, b.rig_toml)


def _copy(path, tmp_path):
    dst = tmp_path / path.name
    shutil.copy(path, dst)
    return dst


# --------------------------------------------------------------------------- round trip

def test_round_trip_keeps_everything(complete):
    s, path = complete
    back = load_session(path)
    assert back.stage == "lut"
    assert back.rig == s.rig
    assert (back.dataset, back.model, back.degree, back.out, back.options, back.positions) == \
           (s.dataset, s.model, s.degree, s.out, s.options, s.positions)
    assert back.comparison == s.comparison
    assert json.loads(back.sim_settings)["name"] == "mild"
    assert back.samples.valid.mean() > 0.9
    _same_samples(s.samples, back.samples)
    _same_lut(s.lut, back.lut)


def test_layout_is_readable_with_plain_h5py(complete):
    _, path = complete
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == "ptp-session/1" and f.attrs["stage"] == "lut"
        assert f["lut"].attrs["format"] == "ptp-lut/1"
        assert list(f["fringes"].attrs["periods_px"]) == [4096, 640, 128, 32]
        assert f["samples/x"].shape == (4, 48, 64)
        assert "ptp-dataset/1" in f["rig"].attrs["toml"]


def test_each_stage_round_trips(dataset, tmp_path):
    s = new_session(dataset, model="pchip", positions=[0, 1, 3])
    save_session(s, tmp_path / "a.ptps.h5")
    back = load_session(tmp_path / "a.ptps.h5")
    assert back.stage == "new" and back.samples is None and back.positions == (0, 1, 3)
    run_session(back, tmp_path / "a.ptps.h5", stop_after="samples")
    again = load_session(tmp_path / "a.ptps.h5")
    assert again.stage == "samples" and again.lut is None
    _same_samples(back.samples, again.samples)
    run_session(again, tmp_path / "a.ptps.h5")
    final = load_session(tmp_path / "a.ptps.h5")
    assert final.stage == "lut" and final.lut.kind == "pchip"
    np.testing.assert_array_equal(final.lut.z_nodes, [0.0, 8.0, 24.0])


def test_next_step_follows_the_stages(dataset, complete, tmp_path):
    s = new_session(dataset, model="poly", degree=1, positions=[0, 2, 3])
    assert next_step(s) == "decode"
    run_session(s, tmp_path / "n.ptps.h5", stop_after="samples")
    assert next_step(load_session(tmp_path / "n.ptps.h5")) == "fit"
    run_session(s, tmp_path / "n.ptps.h5")
    assert next_step(load_session(tmp_path / "n.ptps.h5")) == "compare"
    assert next_step(load_session(complete[1])) is None  # comparison results saved too


def test_smooth_session_round_trips(dataset, tmp_path):
    s = new_session(dataset, model="smooth", degree=1)
    run_session(s, tmp_path / "s.ptps.h5")
    back = load_session(tmp_path / "s.ptps.h5")
    assert back.model == "smooth" and back.degree == 1 and back.stage == "lut"
    assert back.lut.kind == "poly" and back.lut.extra_attrs["method"] == "smooth"
    _same_lut(s.lut, back.lut)
    np.testing.assert_array_equal(back.lut.sigma_x, s.lut.sigma_x)
    with pytest.raises(ValueError, match="degree must be an integer 1 to 5"):
        new_session(dataset, model="smooth", degree=7)


def test_stage_sigma_and_level_bias_round_trip_and_reach_the_sigma_maps(dataset, tmp_path):
    plain = new_session(dataset, model="smooth", degree=1, level_bias=False)
    run_session(plain)
    s = new_session(dataset, model="smooth", degree=1, stage_sigma_um=0.5, level_bias=False)
    run_session(s, tmp_path / "s.ptps.h5")
    back = load_session(tmp_path / "s.ptps.h5")
    assert back.settings.stage_sigma_um == 0.5 and back.settings.level_bias is False
    assert back.settings.footprint is True
    assert back.settings.robust is True and "robust" in s.lut.provenance  # the robust fit is the default
    off = new_session(dataset, model="smooth", degree=1, footprint=False, robust=False)
    save_session(off, tmp_path / "off.ptps.h5")
    assert load_session(tmp_path / "off.ptps.h5").settings.footprint is False
    assert load_session(tmp_path / "off.ptps.h5").settings.robust is False
    m = s.lut.valid
    # The stage term adds (dX/dz * 0.5 um)^2 * leverage: nothing where the ray is vertical.
    assert np.all(s.lut.sigma_x[m] >= plain.lut.sigma_x[m]) and np.mean(s.lut.sigma_x[m] > plain.lut.sigma_x[m]) > 0.9
    np.testing.assert_array_equal(s.lut.x, plain.lut.x)      # and only to the sigma maps
    with pytest.raises(ValueError, match="stage sigma"):
        new_session(dataset, stage_sigma_um=-1.0)


# --------------------------------------------------------------------------- resume

def test_cli_saves_each_stage_and_resume_continues(dataset, complete, tmp_path, capsys):
    """Direct run, resume from 'new', resume from 'samples' without the images: same LUT."""
    direct = tmp_path / "direct.lut.h5"
    assert main(["calibrate", str(dataset), "--out", str(direct), "--model", "poly", "--degree", "2",
                 "--session", str(tmp_path / "d.ptps.h5"), "-q"]) == 0
    assert load_session(tmp_path / "d.ptps.h5").stage == "lut"
    reference = load_lut(direct)
    _same_lut(reference, complete[0].lut)

    # Interrupted before decoding: resume decodes and fits.
    s0 = new_session(dataset, model="poly", degree=2, out=str(tmp_path / "from_new.lut.h5"))
    save_session(s0, tmp_path / "new.ptps.h5")
    assert main(["resume", str(tmp_path / "new.ptps.h5"), "-q"]) == 0
    assert "resuming after stage 'new'" in capsys.readouterr().out
    _same_lut(reference, load_lut(tmp_path / "from_new.lut.h5"))
    assert load_session(tmp_path / "new.ptps.h5").stage == "lut"

    # Interrupted after decoding: resume only fits; the images are not needed any more.
    copy = tmp_path / "ds_copy"
    shutil.copytree(dataset, copy)
    s1 = new_session(copy, model="poly", degree=2)
    run_session(s1, tmp_path / "samples.ptps.h5", stop_after="samples")
    shutil.rmtree(copy)
    assert main(["resume", str(tmp_path / "samples.ptps.h5"), "--out", str(tmp_path / "r.lut.h5"), "-q"]) == 0
    _same_lut(reference, load_lut(tmp_path / "r.lut.h5"))


def test_resume_without_an_output_file_asks_for_one(dataset, tmp_path, capfd):
    s = new_session(dataset, degree=2)
    save_session(s, tmp_path / "x.ptps.h5")
    capfd.readouterr()
    assert main(["resume", str(tmp_path / "x.ptps.h5"), "-q"]) == 2
    err = capfd.readouterr().err
    assert len(err.splitlines()) == 1 and "--out" in err


def test_cancel_during_decode_keeps_the_saved_stage(dataset, tmp_path):
    path = tmp_path / "c.ptps.h5"
    s = new_session(dataset, degree=2)
    save_session(s, path)
    before = path.read_bytes()

    def cancel(fraction, message):
        if fraction > 0.05:  # in the decode (its share of the bar: K of K + 7 K position decodes for auto)
            raise DatasetError("cancelled by test")  # any exception: the file keeps its stage

    with pytest.raises(DatasetError):
        run_session(s, path, progress=cancel)
    assert path.read_bytes() == before and load_session(path).stage == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["c.ptps.h5"]


# --------------------------------------------------------------------------- versions

def _to_fake_v1(path):
    """Rewrite a current file into an invented older layout: rig text as a root attribute."""
    with h5py.File(path, "r+") as f:
        f.attrs["rig_toml"] = f["rig"].attrs["toml"]
        del f["rig"]
        f.attrs["format"] = "ptp-session/1"


def _migrate_v1_to_v2(f):
    f.create_group("rig").attrs["toml"] = f.attrs["rig_toml"]
    del f.attrs["rig_toml"]


def test_migrations_run_step_by_step_in_memory(complete, tmp_path, monkeypatch):
    path = _copy(complete[1], tmp_path)
    _to_fake_v1(path)
    on_disk = path.read_bytes()
    steps = []

    def v1_to_v2(f):
        steps.append((1, f.attrs["format"]))
        _migrate_v1_to_v2(f)

    def v2_to_v3(f):
        steps.append((2, f.attrs["format"]))

    monkeypatch.setattr(sess, "SESSION_VERSION", 3)
    monkeypatch.setattr(sess, "_MIGRATIONS", {1: v1_to_v2, 2: v2_to_v3})
    back = load_session(path)
    assert steps == [(1, "ptp-session/1"), (2, "ptp-session/2")]
    assert back.rig == complete[0].rig
    _same_lut(back.lut, complete[0].lut)
    assert path.read_bytes() == on_disk  # reading never rewrites the file


def test_missing_or_failing_migration_is_a_clear_error(complete, tmp_path, monkeypatch):
    path = _copy(complete[1], tmp_path)
    _to_fake_v1(path)
    monkeypatch.setattr(sess, "SESSION_VERSION", 2)
    monkeypatch.setattr(sess, "_MIGRATIONS", {})
    with pytest.raises(FileFormatError, match="no migration from ptp-session/1 to ptp-session/2"):
        load_session(path)

    def broken(f):
        raise KeyError("rig_toml")

    monkeypatch.setattr(sess, "_MIGRATIONS", {1: broken})
    with pytest.raises(FileFormatError, match=r"cannot upgrade from ptp-session/1"):
        load_session(path)


def test_too_new_is_refused(complete, tmp_path):
    path = _copy(complete[1], tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["format"] = "ptp-session/2"
    with pytest.raises(FileFormatError, match=r"'ptp-session/2' is newer than this software reads"):
        load_session(path)
    lut = tmp_path / "new.lut.h5"
    save_lut(complete[0].lut, lut)
    with h5py.File(lut, "r+") as f:
        f.attrs["format"] = "ptp-lut/7"
    with pytest.raises(FileFormatError, match=r"'ptp-lut/7' is newer"):
        load_lut(lut)


# --------------------------------------------------------------------------- damaged files

@pytest.mark.parametrize("fraction", [0.0, 0.01, 0.3, 0.6, 0.9, 0.999])
def test_truncated_session_is_refused(complete, tmp_path, fraction):
    data = complete[1].read_bytes()
    path = tmp_path / "cut.ptps.h5"
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(FileFormatError) as err:
        load_session(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("fraction", [0.0, 0.2, 0.7, 0.999])
def test_truncated_lut_is_refused(complete, tmp_path, fraction, capfd):
    full = tmp_path / "full.lut.h5"
    save_lut(complete[0].lut, full)
    data = full.read_bytes()
    path = tmp_path / "cut.lut.h5"
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(FileFormatError):
        load_lut(path)
    capfd.readouterr()
    assert main(["inspect", str(path)]) == 2
    err = capfd.readouterr().err
    assert len(err.splitlines()) == 1 and str(path) in err


def _damage(path, edit):
    with h5py.File(path, "r+") as f:
        edit(f)


def _replace(f, name, data):
    del f[name]
    f[name] = data


CASES = {
    "wrong shape": (lambda f: _replace(f, "samples/x", np.zeros((4, 48, 63), np.float32)),
                    "/samples/x has shape (4, 48, 63), expected (4, 48, 64)"),
    "NaN at a valid sample": (lambda f: f["samples/y"].__setitem__((1, 20, 30), np.nan),
                              "/samples/y holds NaN"),
    "NaN in a valid LUT pixel": (lambda f: f["lut/x"].__setitem__((0, 5, 5), np.nan), "/lut/x holds NaN"),
    "LUT shape": (lambda f: _replace(f, "lut/valid", np.ones((48, 60), np.uint8)),
                  "/lut/valid has shape (48, 60)"),
    "LUT degree": (lambda f: f["lut/model"].attrs.__setitem__("degree", 9), "'degree' of /lut/model"),
    "LUT z_scale": (lambda f: f["lut/model"].attrs.__setitem__("z_scale", 0.0), "'z_scale' of /lut/model"),
    "LUT valid flag": (lambda f: _replace(f, "lut/valid", np.full((48, 64), 7, np.uint8)),
                       "/lut/valid must hold only 0 and 1"),
    "missing dataset": (lambda f: f.__delitem__("samples/reasons"), "missing dataset /samples/reasons"),
    "stage without data": (lambda f: f.__delitem__("lut"), "'stage' says 'lut' but /lut is missing"),
    "z disagrees": (lambda f: f["samples/z"].__setitem__(2, 17.0), "/samples/z disagrees"),
    "bad rig": (lambda f: f["rig"].attrs.__setitem__("toml", "format = 'ptp-dataset/1'\n"),
                "/rig: missing section [camera]"),
    "fringes disagree": (lambda f: f["fringes"].attrs.__setitem__("gamma", 1.7), "/fringes"),
    "bad comparison": (lambda f: f["comparison"].attrs.__setitem__("json", "{oops"), "/comparison"),
    "bad model": (lambda f: f["calibration"].attrs.__setitem__("model", "spline"), "/calibration"),
    "negative stage sigma": (lambda f: f["calibration"].attrs.__setitem__(
        "fit_settings", f["calibration"].attrs["fit_settings"].replace('"stage_sigma_um": 0.0', '"stage_sigma_um": -0.1')),
        "stage_sigma_um (the stage sigma) must be a finite number >= 0"),
    "unknown fit setting": (lambda f: f["calibration"].attrs.__setitem__(
        "fit_settings", f["calibration"].attrs["fit_settings"].replace('{', '{"spline": 1, ', 1)),
        "unknown fit setting 'spline'"),
    "not a session": (lambda f: f.attrs.__setitem__("format", "something/1"), "attribute 'format'"),
    "text where a number goes": (lambda f: f["lut/camera"].attrs.__setitem__("width", "64"),
                                 "'width' of /lut/camera must be a number"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_damaged_session_names_file_and_dataset(complete, tmp_path, case):
    edit, expected = CASES[case]
    path = _copy(complete[1], tmp_path)
    _damage(path, edit)
    with pytest.raises(FileFormatError) as err:
        load_session(path)
    msg = str(err.value)
    assert msg.startswith(str(path)) and expected in msg and "\n" not in msg


def test_lut_file_nan_in_valid_pixel(complete, tmp_path):
    path = tmp_path / "a.lut.h5"
    save_lut(complete[0].lut, path)
    _damage(path, lambda f: f["y"].__setitem__((1, 3, 3), np.nan))
    with pytest.raises(FileFormatError, match=r"a\.lut\.h5: /y holds NaN"):
        load_lut(path)


def test_save_refuses_inconsistent_sessions(complete, tmp_path):
    s = dataclasses.replace(complete[0], rig=complete[0].rig.with_z([0.0, 8.0, 16.0]))
    with pytest.raises(ValueError, match="samples have shape"):
        save_session(s, tmp_path / "bad.ptps.h5")
    assert not list(tmp_path.iterdir())
