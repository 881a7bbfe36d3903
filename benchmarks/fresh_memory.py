"""What new memory costs on this machine: writing a new file, fresh and right after another.

    python -m benchmarks.fresh_memory DATASET_DIR [--mb 800]

Writes ``--mb`` MB to a new temporary file (8 MB ``os.pwrite`` blocks) three ways: in a
fresh process; again at once (the pages the first file just gave back are reused); and after
a pass of ``cv2.imread`` over the dataset on all cores (what the benchmark's floors do between
two calibrations). On a VM whose balloon driver reports free pages to the host
(``/sys/module/page_reporting``), pages that stayed free for a few seconds cost a fault in
the host when touched again: the spilled sample stack (1.8 GB at 5 MP x 21) pays that. Prints
one JSON line (seconds of wall and system time per write).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np


def write_new_file(mb: int, directory=None) -> dict:
    block = np.random.default_rng(0).random(1 << 20)  # 8 MB
    data = memoryview(block.view(np.uint8))
    fd, name = tempfile.mkstemp(dir=directory)
    try:
        c0, t0 = os.times(), time.perf_counter()
        for i in range(mb // 8):
            os.pwrite(fd, data, i * len(data))
        c1 = os.times()
        return {"wall_s": round(time.perf_counter() - t0, 3), "sys_s": round(c1.system - c0.system, 3)}
    finally:
        os.close(fd)
        os.unlink(name)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--mb", type=int, default=800)
    args = ap.parse_args(argv)
    files = sorted(Path(args.dataset).glob("*/*.tif")) + sorted(Path(args.dataset).glob("*/*.png"))
    out = {"fresh": write_new_file(args.mb), "again": write_new_file(args.mb)}
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        for _ in pool.map(lambda p: cv2.imread(str(p), cv2.IMREAD_UNCHANGED).shape, files):
            pass
    out["after_cv2_pass"] = write_new_file(args.mb)
    out["again_after"] = write_new_file(args.mb)
    reporting = Path("/sys/module/page_reporting/parameters/page_reporting_order")
    out["page_reporting_order"] = reporting.read_text().strip() if reporting.exists() else None
    out.update(mb=args.mb, images=len(files))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
