"""Public faces, checked from the source with ``ast`` (no import needed).

(a) No module of ``ptpcore`` or ``app`` (imported as ``ptp_studio``) takes a private name from
    another module: a name that starts with ``_`` and is not a dunder (``__version__`` is public),
    whether by ``from x import _y`` (``as`` or not) or as ``m._y`` on a module ``m`` it imported
    (``import x.m as m``, ``from x import m``, ``import x.m`` then ``x.m._y``). A private module
    (``ptpcore/decode/_fused.py``) belongs to its package: the modules inside that package may
    import it and its names; a module outside may not.
(b) The wizard takes the engine's names only from a room's face: ``ptpcore`` itself or
    ``ptpcore.<room>`` (a room's ``__init__`` re-exports what other rooms and the wizard need;
    ``ptpcore.errors`` and the other base modules are faces of their own). Every import in
    ``app/`` counts (at module level, in functions, under ``if TYPE_CHECKING:``): ``from
    ptpcore.fit import describe_lut`` is through the face; ``from ptpcore.fit.corrected import x``,
    ``import ptpcore.fit.corrected`` and ``from ptpcore.fit import corrected`` (a submodule) reach
    inside. :data:`WIZARD_EXCEPTIONS` names the few reaches allowed, each with its reason; the same
    list, with the same reasons, is the section "The wizard's exceptions to the faces" of
    docs/architecture.md (checked here too). At most :data:`MAX_WIZARD_EXCEPTIONS`.

Each offender is reported as ``path:line`` and what it imports.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = (("ptpcore", "ptpcore"), ("app", "ptp_studio"))
"""The packages checked: folder, and the name it is imported as."""
PAGE = ROOT / "docs" / "architecture.md"
SECTION = "The wizard's exceptions to the faces"
MAX_WIZARD_EXCEPTIONS = 5
WIZARD_EXCEPTIONS: dict[str, str] = {
}
"""Module of the engine, inside a room -> why the wizard imports it there and not through the room's face."""


def _modules(folder: Path, name: str) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under ``folder`` (a package imported as ``name``)."""
    out = {}
    for path in sorted(folder.rglob("*.py")):
        parts = list(path.relative_to(folder).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join([name, *parts])] = path
    return out


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _absolute(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The module a ``from ... import`` statement in ``module`` (file ``path``) names, made absolute."""
    if not node.level:
        return node.module or ""
    base = module.split(".")
    if path.name != "__init__.py":
        base = base[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _private_part(target: str, module: str) -> str | None:
    """The first private component of the dotted path ``target`` whose package ``module`` is not in
    (``ptpcore.decode._fused`` is private to ``ptpcore.decode``), or None."""
    parts = target.split(".")
    for i, part in enumerate(parts):
        if _is_private(part):
            owner = ".".join(parts[:i])
            if not (module == owner or module.startswith(owner + ".")):
                return ".".join(parts[:i + 1])
    return None


def _where(path: Path, node: ast.AST, root: Path) -> str:
    return f"{path.relative_to(root).as_posix()}:{node.lineno}"


def private_imports(packages=PACKAGES, root: Path = ROOT) -> list[str]:
    """``path:line what`` of every private name a module takes from another (rule (a)), over the
    ``packages`` ((folder, name) pairs) under ``root``."""
    mods: dict[str, Path] = {}
    for folder, name in packages:
        mods.update(_modules(root / folder, name))
    out = []
    for module, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        bound: dict[str, str] = {}  # local name -> module it stands for
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    bad = _private_part(alias.name, module)
                    if bad:
                        out.append(f"{_where(path, node, root)} import {alias.name}")
                    if alias.asname:
                        bound[alias.asname] = alias.name
                    else:
                        top = alias.name.split(".")[0]
                        bound[top] = top
            elif isinstance(node, ast.ImportFrom):
                target = _absolute(module, path, node)
                for alias in node.names:
                    full = f"{target}.{alias.name}"
                    if full in mods:  # a submodule
                        bad = _private_part(full, module)
                        bound[alias.asname or alias.name] = full
                    else:
                        bad = _private_part(target, module) or (full if _is_private(alias.name) else None)
                    if bad and target != module:
                        out.append(f"{_where(path, node, root)} from {target} import {alias.name}")
        # m._y on an imported module m (a chain of attributes on a bound name)
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and _is_private(node.attr):
                chain, base = [], node.value
                while isinstance(base, ast.Attribute):
                    chain.append(base.attr)
                    base = base.value
                if isinstance(base, ast.Name) and base.id in bound:
                    dotted = ".".join([bound[base.id], *reversed(chain)])
                    full = f"{dotted}.{node.attr}"
                    bad = _private_part(full, module) if full in mods else dotted != module
                    if dotted in mods and bad:
                        out.append(f"{_where(path, node, root)} {full}")
    return sorted(set(out), key=_order)


def _order(line: str):
    where = line.split(" ", 1)[0]
    path, _, number = where.rpartition(":")
    return path, int(number), line


def _face(target: str) -> bool:
    """``ptpcore`` or ``ptpcore.<room or base module>``."""
    parts = target.split(".")
    return parts[0] == "ptpcore" and len(parts) <= 2


def wizard_imports(root: Path = ROOT) -> list[tuple[str, str]]:
    """``(path:line, engine module)`` of every engine module the wizard's imports name: the module a
    ``from`` statement takes from, or the submodule it takes, or the module of ``import``."""
    engine = _modules(root / "ptpcore", "ptpcore")
    out = []
    for module, path in _modules(root / "app", "ptp_studio").items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                out += [(_where(path, node, root), alias.name) for alias in node.names
                        if alias.name.split(".")[0] == "ptpcore"]
            elif isinstance(node, ast.ImportFrom):
                target = _absolute(module, path, node)
                if target.split(".")[0] != "ptpcore":
                    continue
                subs = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in engine]
                if len(subs) < len(node.names):
                    out.append((_where(path, node, root), target))
                out += [(_where(path, node, root), sub) for sub in subs]
    return sorted(out, key=lambda item: (_order(item[0]), item[1]))


