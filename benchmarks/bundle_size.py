"""What each exclusion of packaging/ptp-studio.spec saves: the bundle built with all of them, then
once without each (one at a time), from a copy of this checkout.

    python -m benchmarks.bundle_size [--only NAME ...] [--json FILE]

Prints a Markdown table (docs/performance.md, "The desktop bundle"): the size of each build on
disk (hard links once, as ``du``) and its apparent size (every name counted, as a zip would),
and the difference to the full build. Each build takes about a minute.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SPEC = "packaging/ptp-studio.spec"


def _group(name: str) -> tuple[str, str]:
    line = "EXCLUDES = [m for group in EXCLUDE_GROUPS.values() for m in group]"
    return line, line.replace("EXCLUDE_GROUPS.values()",
                              f"(g for k, g in EXCLUDE_GROUPS.items() if k != {name!r})")


# name -> (text in the spec, its replacement that keeps what the exclusion leaves out)
VARIANTS = {
    "unused packages": _group("unused packages"),
    "unused Qt modules": _group("unused Qt modules"),
    "numba: CUDA and threading layers": _group("numba: CUDA and threading layers"),
    "unused SciPy subpackages": _group("unused SciPy subpackages"),
    "test suites (modules)": _group("test suites"),
    "Qt translations": ('    if d.startswith("PySide6/Qt/translations/"):', "    if False:"),
    "Qt plugins": ("    if d.startswith(QT_PLUGIN_DIR):", "    if False:"),
    "test folders, headers and sources": ('    if "tests" in parts[:-1]', "    if False and parts"),
    "libraries only left-out binaries need": ("        if entry[0] not in needed and _is_elf(entry[1]):",
                                              "        if False:"),
    "symbol tables of libllvmlite and libpython": ('STRIP = ("libllvmlite.so", "libpython3")',
                                                   'STRIP = ("<none>",)'),
    "ptp as a hard link of ptp-studio": ("if _studio.is_file() and _cli.is_file()",
                                         "if False and _studio.is_file()"),
}


def sizes(folder: Path) -> tuple[int, int]:
    """(bytes on disk with each inode once, apparent bytes of every file name)."""
    seen, disk, apparent = set(), 0, 0
    for dirpath, _dirs, files in os.walk(folder):
        for f in files:
            st = os.lstat(os.path.join(dirpath, f))
            apparent += st.st_size
            if (st.st_dev, st.st_ino) not in seen:
                seen.add((st.st_dev, st.st_ino))
                disk += st.st_size
    return disk, apparent


def build(src: Path, spec_text: str, out: Path) -> tuple[int, int, float]:
    spec = src / SPEC
    spec.write_text(spec_text, encoding="utf-8")
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "PyInstaller", "--noconfirm", "--log-level", "WARN",
                        "--distpath", str(out / "dist"), "--workpath", str(out / "work"), str(spec)],
                       cwd=src, capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(f"build failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    disk, apparent = sizes(out / "dist" / "ptp-studio")
    shutil.rmtree(out, ignore_errors=True)
    return disk, apparent, time.monotonic() - t0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", nargs="*", choices=list(VARIANTS), help="measure only these exclusions")
    p.add_argument("--json", metavar="FILE", help="also write the numbers as JSON")
    args = p.parse_args(argv)
    text = (ROOT / SPEC).read_text(encoding="utf-8")
    for name, (old, _new) in VARIANTS.items():
        if text.count(old) != 1:
            raise SystemExit(f"{SPEC} changed: cannot find the line of '{name}': {old!r}")
    with tempfile.TemporaryDirectory(prefix="ptp-bundle-size-") as tmp:
        src = Path(tmp) / "src"
        archive = subprocess.run(["git", "archive", "HEAD"], cwd=ROOT, capture_output=True, check=True).stdout
        src.mkdir()
        subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
        shutil.copy2(ROOT / SPEC, src / SPEC)  # the spec as it is in the work tree
        results = {"all exclusions": build(src, text, Path(tmp) / "b")}
        for name in args.only or VARIANTS:
            old, new = VARIANTS[name]
            results[name] = build(src, text.replace(old, new), Path(tmp) / "b")
            print(f"  {name}: {results[name][0] / 1e6:.1f} MB", file=sys.stderr)
    full_disk, full_app, _ = results["all exclusions"]
    print("| build | on disk, MB | apparent, MB | saved on disk, MB |")
    print("|---|---:|---:|---:|")
    for name, (disk, apparent, _t) in results.items():
        label = name if name == "all exclusions" else f"all but: {name}"
        saved = "" if name == "all exclusions" else f"{(disk - full_disk) / 1e6:.1f}"
        print(f"| {label} | {disk / 1e6:.1f} | {apparent / 1e6:.1f} | {saved} |")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
