"""The desktop bundle (packaging/ptp-studio.spec) and the wheel, built from a clean copy and run.

The slow tests (``python -m pytest -m slow``) build from ``git archive HEAD`` (what is committed,
not the work tree) in a temporary folder:

- the PyInstaller bundle, then run with an empty environment (``env -i``, PATH=/usr/bin:/bin,
  HOME a fresh folder, offscreen Qt): ``ptp-studio --tour`` (every page, none blank), ``ptp
  demo``, ``ptp simulate`` + ``ptp calibrate`` + ``ptp inspect`` + ``ptp apply`` (the numba
  kernels compiled in the bundle: their cache appears under HOME), every subcommand's ``--help``,
  its size and that no test or benchmark is inside;
- the wheel (``pip wheel . --no-deps``, no setuptools warning), installed without ``-e`` in a
  fresh venv (``--system-site-packages`` for numpy, Qt, ...; ptpcore and ptp_studio from the
  wheel), then ``ptp demo`` and ``ptp-studio --tour``.

Each failure message holds the program's own output (stderr first). The fast tests check the
bundle launcher and that the app imports nothing the spec leaves out.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tarfile
import io
import time
from pathlib import Path

import numpy as np
import pytest

from benchmarks.bundle_size import sizes  # bytes on disk (hard links once) and apparent bytes

ROOT = Path(__file__).resolve().parents[2]
SPEC = ROOT / "packaging" / "ptp-studio.spec"
MAX_BUNDLE_MB = 600.0
MIN_TOUR_PAGES = 7


# ---------------------------------------------------------------------------
# Fast checks of the spec and the launcher

def _launcher():
    spec = importlib.util.spec_from_file_location("ptp_bundle_launcher", ROOT / "packaging" / "ptp_studio_main.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("executable, program", [
    ("/opt/ptp-studio/ptp", "ptp"), ("ptp.exe", "ptp"), ("PTP.EXE", "ptp"),
    ("/opt/ptp-studio/ptp-studio", "ptp-studio"), ("ptp-studio.exe", "ptp-studio"),
    ("/somewhere/renamed", "ptp-studio"),
])
def test_launcher_picks_the_program_from_its_name(executable, program):
    assert _launcher().program(executable) == program


def _spec_excludes() -> dict[str, list[str]]:
    """EXCLUDE_GROUPS of the spec, read as a literal (the spec is not run)."""
    tree = ast.parse(SPEC.read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "EXCLUDE_GROUPS" for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError("packaging/ptp-studio.spec has no EXCLUDE_GROUPS")


LAZY_GROUPS = ("vendor camera SDKs",)
"""Groups of EXCLUDE_GROUPS the app may import inside a function (a camera opened on demand), never at
a module's top level: the bundle runs without them and says how to install one when it is asked for."""


def _imports(path: Path, top_level_only: bool = False) -> set[str]:
    names = set()
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in (tree.body if top_level_only else ast.walk(tree)):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