def wizard_reaches(root: Path = ROOT, exceptions=None) -> list[str]:
    """``path:line module`` of every wizard import past a room's face, the named exceptions aside (rule (b))."""
    exceptions = WIZARD_EXCEPTIONS if exceptions is None else exceptions
    return [f"{where} {target}" for where, target in wizard_imports(root)
            if not _face(target) and target not in exceptions]


def documented_exceptions() -> dict[str, str]:
    """{module: reason} from the page's section :data:`SECTION`: one ``- `module`: reason`` item each."""
    text = PAGE.read_text(encoding="utf-8")
    head = re.search(rf"^#+ {re.escape(SECTION)}\s*$", text, re.M)
    assert head, f"docs/architecture.md has no section '{SECTION}'"
    body = re.split(r"^#", text[head.end():], maxsplit=1, flags=re.M)[0]
    out = {}
    for item in re.findall(r"^- `(ptpcore\.[\w.]+)`: (.*(?:\n  .*)*)", body, re.M):
        out[item[0]] = " ".join(item[1].split())
    return out


def test_no_private_name_crosses_a_module():
    offenders = private_imports()
    assert not offenders, "private names imported across modules:\n" + "\n".join(offenders)


def test_the_wizard_imports_the_engine_through_its_faces():
    offenders = wizard_reaches()
    assert not offenders, ("wizard imports past a room's face (import from ptpcore.<room>, or name the "
                           "exception in WIZARD_EXCEPTIONS and docs/architecture.md):\n" + "\n".join(offenders))


def test_the_wizards_exceptions_are_few_used_and_documented():
    assert len(WIZARD_EXCEPTIONS) <= MAX_WIZARD_EXCEPTIONS
    used = {target for _, target in wizard_imports()}
    assert not set(WIZARD_EXCEPTIONS) - used, f"exceptions no import needs: {sorted(set(WIZARD_EXCEPTIONS) - used)}"
    for module, reason in WIZARD_EXCEPTIONS.items():
        assert reason.strip(), f"{module}: no reason"
    assert documented_exceptions() == {m: " ".join(r.split()) for m, r in WIZARD_EXCEPTIONS.items()}


def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)


def test_private_name_finder_sees_every_form(tmp_path):
    """Rule (a) on a small engine: ``from x import _y``, a relative import, ``m._y`` on a module
    imported three ways, a private module from outside its package; not a dunder, not a module's own
    names, not a private module inside its package, not ``obj._y`` on an object that is no module."""
    _write(tmp_path, {
        "ptpcore/__init__.py": "__version__ = '1'\n",
        "ptpcore/a/__init__.py": "from ._k import fast\n",
        "ptpcore/a/_k.py": "def fast():\n    return 1\n",
        "ptpcore/a/m.py": "from . import _k\nfrom ._k import fast\n\ndef _h():\n    return _k.fast()\n",
        "ptpcore/b/__init__.py": "",
        "ptpcore/b/n.py": ("from ptpcore import __version__\nfrom ptpcore.a.m import _h as h\nfrom ..a import m\n"
                           "import ptpcore.a.m\nimport ptpcore.a.m as mm\nfrom ptpcore.a import _k\n\n"
                           "def g(obj):\n    return (m._h(),\n            ptpcore.a.m._h(),\n            mm._h(), obj._x, h)\n"),
    })
    assert private_imports((("ptpcore", "ptpcore"),), tmp_path) == [
        "ptpcore/b/n.py:2 from ptpcore.a.m import _h", "ptpcore/b/n.py:6 from ptpcore.a import _k",
        "ptpcore/b/n.py:9 ptpcore.a.m._h", "ptpcore/b/n.py:10 ptpcore.a.m._h", "ptpcore/b/n.py:11 ptpcore.a.m._h"]


def test_face_finder_sees_every_reach(tmp_path):
    """Rule (b) on a small wizard: a room and a base module are faces; a module inside a room,
    taken by ``from``, as a submodule or by ``import``, at any depth of the code, is a reach unless named."""
    _write(tmp_path, {
        "ptpcore/__init__.py": "",
        "ptpcore/errors.py": "",
        "ptpcore/fit/__init__.py": "from .corrected import f\n",
        "ptpcore/fit/corrected.py": "def f():\n    return 1\n",
        "app/__init__.py": "",
        "app/page.py": ("from ptpcore import fit\nfrom ptpcore.fit import f\nimport ptpcore.errors\n"
                        "from ptpcore.fit.corrected import f as g\nfrom ptpcore.fit import corrected\n\n"
                        "def h():\n    import ptpcore.fit.corrected\n"),
    })
    assert wizard_reaches(tmp_path, {}) == ["app/page.py:4 ptpcore.fit.corrected",
                                            "app/page.py:5 ptpcore.fit.corrected", "app/page.py:8 ptpcore.fit.corrected"]
    assert wizard_reaches(tmp_path, {"ptpcore.fit.corrected": "a reason"}) == []
