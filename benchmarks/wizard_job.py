"""The wizard's decode (Acquire page) and calibrate jobs on a dataset folder, offscreen, as a user runs them.

    QT_QPA_PLATFORM=offscreen python -m benchmarks.wizard_job DATASET_DIR [--model poly|smooth|auto] [--degree D]

Opens the wizard (:class:`ptp_studio.wizard.StudioWizard`) on the folder (the Rig page's "open dataset"
engine call, :meth:`ptp_studio.session.SessionModel.import_dataset`), runs the Acquire page's job (decode
every position) and then the Calibrate page's fit, and prints one JSON line: each job's wall time and
the longest gap between the ticks of a 1 ms timer on the GUI thread while it ran (the event loop's
worst stall). :mod:`benchmarks.commands` runs it in a fresh process for its peak RSS and CPU time.
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
    from ptp_studio.wizard import StudioWizard
    from ptpcore.rig import load_rig

    app = QApplication.instance() or QApplication([])
    wiz = StudioWizard(Session.from_preset("realistic"))
    wiz.resize(1300, 850)
    wiz.show()
    wiz.model.import_dataset(dataset, load_rig(dataset / "rig.toml"))
    gaps: list[float] = []
    last = [None]

    def tick():
        now = time.perf_counter()
        if last[0] is not None:
            gaps.append(now - last[0])
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
        timer.start()
        t0 = time.perf_counter()
        job = start()
        if job is None:
            raise RuntimeError(f"the {key} page did not start its job")
        outcome = _wait(app, job)
        timer.stop()
        out[key] = {"outcome": outcome, "wall_s": time.perf_counter() - t0,
                    "max_gap_ms": 1e3 * max(gaps, default=float("nan")), "ticks": len(gaps)}
        if outcome != "finished":
            raise RuntimeError(f"the {key} job ended {outcome}")
    wiz.model.mark_saved()  # no "unsaved work" question at exit
    return out


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
