"""Never lose the engineer's work (issue 20): outputs checked first, atomic writes, disk full,
SIGTERM, sanity checks from the data, arguments, BOM, broken pipe."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import gc
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import tomli_w
import tomllib

from ptpcore.atomic import DiskFullError, atomic_path, live_temporaries, remove_temporaries
from ptpcore.cli import main
from ptpcore.cli.safety import Terminated, signals_as_interrupts
from ptpcore.errors import ConfigError, DataWarning, OutputError, PtpError
from ptpcore.io import DatasetSource, SimulatedSource, load_lut
from ptpcore.io.dataset import read_image
from ptpcore.store import SpillStore
from ptpcore.io.lutfile import Lut, save_lut
from ptpcore.io.outputs import check_output_file
from ptpcore.rig import Camera, load_rig, save_rig
from ptpcore.run import check_samples, collect_samples
from ptpcore.simulate import VirtualRig, scaled_preset
from ptpcore.simulate.virtual_rig import preset, simulate_dataset

CLI = [sys.executable, "-m", "ptpcore.cli"]


def _small_rig(bit_depth: int = 8, k: int = 3):
    rig, settings = preset("ideal")
    rig = dataclasses.replace(rig, camera=Camera(64, 48, bit_depth)).with_z(np.linspace(0.0, 20.0, k))
    return rig, settings


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A valid 64x48 8-bit dataset, 3 positions (read-only by convention: copy before editing)."""
    root = tmp_path_factory.mktemp("safety")
    rig, settings = _small_rig()
    return simulate_dataset(root / "ds", rig, settings, seed=5)


def _one_error_line(capfd) -> str:
    err = capfd.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _random_lut(h: int, w: int, seed: int = 0) -> Lut:
    rng = np.random.default_rng(seed)
    f32 = lambda: rng.random((h, w), dtype=np.float32)  # noqa: E731
    return Lut("poly", 3, 20.0, 20.0, 0.0, 40.0, rng.random((4, h, w)), rng.random((4, h, w)), None,
               np.ones((h, w), bool), np.full((h, w), 3, np.uint16), np.zeros((h, w), np.float32),
               np.full((h, w), 40.0, np.float32), f32(), f32(), f32(), f32())


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if ".part" in p.name or p.name.startswith("ptp-samples-"))


# --------------------------------------------------------------------------- 1. outputs checked first

def test_out_at_the_datasets_rig_toml_is_refused_fast(dataset, capfd):
    before = (dataset / "rig.toml").read_bytes()
    t0 = time.perf_counter()
    code = main(["calibrate", str(dataset), "--out", str(dataset / "rig.toml"), "--force", "-q"])
    took = time.perf_counter() - t0
    line = _one_error_line(capfd)
    assert code == 2 and took < 10.0 and "rig.toml" in line and "input" in line
    assert (dataset / "rig.toml").read_bytes() == before
    for name in ("truth.h5", "z000/x_T32_n00.png"):  # any file of the dataset
        if (dataset / name).exists():
            assert main(["calibrate", str(dataset), "--out", str(dataset / name), "--force", "-q"]) == 2
    assert main(["compare", str(dataset), "--out", str(dataset / "rig.toml"), "--force", "-q"]) == 2


