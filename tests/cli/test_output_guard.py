"""One output guard over every output argument of every ``ptp`` command (issue 41).

The cases are generated from the parser: every argument marked as an output
(:func:`ptpcore.cli.safety.add_output`) of every subcommand, ``ptp capture``
included, is tried onto a file the command reads, onto an existing file
without ``--force``, onto a file of another kind, into a missing folder and
into a folder that cannot be written. Each must end with exit 2 and one line
on stderr naming the path, leave the target byte for byte as it was and
write nothing, and the command itself must never have started (its function
is replaced by a recorder: the guard runs before any decoding). A fresh
target, and an existing one with ``--force``, pass the guard (the recorder
runs), so the guard refuses what it should and nothing more.

Read-only folders: as root, ``chmod`` does not stop a write, so the folder is
a read-only tmpfs mount where the sandbox allows one (else that test skips),
and a second test makes the guard's write probe fail (monkeypatch); both run
where mounting is allowed.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

import ptpcore.io.outputs as outputs
from ptpcore.cli.main import build_parser, main
from ptpcore.cli.safety import input_actions, output_actions, subcommands
from ptpcore.io.lutfile import Lut, save_lut

climain = sys.modules["ptpcore.cli.main"]  # (ptpcore.cli.main is also the name of its function main)
PARSER = build_parser()
OUTPUTS = [(cmd, action.dest) for cmd, sub in subcommands(PARSER).items() for action in output_actions(sub)]
IDS = [f"{cmd}-{dest}" for cmd, dest in OUTPUTS]
SUFFIX = {"lut": ".lut.h5", "session": ".ptps.h5", "decoded": ".decoded.h5", "points": ".ply",
          "report": ".json", "png": ".png", "rig": ".toml"}


def _random_lut(h: int = 6, w: int = 8) -> Lut:
    rng = np.random.default_rng(0)
    f32 = lambda: rng.random((h, w), dtype=np.float32)  # noqa: E731
    return Lut("poly", 3, 20.0, 20.0, 0.0, 40.0, rng.random((4, h, w)), rng.random((4, h, w)), None,
               np.ones((h, w), bool), np.full((h, w), 3, np.uint16), np.zeros((h, w), np.float32),
               np.full((h, w), 40.0, np.float32), f32(), f32(), f32(), f32())


def _hdf5(path: Path, fmt: str) -> Path:
    with h5py.File(path, "w") as f:
        f.attrs["format"] = fmt
        f["x"] = np.arange(3)
    return path


def _write_kind(path: Path, kind: str, files: dict) -> Path:
    """An existing file of ``kind``, by content (as a ptp command would have written it)."""
    if kind == "lut":
        shutil.copy(files["lut"], path)
    elif kind in ("session", "decoded"):
        _hdf5(path, {"session": "ptp-session/1", "decoded": "ptp-decoded/1"}[kind])
    elif kind == "points":
        path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nend_header\n")
    elif kind == "report":
        path.write_text('{"verdict": "consistent"}\n')
    elif kind == "png":
        path.write_bytes(cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1].tobytes())
    elif kind == "rig":
        shutil.copy(files["dataset"] / "rig.toml", path)
    else:
        raise AssertionError(kind)
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict:
    """The inputs a command may read: a tiny dataset, a LUT, a session file, a scan folder, a config."""
    root = tmp_path_factory.mktemp("guard-inputs")
    assert main(["simulate", str(root / "DS"), "--preset", "ideal", "--width", "32", "--positions", "3", "-q"]) == 0
    lut = root / "A.lut.h5"
    save_lut(_random_lut(), lut)
    scans = root / "scans"
    scans.mkdir()
    (scans / "scan.toml").write_text("# a scan folder (ptp-scan/1)\n")
    (root / "capture.toml").write_text("[camera]\nkind = \"sim\"\n")
    return {"dataset": root / "DS", "lut": lut, "session": _hdf5(root / "S.ptps.h5", "ptp-session/1"),
            "scans": scans, "rig": root / "DS" / "rig.toml", "config": root / "capture.toml", "height": "12.5"}


@pytest.fixture
def calls(monkeypatch):
    """Every command's function replaced by a recorder (the guard must refuse before it runs)."""
    made = []

    def parser():
        p = build_parser()
        for name, sub in subcommands(p).items():
            sub.set_defaults(func=lambda args, name=name: made.append(name) or 0)
        return p

    monkeypatch.setattr(climain, "build_parser", parser)
    return made


