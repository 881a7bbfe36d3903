"""Every shell example in docs/*.md runs (slow tier).

The convention (also stated in docs/index.md):

- a fenced block marked ``bash`` is run: the blocks of one page, in their order, each with
  ``bash -e -o pipefail``, in one fresh temporary folder per page; a block that exits non-zero
  fails the test. So examples are small (a 160 x 120 simulated rig, a few positions) and a later
  block may use what an earlier one wrote.
- a block marked ``console`` is a command shown but never run here: installing packages,
  starting the GUI, a benchmark on gigabytes of data, a real device.
- every other fence names a non-shell language from ``OTHER_KINDS`` (``text`` for output and
  usage lines, ``toml``, ``python``, ``c``, ``json``); a fence without a kind, or with a shell kind
  this test does not know (``sh``, ``shell``, ``zsh``...), fails it, so nothing that looks like
  an example escapes the run by accident.

``ptp`` and ``ptp-studio`` resolve to this checkout: a folder of wrappers (``python -m
ptpcore.cli``, ``python -m ptp_studio`` with this interpreter) comes first on ``PATH``, and the
checkout first on ``PYTHONPATH`` (the caller's entries follow). HOME and the temporary folder are
the test's own, so nothing is written outside it (numba's cache keeps its own folder).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
RUN_KIND = "bash"
SHOWN_KIND = "console"
OTHER_KINDS = {"text", "toml", "python", "c", "json"}
FENCE = re.compile(r"^(\s*)```(.*)$")


def fenced_blocks(path: Path) -> list[tuple[int, str, str]]:
    """(line number, kind, text) of every fenced block of a Markdown file."""
    blocks, open_at, kind, body, indent = [], None, "", [], ""
    for no, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        m = FENCE.match(line)
        if open_at is None and m:
            open_at, indent, kind, body = no, m.group(1), m.group(2).strip(), []
        elif open_at is not None and m and m.group(2).strip() == "":
            blocks.append((open_at, kind, "\n".join(body)))
            open_at = None
        elif open_at is not None:
            body.append(line[len(indent):] if line.startswith(indent) else line)
    assert open_at is None, f"{path.name}:{open_at}: a fence that is never closed"
    return blocks


PAGES = sorted(DOCS.glob("*.md"))


def test_every_fence_in_docs_names_a_known_kind():
    bad = [f"{p.name}:{no}: ```{kind}" for p in PAGES for no, kind, _ in fenced_blocks(p)
           if kind not in OTHER_KINDS | {RUN_KIND, SHOWN_KIND}]
    assert not bad, ("fences of an unknown kind (run: ```bash; shown only: ```console; "
                     f"or one of {sorted(OTHER_KINDS)}): {bad}")


def _wrappers(folder: Path) -> None:
    """``ptp`` and ``ptp-studio`` commands that run this checkout with this interpreter."""
    folder.mkdir()
    for name, module in (("ptp", "ptpcore.cli"), ("ptp-studio", "ptp_studio")):
        script = folder / name
        script.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m {module} "$@"\n')
        script.chmod(0o755)


@pytest.mark.slow
@pytest.mark.parametrize("page", [p for p in PAGES if any(k == RUN_KIND for _, k, _ in fenced_blocks(p))],
                         ids=lambda p: p.name)
def test_the_bash_blocks_of_a_page_run(page, tmp_path):
    bin_dir = tmp_path / "bin"
    _wrappers(bin_dir)
    work, home, temp = tmp_path / "work", tmp_path / "home", tmp_path / "tmp"
    for d in (work, home, temp):
        d.mkdir()
    env = {key: os.environ[key] for key in ("LANG", "LC_ALL", "NUMBA_CACHE_DIR", "XDG_CACHE_HOME")
           if key in os.environ}
    env.setdefault("XDG_CACHE_HOME", str(Path.home() / ".cache"))  # the compiled kernels' cache
    env.update(PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}", HOME=str(home), TMPDIR=str(temp),
               QT_QPA_PLATFORM="offscreen",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH", "")])))
    for no, kind, text in fenced_blocks(page):
        if kind != RUN_KIND:
            continue
        t0 = time.perf_counter()
        run = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", text], cwd=work, env=env,
                             capture_output=True, text=True, timeout=900)
        print(f"{page.name}:{no}: {time.perf_counter() - t0:.1f} s")
        assert run.returncode == 0, (f"{page.name}:{no}: exit {run.returncode}\n--- block\n{text}\n"
                                     f"--- stdout\n{run.stdout[-3000:]}\n--- stderr\n{run.stderr[-3000:]}")
