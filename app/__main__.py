"""``ptp-studio``: start the calibration wizard (``--session FILE`` resumes one, ``--tour OUTDIR`` walks it)."""

from __future__ import annotations

import argparse
import os
import sys


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 320x240, got {text!r}") from None
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError("camera size must be at least 16x16")
    return w, h


def _quiet_offscreen_warnings() -> None:
    """Drop the offscreen platform's "does not support propagateSizeHints()" noise; keep the rest."""
    from PySide6.QtCore import qInstallMessageHandler

    def handler(_mode, _context, message):
        if "propagateSizeHints" not in message:
            print(message, file=sys.stderr)

    qInstallMessageHandler(handler)


def _quit_on_sigterm(app, wiz) -> None:
    """SIGTERM (a logout, ``kill``): stop the jobs and quit without asking, as a confirmed close does.

    Python's default would end the process at once and leave the session's temporary files (the
    spilled samples: 4 GB at 12 MP x 21) in the temporary folder; quitting normally removes them.
    Python runs a signal handler only between its own bytecodes, so a timer gives it a turn.
    """
    import signal

    from PySide6.QtCore import QTimer

    def quit_now() -> None:
        wiz.closing = True  # no "unsaved work" question
        wiz.stop_jobs()
        app.quit()

    signal.signal(signal.SIGTERM, lambda *_: QTimer.singleShot(0, quit_now))
    tick = QTimer(app)
    tick.timeout.connect(lambda: None)
    tick.start(200)


def build_parser() -> argparse.ArgumentParser:
    from ptpcore.simulate import PRESETS

    from . import __version__

    p = argparse.ArgumentParser(prog="ptp-studio", description="PTP Studio: the point-to-point calibration wizard.")
    p.add_argument("--version", action="version", version=f"ptp-studio {__version__}")
    p.add_argument("--preset", default="realistic", choices=list(PRESETS),
                   help="simulated rig to start with (default realistic)")
    p.add_argument("--camera", type=_size, metavar="WxH", help="simulated camera size (default: the preset's)")
    p.add_argument("--session", metavar="FILE",
                   help="open a session file (ptp-session/1, *.ptps.h5) and go on where it stopped; it is saved"
                        " again after each completed stage")
    p.add_argument("--tour", metavar="OUTDIR",
                   help="walk every page offscreen on a small simulated rig, write one PNG per page to OUTDIR, exit")
    p.add_argument("--tour-camera", type=_size, default=(320, 240), metavar="WxH",
                   help="camera size of the tour (default 320x240)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.tour:
        os.environ["QT_QPA_PLATFORM"] = "offscreen"
    else:
        from .platform_check import startup_problem

        problem = startup_problem()  # before Qt is loaded: Qt would abort (exit 134) on it
        if problem:
            print(f"ptp-studio: cannot open a window: {problem}.", file=sys.stderr)
            return 2
    from PySide6.QtWidgets import QApplication

    from .wizard import StudioWizard, configure_app, freeze_startup_objects

    if args.tour:
        _quiet_offscreen_warnings()
    app = QApplication.instance() or QApplication(sys.argv[:1])
    configure_app(app)
    if args.tour:
        from .tour import run_tour

        try:
            run_tour(args.tour, *args.tour_camera)
        except (RuntimeError, OSError, TimeoutError) as exc:
            print(f"ptp-studio: tour failed: {exc}", file=sys.stderr)
            return 1
        return 0

    from ptpcore.store import remove_orphaned_spill_files

    from .session import Session

    remove_orphaned_spill_files()  # what killed runs left (only where spill files have names)
    session = Session.from_preset(args.preset, tuple(args.camera) if args.camera else None)
    session.reset_positions()
    wiz = StudioWizard(session)
    wiz.show()
    _quit_on_sigterm(app, wiz)
    freeze_startup_objects()
    if args.session:  # read in the background; a bad file is reported on the Rig page
        wiz.open_session(args.session)
    return app.exec()


if __name__ == "__main__":
    sys.exit(main())
