"""The house rules the reader relies on, checked from the source with ``ast`` (no import needed).

(a) No import cycle between the modules of ``ptpcore``, nor between those of ``app`` (imported as
    ``ptp_studio``). What counts as an edge ``A -> B``:

    - every ``import`` and ``from ... import`` statement in ``A``, at module level *and inside
      functions and classes* (a function-level import only defers the cycle, it does not remove it);
      imports under ``if TYPE_CHECKING:`` are left out (never executed; import-linter leaves them out
      too);
    - ``B`` is the module the imported names come from: ``import a.b`` and ``from a import b`` with
      ``b`` a submodule give ``a.b``; ``from a import name`` gives ``a`` itself, or, when ``a`` is a
      package whose ``__init__`` re-exports ``name`` from one of its submodules
      (``from .sub import name``), that submodule (followed through further re-exports);
    - a package's ``__init__`` importing its own submodules is the package listing its public
      names, not a dependency: those edges are left out. Python runs a package's ``__init__``
      before any of its submodules anyway, and a submodule that takes a name through the
      package is counted against the submodule that defines it (previous rule), so a real cycle
      through a re-export is still found.

    A cycle is a strongly connected group of two or more modules of this graph; each is reported
    with its modules.
(b) No function (or method) in ``ptpcore`` over :data:`MAX_FUNCTION_LINES` lines, counted from its
    ``def`` line (decorators excluded) to its last line, except in generated files (a module whose
    docstring's first line says ``GENERATED``).
(c) No module in ``ptpcore/fit/`` (recursively) over :data:`MAX_FIT_MODULE_LINES` lines.
(d) No import cycle anywhere in the repository: the same rule over the modules of ``ptpcore``,
    ``app`` (as ``ptp_studio``), ``benchmarks`` and ``research`` taken together, so a cycle through
    two of them is found too.
(e) No test imports the research folder or a diagnosis script: no file under ``tests/`` imports
    ``research`` (or a module under it), or a ``benchmarks`` module that is not a measurement tool
    (:data:`DIAGNOSIS_SCRIPTS`, the scripts that moved to ``research/``), whether by an ``import``
    statement, ``importlib.import_module`` / ``pytest.importorskip`` or ``python -m`` in a command list.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_FUNCTION_LINES = 120
MAX_FIT_MODULE_LINES = 700
PACKAGES = (("ptpcore", "ptpcore"), ("app", "ptp_studio"), ("benchmarks", "benchmarks"), ("research", "research"))
"""Every package of the repository: folder, and the name it is imported as."""
DIAGNOSIS_SCRIPTS = ("trust_mc", "trust_split", "trust_excess", "trust_parts", "loo_terms", "stage_leak", "stage_luck",
                     "footprint_truth", "real_bow", "smooth_noise", "scoring", "rigs")
"""The research tools' names (``research/``): a ``benchmarks.NAME`` of one of them is a diagnosis script."""


