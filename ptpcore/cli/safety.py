"""What every ``ptp`` command shares to end cleanly: argument types, signals, a closed pipe.

- argument types that refuse bad values with one line (:func:`positive_int`,
  :func:`seed`, :func:`existing_dir`, ...), and a parser whose errors are one
  line and exit 2 (:class:`OneLineParser`);
- SIGTERM handled like Ctrl-C (:func:`signals_as_interrupts`): the job stops
  through the same ``finally`` blocks, every temporary file is removed, exit
  143 (130 for Ctrl-C);
- a closed standard output (``ptp inspect F | head -1``) ends quietly
  (:func:`quiet_broken_pipe`, exit 141 as a shell reports SIGPIPE);
- every output argument marked in the parser (:func:`add_output`), every
  input too (:func:`add_input`), so one guard (:func:`guard_arguments`,
  applied by :func:`ptpcore.cli.main.main` before any command runs) checks
  every output of every command, a new one included.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import threading
from pathlib import Path

from ptpcore.io.outputs import KINDS, Output, guard_outputs

EXIT_BAD_INPUT = 2
EXIT_PARTIAL = 3
"""``ptp calibrate`` / ``resume``: the XY LUT is written, the scanner's height map failed (the reason printed)."""
EXIT_SIGINT = 130
EXIT_SIGPIPE = 141
EXIT_SIGTERM = 143

__all__ = ["add_output", "add_input", "subcommands", "output_actions", "input_actions", "guard_arguments",
           "OneLineParser", "Terminated", "positive_int", "nonneg_int", "seed", "positive_float",
           "nonneg_float", "existing_dir", "existing_file", "signals_as_interrupts", "raise_if_terminated",
           "termination_requested", "quiet_broken_pipe",
           "EXIT_BAD_INPUT", "EXIT_SIGINT", "EXIT_SIGPIPE", "EXIT_SIGTERM"]


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread: stops the job exactly as Ctrl-C does."""


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (``ptp: error: ...``, as every error) and exit 2."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        self.exit(EXIT_BAD_INPUT, f"ptp: error: {message} (see `{self.prog} --help`)\n")


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1 (pixels, positions, points)."""
    value = _int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, got {value}")
    return value


