"""`make test`: the C reader against the Python engine (ptpcore), and its errors under AddressSanitizer.

Usage: python test_reader.py ./ptplut_tool ./ptplut_tool_asan

1. Writes LUTs of every kind (poly of degree 1 to 5, linear, pchip) with NaN
   nodes, runs of one node, invalid pixels, flat and non-monotonic tables, and
   evaluates them in C (whole map, constant height, single pixels; with and
   without extrapolation) and with ``Lut.evaluate``: X and Y agree to 1e-9 mm,
   NaN where Python has NaN, and the valid / in-range flags are identical,
   at heights below, above, on and between the nodes, in NaN gaps, within
   1e-9 mm of the range bounds, and NaN.
2. Writes LUTs with the scanner's height map (/height, rational of degree 1 to 5, invalid
   pixels) and evaluates it in C (``ptplut_height_eval_map`` and ``ptplut_height_eval``) and
   with ``HeightMap.evaluate`` at u_p inside, on and just beyond each pixel's calibrated range,
   NaN and infinite: Z to 1e-9 mm, dZ/du_p to 1e-12 mm/px, NaN and flags identical; the pattern
   design attributes read in C equal Python's.
3. Runs damaged and foreign files through the AddressSanitizer build: every one
   ends with exit status 1 and one "ptplut: STATUS: FILE: message" line, never a
   crash or a sanitizer report; the Python reader refuses the same files.

Exits 0 when everything holds, 1 with the failures listed.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from ptpcore.errors import FileFormatError  # noqa: E402
from ptpcore import Lut, load_lut, save_lut  # noqa: E402
from ptpcore.io.heightmap import HeightMap  # noqa: E402
from ptpcore.rig.rigfile import Projector  # noqa: E402

TOL_MM = 1e-9
TOL_SLOPE = 1e-12  # mm per projector px
HERE = Path(__file__).resolve().parent
OUT = HERE / "test-output"
FAILURES: list[str] = []
ASAN_ENV = {**os.environ, "ASAN_OPTIONS": "detect_leaks=1:abort_on_error=0:exitcode=99",
            "LSAN_OPTIONS": f"suppressions={HERE / 'lsan.supp'}:print_suppressions=0",
            "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1:exitcode=98"}
HDF5_EXIT_NOISE: list[str] = []


def _hdf5_exit_noise(lines: list[str]) -> bool:
    """HDF5 1.10's own at-exit complaint after a garbled object header (its free lists keep a
    block): "HDF5: infinite loop closing library" and a line of package codes. Not our code."""
    return (bool(lines) and lines[0].startswith("HDF5: infinite loop closing library")
            and all(re.fullmatch(r"[A-Za-z_,\s]*", line) for line in lines[1:]))


def check(cond: bool, what: str) -> None:
    if not cond:
        FAILURES.append(what)
        print("FAIL:", what, flush=True)


# --------------------------------------------------------------------------- LUTs to compare

H, W = 13, 17


def _quality(rng, valid, lo, hi, sigma=False):
    q = dict(n_positions=np.where(valid, 5, 0).astype(np.uint16),
             pixel_z_min=np.where(valid, lo, np.nan).astype(np.float32),
             pixel_z_max=np.where(valid, hi, np.nan).astype(np.float32),
             rms_x=np.full((H, W), 1e-4, np.float32), rms_y=np.full((H, W), 1e-4, np.float32),
             loo_x=np.full((H, W), 2e-4, np.float32), loo_y=np.full((H, W), 2e-4, np.float32))
    if sigma:
        q["sigma_x"] = rng.uniform(1e-4, 1e-3, (H, W)).astype(np.float32)
        q["sigma_y"] = rng.uniform(1e-4, 1e-3, (H, W)).astype(np.float32)
    return q


def poly_lut(rng, degree: int) -> Lut:
    """Coefficients of rays bending like a lens, X ~ 100 mm, per-pixel ranges inside [0.1, 10.7]."""
    d1 = degree + 1
    x = rng.normal(0, 1, (d1, H, W)) * np.array([30.0, 2.0, 0.05, 0.01, 0.003, 0.001])[:d1, None, None]
    y = rng.normal(0, 1, (d1, H, W)) * np.array([30.0, 2.0, 0.05, 0.01, 0.003, 0.001])[:d1, None, None]
    x[0] += 100.0
    valid = rng.random((H, W)) > 0.15
    x[:, ~valid] = np.nan
    y[:, ~valid] = np.nan
    lo = rng.choice([0.1, 0.7, 1.3, 2.0], (H, W))
    hi = rng.choice([9.1, 10.7, 8.3, 10.0], (H, W))
    return Lut("poly", degree, 5.4, 5.3, 0.1, 10.7, x, y, None, valid, **_quality(rng, valid, lo, hi, sigma=True))


NODES = np.array([0.1, 0.7, 1.3, 2.0, 3.3, 4.0, 5.5, 6.1, 7.9, 9.1, 10.7])


def table_lut(rng, kind: str) -> Lut:
    """Tables with NaN nodes (gaps, runs of one node), flat stretches and wiggles."""
    k = NODES.size
    base = 100.0 + 0.08 * NODES[:, None, None] + rng.normal(0, 1e-3, (k, H, W))
    style = rng.integers(0, 4, (H, W))
    wiggle = 0.02 * np.sin(3 * NODES)[:, None, None] * (style == 1)
    flat = (style == 2)
    x = base + wiggle
    x[:, flat] = np.round(x[:, flat], 2)  # equal neighbours: zero secants
    x[:, style == 3] = rng.normal(100, 0.5, (k, int((style == 3).sum())))  # sign changes everywhere
    y = 50.0 - 0.06 * NODES[:, None, None] + rng.normal(0, 1e-3, (k, H, W)) + 0.5 * wiggle
    finite = rng.random((k, H, W)) > 0.22
    finite[:, 0, :4] = True  # whole-run pixels
    x[~finite] = np.nan
    y[~finite] = np.nan
    # A few pixels whose X and Y lose different nodes.
    y[3, 5, :5] = np.nan
    valid = (np.isfinite(x).sum(axis=0) >= 2) & (np.isfinite(y).sum(axis=0) >= 2) & (rng.random((H, W)) > 0.1)
    x[:, ~valid] = np.nan
    y[:, ~valid] = np.nan
    idx = np.arange(k)[:, None, None]
    first = np.where(finite, idx, k).min(axis=0)
    last = np.where(finite, idx, -1).max(axis=0)
    lo = NODES[np.clip(first, 0, k - 1)]
    hi = NODES[np.clip(last, 0, k - 1)]
    return Lut(kind, None, 5.4, 5.3, 0.1, 10.7, x, y, NODES.copy(), valid, **_quality(rng, valid, lo, hi))


def height_map(rng) -> np.ndarray:
    """Heights below, above, on, near (+-5e-10, +-2e-9 mm) and between the nodes; NaN."""
    special = np.concatenate([NODES, NODES - 5e-10, NODES + 5e-10, NODES - 2e-9, NODES + 2e-9,
                              np.float32(NODES).astype(float), [-3.0, -0.2, 11.5, 14.0, np.nan]])
    z = rng.uniform(-1.0, 12.0, (H, W))
    pick = rng.random((H, W)) < 0.5
    z[pick] = rng.choice(special, int(pick.sum()))
    return z


def run_map(tool: str, path: Path, z, extrapolate: bool, env=None):
    zarg = repr(float(z)) if np.ndim(z) == 0 else str(path.with_suffix(".z.f64"))
    if np.ndim(z):
        np.asarray(z, "<f8").tofile(zarg)
    out = path.with_suffix(".out.bin")
    cmd = [tool, "map", str(path), zarg, str(out)] + (["--extrapolate"] if extrapolate else [])
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        return None, f"{' '.join(cmd)} exited {res.returncode}: {res.stderr.strip()}"
    raw = out.read_bytes()
    n = H * W
    x = np.frombuffer(raw[:8 * n], "<f8").reshape(H, W)
    y = np.frombuffer(raw[8 * n:16 * n], "<f8").reshape(H, W)
    flags = np.frombuffer(raw[16 * n:], np.uint8).reshape(H, W)
    return (x, y, flags), None


def compare(label: str, lut: Lut, c_result, z, extrapolate: bool) -> int:
    ev = lut.evaluate(z, extrapolate=extrapolate)
    x, y, flags = c_result
    want_flags = lut.valid.astype(np.uint8) | (ev.in_range.astype(np.uint8) << 1)
    bad = 0
    for name, cv, pv in (("X", x, ev.x), ("Y", y, ev.y)):
        nan_c, nan_p = np.isnan(cv), np.isnan(pv)
        if np.any(nan_c != nan_p):
            r, c = np.argwhere(nan_c != nan_p)[0]
            check(False, f"{label}: {name} NaN in C {nan_c[r, c]} vs Python {nan_p[r, c]} at ({r}, {c}),"
                         f" z={np.broadcast_to(z, (H, W))[r, c]!r}, {int(np.sum(nan_c != nan_p))} pixels")
            bad += 1
        both = ~nan_c & ~nan_p
        err = np.max(np.abs(cv[both] - pv[both]), initial=0.0)
        if err > TOL_MM:
            check(False, f"{label}: {name} differs by {err:.3g} mm")
            bad += 1
    if np.any(flags != want_flags):
        r, c = np.argwhere(flags != want_flags)[0]
        check(False, f"{label}: flags C {flags[r, c]} vs Python {want_flags[r, c]} at ({r}, {c})"
                     f" z={np.broadcast_to(z, (H, W))[r, c]!r}")
        bad += 1
    return int(np.count_nonzero(np.isfinite(ev.x)))


def compare_kinds(tool: str, asan_tool: str) -> None:
    rng = np.random.default_rng(17)
    luts = [(f"poly{d}", poly_lut(rng, d)) for d in range(1, 6)]
    luts += [(kind, table_lut(rng, kind)) for kind in ("linear", "pchip")]
    for name, lut in luts:
        path = OUT / f"{name}.lut.h5"
        save_lut(lut, path)
        lut = load_lut(path)  # what Python reads back (float32 ranges etc.)
        n_values = 0
        for extrapolate in (False, True):
            for i in range(4):
                z = height_map(rng)
                res, err = run_map(tool, path, z, extrapolate)
                check(err is None, f"{name}: {err}")
                if res is not None:
                    n_values += compare(f"{name} map#{i} extrapolate={extrapolate}", lut, res, z, extrapolate)
            for zc in (-0.5, 0.1, 0.7, float(np.float32(0.7)), 3.3 + 4e-10, 4.6, 10.7, 10.7 + 2e-9, 12.0):
                res, err = run_map(tool, path, zc, extrapolate)
                check(err is None, f"{name}: {err}")
                if res is not None:
                    n_values += compare(f"{name} z={zc!r} extrapolate={extrapolate}", lut, res, zc, extrapolate)
        # Single pixels through ptplut_eval (the map path is ptplut_eval_map).
        z = height_map(rng)
        for r, c in zip(rng.integers(0, H, 12), rng.integers(0, W, 12)):
            res = subprocess.run([tool, "pixel", str(path), str(r), str(c), repr(float(z[r, c]))],
                                 capture_output=True, text=True)
            ev = lut.evaluate(z)
            got = res.stdout.split()
            ok = res.returncode == 0 and len(got) == 3
            if ok:
                cx, cy = float(got[0]), float(got[1])
                px, py = ev.x[r, c], ev.y[r, c]
                ok = all((np.isnan(a) and np.isnan(b)) or abs(a - b) <= TOL_MM for a, b in ((cx, px), (cy, py)))
                ok &= int(got[2]) == int(lut.valid[r, c]) | (int(ev.in_range[r, c]) << 1)
            check(ok, f"{name}: pixel ({r}, {c}) z={z[r, c]!r}: C {res.stdout.strip()!r} {res.stderr.strip()!r},"
                      f" Python {ev.x[r, c]!r} {ev.y[r, c]!r}")
        # The sanitizer build on the good file, too.
        z = height_map(rng)
        res, err = run_map(asan_tool, path, z, True, env=ASAN_ENV)
        check(err is None, f"{name} (ASan): {err}")
        if res is not None:
            compare(f"{name} ASan", lut, res, z, True)
        check(n_values > 500, f"{name}: only {n_values} finite values compared")
        print(f"ok  {name:7s} C = Python to {TOL_MM:g} mm ({n_values} values, flags identical)", flush=True)


# --------------------------------------------------------------------------- the height map

def make_height_map(rng, degree: int) -> HeightMap:
    """A rational map per pixel: Z ~ 20 mm over u_p ranges of 10 to 120 projector px, |q_1| < 0.4."""
    centre = rng.uniform(100.0, 1200.0, (H, W))
    scale = rng.uniform(5.0, 60.0, (H, W))
    valid = rng.random((H, W)) > 0.15
    p = rng.normal(0, 1, (degree + 1, H, W)) * np.array([5.0, 20.0, 0.3, 0.05, 0.01, 0.003])[:degree + 1, None, None]
    p[0] += 20.0
    q = rng.uniform(-0.4, 0.4, (1, H, W))
    p[:, ~valid] = np.nan
    q[:, ~valid] = np.nan
    f32 = np.float32
    design = {**Projector().design_attrs, "phase_origin_rad": 0.25, "shift_sign": -1, "unwrap": "heterodyne"}
    return HeightMap(
        degree=degree, direction="x", u_center=centre, u_scale=scale, p=p, q=q, valid=valid,
        u_min=np.where(valid, centre - scale, np.nan).astype(f32), u_max=np.where(valid, centre + scale, np.nan).astype(f32),
        rms_z=np.full((H, W), 0.01, f32), loo_z=np.full((H, W), 0.012, f32),
        sigma_z=np.where(valid, rng.uniform(0.005, 0.05, (H, W)), np.nan).astype(f32),
        n_positions=np.where(valid, 21, 0).astype(np.uint16), design=design, chosen_by="held-out positions",
        provenance={"degree_choice": {"1": 0.01}}, camera_noise=(4.5, 0.02))


def u_map(rng, hm: HeightMap) -> np.ndarray:
    """u_p inside each pixel's range, on its float32 and float64 edges, within and just beyond the
    slack (1e-6 px + |bound| 2^-23), far outside, NaN and infinite."""
    lo, hi = hm.u_min.astype(float), hm.u_max.astype(float)
    tol_lo = 1e-6 + np.abs(lo) * 2.0 ** -23
    tol_hi = 1e-6 + np.abs(hi) * 2.0 ** -23
    t = rng.uniform(0, 1, (H, W))
    choices = [lo + t * (hi - lo), lo, hi, hm.u_center - hm.u_scale, hm.u_center + hm.u_scale,
               lo - 0.5 * tol_lo, hi + 0.5 * tol_hi, lo - tol_lo, hi + tol_hi, lo - 2 * tol_lo, hi + 2 * tol_hi,
               lo - 1e-3, hi + 1e-3, lo - 50.0, hi + 50.0, np.full((H, W), np.nan), np.full((H, W), np.inf),
               np.full((H, W), -np.inf), np.nextafter(lo - tol_lo, -np.inf), np.nextafter(hi + tol_hi, np.inf)]
    pick = rng.integers(0, len(choices), (H, W))
    pick[rng.random((H, W)) < 0.4] = 0  # plenty of values inside
    return np.choose(pick, choices)


def run_height_map(tool: str, path: Path, u, env=None):
    h, w = np.shape(u)
    upath = path.with_suffix(".u.f64")
    np.asarray(u, "<f8").tofile(upath)
    out = path.with_suffix(".hout.bin")
    cmd = [tool, "height-map", str(path), str(upath), str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        return None, f"{' '.join(cmd)} exited {res.returncode}: {res.stderr.strip()}"
    raw = out.read_bytes()
    n = h * w
    z = np.frombuffer(raw[:8 * n], "<f8").reshape(h, w)
    dz = np.frombuffer(raw[8 * n:16 * n], "<f8").reshape(h, w)
    flags = np.frombuffer(raw[16 * n:17 * n], np.uint8).reshape(h, w)
    sigma = np.frombuffer(raw[17 * n:], "<f8").reshape(h, w)
    return (z, dz, flags, sigma), None


def compare_height(label: str, hm: HeightMap, c_result, u) -> tuple[int, int]:
    """C against HeightMap.evaluate; returns (finite values compared, bit-identical ones)."""
    ev = hm.evaluate(u)
    z, dz, flags, sigma = c_result
    want_flags = hm.valid.astype(np.uint8) | (ev.in_range.astype(np.uint8) << 1)
    for name, cv, pv, tol in (("Z", z, ev.z, TOL_MM), ("dZ/du", dz, ev.dz_du, TOL_SLOPE)):
        nan_c, nan_p = np.isnan(cv), np.isnan(pv)
        if np.any(nan_c != nan_p):
            r, c = np.argwhere(nan_c != nan_p)[0]
            check(False, f"{label}: {name} NaN in C {nan_c[r, c]} vs Python {nan_p[r, c]} at ({r}, {c}),"
                         f" u={u[r, c]!r}, {int(np.sum(nan_c != nan_p))} pixels")
        both = ~nan_c & ~nan_p
        err = np.max(np.abs(cv[both] - pv[both]), initial=0.0)
        check(err <= tol, f"{label}: {name} differs by {err:.3g}")
    if np.any(flags != want_flags):
        r, c = np.argwhere(flags != want_flags)[0]
        check(False, f"{label}: flags C {flags[r, c]} vs Python {want_flags[r, c]} at ({r}, {c}) u={u[r, c]!r}")
    want_sigma = np.where(hm.valid, hm.sigma_z.astype(float), np.nan)
    check(np.array_equal(sigma, want_sigma, equal_nan=True), f"{label}: sigma_z differs from /height/quality/sigma_z")
    fin = np.isfinite(ev.z)
    same = int(np.count_nonzero((z[fin] == ev.z[fin]) & (dz[fin] == ev.dz_du[fin])))
    return int(np.count_nonzero(fin)), same


def check_height_design(tool: str, path: Path, hm: HeightMap) -> None:
    res = subprocess.run([tool, "height-info", str(path)], capture_output=True, text=True)
    got = dict(line.split(" ", 1) for line in res.stdout.splitlines())
    d = hm.design
    want = {"degree": str(hm.degree), "direction": hm.direction, "chosen_by": hm.chosen_by,
            "width": str(d["width"]), "height": str(d["height"]),
            "steps": " ".join(str(v) for v in d["steps"]), "shift_sign": str(d["shift_sign"]), "unwrap": d["unwrap"]}
    nums = {"phase_origin_rad": d["phase_origin_rad"], "offset": d["offset"], "amplitude": d["amplitude"],
            "gamma": d["gamma"], "camera_noise_read_var": hm.camera_noise[0], "camera_noise_gain": hm.camera_noise[1]}
    ok = res.returncode == 0 and all(got.get(k) == v for k, v in want.items())
    ok = ok and all(k in got and float(got[k]) == float(v) for k, v in nums.items())
    ok = ok and [float(v) for v in got.get("periods_px", "").split()] == [float(v) for v in d["periods_px"]]
    check(ok, f"height-info of {path.name}: C {got!r} {res.stderr.strip()!r}, Python {want!r} {nums!r}")


def compare_fitted_height(tool: str, asan_tool: str) -> None:
    """A height map fitted to a simulated sweep (scanner-mild, 64 x 48, 5 plate heights), read in C at the
    sweep's own decoded u_p: C = Python, and every sample the map was fitted to is in its pixel's range
    (its extreme samples on the float32 bounds included)."""
    from ptpcore.fit.height import fit_height_map
    from ptpcore.run.scanner import decode_projector
    from ptpcore.simulate.scanner import HeightSweepSource, ScannerRig, scanner_preset

    rig, sim, sc = scanner_preset("scanner-mild", 64, heights=5)
    dec = decode_projector(HeightSweepSource(ScannerRig(rig, sim, sc, seed=2)))
    hm = fit_height_map(dec.u, dec.sigma_u, dec.z_mm, design=rig.projector.design_attrs)
    hm.camera_noise = (dec.noise.read_var, dec.noise.gain)
    h, w = hm.shape
    f32 = np.float32
    zero = np.zeros((h, w), f32)
    lut = Lut("poly", 1, 20.0, 20.0, 0.0, 40.0, np.stack([np.full((h, w), 100.0), np.full((h, w), 2.0)]),
              np.stack([np.full((h, w), 50.0), np.full((h, w), -1.0)]), None, np.ones((h, w), bool),
              np.full((h, w), 9, np.uint16), zero, zero + f32(40.0), zero, zero, zero, zero, height=hm)
    path = OUT / "height-fitted.lut.h5"
    save_lut(lut, path)
    hm = load_lut(path).height
    n_values = n_same = n_samples = n_in = 0
    for k in range(dec.u.shape[0]):
        u = dec.u[k].astype(float)
        res, err = run_height_map(asan_tool if k == 0 else tool, path, u, env=ASAN_ENV if k == 0 else None)
        check(err is None, f"fitted map, height {k}: {err}")
        if res is None:
            continue
        n, same = compare_height(f"fitted map, height {k}", hm, res, u)
        n_values, n_same = n_values + n, n_same + same
        sample = hm.valid & np.isfinite(u)
        n_samples += int(sample.sum())
        n_in += int((res[2][sample] & 2).astype(bool).sum())
    check(n_in == n_samples, f"fitted map: {n_samples - n_in} of the sweep's own samples out of range in C")
    check(n_values > 1000, f"fitted map: only {n_values} values compared")
    print(f"ok  fitted  C = Python on a simulated sweep's own u_p ({n_values} values, {n_same} bit-identical;"
          f" {n_in} of {n_samples} samples in range, degree {hm.degree})", flush=True)


def compare_heights(tool: str, asan_tool: str) -> Path:
    """Height maps of degree 1 to 5 in C and Python; returns the degree-2 file (for the bad-file edits)."""
    rng = np.random.default_rng(34)
    for degree in range(1, 6):
        name = f"height{degree}"
        lut = poly_lut(rng, 2)
        lut.height = make_height_map(rng, degree)
        path = OUT / f"{name}.lut.h5"
        save_lut(lut, path)
        lut = load_lut(path)
        hm = lut.height
        n_values = n_same = 0
        for i in range(6):
            u = u_map(rng, hm)
            res, err = run_height_map(tool, path, u)
            check(err is None, f"{name}: {err}")
            if res is not None:
                n, same = compare_height(f"{name} map#{i}", hm, res, u)
                n_values, n_same = n_values + n, n_same + same
        u = u_map(rng, hm)
        ev = hm.evaluate(u)
        for r, c in zip(rng.integers(0, H, 12), rng.integers(0, W, 12)):
            res = subprocess.run([tool, "height-pixel", str(path), str(r), str(c), repr(float(u[r, c]))],
                                 capture_output=True, text=True)
            got = res.stdout.split()
            ok = res.returncode == 0 and len(got) == 3
            if ok:
                pairs = ((float(got[0]), ev.z[r, c], TOL_MM), (float(got[1]), ev.dz_du[r, c], TOL_SLOPE))
                ok = all((np.isnan(a) and np.isnan(b)) or abs(a - b) <= tol for a, b, tol in pairs)
                ok &= int(got[2]) == int(hm.valid[r, c]) | (int(ev.in_range[r, c]) << 1)
            check(ok, f"{name}: pixel ({r}, {c}) u={u[r, c]!r}: C {res.stdout.strip()!r} {res.stderr.strip()!r},"
                      f" Python {ev.z[r, c]!r} {ev.dz_du[r, c]!r}")
        check_height_design(tool, path, hm)
        u = u_map(rng, hm)
        res, err = run_height_map(asan_tool, path, u, env=ASAN_ENV)
        check(err is None, f"{name} (ASan): {err}")
        if res is not None:
            compare_height(f"{name} ASan", hm, res, u)
        check(n_values > 500, f"{name}: only {n_values} finite values compared")
        print(f"ok  {name:7s} C = Python: Z to {TOL_MM:g} mm, dZ/du to {TOL_SLOPE:g} ({n_values} values,"
              f" {n_same} bit-identical, flags identical, design equal)", flush=True)
    compare_fitted_height(tool, asan_tool)
    # A LUT without /height: the height functions say so.
    for args in (["height-info", str(OUT / "poly2.lut.h5")], ["height-pixel", str(OUT / "poly2.lut.h5"), "1", "1", "5"]):
        res = subprocess.run([asan_tool, *args], capture_output=True, text=True, env=ASAN_ENV)
        check(res.returncode == 1 and "no height" in res.stderr, f"{args[0]} without /height: exit {res.returncode}"
                                                                 f" {res.stderr.strip()!r}")
    print("ok  a LUT without /height: the height functions return PTPLUT_ERR_NO_HEIGHT", flush=True)
    return OUT / "height2.lut.h5"


# --------------------------------------------------------------------------- bad files

def _copy_with(good: Path, name: str, edit) -> Path:
    path = OUT / f"bad-{name}.lut.h5"
    shutil.copyfile(good, path)
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


def _replace(f, name, data):
    del f[name]
    f[name] = data


def _set_attr(f, obj, key, value):
    f[obj].attrs[key] = value


def height_edits() -> dict:
    """Damaged /height groups: each is refused by both readers."""
    h = "height"
    return {
        "height-kind": lambda f: _set_attr(f, h, "kind", "poly"),
        "height-degree-nine": lambda f: _set_attr(f, h, "degree", 9),
        "height-no-degree": lambda f: f[h].attrs.__delitem__("degree"),
        "height-direction": lambda f: _set_attr(f, h, "direction", "z"),
        "height-no-chosen-by": lambda f: f[h].attrs.__delitem__("chosen_by"),
        "height-no-periods": lambda f: f[h].attrs.__delitem__("periods_px"),
        "height-periods-scalar": lambda f: _set_attr(f, h, "periods_px", 20.0),
        "height-periods-nan": lambda f: _set_attr(f, h, "periods_px", np.array([1280.0, np.nan, 20.0])),
        "height-periods-text": lambda f: _set_attr(f, h, "periods_px", "1280, 160, 20"),
        "height-steps-fraction": lambda f: _set_attr(f, h, "steps", np.array([4.0, 4.5, 8.0])),
        "height-steps-length": lambda f: _set_attr(f, h, "steps", np.array([4, 4])),
        "height-width-text": lambda f: _set_attr(f, h, "width", "wide"),
        "height-no-width": lambda f: f[h].attrs.__delitem__("width"),
        "height-shift-fraction": lambda f: _set_attr(f, h, "shift_sign", 0.5),
        "height-gamma-nan": lambda f: _set_attr(f, h, "gamma", np.nan),
        "height-unwrap-number": lambda f: _set_attr(f, h, "unwrap", 3),
        "height-noise-negative": lambda f: _set_attr(f, h, "camera_noise_read_var", -1.0),
        "height-noise-no-gain": lambda f: f[h].attrs.__delitem__("camera_noise_gain"),
        "height-valid-two": lambda f: _replace(f, "height/valid", np.full(f["height/valid"].shape, 2, np.uint8)),
        "height-p-nan-valid": lambda f: _replace(f, "height/p", np.full(f["height/p"].shape, np.nan)),
        "height-p-shape": lambda f: _replace(f, "height/p", np.zeros((2, 3, 3))),
        "height-p-degree": lambda f: _set_attr(f, h, "degree", 3),
        "height-q-one": lambda f: _replace(f, "height/q", np.ones(f["height/q"].shape)),
        "height-q-2d": lambda f: _replace(f, "height/q", f["height/q"][0]),
        "height-scale-zero": lambda f: _replace(f, "height/u_scale", np.zeros(f["height/u_scale"].shape)),
        "height-centre-text": lambda f: _replace(f, "height/u_center", np.array([b"a", b"b"])),
        "height-no-u-min": lambda f: f["height/quality"].__delitem__("u_min"),
        "height-sigma-shape": lambda f: _replace(f, "height/quality/sigma_z", np.zeros((3, 3), np.float32)),
        "height-no-n-positions": lambda f: f["height/quality"].__delitem__("n_positions"),
        "height-dataset": lambda f: (f.__delitem__(h), f.create_dataset(h, data=np.zeros(3))),
    }


def bad_files(good_poly: Path, good_table: Path, good_height: Path) -> list[tuple[str, Path]]:
    files = [("missing file", OUT / "does-not-exist.lut.h5")]
    text = OUT / "bad-text.lut.h5"
    text.write_text("format = 'ptp-lut/1'\n" * 50)
    files.append(("text file", text))
    empty = OUT / "bad-empty.lut.h5"
    empty.write_bytes(b"")
    files.append(("empty file", empty))
    data = good_poly.read_bytes()
    for frac in (0.02, 0.1, 0.3, 0.5, 0.8, 0.99):
        p = OUT / f"bad-truncated-{int(frac * 100)}.lut.h5"
        p.write_bytes(data[:int(len(data) * frac)])
        files.append((f"truncated to {frac:.0%}", p))
    p = OUT / "bad-truncated-sig.lut.h5"
    p.write_bytes(data[:8])
    files.append(("signature only", p))
    p = OUT / "bad-garbled.lut.h5"
    garbled = bytearray(data)
    rng = np.random.default_rng(5)
    for i in rng.integers(600, len(garbled), 200):
        garbled[i] = int(rng.integers(0, 256))
    p.write_bytes(bytes(garbled))
    files.append(("garbled bytes", p))

    def foreign(name, build):
        path = OUT / f"bad-{name}.h5"
        with h5py.File(path, "w") as f:
            build(f)
        files.append((name, path))

    foreign("empty-hdf5", lambda f: None)
    foreign("decoded", lambda f: (f.attrs.__setitem__("format", "ptp-decoded/1"),
                                  f.create_dataset("u", data=np.zeros((2, 4, 4), np.float32))))
    foreign("format-number", lambda f: f.attrs.__setitem__("format", 7))
    foreign("format-array", lambda f: f.attrs.__setitem__("format", np.array([1.0, 2.0])))
    edits = {
        "newer-version": lambda f: f.attrs.__setitem__("format", "ptp-lut/2"),
        "other-format": lambda f: f.attrs.__setitem__("format", "ptp-session/1"),
        "no-x": lambda f: f.__delitem__("x"),
        "x-integer": lambda f: _replace(f, "x", np.zeros(f["x"].shape, np.int32)),
        "x-strings": lambda f: _replace(f, "x", np.array([b"a", b"b"])),
        "x-group": lambda f: (f.__delitem__("x"), f.create_group("x")),
        "x-shape": lambda f: _replace(f, "x", np.zeros((2, 3, 3))),
        "x-2d": lambda f: _replace(f, "x", np.zeros((3, 3))),
        "x-scalar": lambda f: _replace(f, "x", 1.0),
        "x-nan-valid": lambda f: f["x"].__setitem__((0, 1, 1), np.nan) if f["valid"][1, 1] else
        f["x"].__setitem__((0, 0, 0), np.nan),
        "valid-two": lambda f: _replace(f, "valid", np.full(f["valid"].shape, 2, np.uint8)),
        "valid-float": lambda f: _replace(f, "valid", np.ones(f["valid"].shape, np.float64)),
        "no-camera": lambda f: f.__delitem__("camera"),
        "width-text": lambda f: f["camera"].attrs.__setitem__("width", "seventeen"),
        "width-zero": lambda f: f["camera"].attrs.__setitem__("width", 0),
        "width-huge": lambda f: f["camera"].attrs.__setitem__("width", 2_000_000_000),
        "width-fraction": lambda f: f["camera"].attrs.__setitem__("width", 16.5),
        "height-array": lambda f: f["camera"].attrs.__setitem__("height", np.array([13, 13])),
        "kind-unknown": lambda f: f["model"].attrs.__setitem__("kind", "spline"),
        "kind-number": lambda f: f["model"].attrs.__setitem__("kind", 3),
        "degree-nine": lambda f: f["model"].attrs.__setitem__("degree", 9),
        "no-degree": lambda f: f["model"].attrs.__delitem__("degree"),
        "z-scale-zero": lambda f: f["model"].attrs.__setitem__("z_scale", 0.0),
        "z-center-nan": lambda f: f["model"].attrs.__setitem__("z_center", np.nan),
        "no-quality": lambda f: f.__delitem__("quality"),
        "no-zmin": lambda f: f["quality"].__delitem__("z_min"),
        "zmin-shape": lambda f: _replace(f, "quality/z_min", np.zeros((3, 3), np.float32)),
        "zmin-nan-valid": lambda f: _replace(f, "quality/z_min", np.full(f["valid"].shape, np.nan, np.float32)),
        "zmin-above-zmax": lambda f: _replace(f, "quality/z_min", np.full(f["valid"].shape, 99.0, np.float32)),
    }
    for name, edit in edits.items():
        path = _copy_with(good_poly, name, edit)
        files.append((name, path))
    table_edits = {
        "no-nodes": lambda f: f.__delitem__("z_nodes"),
        "nodes-descending": lambda f: _replace(f, "z_nodes", f["z_nodes"][()][::-1].copy()),
        "nodes-nan": lambda f: _replace(f, "z_nodes", np.where(np.arange(f["z_nodes"].size) == 3, np.nan,
                                                                f["z_nodes"][()])),
        "nodes-one": lambda f: _replace(f, "z_nodes", np.array([1.0])),
        "nodes-2d": lambda f: _replace(f, "z_nodes", np.zeros((2, 2))),
        "nodes-count": lambda f: _replace(f, "z_nodes", np.arange(5.0)),
        "table-inf": lambda f: f["x"].__setitem__((0, 0, 0), np.inf),
        "table-one-node": lambda f: _replace(f, "x", np.where(np.arange(f["x"].shape[0])[:, None, None] == 0,
                                                               f["x"][()], np.nan)),
    }
    for name, edit in table_edits.items():
        files.append((name, _copy_with(good_table, name, edit)))
    for name, edit in height_edits().items():
        files.append((name, _copy_with(good_height, name, edit)))
    return files


def check_bad_files(tool: str, asan_tool: str, good_poly: Path, good_table: Path, good_height: Path) -> None:
    n = 0
    for label, path in bad_files(good_poly, good_table, good_height):
        for t, env in ((tool, None), (asan_tool, ASAN_ENV)):
            res = subprocess.run([t, "info", str(path)], capture_output=True, text=True, env=env)
            err = res.stderr.strip()
            sanitizer = "Sanitizer" in err or "runtime error" in err
            lines = err.splitlines()
            if len(lines) > 1 and _hdf5_exit_noise(lines[1:]):
                HDF5_EXIT_NOISE.append(f"{label} ({Path(t).name})")
                lines = lines[:1]
            check(res.returncode == 1 and not sanitizer and len(lines) == 1 and lines[0].startswith("ptplut: ")
                  and str(path) in lines[0],
                  f"{label} ({Path(t).name}): exit {res.returncode}, stderr {err[:2000]!r}")
        try:
            load_lut(path)
            check(False, f"{label}: the Python reader accepts {path.name} but the C reader refuses it")
        except FileFormatError:
            pass
        n += 1
        print(f"ok  refused: {label:22s} {lines[0] if lines else ''}", flush=True)
    print(f"ok  {n} damaged or foreign files refused with a message, clean under AddressSanitizer", flush=True)
    if HDF5_EXIT_NOISE:
        print(f"note: HDF5 itself complained at exit (its free lists, not ptplut.c) after: {', '.join(HDF5_EXIT_NOISE)}")


def main(argv) -> int:
    if len(argv) != 3:
        print(__doc__)
        return 2
    tool, asan_tool = (str(Path(a).resolve()) for a in argv[1:])
    if OUT.exists():
        shutil.rmtree(OUT)
    OUT.mkdir()
    compare_kinds(tool, asan_tool)
    good_height = compare_heights(tool, asan_tool)
    check_bad_files(tool, asan_tool, OUT / "poly3.lut.h5", OUT / "pchip.lut.h5", good_height)
    # A fixed-length (not variable-length) format string is text too.
    p = OUT / "fixed-string.lut.h5"
    shutil.copyfile(OUT / "linear.lut.h5", p)
    with h5py.File(p, "r+") as f:
        f.attrs["format"] = np.bytes_(b"ptp-lut/1")
        f["model"].attrs["kind"] = np.bytes_(b"linear")
    res = subprocess.run([asan_tool, "info", str(p)], capture_output=True, text=True, env=ASAN_ENV)
    check(res.returncode == 0 and res.stdout.startswith("linear"), f"fixed-length strings: {res.stderr.strip()}")
    if FAILURES:
        print(f"\n{len(FAILURES)} FAILURES")
        return 1
    print("\nall C reader checks passed")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
