"""Issue 34's Must show, measured: the height map and reconstructed scans against the simulator's truth.

    python -m benchmarks.scanner_must_show [--presets scanner-mild scanner-rough] [--seeds 0 1 2 3 4]
                                           [--width 160] [--keep DIR]

Per preset and seed: ``ptp simulate --preset P --width W --seed S``; the height sweep decoded and its
map fitted on every second height, read at the exact ``u_p`` of the other heights (error RMS / max in
µm, RMS of error / sigma_z); then ``ptp calibrate`` (XY LUT and ``/height``) and every scan
reconstructed (points, RMS distance from the true surface in µm, RMS of distance / sigma along the
normal, points beyond 4 sigma against the 0.3 % VDI/VDE 2634-2 lets a fit leave out, coverage of the
lit truth pixels). One JSON line per run on standard output. Counts and accuracy only, no timing.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np


def measure(preset: str, seed: int, width: int, folder: Path) -> dict:
    """One preset and seed in ``folder`` (created); the numbers as a dict."""
    from ptpcore.cli.main import main
    from ptpcore.evaluate.scanner import height_map_accuracy, scan_accuracy
    from ptpcore.fit.height import fit_height_map
    from ptpcore.io.dataset import DatasetSource
    from ptpcore.io.lutfile import load_lut
    from ptpcore.rig.rigfile import load_rig
    from ptpcore.run.scanner import decode_projector, reconstruct
    from ptpcore.simulate.scanner import load_scan_truth, load_scanner

    ds = folder / f"{preset}-{seed}"
    with contextlib.redirect_stdout(io.StringIO()):
        if main(["simulate", "--preset", preset, "--width", str(width), "--seed", str(seed), "-q", "--force",
                 str(ds)]) != 0:
            raise RuntimeError(f"ptp simulate failed for {preset} seed {seed}")
    rig = load_rig(ds)
    dec = decode_projector(DatasetSource(ds, rig=rig.height_rig()))
    k = len(dec.z_mm)
    hm = fit_height_map(dec.u, dec.sigma_u, dec.z_mm, positions=np.arange(0, k, 2))
    acc = height_map_accuracy(hm, load_scanner(ds), dec.z_mm[1::2])
    out = {"preset": preset, "seed": seed, "width": width, "degree": hm.degree,
           "held_out_rms_um": round(acc.rms_um, 2), "held_out_max_um": round(acc.max_um, 1),
           "held_out_rms_z": round(acc.rms_z, 3), "coverage": acc.coverage,
           "model_error_resolved": hm.provenance["model_error"]["resolved"]}
    lut_path = folder / f"{preset}-{seed}.lut.h5"
    with contextlib.redirect_stdout(io.StringIO()):
        if main(["calibrate", str(ds), "--out", str(lut_path), "-q", "--force"]) != 0:
            raise RuntimeError(f"ptp calibrate failed for {preset} seed {seed}")
    lut = load_lut(lut_path)
    for name in sorted(p.name for p in (ds / "scans").iterdir()):
        res = reconstruct(ds / "scans" / name, lut)[0]
        obj, truth = load_scan_truth(ds / "scans" / name)
        a = scan_accuracy(res, obj, truth)
        out[name] = {"points": a.n_points, "rms_um": round(a.rms_um, 1), "rms_normalised": round(a.rms_normalised, 3),
                     "beyond_4": a.n_beyond_4, "allowed_out": a.allowed_out, "coverage": round(a.coverage, 3)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--presets", nargs="+", default=["scanner-mild", "scanner-rough"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--keep", help="keep the datasets and LUTs in this folder (default: a temporary one, removed)")
    args = p.parse_args(argv)
    warnings.simplefilter("ignore")
    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="ptp-scanner-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        for preset in args.presets:
            for seed in args.seeds:
                print(json.dumps(measure(preset, seed, args.width, folder)), flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