def test_the_app_imports_nothing_the_bundle_leaves_out():
    groups = _spec_excludes()
    excluded = [m for g, group in groups.items() if g not in LAZY_GROUPS for m in group]
    lazy = [m for g in LAZY_GROUPS for m in groups.get(g, [])]
    assert "tests" in excluded and "benchmarks" in excluded
    found = []
    for folder in ("ptpcore", "app", "packaging"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for name in _imports(path):
                hit = [m for m in excluded if name == m or name.startswith(m + ".")]
                if hit:
                    found.append(f"{path.relative_to(ROOT)} imports {name} (left out: {hit[0]})")
            for name in _imports(path, top_level_only=True):
                hit = [m for m in lazy if name == m or name.startswith(m + ".")]
                if hit:
                    found.append(f"{path.relative_to(ROOT)} imports {name} at its top level (left out: {hit[0]})")
    assert not found, "remove them from EXCLUDE_GROUPS in packaging/ptp-studio.spec:\n" + "\n".join(found)


def test_every_package_folder_is_in_the_wheel():
    """pyproject.toml lists the packages by name: a new subpackage missing from the list is left out
    of the wheel (and the wheel's ``ptp`` then fails to import it), while the editable install the
    other tests use still finds it."""
    import tomllib
    setup = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    listed = set(setup["packages"])
    source = {name: ROOT / folder for name, folder in setup["package-dir"].items()}
    source.setdefault("ptpcore", ROOT / "ptpcore")
    missing = []
    for top in ("ptpcore", "ptp_studio"):
        for init in sorted(source[top].rglob("__init__.py")):
            rel = init.parent.relative_to(source[top])
            name = ".".join((top, *rel.parts))
            if "__pycache__" not in rel.parts and name not in listed:
                missing.append(name)
    assert not missing, f"pyproject.toml [tool.setuptools] packages lacks {missing}"


# ---------------------------------------------------------------------------
# Helpers of the slow tests

def _run(cmd, *, env=None, cwd=None, timeout=900, what=None) -> subprocess.CompletedProcess:
    t0 = time.monotonic()
    r = subprocess.run([str(c) for c in cmd], env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    r.seconds = time.monotonic() - t0
    print(f"[{r.seconds:6.1f} s] {what or ' '.join(map(str, cmd))}")
    return r


def _output(r: subprocess.CompletedProcess, limit: int = 6000) -> str:
    return (f"exit code {r.returncode}\n--- stderr ---\n{r.stderr[-limit:]}\n"
            f"--- stdout ---\n{r.stdout[-limit:]}")


def _ok(r: subprocess.CompletedProcess, what: str) -> subprocess.CompletedProcess:
    assert r.returncode == 0, f"{what} failed: {_output(r)}"
    return r


def _clean_copy(dest: Path) -> Path:
    """``git archive HEAD`` of this repository, unpacked into ``dest``."""
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: nothing to archive")
    data = subprocess.run(["git", "archive", "--format=tar", "HEAD"], cwd=ROOT, capture_output=True, check=True).stdout
    dest.mkdir(parents=True)
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        tar.extractall(dest, filter="data")
    return dest


def _need(module: str, why: str):
    """Import ``module``, or skip; on CI (CI set) a missing tool fails instead of skipping."""
    try:
        return importlib.import_module(module)
    except ImportError:
        if os.environ.get("CI"):
            pytest.fail(f"{module} is not installed: {why}")
        pytest.skip(f"{module} is not installed: {why}")


def _bare_env(home: Path) -> dict[str, str]:
    """The bare minimum: the system PATH, a fresh HOME, offscreen Qt."""
    home.mkdir(parents=True, exist_ok=True)
    return {"PATH": "/usr/bin:/bin", "HOME": str(home), "QT_QPA_PLATFORM": "offscreen"}


def _empty_env(home: Path) -> list[str]:
    """``env -i`` and :func:`_bare_env`: nothing of the caller's environment (no virtualenv, no
    PYTHONPATH) reaches the program."""
    return ["env", "-i", *(f"{k}={v}" for k, v in _bare_env(home).items())]


def _check_tour(outdir: Path, r: subprocess.CompletedProcess, what: str) -> list[Path]:
    _ok(r, what)
    pages = sorted(outdir.glob("*.png"))
    assert len(pages) >= MIN_TOUR_PAGES, f"{what}: {len(pages)} pages, expected >= {MIN_TOUR_PAGES}\n{_output(r)}"
    import cv2

    for page in pages:
        img = cv2.imread(str(page), cv2.IMREAD_GRAYSCALE)
        assert img is not None and img.size, f"{what}: {page.name} is not a readable PNG"
        # A blank page is one colour; a page with its widgets and data has text and plots:
        # a spread of grey levels well above the PNG's exactness (0).
        assert img.std() > 8.0 and np.unique(img).size >= 32, \
            f"{what}: {page.name} looks blank (std {img.std():.2f}, {np.unique(img).size} grey levels)"
    return pages


def _check_demo(r: subprocess.CompletedProcess, what: str) -> None:
    _ok(r, what)
    for line in ("PTP demo:", "held-out accuracy", "3DSTC comparison"):
        assert line in r.stdout, f"{what}: no '{line}' in its summary\n{_output(r)}"


# ---------------------------------------------------------------------------
# The bundle

@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """(folder of the built bundle, temporary folder) from a clean copy of HEAD."""
    _need("PyInstaller", 'the bundle is built with PyInstaller: pip install -e ".[gui,bundle]"')
    tmp = tmp_path_factory.mktemp("bundle")
    src = _clean_copy(tmp / "src")
    r = _run([sys.executable, "-m", "PyInstaller", "--noconfirm", "--distpath", tmp / "dist",
              "--workpath", tmp / "work", "packaging/ptp-studio.spec"], cwd=src, timeout=1800,
             what="pyinstaller packaging/ptp-studio.spec")
    _ok(r, "building the bundle")
    folder = tmp / "dist" / "ptp-studio"
    assert (folder / "ptp-studio").is_file() and (folder / "ptp").is_file(), _output(r)
    shutil.rmtree(tmp / "work", ignore_errors=True)  # ~1 GB of intermediate files
    return folder, tmp


@pytest.mark.slow
def test_bundle_size_and_contents(bundle):
    folder, _tmp = bundle
    disk, apparent = sizes(folder)
    print(f"bundle: {disk / 1e6:.1f} MB on disk ({apparent / 1e6:.1f} MB counting ptp and ptp-studio apart)")
    assert disk / 1e6 < MAX_BUNDLE_MB, f"the bundle is {disk / 1e6:.1f} MB (limit {MAX_BUNDLE_MB:g} MB)"

    # Nothing of the project's tests or benchmarks (nor any package's test suite): no folder of
    # that name anywhere in the bundle...
    internal = folder / "_internal"
    leaked = [str(p.relative_to(folder)) for p in internal.rglob("*")
              if p.is_dir() and p.name in ("tests", "benchmarks")]
    assert not leaked, f"tests or benchmarks in the bundle: {leaked[:20]}"
    # ... and no such module in its archive.
    from PyInstaller.archive.readers import CArchiveReader

    pkg = CArchiveReader(str(folder / "ptp"))
    modules = set(pkg.open_embedded_archive("PYZ.pyz").toc)
    stray = sorted(m for m in modules if m.split(".")[0] in ("tests", "benchmarks", "conftest"))
    assert not stray, f"modules of the project's tests or benchmarks in the bundle: {stray}"
    assert [m for m in modules if m.split(".")[-1] == "_fused" and m.startswith("ptpcore.")], \
        "the numba kernels (ptpcore.decode._fused) are not in the bundle"
    assert "numba" in modules and "llvmlite" in modules
    # The resources, as ptp_studio.assets looks them up (sys._MEIPASS/resources).
    for p in (ROOT / "resources").rglob("*"):
        if p.is_file() and p.name != "__init__.py" and "__pycache__" not in p.parts:
            assert (internal / "resources" / p.relative_to(ROOT / "resources")).is_file(), f"{p.name} not bundled"
    # ptp and ptp-studio are the same program (the launcher picks by name): same bytes.
    assert (folder / "ptp").read_bytes() == (folder / "ptp-studio").read_bytes()


@pytest.mark.slow
def test_bundled_wizard_tour(bundle):
    folder, tmp = bundle
    out = tmp / "tour"
    env = _empty_env(tmp / "home-tour")
    t0, first_page = time.monotonic(), None
    with (tmp / "tour.stdout").open("w+") as log_out, (tmp / "tour.stderr").open("w+") as log_err:
        proc = subprocess.Popen([*env, str(folder / "ptp-studio"), "--tour", str(out)], cwd=tmp,
                                stdout=log_out, stderr=log_err, text=True)
        while proc.poll() is None:  # the time to the first page: when its PNG appears
            if first_page is None and out.is_dir() and any(out.glob("*.png")):
                first_page = time.monotonic() - t0
            if time.monotonic() - t0 > 900:
                proc.kill()
            time.sleep(0.02)
        total = time.monotonic() - t0
        log_out.seek(0), log_err.seek(0)
        r = subprocess.CompletedProcess(proc.args, proc.returncode, log_out.read(), log_err.read())
    pages = _check_tour(out, r, "the bundled ptp-studio --tour")
    print(f"bundled wizard: first page written {first_page or float('nan'):.1f} s after launch;"
          f" tour of {len(pages)} pages {total:.1f} s")


@pytest.mark.slow
def test_bundled_demo(bundle):
    folder, tmp = bundle
    r = _run([*_empty_env(tmp / "home-demo"), folder / "ptp", "demo"], cwd=tmp, what="bundled ptp demo")
    _check_demo(r, "the bundled ptp demo")


@pytest.mark.slow
def test_bundled_cli_simulate_calibrate_apply_with_the_numba_kernels(bundle):
    folder, tmp = bundle
    home = tmp / "home-cli"
    env = _empty_env(home)
    data, lut = tmp / "sim", tmp / "cal.lut.h5"
    # Run from a folder without a ptpcore/ source tree: numba, frozen, caches a kernel beside
    # ptpcore/decode/_fused.py relative to the working directory when that file exists there.
    work = tmp / "cli"
    work.mkdir()
    _ok(_run([*env, folder / "ptp", "simulate", data, "--width", 160, "--height", 120, "-q"], cwd=work,
             what="bundled ptp simulate"), "the bundled ptp simulate")
    rc = _ok(_run([*env, folder / "ptp", "calibrate", data, "--out", lut, "-q"], cwd=work,
                  what="bundled ptp calibrate"), "the bundled ptp calibrate")
    assert lut.is_file(), _output(rc)
    r = _ok(_run([*env, folder / "ptp", "inspect", lut], cwd=work, what="bundled ptp inspect"),
            "the bundled ptp inspect")
    assert "ptp-lut/1" in r.stdout and "160x120 px" in r.stdout, _output(r)
    cloud = tmp / "cloud.ply"
    ra = _ok(_run([*env, folder / "ptp", "apply", lut, "--z", 20, "--out", cloud], cwd=work, what="bundled ptp apply"),
             "the bundled ptp apply")
    assert cloud.is_file() and cloud.read_bytes()[:4] == b"ply\n", _output(ra)
    # Every subcommand answers --help (its parser and the modules it imports are bundled).
    rh = _ok(_run([*env, folder / "ptp", "--help"], cwd=work, what="bundled ptp --help"), "the bundled ptp --help")
    commands = re.findall(r"^    (\w+)\s", rh.stdout, flags=re.M)
    assert {"simulate", "calibrate", "demo", "apply", "capture"} <= set(commands), rh.stdout
    for command in commands:
        _ok(_run([*env, folder / "ptp", command, "--help"], cwd=work, what=f"bundled ptp {command} --help"),
            f"the bundled ptp {command} --help")
    # numba caches each compiled kernel under ~/.cache/numba: the fused kernels ran in the bundle
    # (without numba, or with its import broken, the engine would have run its numpy path).
    cached = sorted(p.name for p in (home / ".cache" / "numba").rglob("_fused.*.nbi"))
    kernels = {re.sub(r"-\d+\.py\d+\.nbi$", "", n).removeprefix("_fused.") for n in cached}
    assert {"nstep_rows", "unwrap_classify_rows", "store_rows"} <= kernels, \
        f"the numba kernels did not run in the bundle (cached: {sorted(kernels)})\n{_output(rc)}"
    # Run again: the kernels load from that cache, the same LUT comes out.
    again = tmp / "again.lut.h5"
    r2 = _ok(_run([*env, folder / "ptp", "calibrate", data, "--out", again, "-q"], cwd=work,
                  what="bundled ptp calibrate, cached"), "the bundled ptp calibrate (second run)")
    r3 = _ok(_run([*env, folder / "ptp", "inspect", again], cwd=work, what="bundled ptp inspect"),
             "the bundled ptp inspect")
    assert r3.stdout.replace(str(again), str(lut)) == r.stdout.replace(str(again), str(lut)), \
        f"a second calibration of the same data differs:\n{r.stdout}\n{r3.stdout}"
    print(f"bundled calibrate 160x120: {rc.seconds:.1f} s with the kernels compiled, {r2.seconds:.1f} s from the cache")


# ---------------------------------------------------------------------------
# The wheel

@pytest.mark.slow
def test_wheel_builds_clean_and_runs_from_a_fresh_venv(tmp_path):
    src = _clean_copy(tmp_path / "src")
    wheels = tmp_path / "wheels"
    r = _ok(_run([sys.executable, "-m", "pip", "wheel", ".", "--no-deps", "-v", "-w", wheels], cwd=src, timeout=900,
                 what="pip wheel . --no-deps"), "pip wheel .")
    log = r.stdout + r.stderr
    warnings = [line.strip() for line in log.splitlines()
                if re.search(r"(Warning|warning:|!!)", line) and "byte-compiling is disabled" not in line
                and "Running pip as the 'root' user" not in line]
    assert not warnings, "setuptools warned while building the wheel:\n" + "\n".join(warnings[:20])
    (wheel,) = wheels.glob("ptp_studio-*.whl")

    import zipfile

    names = set(zipfile.ZipFile(wheel).namelist())
    for p in (ROOT / "resources").rglob("*"):
        if p.is_file() and "__pycache__" not in p.parts:
            assert f"ptp_studio/resources/{p.relative_to(ROOT / 'resources').as_posix()}" in names, \
                f"{p.name} is not in the wheel"
    assert not [n for n in names if n.split("/")[0] in ("tests", "benchmarks", "app", "resources")]

    venv = tmp_path / "venv"
    _ok(_run([sys.executable, "-m", "venv", "--system-site-packages", venv], what="python -m venv"), "python -m venv")
    py = venv / "bin" / "python"
    _ok(_run([py, "-m", "pip", "install", "--no-deps", "--no-index", "--ignore-installed", wheel],
             what="pip install the wheel"), "pip install the wheel")
    home = tmp_path / "home"
    env = _bare_env(home)  # no PYTHONPATH or virtualenv of the caller: the venv alone
    env["PATH"] = f"{venv / 'bin'}:{env['PATH']}"
    r = _ok(_run([py, "-c", "import ptpcore, ptp_studio, ptp_studio.assets as a;"
                  " print(ptpcore.__file__); print(ptp_studio.__file__); print(a.resource_dir())"],
                 env=env, cwd=tmp_path, what="where the packages come from"), "importing from the venv")
    for line in r.stdout.split():
        assert Path(line).resolve().is_relative_to(venv.resolve()), f"not from the wheel: {line}\n{_output(r)}"
    _check_demo(_run([venv / "bin" / "ptp", "demo"], env=env, cwd=tmp_path, what="wheel: ptp demo"), "the wheel's ptp demo")
    out = tmp_path / "tour"
    _check_tour(out, _run([venv / "bin" / "ptp-studio", "--tour", out], env=env, cwd=tmp_path,
                          what="wheel: ptp-studio --tour"), "the wheel's ptp-studio --tour")