def nonneg_int(text: str) -> int:
    """An integer >= 0."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def seed(text: str) -> int:
    """A random seed: an integer 0 .. 2**32 - 1 (what numpy and OpenCV accept everywhere)."""
    value = _int(text)
    if not 0 <= value < 2 ** 32:
        raise argparse.ArgumentTypeError(f"a seed is 0 .. 4294967295, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be more than 0, got {text}")
    return value


def nonneg_float(text: str) -> float:
    """A finite number >= 0."""
    value = _float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {text}")
    return value


# --------------------------------------------------------------------------- inputs and outputs, marked

OUTPUT_KINDS = (*KINDS, "dataset")
"""What an output argument writes: a file kind of :data:`ptpcore.io.outputs.KINDS`, or a dataset folder."""

INPUT_KINDS = ("dataset", "scans", "lut", "session", "rig", "config", "height")
"""What an input argument reads (a dataset or scan folder, a file; ``height``: a number or a file)."""


def add_output(parser, *flags, kind: str, resume: str | None = None, hint: str = "",
               **kwargs) -> argparse.Action:
    """Add an output argument, marked (``action.ptp_output = kind``) so the guard checks it.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        A subcommand's parser.
    *flags : str
        As for ``add_argument`` (``"--out"``, or a positional's name).
    kind : str
        One of :data:`OUTPUT_KINDS`: what is written there.
    resume : str, optional
        For a dataset folder: the ``args`` attribute (e.g. ``"resume"``) that, when true, lets the
        folder hold the dataset being continued.
    hint : str
        What to do when the output exists and may not be replaced (``{path}`` filled in; default:
        add ``--force``, or the ``resume`` flag).
    **kwargs
        As for ``add_argument``; ``help`` is required.

    Returns
    -------
    argparse.Action
        The marked action.

    Raises
    ------
    ValueError
        An unknown kind, or no help text.
    """
    action = _marked(parser, flags, kwargs, "add_output", kind, OUTPUT_KINDS)
    action.ptp_output = kind
    action.ptp_resume = resume
    action.ptp_hint = hint or (f"add --{resume} to continue it" if resume else "")
    return action


def add_input(parser, *flags, kind: str, **kwargs) -> argparse.Action:
    """Add an input argument, marked (``action.ptp_input = kind``): the guard never writes onto it.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        A subcommand's parser.
    *flags : str
        As for ``add_argument``.
    kind : str
        One of :data:`INPUT_KINDS`.
    **kwargs
        As for ``add_argument``; ``help`` is required.

    Returns
    -------
    argparse.Action
        The marked action.

    Raises
    ------
    ValueError
        An unknown kind, or no help text.
    """
    action = _marked(parser, flags, kwargs, "add_input", kind, INPUT_KINDS)
    action.ptp_input = kind
    return action


def _marked(parser, flags, kwargs: dict, who: str, kind: str, kinds: tuple) -> argparse.Action:
    """``parser.add_argument(*flags, **kwargs)`` once ``kind`` is one of ``kinds`` and a help text is given."""
    if kind not in kinds:
        raise ValueError(f"{who}: kind {kind!r} is not one of {', '.join(kinds)}")
    if not kwargs.get("help"):
        raise ValueError(f"{who}: {flags[0]} needs a help text")
    return parser.add_argument(*flags, **kwargs)


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The subcommand parsers of ``parser`` by name (``{"simulate": ..., "calibrate": ...}``)."""
    out: dict[str, argparse.ArgumentParser] = {}
    for action in parser._actions:  # noqa: SLF001 - argparse keeps its actions there, documented by use
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            out.update(action.choices)
    return out


def output_actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The marked output arguments of one (sub)command's parser, in the order they were added."""
    return [a for a in parser._actions if getattr(a, "ptp_output", None)]  # noqa: SLF001


def input_actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The marked input arguments of one (sub)command's parser, in the order they were added."""
    return [a for a in parser._actions if getattr(a, "ptp_input", None)]  # noqa: SLF001


def _values(value) -> list:
    if value is None:
        return []
    return list(value) if isinstance(value, (list, tuple)) else [value]


def _argument_name(action: argparse.Action) -> str:
    if action.option_strings:
        return max(action.option_strings, key=len)
    return action.metavar if isinstance(action.metavar, str) else action.dest.upper()


def guard_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[Path]:
    """The output guard over every marked output of the command ``args.command``, before it runs.

    Inputs are the values of its marked input arguments (for ``height``, only a value that
    names an existing file); ``--force`` is ``args.force`` where the command has it.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The ``ptp`` parser (:func:`ptpcore.cli.main.build_parser`).
    args : argparse.Namespace
        Its parsed arguments.

    Returns
    -------
    list of Path
        The outputs checked.

    Raises
    ------
    OutputError
        The first output refused (:func:`ptpcore.io.outputs.guard_outputs`).
    """
    sub = subcommands(parser).get(getattr(args, "command", None))
    if sub is None:
        return []
    inputs = []
    for action in input_actions(sub):
        for value in _values(getattr(args, action.dest, None)):
            if action.ptp_input != "height" or Path(str(value)).is_file():
                inputs.append(Path(str(value)))
    outputs = []
    for action in output_actions(sub):
        resume = bool(action.ptp_resume and getattr(args, action.ptp_resume, False))
        outputs += [Output(Path(str(v)), action.ptp_output, _argument_name(action), resume, action.ptp_hint)
                    for v in _values(getattr(args, action.dest, None))]
    return guard_outputs(outputs, inputs=inputs, force=bool(getattr(args, "force", False)))


def existing_dir(text: str) -> str:
    """A folder that exists."""
    p = Path(text)
    if not p.exists():
        raise argparse.ArgumentTypeError(f"{text}: no such folder")
    if not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: is a file, not a folder")
    return text


def existing_file(text: str) -> str:
    """A file that exists."""
    p = Path(text)
    if not p.exists():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: is a folder, not a file")
    return text


# Set by the SIGTERM handler. The exception it raises can be swallowed when the
# signal lands inside a C callback (numba compiling its kernels on a cold cache
# reports "Exception ignored on calling ctypes callback function"), so the
# request is also kept here and honoured at the next progress report.
_termination_requested = threading.Event()


def _raise_terminated(signum, frame) -> None:
    _termination_requested.set()
    raise Terminated()


def _quiet_about_swallowed_interrupts(unraisable) -> None:
    """``sys.unraisablehook``: no traceback for a Terminated that a C callback swallowed.

    The request is kept (:func:`raise_if_terminated` honours it); the user sees
    the one ``ptp: terminated`` line, as for any other SIGTERM. Once SIGTERM has
    arrived, a finaliser's error is quiet too: the signal can land inside a
    library's constructor (llvmlite building a compiler pass while numba
    compiles), and the half-built object's ``__del__`` then fails when the
    unwinding drops it, which is the interruption's echo, not a new fault.
    Everything else goes to Python's default hook.
    """
    if isinstance(unraisable.exc_value, Terminated) or _termination_requested.is_set():
        return
    sys.__unraisablehook__(unraisable)


def termination_requested() -> bool:
    """True once SIGTERM has arrived inside :func:`signals_as_interrupts`."""
    return _termination_requested.is_set()


def raise_if_terminated() -> None:
    """Raise :class:`Terminated` if a SIGTERM arrived whose exception was swallowed on its way.

    Called at every progress report, so a lost exception stops the job at the
    next step instead of letting it finish and exit 0.
    """
    if _termination_requested.is_set():
        raise Terminated()


@contextlib.contextmanager
def signals_as_interrupts():
    """SIGTERM raises :class:`Terminated` in the main thread while the block runs.

    Ctrl-C (SIGINT) already raises :class:`KeyboardInterrupt`; both then unwind
    through the writers' ``finally`` blocks, which remove their temporary
    files. The previous handlers are restored afterwards. Outside the main
    thread (a GUI worker) nothing is installed.
    """
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "SIGTERM"):
        yield
        return
    _termination_requested.clear()
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    previous_hook = sys.unraisablehook
    sys.unraisablehook = _quiet_about_swallowed_interrupts
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        sys.unraisablehook = previous_hook
        _termination_requested.clear()


def quiet_broken_pipe() -> int:
    """Standard output was closed by its reader: point it at the null device, return exit 141.

    Python would otherwise report the failed flush at exit as a traceback.
    """
    with contextlib.suppress(OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    return EXIT_SIGPIPE