def _action(cmd: str, dest: str) -> argparse.Action:
    return next(a for a in subcommands(PARSER)[cmd]._actions if a.dest == dest)


def _argv(cmd: str, dest: str, target, files: dict, fresh: Path, *extra: str) -> list[str]:
    """``ptp CMD`` with every marked input filled, ``dest`` set to ``target`` and other required outputs fresh."""
    sub = subcommands(PARSER)[cmd]
    positional, options = [], []
    for i, action in enumerate(sub._actions):
        if isinstance(action, argparse._HelpAction):
            continue
        if action.dest == dest:
            value = str(target)
        elif getattr(action, "ptp_input", None):
            value = str(files[action.ptp_input])
        elif getattr(action, "ptp_output", None) and (action.required or not action.option_strings):
            kind = action.ptp_output
            value = str(fresh / (f"other{i}" + SUFFIX.get(kind, "")))
        elif action.required:
            raise AssertionError(f"ptp {cmd}: required argument {action.dest} is neither an input nor an output")
        else:
            continue
        if action.option_strings:
            options += [action.option_strings[-1], value]
        else:
            positional.append(value)
    return [cmd, *positional, *options, *extra]


def _snapshot(path: Path):
    if path.is_dir():
        return sorted((str(p.relative_to(path)), p.read_bytes() if p.is_file() else None) for p in path.rglob("*"))
    return path.read_bytes() if path.exists() else None


def _refused(capfd, calls, argv, target: Path, *words: str) -> str:
    """Run ``argv``: exit 2, one line naming ``target``, the command never started, the target unchanged."""
    folder = target.parent
    before, listing = _snapshot(target), _snapshot(folder) if folder.is_dir() else None
    capfd.readouterr()
    code = main(argv)
    err = capfd.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, (argv, err)
    assert len(lines) == 1 and lines[0].startswith("ptp: error: ") and "Traceback" not in err, err
    assert str(target) in lines[0] or target.name in lines[0], (target, lines[0])
    assert "Errno" not in lines[0] and ".part" not in lines[0] and ".ptp-write-test" not in lines[0], lines[0]
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert calls == [], f"ptp {argv[0]} started before its output was refused"
    assert _snapshot(target) == before
    if listing is not None:
        assert _snapshot(folder) == listing, "something was written beside the target"
    return lines[0]


def _passes(calls, argv) -> None:
    """The guard lets ``argv`` through: the (recorded) command runs."""
    calls.clear()
    assert main(argv) == 0, argv
    assert calls == [argv[0]]
    calls.clear()


def _replace_flag(cmd: str, dest: str) -> list[str]:
    """The flag that lets an existing output be replaced or written into (``--force``, ``--resume``)."""
    sub = subcommands(PARSER)[cmd]
    if any(a.dest == "force" for a in sub._actions):
        return ["--force"]
    resume = getattr(_action(cmd, dest), "ptp_resume", None)
    return [f"--{resume}"] if resume else []


# --------------------------------------------------------------------------- the parser's marks

def test_every_output_argument_is_marked_and_kinds_known():
    """Arguments named like outputs carry the mark; every command that writes has one (a new one is then
    covered by the tests below without editing them)."""
    assert {cmd for cmd, _ in OUTPUTS} >= {"simulate", "calibrate", "resume", "decode", "apply", "reconstruct",
                                            "acceptance", "compare", "diff", "demo", "capture"}
    for cmd, sub in subcommands(PARSER).items():
        for action in sub._actions:
            if action.dest in ("out", "out_dir", "json", "png") or (cmd == "calibrate" and action.dest == "session"):
                assert getattr(action, "ptp_output", None), f"ptp {cmd} {action.dest}: an output without the mark"
        for action in output_actions(sub):
            assert action.ptp_output in (*SUFFIX, "dataset")
        for action in input_actions(sub):
            assert action.ptp_input in ("dataset", "scans", "lut", "session", "rig", "config", "height")
    assert any(a.dest == "force" for a in subcommands(PARSER)["decode"]._actions)
    assert any(a.dest == "force" for a in subcommands(PARSER)["diff"]._actions)


