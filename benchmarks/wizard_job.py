"""The wizard's decode (Acquire page) and calibrate jobs on a dataset folder, offscreen, as a user runs them.

    QT_QPA_PLATFORM=offscreen python -m benchmarks.wizard_job DATASET_DIR [--model poly|smooth|auto] [--degree D]

Opens the wizard (:class:`ptp_studio.wizard.StudioWizard`) on the folder (the Rig page's "open dataset"
engine call, :meth:`ptp_studio.session.SessionModel.import_dataset`), runs the Acquire page's job (decode
every position) and then the Calibrate page's fit, and prints one JSON line: each job's wall time,
the longest gap between the ticks of a 1 ms timer on the GUI thread while it ran (the event loop's
worst stall), the job phase it fell in (the job's progress message then, or "handing the result to
the page" for the page's own handling of the result) and the worst gap of the five worst phases. :mod:`benchmarks.commands` runs it in a fresh process for its peak RSS and CPU time.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path


def _wait(app, job, timeout_s: float = 7200.0) -> str:
    """Process events until ``job`` is done; its outcome."""
    t_end = time.perf_counter() + timeout_s
    while job.running and time.perf_counter() < t_end:
        app.processEvents()
        time.sleep(0.0005)
    return job.outcome


def run(dataset: Path, model: str, degree: int) -> dict:
    """Decode and calibrate ``dataset`` through the wizard; timings and event-loop stalls."""
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtCore import QTimer
    from PySide6.QtWidgets import QApplication

    from ptp_studio.session import Session
    from ptp_studio.wizard import StudioWizard, freeze_startup_objects
    from ptpcore.rig import load_rig

    app = QApplication.instance() or QApplication([])
    wiz = StudioWizard(Session.from_preset("realistic"))
    wiz.resize(1300, 850)
    wiz.show()
    freeze_startup_objects()  # as ptp-studio does at start-up
    wiz.model.import_dataset(dataset, load_rig(dataset / "rig.toml"))
    gaps: list[tuple[float, str]] = []  # (gap s, the job's latest progress message then)
    last = [None]
    phase = [""]

    def tick():
        now = time.perf_counter()
        if last[0] is not None:
            gaps.append((now - last[0], phase[0]))
        last[0] = now

    timer = QTimer()
    timer.setInterval(1)
    timer.timeout.connect(tick)
    out = {"dataset": str(dataset), "model": model, "degree": degree}
    for key, start in (("acquire", lambda: wiz.page_by_key["acquire"].start()),
                       ("calibrate", lambda: _calibrate(wiz, model, degree))):
        wiz.go_to(key)
        gaps.clear()
        last[0] = None
        phase[0] = "starting the job"
        timer.start()
        t0 = time.perf_counter()
        job = start()
        if job is None:
            raise RuntimeError(f"the {key} page did not start its job")
        _follow(job, phase)
        outcome = _wait(app, job)
        timer.stop()
        out[key] = {"outcome": outcome, "wall_s": time.perf_counter() - t0, "ticks": len(gaps), **_worst(gaps)}
        if outcome != "finished":
            raise RuntimeError(f"the {key} job ended {outcome}")
    wiz.model.mark_saved()  # no "unsaved work" question at exit
    return out


def _follow(job, phase: list[str]) -> None:
    """Keep ``phase[0]`` at the job's latest progress message, so a stall says where it happened."""
    job.progress.connect(lambda _f, message: phase.__setitem__(0, message or phase[0]))
    # The page's handlers of the result (maps, tables, plots) run on the GUI thread too.
    job.finished.connect(lambda _r: phase.__setitem__(0, "handing the result to the page"))


def _worst(gaps: list[tuple[float, str]]) -> dict:
    """The longest gap (ms), the phase it fell in, and the next longest in other phases (ms by phase)."""
    if not gaps:
        return {"max_gap_ms": float("nan"), "max_gap_phase": None, "max_gap_ms_by_phase": {}}
    by_phase: dict[str, float] = {}
    for gap, where in gaps:
        by_phase[where] = max(by_phase.get(where, 0.0), 1e3 * gap)
    top = sorted(by_phase.items(), key=lambda kv: -kv[1])[:5]  # the five worst phases, enough to say where
    gap, where = max(gaps)
    return {"max_gap_ms": 1e3 * gap, "max_gap_phase": where,
            "max_gap_ms_by_phase": {k: round(v, 1) for k, v in top}}


def _calibrate(wiz, model: str, degree: int):
    cal = wiz.page_by_key["calibrate"]
    cal.configure(model, degree, "all")
    return cal.fit()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--model", default="auto")
    ap.add_argument("--degree", type=int, default=3)
    args = ap.parse_args(argv)
    print(json.dumps(run(Path(args.dataset), args.model, args.degree)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
