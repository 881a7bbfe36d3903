"""docs/cli.md against the argument parsers of ``ptp`` and ``ptp-studio``, both ways.

The page's structure (stated at its top):

- one ``### ptp NAME`` heading per ``ptp`` command, ``### ptp`` for the top-level options and
  ``### ptp-studio`` for the wizard's launcher;
- under it, one bullet per argument beginning with the argument in backticks: a flag
  (``- `-q`, `--quiet`: ...``, aliases separated by commas) or a positional argument's
  placeholder (``- `DATASET_DIR`: ...``);
- an option with a default value says ``default `VALUE``` in its bullet.

So a command, an option or a positional argument added to a parser without its line in the page
fails here, and so does a line left in the page for one that is gone, or a stale default.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

CLI_MD = Path(__file__).resolve().parents[2] / "docs" / "cli.md"
HEADING = re.compile(r"^### (ptp(?:-studio)?)(?: ([a-z-]+))?\s*$")
BULLET = re.compile(r"^- ((?:`[^`]+`(?:, )?)+)")
DEFAULT = re.compile(r"default `([^`]*)`")


def _documented() -> dict[str, dict[str, dict]]:
    """{"ptp simulate": {"--seed": {"default": "0"}, "OUT_DIR": {...}}, ...} from docs/cli.md."""
    doc: dict[str, dict[str, dict]] = {}
    current = None
    fence = False
    lines: list[str] = []
    for line in CLI_MD.read_text(encoding="utf-8").splitlines():
        if line.startswith("  ") and lines and lines[-1].startswith("- "):
            lines[-1] += " " + line.strip()  # a bullet's continuation line
        else:
            lines.append(line)
    for line in lines:
        if line.startswith("```"):
            fence = not fence
            continue
        if fence:
            continue
        m = HEADING.match(line)
        if m:
            current = " ".join(filter(None, m.groups()))
            assert current not in doc, f"docs/cli.md: '### {current}' twice"
            doc[current] = {}
            continue
        if line.startswith("## "):
            current = None
            continue
        m = BULLET.match(line)
        if m and current is not None:
            names = re.findall(r"`([^`]+)`", m.group(1))
            d = DEFAULT.search(line)
            entry = {"default": d.group(1) if d else None, "aliases": set(names)}
            for name in names:
                doc[current][name] = entry
    return doc


def _arg_names(action: argparse.Action) -> list[str]:
    if action.option_strings:
        return list(action.option_strings)
    meta = action.metavar if isinstance(action.metavar, str) else action.dest.upper()
    return [meta]


def _shown_default(action: argparse.Action) -> str | None:
    """The default as the page writes it; None where the page need not name one."""
    value = action.default
    if not action.option_strings or value is None or isinstance(value, bool) or action.nargs == 0:
        return None
    if isinstance(value, tuple):
        return "x".join(str(v) for v in value)
    return str(value)


def _parsed() -> dict[str, dict[str, argparse.Action]]:
    """{"ptp simulate": {"--seed": action, "OUT_DIR": action}, ...} from the parsers themselves."""
    from ptp_studio.__main__ import build_parser as studio_parser
    from ptpcore.cli.main import build_parser

    def args_of(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
        out = {}
        for action in parser._actions:  # argparse has no public list of a parser's arguments
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            for name in _arg_names(action):
                out[name] = action
        return out

    top = build_parser()
    parsed = {"ptp": args_of(top), "ptp-studio": args_of(studio_parser())}
    sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))
    for name, parser in sub.choices.items():
        parsed[f"ptp {name}"] = args_of(parser)
    return parsed


def test_the_page_documents_exactly_the_commands_of_the_parsers():
    doc, parsed = _documented(), _parsed()
    assert set(doc) == set(parsed), (f"commands without a '### ' section in docs/cli.md:"
                                     f" {sorted(set(parsed) - set(doc))}; sections for no command:"
                                     f" {sorted(set(doc) - set(parsed))}")


@pytest.mark.parametrize("command", sorted(_parsed()))
def test_each_command_documents_exactly_its_arguments_and_defaults(command):
    doc = _documented().get(command, {})
    parsed = _parsed()[command]
    assert set(doc) == set(parsed), (f"{command}: arguments in the parser but not in docs/cli.md:"
                                     f" {sorted(set(parsed) - set(doc))}; in docs/cli.md but not in the parser:"
                                     f" {sorted(set(doc) - set(parsed))}")
    for name, action in parsed.items():
        assert doc[name]["aliases"] == set(_arg_names(action)), f"{command} {name}: aliases differ"
        want = _shown_default(action)
        if want is not None:
            assert doc[name]["default"] == want, (f"{command} {name}: docs/cli.md says default"
                                                  f" {doc[name]['default']!r}, the parser {want!r}")


def test_the_exit_codes_table_holds_every_exit_code_of_the_cli():
    from ptpcore.cli import safety

    text = CLI_MD.read_text(encoding="utf-8")
    table = text.split("## Exit codes", 1)[1].split("\n## ", 1)[0]
    rows = {int(code) for code in re.findall(r"^\| `(\d+)` \|", table, flags=re.M)}
    codes = {value for key, value in vars(safety).items() if key.startswith("EXIT_")}
    assert codes, "ptpcore.cli.safety defines no EXIT_ codes"
    # 0 done, 1 `ptp diff` DIFFER (ptpcore/cli/main.py cmd_diff), the rest from ptpcore.cli.safety.
    assert rows == codes | {0, 1}