@pytest.mark.parametrize("cmd,dest", OUTPUTS, ids=IDS)
def test_a_fresh_output_passes(cmd, dest, files, tmp_path, calls):
    kind = _action(cmd, dest).ptp_output
    _passes(calls, _argv(cmd, dest, tmp_path / ("new" + SUFFIX.get(kind, "")), files, tmp_path))


# --------------------------------------------------------------------------- the five refusals

def _input_targets(cmd: str, kind: str, files: dict) -> list[Path]:
    """Files the command reads (input files, a file inside each input folder) and, for a folder output,
    the input folders themselves."""
    out = []
    for action in input_actions(subcommands(PARSER)[cmd]):
        value = files[action.ptp_input]
        if action.ptp_input == "height":
            continue
        value = Path(value)
        if value.is_dir():
            out.append(next(p for p in sorted(value.rglob("*")) if p.is_file()))
            if kind == "dataset":
                out.append(value)
        else:
            out.append(value)
    return out


@pytest.mark.parametrize("cmd,dest", OUTPUTS, ids=IDS)
def test_onto_a_file_the_command_reads(cmd, dest, files, tmp_path, calls, capfd):
    kind = _action(cmd, dest).ptp_output
    targets = _input_targets(cmd, kind, files)
    if not targets:
        pytest.skip(f"ptp {cmd} reads no file")
    for target in targets:
        _refused(capfd, calls, _argv(cmd, dest, target, files, tmp_path, *_replace_flag(cmd, dest)), target)


@pytest.mark.parametrize("cmd,dest", OUTPUTS, ids=IDS)
def test_onto_an_existing_file_without_force(cmd, dest, files, tmp_path, calls, capfd):
    kind = _action(cmd, dest).ptp_output
    if kind == "dataset":  # a folder that already holds a dataset
        target = tmp_path / "old"
        target.mkdir()
        shutil.copy(files["dataset"] / "rig.toml", target / "rig.toml")
        line = _refused(capfd, calls, _argv(cmd, dest, target, files, tmp_path), target / "rig.toml",
                        "already holds a dataset")
    else:
        target = _write_kind(tmp_path / ("old" + SUFFIX[kind]), kind, files)
        line = _refused(capfd, calls, _argv(cmd, dest, target, files, tmp_path), target, "exists")
    assert _replace_flag(cmd, dest)[0] in line
    _passes(calls, _argv(cmd, dest, target, files, tmp_path, *_replace_flag(cmd, dest)))


@pytest.mark.parametrize("cmd,dest", OUTPUTS, ids=IDS)
def test_onto_a_file_of_another_kind(cmd, dest, files, tmp_path, calls, capfd):
    """Judged by content: the output's own file name, another kind's bytes; --force does not help."""
    kind = _action(cmd, dest).ptp_output
    name = "x" + SUFFIX.get(kind, ".d")
    others = [b"plain text: not a file ptp writes\n"]
    for other in ("lut", "report", "png"):
        if other != kind:
            _write_kind(tmp_path / f"kind{SUFFIX[other]}", other, files)
            others.append((tmp_path / f"kind{SUFFIX[other]}").read_bytes())
    for i, content in enumerate(others):
        target = tmp_path / f"k{i}" / name
        target.parent.mkdir()
        target.write_bytes(content)
        words = ("not a folder",) if kind == "dataset" else ("another kind" if i == 0 else "exists and is a",)
        _refused(capfd, calls, _argv(cmd, dest, target, files, tmp_path, *_replace_flag(cmd, dest)), target, *words)


@pytest.mark.parametrize("cmd,dest", OUTPUTS, ids=IDS)
def test_into_a_missing_folder(cmd, dest, files, tmp_path, calls, capfd):
    kind = _action(cmd, dest).ptp_output
    target = tmp_path / "missing" / ("x" + SUFFIX.get(kind, ""))
    _refused(capfd, calls, _argv(cmd, dest, target, files, tmp_path), target, "does not exist")
    assert not (tmp_path / "missing").exists()


@contextlib.contextmanager
def _read_only_mount(tmp_path: Path):
    folder = tmp_path / "ro"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
        try:
            yield folder
        finally:
            folder.chmod(0o755)
        return
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(folder)],
                      capture_output=True).returncode != 0:
        pytest.skip("running as root and mounting a read-only tmpfs is not permitted here")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=False)