def test_existing_outputs_need_force_and_the_same_kind(dataset, tmp_path, capfd):
    lut = tmp_path / "a.lut.h5"
    save_lut(_random_lut(6, 8), lut)
    before = lut.read_bytes()
    assert main(["calibrate", str(dataset), "--out", str(lut), "-q"]) == 2
    assert "--force" in _one_error_line(capfd) and lut.read_bytes() == before
    other = tmp_path / "photo.png"
    other.write_bytes(b"\x89PNG not a LUT")
    assert main(["calibrate", str(dataset), "--out", str(other), "--force", "-q"]) == 2
    assert "another kind" in _one_error_line(capfd) and other.read_bytes() == b"\x89PNG not a LUT"
    assert main(["calibrate", str(dataset), "--out", str(tmp_path / "s.ptps.h5"), "--session", str(lut),
                 "--force", "-q"]) == 2
    assert "ptp-lut/1 file, not a ptp-session/1" in _one_error_line(capfd)
    assert main(["calibrate", str(dataset), "--out", str(tmp_path / "no" / "x.lut.h5"), "-q"]) == 2
    assert "does not exist" in _one_error_line(capfd)
    assert main(["calibrate", str(dataset), "--out", str(tmp_path), "-q"]) == 2
    assert "is a folder" in _one_error_line(capfd)
    assert main(["calibrate", str(dataset), "--out", str(lut), "--force", "--degree", "1", "-q"]) == 0
    assert load_lut(lut).degree == 1


@contextlib.contextmanager
def _read_only_folder(tmp_path: Path):
    """A folder no file can be created in: a read-only tmpfs as root, else mode 0555."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if os.geteuid() == 0:
        if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(folder)],
                          capture_output=True).returncode != 0:
            pytest.skip("running as root and mounting a read-only tmpfs is not permitted here")
        try:
            yield folder
        finally:
            subprocess.run(["umount", str(folder)], check=False)
    else:
        folder.chmod(0o555)
        try:
            yield folder
        finally:
            folder.chmod(0o755)


def test_read_only_folder_is_refused_before_the_work(dataset, tmp_path, capfd):
    with _read_only_folder(tmp_path) as ro:
        t0 = time.perf_counter()
        assert main(["calibrate", str(dataset), "--out", str(ro / "a.lut.h5"), "-q"]) == 2
        assert time.perf_counter() - t0 < 10.0
        assert "cannot write" in _one_error_line(capfd)
        assert main(["simulate", str(ro / "new"), "--width", "16", "--positions", "2", "-q"]) == 2
        assert "cannot write" in _one_error_line(capfd)


def test_simulate_and_demo_refuse_a_dataset_folder(dataset, tmp_path, capfd):
    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds)
    before = (ds / "rig.toml").read_bytes()
    assert main(["simulate", str(ds), "--width", "16", "--positions", "2", "-q"]) == 2
    assert "already holds a dataset" in _one_error_line(capfd) and (ds / "rig.toml").read_bytes() == before
    assert main(["demo", "--out", str(ds), "-q"]) == 2
    assert "already holds a dataset" in _one_error_line(capfd)
    assert main(["simulate", str(ds), "--width", "16", "--positions", "2", "--force", "-q"]) == 0
    assert load_rig(ds / "rig.toml").camera.width == 16
    assert main(["capture", "--out", str(dataset), "--width", "16", "--positions", "2", "-q"]) == 2
    assert "already holds a dataset" in _one_error_line(capfd)


def test_check_output_file_engine_call(dataset, tmp_path):
    """The call the wizard can use before a job: same rules, OutputError."""
    with pytest.raises(OutputError, match="input"):
        check_output_file(dataset / "rig.toml", "lut", force=True, inputs=[dataset])
    assert check_output_file(tmp_path / "new.lut.h5", "lut", inputs=[dataset]) == tmp_path / "new.lut.h5"


def test_demo_removes_its_temporary_folder(monkeypatch, tmp_path):
    climain = sys.modules["ptpcore.cli.main"]

    made = []

    def fake_demo(args, workdir):
        made.append(workdir)
        (workdir / "big.png").write_bytes(b"x" * 1000)
        if len(made) == 2:
            raise KeyboardInterrupt
        return 0

    monkeypatch.setattr(climain, "_demo", fake_demo)
    monkeypatch.setattr(climain.tempfile, "tempdir", str(tmp_path))
    assert main(["demo", "-q"]) == 0
    assert main(["demo", "-q"]) == 130
    assert len(made) == 2 and not any(p.exists() for p in made) and list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- 2. atomic writes, disk full, signals

def test_atomic_temporaries_are_registered_and_removed_on_terminate(tmp_path):
    target = tmp_path / "x.bin"
    with pytest.raises(Terminated):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            assert tmp in live_temporaries()
            raise Terminated()
    assert not target.exists() and list(tmp_path.iterdir()) == [] and live_temporaries() == []
    # a temporary whose writer never got to its finally: removed by the CLI's last step
    with atomic_path(tmp_path / "y.bin") as tmp:
        tmp.write_bytes(b"x")
        assert remove_temporaries() == [tmp] and not tmp.exists()
        tmp.write_bytes(b"y")  # the writer goes on; the rename still works
    assert (tmp_path / "y.bin").read_bytes() == b"y"


class _HalfBuilt:
    """An object whose constructor SIGTERM interrupts, as llvmlite's compiler passes were in CI."""

    def __init__(self, signal_it: bool):
        if signal_it:
            os.kill(os.getpid(), signal.SIGTERM)  # lands before the handle exists
        self._handle = 1

    def __del__(self):
        del self._handle  # AttributeError on a half-built object, as llvmlite's detach()


