"""Every option and positional argument of every ``ptp`` command says what it is (issue 41)."""

from __future__ import annotations

import argparse

from ptpcore.cli.main import build_parser
from ptpcore.cli.safety import subcommands

PARSER = build_parser()


def _missing(parser: argparse.ArgumentParser, where: str) -> list[str]:
    out = []
    for action in parser._actions:
        text = action.help
        if text is None or text == argparse.SUPPRESS or not str(text).strip():
            out.append(f"{where} {'/'.join(action.option_strings) or action.metavar or action.dest}")
    return out


def test_every_argument_of_every_command_has_help():
    missing = _missing(PARSER, "ptp")
    subs = subcommands(PARSER)
    assert {"simulate", "calibrate", "resume", "decode", "inspect", "apply", "reconstruct", "acceptance",
            "compare", "diff", "demo", "capture"} <= set(subs)
    for name, sub in subs.items():
        missing += _missing(sub, f"ptp {name}")
    assert missing == [], "arguments without help text: " + ", ".join(missing)


def test_every_command_has_a_one_line_summary_and_its_help_renders():
    listed = {a.dest: a.help for a in next(a for a in PARSER._actions
                                           if isinstance(a, argparse._SubParsersAction))._choices_actions}
    for name, sub in subcommands(PARSER).items():
        assert listed.get(name, "").strip(), f"ptp {name}: no summary in `ptp --help`"
        text = sub.format_help()
        for action in sub._actions:  # every help text is shown (a % in one would break argparse's formatting)
            if action.help and action.help != argparse.SUPPRESS:
                assert " ".join(str(action.help % {**vars(action), "prog": sub.prog}).split()[:3]) in " ".join(
                    text.split()), (name, action.dest)