@pytest.mark.parametrize("cmd,dest", OUTPUTS, ids=IDS)
def test_into_a_read_only_folder(cmd, dest, files, tmp_path, calls, capfd):
    """A read-only mount (root) or a 0555 folder (anyone else)."""
    kind = _action(cmd, dest).ptp_output
    with _read_only_mount(tmp_path) as ro:
        target = ro / ("x" + SUFFIX.get(kind, ""))
        _refused(capfd, calls, _argv(cmd, dest, target, files, tmp_path), target, "cannot write", str(ro))


@pytest.mark.parametrize("cmd,dest", OUTPUTS, ids=IDS)
def test_when_the_write_probe_fails(cmd, dest, files, tmp_path, calls, capfd, monkeypatch):
    """The probe's error as a full file system would give it: the message names the folder, not the probe."""
    kind = _action(cmd, dest).ptp_output
    target = tmp_path / "full" / ("x" + SUFFIX.get(kind, ""))
    target.parent.mkdir()
    probe = outputs.probe_writable

    def refuse(folder):
        if Path(folder) != target.parent:  # the command's other outputs go elsewhere
            return probe(folder)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(Path(folder) / ".ptp-write-test-abc123"))

    monkeypatch.setattr(outputs, "probe_writable", refuse)
    line = _refused(capfd, calls, _argv(cmd, dest, target, files, tmp_path), target, "cannot write")
    assert os.strerror(errno.ENOSPC) in line


def test_two_outputs_of_one_command_never_name_one_file(files, tmp_path, calls, capfd):
    target = tmp_path / "same.json"
    _refused(capfd, calls, ["diff", str(files["lut"]), str(files["lut"]), "--json", str(target), "--png",
                            str(target)], target, "--json and --png")
    _refused(capfd, calls, ["calibrate", str(files["dataset"]), "--out", str(target), "--session", str(target)],
             target, "--out and --session")


# --------------------------------------------------------------------------- for real: decode and diff

def test_decode_and_diff_guarded_for_real(files, tmp_path, capfd):
    """The commands the issue found unguarded, run whole: refused first, replaced only with --force."""
    ds = tmp_path / "DS"
    shutil.copytree(files["dataset"], ds)
    rig = (ds / "rig.toml").read_bytes()
    assert main(["decode", str(ds), "--out", str(ds / "rig.toml"), "--force", "-q"]) == 2
    assert main(["decode", str(ds), "--out", str(ds), "-q"]) == 2
    assert (ds / "rig.toml").read_bytes() == rig and "input" in capfd.readouterr().err
    dec = tmp_path / "a.decoded.h5"
    assert main(["decode", str(ds), "--out", str(dec), "-q"]) == 0
    first = dec.read_bytes()
    assert main(["decode", str(ds), "--out", str(dec), "--positions", "0", "-q"]) == 2
    assert dec.read_bytes() == first and "--force" in capfd.readouterr().err
    assert main(["decode", str(ds), "--out", str(dec), "--positions", "0", "--force", "-q"]) == 0
    with h5py.File(dec, "r") as f:
        assert f.attrs["format"] == "ptp-decoded/1" and f["u"].shape[0] == 1

    lut = tmp_path / "A.lut.h5"
    assert main(["calibrate", str(ds), "--out", str(lut), "--degree", "1", "-q"]) == 0
    before = lut.read_bytes()
    capfd.readouterr()
    assert main(["diff", str(lut), str(lut), "--png", str(lut), "--force"]) == 2
    assert lut.read_bytes() == before and "input" in capfd.readouterr().err
    assert main(["diff", str(lut), str(lut), "--json", str(ds / "rig.toml"), "--force"]) == 2
    assert (ds / "rig.toml").read_bytes() == rig
    js, png = tmp_path / "d.json", tmp_path / "d.png"
    assert main(["diff", str(lut), str(lut), "--json", str(js), "--png", str(png)]) == 0
    assert main(["diff", str(lut), str(lut), "--json", str(js)]) == 2 and "--force" in capfd.readouterr().err
    assert main(["diff", str(lut), str(lut), "--json", str(js), "--png", str(png), "--force"]) == 0
    assert png.read_bytes().startswith(b"\x89PNG") and js.read_text().lstrip().startswith("{")
