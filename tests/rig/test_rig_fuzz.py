"""Property test: malformed rig.toml documents give ConfigError, never another exception.

Documents are mutations of a valid rig.toml (wrong types, missing and extra
keys, garbage values, broken templates) and plain random text.
"""

from __future__ import annotations

import copy
import os
import tomllib

import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ptpcore.errors import ConfigError
from ptpcore.rig import Rig, rig_from_toml, rig_to_toml
from ptpcore.simulate import preset

VALID = rig_to_toml(preset("realistic")[0])
DOC = tomllib.loads(VALID)
SECTIONS = [k for k, v in DOC.items() if isinstance(v, dict)]
# More examples for a deeper search: PTP_FUZZ_EXAMPLES=20000 python -m pytest tests/test_rig_fuzz.py
N = int(os.environ.get("PTP_FUZZ_EXAMPLES", "0")) or None
PATHS = [(k,) for k in DOC] + [(s, k) for s in SECTIONS for k in DOC[s]]

scalars = st.one_of(
    st.none(),  # stands for "delete the key"
    st.booleans(),
    st.integers(),
    st.integers(min_value=-(10**400), max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=40),
    st.sampled_from(["x", "y", "z", "", "ptp-dataset/1", "ptp-dataset/2", "{pos}", "{pos.__class__}",
                     "{dir[0]}", "{pos!r}", "{pos:{dir}}", "{pos:>999999999999}", "{pos:>100000}",
                     "../{pos}{dir}{period}{step}", "/abs/{pos}{dir}{period}{step}.png",
                     "{pos}{dir}{period}{step}{steps}{", "{pos}{dir}{period}{step:d}{0}",
                     "{pos:03d}/{dir}_T{period}_n{step:02d}.png", "{pos:%}{dir}{period}{step}"]),
    st.dates(),
    st.datetimes(),
    st.times(),
)
values = st.recursive(scalars.filter(lambda v: v is not None),
                      lambda inner: st.one_of(st.lists(inner, max_size=5),
                                              st.dictionaries(st.text(max_size=8), inner, max_size=3)),
                      max_leaves=12)
numbers_list = st.lists(st.one_of(st.integers(-10**20, 10**20), st.floats(allow_nan=True, allow_infinity=True)),
                        max_size=30)
extremes = st.sampled_from([10**400, -10**400, 2**63, -2**63 - 1, 2**31, 0, -1, 1, 2, 3, 10**9, 1e308, -1e308,
                             float("nan"), float("inf"), -float("inf"), 5e-324, -0.0, True, "", "x", "y",
                             [], {}])
mutation = st.tuples(st.sampled_from(PATHS), st.one_of(st.none(), values, numbers_list, extremes))


@st.composite
def element_mutation(draw):
    """Keep a list key's shape but break one element (or the list's length)."""
    path = draw(st.sampled_from([p for p in PATHS if len(p) == 2 and isinstance(DOC[p[0]][p[1]], list)]))
    items = list(DOC[path[0]][path[1]])
    action = draw(st.sampled_from(["replace", "drop", "duplicate", "reverse"]))
    if action == "replace":
        items[draw(st.integers(0, len(items) - 1))] = draw(st.one_of(extremes, scalars.filter(lambda v: v is not None)))
    elif action == "drop":
        del items[draw(st.integers(0, len(items) - 1))]
    elif action == "duplicate":
        i = draw(st.integers(0, len(items) - 1))
        items.insert(i, items[i])
    else:
        items.reverse()
    return path, items


def _apply(doc: dict, mutations) -> dict:
    doc = copy.deepcopy(doc)
    for path, value in mutations:
        table = doc
        for key in path[:-1]:
            if not isinstance(table.get(key), dict):
                table[key] = {}
            table = table[key]
        if value is None:
            table.pop(path[-1], None)
        else:
            # A copy: Hypothesis may hand the same object to two mutations, and
            # mutating it in place could build a cycle (and a flaky test).
            table[path[-1]] = copy.deepcopy(value)
    return doc


def _check(text: str) -> None:
    try:
        rig = rig_from_toml(text, "fuzz.toml")
    except ConfigError as exc:
        msg = str(exc)
        assert msg.startswith("fuzz.toml"), msg
        assert "\n" not in msg, msg
        return
    assert isinstance(rig, Rig)
    # Whatever loads must also save and load again to the same rig.
    assert rig_from_toml(rig_to_toml(rig)) == rig


def test_valid_document_loads():
    assert rig_from_toml(VALID) == preset("realistic")[0]


@settings(max_examples=N or 600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(mutation, element_mutation()), min_size=1, max_size=4),
       st.dictionaries(st.sampled_from(["extra", "camera.extra", "zz"]), values, max_size=2))
def test_mutated_documents(mutations, extra):
    doc = _apply(DOC, mutations)
    for key, value in extra.items():
        section, _, name = key.rpartition(".")
        target = doc.setdefault(section, {}) if section else doc
        if isinstance(target, dict):
            target[name] = copy.deepcopy(value)
    try:
        text = tomli_w.dumps(doc)
    except (TypeError, ValueError):
        return  # not expressible in TOML (e.g. a NUL in a key): nothing to load
    _check(text)


@settings(max_examples=N or 200, deadline=None)
@given(st.text(max_size=400))
def test_random_text(text):
    _check(text)


@settings(max_examples=N or 200, deadline=None)
@given(st.integers(0, len(VALID)), st.integers(0, len(VALID)), st.text(max_size=20))
def test_cut_and_spliced_text(start, stop, insert):
    a, b = sorted((start, stop))
    _check(VALID[:a] + insert + VALID[b:])


def _with(section, key, value) -> str:
    doc = copy.deepcopy(DOC)
    doc[section][key] = value
    return tomli_w.dumps(doc)


# Found by the fuzzer or written down as its regressions.
NASTY = {
    "integer too big for a float": (_with("lcd", "pitch_mm", [10**400, 0.05]), "lcd.pitch_mm"),
    "integer too long to read": (VALID.replace("width = 640", "width = 1" + "0" * 5000, 1), "not valid TOML"),
    "huge width in the template": (_with("images", "template", "{pos:>999999999}{dir}{period}{step}"),
                                   "images.template"),
    "NUL in the template": (_with("images", "template", "z{pos}\x00{dir}{period}{step}.png"), "control"),
    "character type in the template": (_with("images", "template", "{pos:c}{dir}{period}{step}"),
                                       "images.template"),
    "million steps": (_with("fringes", "steps", 10**6), "fringes.steps"),
    "newline in an unknown key": (VALID + '\n"a\\nb" = 1\n', "unknown key 'images.a\\nb'"),
}


def test_known_nasty_documents():
    import pytest

    for name, (text, expected) in NASTY.items():
        with pytest.raises(ConfigError) as err:
            rig_from_toml(text, "fuzz.toml")
        msg = str(err.value)
        assert expected in msg and "\n" not in msg and len(msg) < 400, (name, msg)
