"""Time the `fringes` package (GPL) decoding a dataset position. Run ONLY in its own venv.

    /tmp/fringes-venv/bin/python benchmarks/fringes_decode.py DATASET_DIR --position 0 --repeat 3 --out OUT.npz

It must never be imported by ptpcore or installed with it: this script imports
only fringes, numpy, OpenCV and the standard library, reads ``rig.toml`` with
``tomllib``, reads the same image files as PTP Studio does, and prints one
JSON line: the best decode time after a JIT warm-up, and where its decoded
coordinates are saved (to check both decoders agree).

Our frames are ``A + B cos(2 pi c / T + 2 pi n / N)`` with ``c`` the virtual LCD
coordinate; in fringes' terms that is ``reverse=True`` (phase shifts of the
opposite sign), ``p0 = 0`` and ``v = Lext / T`` periods over its coding
length ``Lext`` (the LCD's larger side), so its decoded ``x`` is ``c``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import tomllib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--position", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import fringes  # noqa: only in the benchmark venv
    import numba

    folder = Path(args.dataset)
    rig = tomllib.loads((folder / "rig.toml").read_text())
    f = rig["fringes"]
    periods, steps = list(f["periods_px"]), list(f["steps"])
    lw, lh = rig["lcd"]["width"], rig["lcd"]["height"]
    names = [rig["images"]["template"].format(pos=args.position, dir=d, period=t, step=n, steps=big_n)
             for d in f["directions"] for t, big_n in zip(periods, steps) for n in range(big_n)]
    first = cv2.imread(str(folder / names[0]), cv2.IMREAD_UNCHANGED)
    stack = np.empty((len(names), *first.shape), first.dtype)
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        for i, img in enumerate(pool.map(lambda n: cv2.imread(str(folder / n), cv2.IMREAD_UNCHANGED), names)):
            stack[i] = img
    lext = max(lw, lh)
    d = len(f["directions"])
    fr = fringes.Fringes(X=lw, Y=lh, K=len(periods), N=[steps] * d, v=[[lext / t for t in periods]] * d,
                         f=[[1.0] * len(periods)] * d, p0=0.0, reverse=True,
                         bits=8 if stack.dtype == np.uint8 else 16,
                         dtype="uint8" if stack.dtype == np.uint8 else "uint16")
    t0 = time.perf_counter()
    fr.decode(np.ascontiguousarray(stack[:, :64, :64]))  # JIT compile (cached after the first run)
    warm = time.perf_counter() - t0
    best = float("inf")
    res = None
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        res = fr.decode(stack)
        best = min(best, time.perf_counter() - t0)
    a, b, x = res[:3]
    if args.out:
        np.savez_compressed(args.out, x=np.asarray(x)[..., 0][:, ::8, ::8].astype(np.float32))
    print(json.dumps({"seconds": best, "warmup_s": warm, "frames": len(names), "threads": numba.get_num_threads(),
                      "fringes": getattr(fringes, "__version__", "?"), "numba": numba.__version__}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
