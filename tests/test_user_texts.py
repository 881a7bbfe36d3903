"""User-facing texts (issue 31): one spelling of the micrometre, "µm", in every string the engine and the
wizard show (summaries, messages, help, tooltips), and positions named as the dataset counts them."""

from __future__ import annotations

import io
import re
import tokenize
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ASCII_MICRON = re.compile(r"(?<![-A-Za-z_µ])um\b(?![_(])")  # " um", "2.95um", "(um," — not "--tolerance-um", "_um"
FORMAT_VALUES = {'"um"'}  # the comparison JSON's "units" entry (FORMATS.md): a file format, not a text


def _texts(path: Path):
    """(line, string literal) of ``path``'s strings that are not docstrings."""
    toks = list(tokenize.generate_tokens(io.StringIO(path.read_text(encoding="utf-8")).readline))
    skip = (tokenize.NL, tokenize.COMMENT)
    for i, t in enumerate(toks):
        if t.type != tokenize.STRING:
            continue
        prev = next((x for x in reversed(toks[:i]) if x.type not in skip), None)
        if prev is None or prev.type in (tokenize.INDENT, tokenize.DEDENT, tokenize.NEWLINE):
            continue  # a docstring: for the next engineer, not the user
        yield t.start[0], t.string


def test_micrometres_are_spelled_one_way():
    found = [f"{p.relative_to(ROOT)}:{line}: {s[:90]}" for folder in ("ptpcore", "app")
             for p in sorted((ROOT / folder).rglob("*.py")) for line, s in _texts(p)
             if s not in FORMAT_VALUES and ASCII_MICRON.search(s)]
    assert not found, "\n".join(found)


def test_the_scan_sees_a_micrometre_spelled_um(tmp_path):
    p = tmp_path / "m.py"
    p.write_text('"""Docstring in um."""\nx = f"RMS {r:.2f} um"\ny = "--tolerance-um"\n', encoding="utf-8")
    assert [s for _line, s in _texts(p) if ASCII_MICRON.search(s)] == ['f"RMS {r:.2f} um"']


def test_positions_are_named_from_0_with_their_height():
    from ptpcore.rig import position_label

    assert position_label(3, 12.0) == "position 3, z = 12 mm"
    assert position_label(0, 0.0) == "position 0, z = 0 mm"
    assert position_label(np.int64(2)) == position_label(2, float("nan")) == "position 2"