def _modules(folder: Path, name: str) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under ``folder`` (a package imported as ``name``)."""
    out = {}
    for path in sorted(folder.rglob("*.py")):
        parts = list(path.relative_to(folder).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join([name, *parts])] = path
    return out


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """ids of the statements under ``if TYPE_CHECKING:`` (not executed)."""
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If):
            test = node.test
            name = test.id if isinstance(test, ast.Name) else test.attr if isinstance(test, ast.Attribute) else ""
            if name == "TYPE_CHECKING":
                for child in node.body:
                    skip.update(id(n) for n in ast.walk(child))
    return skip


def _imports(module: str, path: Path) -> list[tuple[str, list[str]]]:
    """``(imported module, [names])`` of every import statement (names empty for ``import a.b``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = _type_checking_nodes(tree)
    package = module if _is_package(path) else module.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out.extend((alias.name, []) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.append((target, [alias.name for alias in node.names]))
    return out


def _import_graph(mods: dict[str, Path]) -> dict[str, set[str]]:
    """The edges of the module docstring's rule (a), between the modules of ``mods``."""
    raw = {m: _imports(m, p) for m, p in mods.items()}
    # name -> submodule it comes from, for the names a package's __init__ re-exports.
    reexport: dict[str, dict[str, str]] = {}
    for m, p in mods.items():
        if _is_package(p):
            table = {}
            for target, names in raw[m]:
                if target.startswith(m + ".") and target in mods:
                    table.update({n: target for n in names})
            reexport[m] = table

    def origin(target: str, name: str) -> str:
        seen = set()
        while target in reexport and name in reexport[target] and target not in seen:
            seen.add(target)
            target = reexport[target][name]
        return target

    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, p in mods.items():
        for target, names in raw[m]:
            ends = set()
            if not names:
                ends.add(target)
            for n in names:
                sub = f"{target}.{n}"
                ends.add(sub if sub in mods else origin(target, n))
            for end in ends:
                if end not in mods or end == m:
                    continue
                if _is_package(p) and end.startswith(m + "."):
                    continue  # the package listing its own submodules' names
                graph[m].add(end)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of two or more modules (Tarjan's algorithm, iterative)."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    group.append(top)
                    if top == node:
                        break
                if len(group) > 1:
                    out.append(sorted(group))
    return out


def import_cycles(folder: Path, name: str) -> list[list[str]]:
    """Every import cycle (rule (a)) between the modules of the package in ``folder``, imported as ``name``."""
    return _cycles(_import_graph(_modules(folder, name)))


def long_functions(folder: Path, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    """``path:line name (n lines)`` of every function over ``limit`` lines outside generated files."""
    out = []
    for path in sorted(folder.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        doc = ast.get_docstring(tree) or ""
        if doc.strip().splitlines()[:1] and "GENERATED" in doc.strip().splitlines()[0]:
            continue
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > limit:
                    out.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    return out


def long_modules(folder: Path, limit: int = MAX_FIT_MODULE_LINES) -> list[str]:
    """``path (n lines)`` of every module under ``folder`` over ``limit`` lines (as ``wc -l`` counts)."""
    out = []
    for path in sorted(folder.rglob("*.py")):
        n = path.read_bytes().count(b"\n")
        if n > limit:
            out.append(f"{path.relative_to(ROOT)} ({n} lines)")
    return out


def test_cycle_finder_sees_function_level_imports_and_reexports(tmp_path):
    """The rule itself on a small package: a function-level import closes a cycle, a name taken
    through the package's ``__init__`` counts against its defining submodule, and the ``__init__``
    listing its submodules is no cycle."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from .a import f\nfrom .b import g\nfrom .sub import h\n")
    (pkg / "a.py").write_text("def f():\n    from pkg.b import g\n    return g\n")
    (pkg / "b.py").write_text("from pkg import f\n\ndef g():\n    return 1\n")  # f is pkg.a's
    (pkg / "sub" / "__init__.py").write_text("from .c import h\n")
    (pkg / "sub" / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                      "    from pkg.a import f\n\ndef h():\n    return 2\n")
    assert import_cycles(pkg, "pkg") == [["pkg.a", "pkg.b"]]
    (pkg / "b.py").write_text("def g():\n    return 1\n")
    assert import_cycles(pkg, "pkg") == []


def test_engine_has_no_import_cycle():
    assert import_cycles(ROOT / "ptpcore", "ptpcore") == []


def test_gui_has_no_import_cycle():
    assert import_cycles(ROOT / "app", "ptp_studio") == []


def test_engine_functions_fit_a_reading():
    assert long_functions(ROOT / "ptpcore") == []


def test_fit_modules_fit_a_reading():
    assert long_modules(ROOT / "ptpcore" / "fit") == []


def repository_import_cycles(packages=PACKAGES, root: Path = ROOT) -> list[list[str]]:
    """Every import cycle (rule (a)) between the modules of all ``packages`` ((folder, name) pairs) taken
    together."""
    mods: dict[str, Path] = {}
    for folder, name in packages:
        if (root / folder).is_dir():
            mods.update(_modules(root / folder, name))
    return _cycles(_import_graph(mods))


def _is_research(module: str) -> bool:
    parts = module.split(".")
    return parts[0] == "research" or (parts[0] == "benchmarks" and len(parts) > 1 and parts[1] in DIAGNOSIS_SCRIPTS)


def _named_modules(tree: ast.AST) -> list[tuple[int, str]]:
    """``(line, module)`` of every module a test file reaches: imports (``from benchmarks import x``
    names ``benchmarks.x``), ``import_module``/``importorskip`` calls and ``-m MODULE`` in a list."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            out.append((node.lineno, node.module))
            out += [(node.lineno, f"{node.module}.{alias.name}") for alias in node.names]
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if func in ("import_module", "importorskip", "__import__") and isinstance(node.args[0].value, str):
                out.append((node.lineno, node.args[0].value))
        elif isinstance(node, (ast.List, ast.Tuple)):
            items = node.elts
            for flag, value in zip(items, items[1:]):
                if (isinstance(flag, ast.Constant) and flag.value == "-m" and isinstance(value, ast.Constant)
                        and isinstance(value.value, str)):
                    out.append((node.lineno, value.value))
    return out


def research_imports(folder: Path) -> list[str]:
    """``path:line module`` of every place a file under ``folder`` reaches the research folder or a
    diagnosis script (rule (e))."""
    out = []
    for path in sorted(folder.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        out += [f"{path.relative_to(folder.parent)}:{line} {module}" for line, module in _named_modules(tree)
                if _is_research(module)]
    return out


def test_the_repository_has_no_import_cycle():
    assert repository_import_cycles() == []


def test_cycle_finder_sees_cycles_between_packages(tmp_path):
    """Rule (d) on two small packages: a cycle through both is found, and none once it is broken."""
    for pkg in ("one", "two"):
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "one" / "a.py").write_text("from two.b import g\n\ndef f():\n    return g()\n")
    (tmp_path / "two" / "b.py").write_text("def g():\n    from one.a import f\n    return f\n")
    pairs = (("one", "one"), ("two", "two"))
    assert repository_import_cycles(pairs, tmp_path) == [["one.a", "two.b"]]
    (tmp_path / "two" / "b.py").write_text("def g():\n    return 1\n")
    assert repository_import_cycles(pairs, tmp_path) == []


def test_no_test_imports_research_or_a_diagnosis_script():
    assert research_imports(ROOT / "tests") == []


def test_research_import_finder_sees_every_form(tmp_path):
    """Rule (e) on small files: import statements, ``from benchmarks import NAME``, importorskip,
    ``python -m`` in a command list; a measurement tool of ``benchmarks`` is allowed."""
    tests = tmp_path / "tests"
    tests.mkdir()
    (tests / "test_a.py").write_text(
        "import research.trust_mc\nfrom benchmarks import trust_split, synth\nimport benchmarks.commands\n"
        "import pytest\nx = pytest.importorskip('benchmarks.stage_luck')\n"
        "cmd = ['python', '-m', 'research.real_bow', 'OUT']\nok = ['python', '-m', 'benchmarks.measure']\n")
    assert research_imports(tests) == ["tests/test_a.py:1 research.trust_mc", "tests/test_a.py:2 benchmarks.trust_split",
                                       "tests/test_a.py:5 benchmarks.stage_luck", "tests/test_a.py:6 research.real_bow"]