@pytest.mark.skipif(not hasattr(signal, "SIGTERM") or threading.current_thread() is not threading.main_thread(),
                    reason="signal handlers need the main thread")
def test_a_finaliser_failing_after_sigterm_prints_no_traceback(capfd):
    with signals_as_interrupts():
        try:
            _HalfBuilt(signal_it=True)
        except Terminated:
            pass
        gc.collect()
        quiet = capfd.readouterr().err
    with signals_as_interrupts():
        broken = _HalfBuilt(signal_it=False)
        del broken._handle
        del broken  # the same failure without a SIGTERM is a real fault: reported
        gc.collect()
        loud = capfd.readouterr().err
    assert "Traceback" not in quiet and "AttributeError" not in quiet
    assert "AttributeError" in loud


def test_disk_full_monkeypatched_lut_session_and_spill(tmp_path, monkeypatch):
    """ENOSPC from the write itself: DiskFullError naming the path and the size, nothing left."""
    real = Path.write_bytes

    def full(self, data):
        real(self, bytes(data)[:100])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full)
    lut = _random_lut(40, 50)
    with pytest.raises(DiskFullError) as exc:
        save_lut(lut, tmp_path / "a.lut.h5")
    msg = str(exc.value)
    assert "a.lut.h5" in msg and "MB" in msg and "disk full" in msg and "\n" not in msg
    assert isinstance(exc.value, PtpError) and exc.value.errno == errno.ENOSPC  # user-facing, and still an OSError
    assert list(tmp_path.iterdir()) == []
    from ptpcore.run.session import Session, save_session

    rig, _ = _small_rig()
    with pytest.raises(DiskFullError, match="s.ptps.h5"):
        save_session(Session(rig=rig), tmp_path / "s.ptps.h5")
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()

    def no_space(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", no_space, raising=False)
    with pytest.raises(DiskFullError, match="PTP_SPILL_DIR") as exc:
        SpillStore(3, (48, 64), {"x": np.float32}, {}, directory=tmp_path)
    assert "0.0 MB" in str(exc.value) or "MB" in str(exc.value)
    assert list(tmp_path.iterdir()) == []


def test_big_hdf5_files_go_straight_to_disk_after_a_space_check(tmp_path, monkeypatch):
    """Above IN_MEMORY_MAX (a large sensor's session) the file is not built in memory: the disk's room
    for the uncompressed size is checked first."""
    import ptpcore.io.lutfile as lutfile

    monkeypatch.setattr(lutfile, "IN_MEMORY_MAX", 0)
    lut = _random_lut(30, 40)
    save_lut(lut, tmp_path / "a.lut.h5")
    np.testing.assert_array_equal(load_lut(tmp_path / "a.lut.h5").x, lut.x)
    real = shutil.disk_usage
    monkeypatch.setattr(lutfile.shutil, "disk_usage", lambda p: real(p)._replace(free=1000))
    with pytest.raises(DiskFullError, match="b.lut.h5"):
        save_lut(lut, tmp_path / "b.lut.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.lut.h5"]


@pytest.fixture
def tiny_fs(tmp_path):
    """A 1 MB tmpfs (root only); skipped with the reason when mounting is not permitted."""
    folder = tmp_path / "tiny"
    folder.mkdir()
    if os.geteuid() != 0:
        pytest.skip("a 1 MB tmpfs needs root (mount -t tmpfs); the monkeypatched ENOSPC test covers the logic")
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(folder)],
                      capture_output=True).returncode != 0:
        pytest.skip("mounting a tmpfs is not permitted in this environment")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=False)


