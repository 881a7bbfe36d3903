"""docs/architecture.md names every module of ``ptpcore/`` and ``app/``, and names nothing that is gone.

A module is named by its path from the repository's root in backticks (`` `ptpcore/fit/height.py` ``),
on a line of its own in the page's module tables. So a module added without its line fails here,
and so does a line (or any backticked ``ptpcore/...`` or ``app/...`` path, a folder included)
left in the page for a file or folder that no longer exists.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "architecture.md"
TREES = ("ptpcore", "app")
PATH = re.compile(r"`((?:ptpcore|app)/[^`\s]*)`")
# A module line of the page's tables: | `ptpcore/x/y.py` | what it is for |
MODULE_LINE = re.compile(r"^\|\s*`((?:ptpcore|app)/[^`\s]+\.py)`\s*\|\s*(.*?)\s*\|\s*$")


def modules_on_disk() -> set[str]:
    """Every ``.py`` file under the engine and the wizard, as a path from the root."""
    return {p.relative_to(ROOT).as_posix() for tree in TREES for p in (ROOT / tree).rglob("*.py")
            if "__pycache__" not in p.parts}


def module_lines() -> dict[str, str]:
    """{path: what it is for} from the page's module tables."""
    out: dict[str, str] = {}
    for line in PAGE.read_text(encoding="utf-8").splitlines():
        m = MODULE_LINE.match(line)
        if m:
            assert m.group(1) not in out, f"docs/architecture.md: {m.group(1)} has two lines"
            out[m.group(1)] = m.group(2)
    return out


def test_every_module_has_its_line():
    missing = sorted(modules_on_disk() - set(module_lines()))
    assert not missing, ("modules without their line in docs/architecture.md "
                         f"('| `path` | what it is for |'): {missing}")


def test_every_line_says_what_its_module_is_for():
    empty = sorted(path for path, what in module_lines().items() if not what)
    assert not empty, f"docs/architecture.md: module lines that say nothing: {empty}"


def test_every_path_named_exists():
    named = set(PATH.findall(PAGE.read_text(encoding="utf-8")))
    gone = sorted(p for p in named if not (ROOT / p.rstrip("/")).exists())
    assert not gone, f"docs/architecture.md names paths that do not exist: {gone}"