def test_disk_full_on_a_1mb_filesystem_lut(tiny_fs, dataset, capfd):
    with pytest.raises(DiskFullError):
        save_lut(_random_lut(120, 160), tiny_fs / "big.lut.h5")  # ~2.5 MB of random coefficients
    assert list(tiny_fs.iterdir()) == []
    (tiny_fs / "filler").write_bytes(b"\0" * (1024 * 1024 - 8 * 1024))  # leaves 8 kB
    code = main(["calibrate", str(dataset), "--out", str(tiny_fs / "c.lut.h5"), "--degree", "1", "-q"])
    line = _one_error_line(capfd)
    assert code == 2 and "c.lut.h5" in line and "disk full" in line and "needs" in line
    assert sorted(p.name for p in tiny_fs.iterdir()) == ["filler"]


def test_disk_full_on_a_1mb_filesystem_spill(tiny_fs, dataset, capfd, monkeypatch):
    with pytest.raises(DiskFullError, match="PTP_SPILL_DIR"):
        SpillStore(40, (120, 160), {"x": np.float32, "y": np.float32}, {}, directory=tiny_fs)
    assert list(tiny_fs.iterdir()) == []
    import ptpcore.run.pipeline as pipeline

    monkeypatch.setattr(pipeline, "SPILL_BYTES", 0)  # the CLI spills this small dataset
    monkeypatch.setenv("PTP_SPILL_DIR", str(tiny_fs))
    (tiny_fs / "filler").write_bytes(b"\0" * (1024 * 1024 - 32 * 1024))
    out = tiny_fs.parent / "c.lut.h5"
    assert main(["calibrate", str(dataset), "--out", str(out), "--degree", "1", "-q"]) == 2
    line = _one_error_line(capfd)
    assert "disk full" in line and "spill" in line and not out.exists()
    assert sorted(p.name for p in tiny_fs.iterdir()) == ["filler"]


@pytest.mark.slow  # ~55 s (a decode big enough to be stopped mid-way, then resumed)
def test_sigterm_mid_decode_leaves_no_temporary_and_resumes(tmp_path):
    rig, settings = scaled_preset("realistic", 320, positions=6)
    ds = simulate_dataset(tmp_path / "ds", rig, settings, seed=1)
    out, session, spill = tmp_path / "out", tmp_path / "out" / "s.ptps.h5", tmp_path / "spill"
    out.mkdir()
    spill.mkdir()
    env = dict(os.environ, PTP_SPILL_DIR=str(spill))
    proc = subprocess.Popen([*CLI, "calibrate", str(ds), "--out", str(out / "c.lut.h5"), "--session", str(session),
                             "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    t0 = time.monotonic()
    while not session.exists() and proc.poll() is None and time.monotonic() - t0 < 60:
        time.sleep(0.01)
    time.sleep(0.3)  # decoding has started
    if proc.poll() is not None:
        pytest.fail(f"calibration ended before SIGTERM: {proc.communicate()}")
    proc.send_signal(signal.SIGTERM)
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err.decode()
    assert "Traceback" not in err.decode() and "terminated" in err.decode()
    assert _leftovers(tmp_path) == [] and list(spill.iterdir()) == []
    assert sorted(p.name for p in out.iterdir()) == ["s.ptps.h5"]
    done = subprocess.run([*CLI, "resume", str(session), "-q"], capture_output=True, text=True, env=env,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert load_lut(out / "c.lut.h5").shape == (240, 320) and _leftovers(tmp_path) == []


def test_sigterm_swallowed_by_a_c_callback_still_stops_at_the_next_progress_report():
    """CI saw SIGTERM land while numba compiled (a ctypes callback prints and drops the exception)."""
    from ptpcore.cli.progress import ProgressBar
    from ptpcore.cli.safety import signals_as_interrupts

    bar = ProgressBar(enabled=False)
    with signals_as_interrupts():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)  # the handler runs here
        except Terminated:
            pass  # what a ctypes callback does with an exception
        with pytest.raises(Terminated):
            bar(0.5, "decoding")
    bar(0.6, "a later job is not stopped")  # the request ends with its block


def test_sigterm_swallowed_after_the_last_step_still_exits_143(monkeypatch, capfd):
    def job(_args):
        with contextlib.suppress(Terminated):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        return 0

    monkeypatch.setattr(sys.modules["ptpcore.cli.main"], "_run", job)  # ptpcore.cli.main is also the function
    assert main(["inspect", str(Path(__file__))]) == 143
    assert "terminated" in capfd.readouterr().err


# --------------------------------------------------------------------------- 3. sanity checks from the data

@pytest.fixture(scope="module")
def small_samples():
    rig, settings = scaled_preset("realistic", 80, positions=5)
    vr = VirtualRig(rig, settings, 2)
    return vr, collect_samples(SimulatedSource(vr))


def test_reversed_readings_are_an_error_naming_z_mm(small_samples):
    _vr, s = small_samples
    assert check_samples(s, warn=False) == []
    with pytest.raises(ConfigError, match="z_mm"):
        check_samples(dataclasses.replace(s, z=s.z[::-1].copy()))
    with pytest.raises(ConfigError, match="z_mm"):  # negated readings run the wrong way too
        check_samples(dataclasses.replace(s, z=-s.z))


def test_reversed_readings_in_rig_toml_exit_2(dataset, tmp_path, capfd):
    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds)
    doc = tomllib.loads((ds / "rig.toml").read_text())
    doc["stage"]["z_mm"] = doc["stage"]["z_mm"][::-1]
    (ds / "rig.toml").write_text(tomli_w.dumps(doc))
    assert main(["calibrate", str(ds), "--out", str(tmp_path / "c.lut.h5"), "--degree", "1", "-q"]) == 2
    line = _one_error_line(capfd)
    assert "z_mm" in line and "rig.toml" in line and not (tmp_path / "c.lut.h5").exists()


def test_stuck_stage_is_a_warning_naming_both_positions(small_samples):
    vr, _ = small_samples
    stuck = VirtualRig(vr.rig, vr.settings, vr.seed)
    stuck.z_true = stuck.z_true.copy()
    stuck.z_true[3] = stuck.z_true[2]  # the stage did not move from position 2 to 3
    s = collect_samples(SimulatedSource(stuck))
    with pytest.warns(DataWarning) as rec:
        found = check_samples(s)
    assert len(found) == 1 and "positions 2 " in found[0] and " and 3 " in found[0]
    assert str(rec[0].message) == found[0]


def test_duplicated_images_warn_in_the_cli(dataset, tmp_path, capfd):
    ds = tmp_path / "ds"
    shutil.copytree(dataset, ds)
    shutil.rmtree(ds / "z002")
    shutil.copytree(ds / "z001", ds / "z002")
    assert main(["calibrate", str(ds), "--out", str(tmp_path / "c.lut.h5"), "--degree", "1", "-q"]) == 0
    err = capfd.readouterr().err
    assert "ptp: warning: positions 1 (z = 10 mm) and 2 (z = 20 mm)" in err and "stuck" in err


def test_msb_aligned_16_bit_images(tmp_path, capfd):
    """12-bit samples stored as value << 4: warned without bit_shift, read exactly with it."""
    rig, settings = _small_rig(bit_depth=12)
    ds = simulate_dataset(tmp_path / "ds", rig, settings, seed=5)
    plain = collect_samples(DatasetSource(ds))
    files = sorted(ds.rglob("*.png"))
    originals = {p: cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in files}
    for p, img in originals.items():
        assert img.dtype == np.uint16 and int(img.max()) < 4096
        cv2.imwrite(str(p), (img << 4).astype(np.uint16))
    with pytest.warns(DataWarning, match="bit_shift = 4"):
        collect_samples(DatasetSource(ds))
    assert main(["calibrate", str(ds), "--out", str(tmp_path / "c.lut.h5"), "--degree", "1", "-q"]) in (0, 2)
    assert "ptp: warning:" in capfd.readouterr().err
    save_rig(dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, bit_shift=4)), ds / "rig.toml")
    shifted = DatasetSource(ds)
    assert shifted.rig.camera.bit_shift == 4
    np.testing.assert_array_equal(read_image(files[0], shifted.rig), originals[files[0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        again = collect_samples(shifted)
    np.testing.assert_array_equal(again.x, plain.x)
    np.testing.assert_array_equal(again.reasons, plain.reasons)


# --------------------------------------------------------------------------- 4. arguments, BOM, broken pipe

@pytest.mark.parametrize("argv, culprit", [
    (["simulate", "X", "--width", "-5"], "--width"),
    (["simulate", "X", "--positions", "0"], "--positions"),
    (["simulate", "X", "--seed", "-1"], "--seed"),
    (["simulate", "X", "--height", "abc"], "--height"),
    (["calibrate", "NOPE", "--out", "x.lut.h5"], "NOPE"),
    (["calibrate", ".", "--out", "x.lut.h5", "--degree", "9"], "--degree"),
    (["compare", ".", "--out", "r.json", "--points", "0"], "--points"),
    (["demo", "--seed", "-3"], "--seed"),
    (["demo", "--degree", "0"], "--degree"),
    (["inspect", "missing.lut.h5"], "missing.lut.h5"),
    (["resume", "missing.ptps.h5"], "missing.ptps.h5"),
    (["capture", "--out", "C", "--config", "missing.toml"], "missing.toml"),
    (["capture", "--out", "C", "--exposure-us", "-1"], "--exposure-us"),
])
def test_bad_arguments_are_one_line_exit_2(argv, culprit, tmp_path, capfd, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    line = _one_error_line(capfd)
    assert culprit in line and "error" in line
    assert not (tmp_path / "X").exists()


def test_bad_argument_in_a_subprocess_has_no_traceback():
    proc = subprocess.run([*CLI, "simulate", "X", "--width", "-5"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_rig_toml_with_a_byte_order_mark(dataset, tmp_path):
    text = (dataset / "rig.toml").read_text(encoding="utf-8")
    (tmp_path / "rig.toml").write_bytes(b"\xef\xbb\xbf" + text.encode("utf-8"))
    assert load_rig(tmp_path / "rig.toml") == load_rig(dataset / "rig.toml")


def test_broken_pipe_ends_quietly(tmp_path, monkeypatch, capsys):
    lut = tmp_path / "a.lut.h5"
    save_lut(_random_lut(6, 8), lut)
    proc = subprocess.run(f"{sys.executable} -m ptpcore.cli inspect {lut} | head -c 1 >/dev/null;"
                          " exit ${PIPESTATUS[0]}", shell=True, executable="/bin/bash", capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode in (0, 141) and proc.stderr == ""

    class Closed:
        def write(self, text):
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")

        def flush(self):
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")

        def fileno(self):
            raise OSError("no file descriptor")

    monkeypatch.setattr(sys, "stdout", Closed())
    assert main(["inspect", str(lut)]) == 141
