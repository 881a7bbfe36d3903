"""The ``ptp`` command line.

Every command is a thin layer over one engine call; bad input ends with exit
code 2 and one line naming the culprit, never a traceback.
"""

from __future__ import annotations

import argparse
import gc
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from ptpcore import __version__
from ptpcore.atomic import remove_temporaries
from ptpcore.cli.progress import progress_bar
from ptpcore.cli.safety import (EXIT_BAD_INPUT, EXIT_PARTIAL, EXIT_SIGINT, EXIT_SIGTERM, OneLineParser,
                                Terminated,
                                add_input, add_output, existing_dir, existing_file, guard_arguments,
                                positive_int, quiet_broken_pipe, seed, signals_as_interrupts,
                                termination_requested)
from ptpcore.errors import Cancelled, OutputError, PtpError
from ptpcore.io.outputs import Output, check_output_file, check_output_folder, guard_outputs
from ptpcore.rig import position_label


# --------------------------------------------------------------------------- commands

def cmd_simulate(args) -> int:
    from dataclasses import replace

    from ptpcore.simulate.virtual_rig import preset, scaled_preset, simulate_dataset

    # OUT_DIR passed the output guard (main) before this runs.
    if args.preset.startswith("scanner-"):
        return _simulate_scanner(args)
    if args.acceptance:
        raise PtpError("--acceptance goes with a scanner preset (--preset scanner-mild or scanner-rough)")
    rig, settings = preset(args.preset)
    if args.width or args.height or args.positions:
        # Same field of view and lens with another sensor size (see scaled_preset).
        rig, settings = scaled_preset(args.preset, args.width or rig.camera.width, args.height,
                                      args.positions)
    if args.drift_um is not None and not args.repeat:
        raise ValueError("--drift-um moves the camera before the repeat position: give --repeat too")
    if args.repeat:  # the first position again at the end (ptp-dataset/2 [stage] repeat_z_mm)
        rig = replace(rig, stage=replace(rig.stage, repeat_z_mm=(rig.stage.z_mm[0],)))
        settings = replace(settings, drift_um=tuple(args.drift_um or (0.0, 0.0)))
    if args.gray:
        from ptpcore.decode.patterns import gray_code_rig
        rig = gray_code_rig(rig, args.gray, inverse=args.gray_inverse, references=args.references)
    elif args.gray_inverse or args.references:
        raise PtpError("--gray-inverse and --references go with --gray LEVELS")
    if args.heterodyne:
        if args.gray:
            raise PtpError("--heterodyne and --gray are two ways to unwrap: give one")
        from ptpcore.decode.patterns import heterodyne_rig
        rig = heterodyne_rig(rig, args.heterodyne, args.heterodyne_steps)
    elif args.heterodyne_steps:
        raise PtpError("--heterodyne-steps goes with --heterodyne PERIODS")
    bar = progress_bar(args)
    try:
        out = simulate_dataset(args.out_dir, rig, settings, seed=args.seed, progress=bar,
                               image_ext=".tif" if args.tiff else ".png")
    finally:
        bar.close()
    per_position = rig.fringes.frames_per_position + 2 * rig.has_references
    n = (rig.stage.n_positions + len(rig.stage.repeat_z_mm)) * per_position
    print(f"wrote {n} images of {rig.camera.width}x{rig.camera.height} ({args.preset} preset, seed {args.seed})"
          f" and truth.h5 to {out}")
    return 0


def _simulate_scanner(args) -> int:
    """``ptp simulate --preset scanner-*``: the LCD sweep, the plate's height sweep and object scans."""
    from ptpcore.simulate.scanner import ACCEPTANCE_FOLDER, scanner_preset, simulate_scanner_dataset

    for flag in ("repeat", "drift_um", "gray", "gray_inverse", "references", "heterodyne", "heterodyne_steps",
                 "positions"):
        if getattr(args, flag):
            raise PtpError(f"--{flag.replace('_', '-')} is not available with the scanner presets")
    rig, sim, scanner = scanner_preset(args.preset, args.width, args.height)
    bar = progress_bar(args)
    try:
        out = simulate_scanner_dataset(args.out_dir, rig, sim, scanner, seed=args.seed, progress=bar,
                                       image_ext=".tif" if args.tiff else ".png", acceptance=args.acceptance)
    finally:
        bar.close()
    accept = f", VDI/VDE 2634-2 acceptance scans in {out / ACCEPTANCE_FOLDER}" if args.acceptance else ""
    print(f"wrote a {rig.camera.width}x{rig.camera.height} scanner dataset ({args.preset} preset, seed {args.seed}):"
          f" {rig.stage.n_positions} LCD positions, {len(rig.height.z_mm)} plate heights, scans in"
          f" {out / 'scans'}{accept}, truth in truth.h5, scanner_truth.h5 and each scan's truth.h5, to {out}")
    return 0


def cmd_calibrate(args) -> int:
    from ptpcore.fit.settings import FitSettings
    from ptpcore.run.session import new_session, save_session

    _check_calibrate_outputs(args)
    _check_height_sweep(args.dataset_dir)
    # Validates rig.toml, the design and every image in one pass, before the long decode.
    session = new_session(args.dataset_dir, FitSettings.from_flags(args), out=args.out)
    if args.session:
        save_session(session, args.session)
    return _finish_session(args, session, args.session, Path(args.out), validate=False)


def _check_height_sweep(dataset_dir) -> None:
    """A dataset's height sweep (``[projector]``, ``[height]``): every frame present and readable
    (headers), before the long decode of the LCD sweep; nothing without one."""
    from ptpcore.io.dataset import validate_dataset
    from ptpcore.rig import load_rig

    rig = load_rig(dataset_dir)
    if rig.height is not None:
        validate_dataset(dataset_dir, rig.height_rig(), check_design=False)


def _check_calibrate_outputs(args) -> None:
    """``--out`` and ``--session`` checked before anything is decoded (the output guard of :func:`main`,
    again for a caller that runs the command without it)."""
    guard_outputs([Output(Path(args.out), "lut", "--out"),
                   *([Output(Path(args.session), "session", "--session", hint=_SESSION_EXISTS)]
                     if args.session else [])],
                  inputs=[args.dataset_dir], force=args.force)


def cmd_resume(args) -> int:
    from ptpcore.run.session import load_session

    session = load_session(args.session_file)
    out = args.out or session.out
    if not out:
        raise OutputError(f"{args.session_file}: the session names no LUT file; give --out FILE.lut.h5")
    if Path(out).resolve() == Path(args.session_file).resolve():
        raise OutputError(f"{out}: is the session file; give --out another name")
    # The LUT the session names was checked (or --force given) when the calibration started.
    check_output_file(out, "lut", force=args.force or not args.out,
                      inputs=[session.dataset] if session.dataset else [])
    print(f"{args.session_file}: resuming after stage '{session.stage}'")
    return _finish_session(args, session, args.session_file, Path(out), validate=True)


def _finish_session(args, session, session_path, out: Path, validate: bool) -> int:
    """Run a session's remaining stages through the one door (saved after each), write the LUT, report.

    Exit 0, or :data:`EXIT_PARTIAL` when the height map failed (the XY LUT written, the reason printed).
    """
    from ptpcore.run.calibration import calibrate_session

    bar = progress_bar(args)
    try:
        result = calibrate_session(session, session_path, validate=validate, out=out, progress=bar)
    finally:
        bar.close()
    print(_lut_report(session.lut, out))  # the drift among it (/provenance drift)
    fitted = result.fitted_samples()
    if fitted is not None:
        from ptpcore.evaluate.lut_report import fit_width
        from ptpcore.evaluate.residuals import residual_field

        field = residual_field(session.lut, fitted, session.positions)
        print("\n".join(out for line in field.lines() for out in fit_width("  " + line)))
    if result.partial:
        print(f"ptp: partial: {out} holds the XY LUT without /height; {result.height_error}", file=sys.stderr)
        return EXIT_PARTIAL
    return 0

def _lut_report(lut, path) -> str:
    """What ``ptp calibrate``, ``resume`` and ``inspect`` print of a LUT: its report
    (:class:`ptpcore.evaluate.lut_report.LutReport`), every line within 100 columns."""
    from ptpcore.evaluate.lut_report import LutReport

    return LutReport.of(lut, path).text()


def cmd_decode(args) -> int:
    from ptpcore.io.dataset import DatasetSource
    from ptpcore.run.decoding import decode_dataset

    # --out passed the output guard (main): not an input, not a folder, its folder writable, an existing
    # ptp-decoded/1 file replaced only with --force.
    source = DatasetSource(args.dataset_dir)
    positions = _parse_positions(args.positions, source.rig.stage.n_positions) if args.positions else None
    source.validate(check_design=False)
    bar = progress_bar(args)
    try:  # written position by position: one position's maps in memory
        run = decode_dataset(source, positions, min_fraction=args.min_valid / 100.0, progress=bar, out=args.out,
                             compression=args.compression)
    finally:
        bar.close()
    rig = source.rig
    n_done = len(positions) if positions is not None else rig.stage.n_positions
    print(f"{args.out}: ptp-decoded/1, {n_done} position(s), direction(s)"
          f" {', '.join(rig.fringes.directions)}, {rig.camera.width}x{rig.camera.height} px")
    for (k, d), frac in run.valid_fraction.items():
        src = run.noise_sources.get((k, d))
        print(f"  position {k} (z = {rig.stage.z_mm[k]:g} mm) {d}: {100 * frac:.1f} % valid"
              + (f"; noise from the {src}" if src else ""))
    return 0


def _parse_positions(text: str, k_total: int) -> list[int]:
    """``"0,2,5-7"`` -> ``[0, 2, 5, 6, 7]``; every index must exist."""
    out = []
    for part in text.split(","):
        part = part.strip()
        try:
            if "-" in part[1:]:
                a, b = part.split("-", 1)
                out.extend(range(int(a), int(b) + 1))
            else:
                out.append(int(part))
        except ValueError:
            raise ValueError(f"--positions: {part!r} is not a position index or range (e.g. 0,2,5-7)") from None
    bad = [k for k in out if not 0 <= k < k_total]
    if bad:
        raise ValueError(f"--positions: {bad[0]} does not exist (the dataset has {k_total}: 0 to {k_total - 1})")
    return out


def cmd_inspect(args) -> int:
    from ptpcore.io.lutfile import load_lut

    lut = load_lut(args.lut_file)
    print(_lut_report(lut, args.lut_file))
    return 0


def cmd_apply(args) -> int:
    from ptpcore.io.lutfile import load_lut
    from ptpcore.io.pointcloud import POINT_CLOUD_SUFFIXES, write_point_cloud

    out = Path(args.out)
    if out.suffix.lower() not in POINT_CLOUD_SUFFIXES:
        raise ValueError(f"--out {out}: must end in {', '.join(POINT_CLOUD_SUFFIXES)}")
    lut = load_lut(args.lut_file)
    z, z_text = _height_argument(args.z, lut.shape)
    cloud = lut.points(z, extrapolate=args.extrapolate)
    if cloud.n_points == 0:
        raise ValueError(f"{args.lut_file}: no point at {z_text} ({cloud.summary()}); the LUT covers"
                         f" z {lut.z_min:g} .. {lut.z_max:g} mm" + ("" if args.extrapolate else
                                                                    " (--extrapolate keeps heights outside it)"))
    write_point_cloud(cloud, out, comment=f"ptp apply {Path(args.lut_file).name} --z {args.z}"
                      + (" --extrapolate" if args.extrapolate else ""))
    print(f"{out}: {cloud.summary()}")
    return 0


def cmd_reconstruct(args) -> int:
    """``ptp reconstruct SCAN_DIR --lut F.lut.h5 --out cloud.ply``: the scanner's point cloud."""
    from ptpcore.io.pointcloud import POINT_CLOUD_SUFFIXES, write_point_cloud
    from ptpcore.run.scanner import reconstruct

    out = Path(args.out)
    if out.suffix.lower() not in POINT_CLOUD_SUFFIXES:
        raise ValueError(f"--out {out}: must end in {', '.join(POINT_CLOUD_SUFFIXES)}")
    lut = _load_scanner_lut(args.lut)
    bar = progress_bar(args)
    try:
        views = reconstruct(args.scan_dir, lut, progress=bar)
    finally:
        bar.close()
    for i, view in enumerate(views):
        path = out if len(views) == 1 else out.with_name(f"{out.stem}.view{i:03d}{out.suffix}")
        if view.cloud.n_points == 0:
            raise ValueError(f"{args.scan_dir}: no point in view {i} ({view.cloud.summary()})")
        write_point_cloud(view.cloud, path, comment=f"ptp reconstruct {Path(args.scan_dir).name} --lut"
                                                    f" {Path(args.lut).name}")
        print(f"{path}: {view.cloud.summary()}")
    return 0


def _load_scanner_lut(path):
    """A LUT with the scanner's height map (``ptp reconstruct``, ``ptp acceptance``); else one clear error."""
    from ptpcore.io.lutfile import load_lut

    lut = load_lut(path)
    if lut.height is None:
        raise ValueError(f"{path}: the LUT has no height map (/height); calibrate a dataset with a height"
                         " sweep ([projector] and [height] in rig.toml)")
    return lut


def cmd_acceptance(args) -> int:
    """``ptp acceptance DATASET SCANS... --lut F.lut.h5 --out REPORT.json``: VDI/VDE 2634-2 on both
    scanner calibrations (the LUT's height map, the conventional camera-projector pinholes)."""
    import json

    from ptpcore.atomic import write_text_atomic
    from ptpcore.evaluate.acceptance_png import acceptance_png
    from ptpcore.evaluate.vdi2634 import evaluate_acceptance, format_acceptance, parse_mpe
    from ptpcore.run.acceptance import conventional_calibration, reconstruct_scans

    mpe = parse_mpe(args.mpe)
    scans = _acceptance_scans(args.scans)
    png = Path(args.png) if args.png else Path(args.out).with_suffix(".png")
    if not args.png:  # the page's default name, beside the report (--out, --png: the guard of main)
        guard_outputs([Output(Path(args.out), "report", "--out"), Output(png, "png", "the page of plots")],
                      inputs=[args.dataset_dir, args.lut, *scans], force=args.force)
    lut = _load_scanner_lut(args.lut)
    bar = progress_bar(args)
    try:
        conventional = None
        if args.conventional:
            conventional = conventional_calibration(args.dataset_dir,
                                                    progress=lambda f, m: bar(0.3 * f, f"conventional: {m}"))
        points = reconstruct_scans(scans, lut, conventional=conventional,
                                   progress=lambda f, m: bar(0.3 + 0.65 * f, m))
        report = evaluate_acceptance(points, mpe_mm=mpe, seed=args.seed)
        bar(0.97, "writing the report")
    finally:
        bar.close()
    js = {"dataset": str(args.dataset_dir), "lut": str(args.lut), "scans": [str(s) for s in scans],
          **report.to_json_dict(),
          "points": {sp.name: sp.counts for sp in points}}
    if conventional is not None and hasattr(conventional, "to_json_dict"):
        # both pinholes with every parameter's standard error: a calibration done well or not
        js["conventional_calibration"] = conventional.to_json_dict()
    write_text_atomic(args.out, json.dumps(js, indent=1, allow_nan=False) + "\n")
    acceptance_png(report, png, title=f"VDI/VDE 2634-2 acceptance: {Path(args.dataset_dir).name},"
                                      f" {len(scans)} poses")
    print(format_acceptance(report))
    print(f"report written to {args.out}, plots to {png}")
    return 0


def _acceptance_scans(args_scans) -> list[Path]:
    """SCANS: scan folders (``scan.toml``), or folders of them, in the order given; each names its
    artefact (``artefact.toml``) or has the simulator's truth."""
    from ptpcore.evaluate.vdi2634 import ARTEFACT_FILE, scan_artefact
    from ptpcore.run.acceptance import scan_folders
    from ptpcore.simulate.scanner import SCAN_TRUTH_FILE

    out = scan_folders(args_scans)
    for folder in out:  # which artefact each scan shows, before any decoding
        if (folder / ARTEFACT_FILE).exists():
            scan_artefact(folder)
        elif not (folder / SCAN_TRUTH_FILE).exists():
            raise ValueError(f"{folder}: no {ARTEFACT_FILE} saying which artefact it shows (kind, diameter_mm,"
                             " distance_mm) and no simulator truth")
    return out


def _height_argument(text: str, shape) -> tuple[object, str]:
    """``--z``: a height map file, or one height (mm) for every pixel."""
    from ptpcore.io.pointcloud import read_height_map

    if Path(text).is_file():
        return read_height_map(text, shape), text
    try:
        z = float(text)
    except ValueError:
        raise ValueError(f"--z {text}: neither a height in mm nor an existing height-map file") from None
    if not np.isfinite(z):
        raise ValueError(f"--z {text}: the height must be a finite number of mm")
    return z, f"z = {z:g} mm"


def _diff_exact(args) -> int:
    """``ptp diff A B --exact``: every dataset and attribute equal (the time of writing and the program's
    version aside); exit 0 identical, 1 not (each difference one line)."""
    from ptpcore.evaluate.lutcompare import compare_lut_files

    if args.json or args.png:
        raise ValueError("--exact compares the files and writes nothing: leave out --json and --png")
    result = compare_lut_files(args.lut_a, args.lut_b, ignore=("created", "software", *args.ignore))
    print("\n".join(result.lines()))
    return 0 if result.equal else 1


def cmd_diff(args) -> int:
    """``ptp diff A B``: exit 0 consistent, 1 differ (2 on bad input, from :func:`main`)."""
    import json

    from ptpcore.atomic import atomic_path
    from ptpcore.evaluate.diff import diff_luts, diff_png
    from ptpcore.io.lutfile import load_lut

    if args.exact:
        return _diff_exact(args)
    # --json and --png passed the output guard (main): never an input LUT, a file of another kind or a
    # read-only folder; an existing file replaced only with --force.
    a, b = load_lut(args.lut_a), load_lut(args.lut_b)
    r = diff_luts(a, b, tolerance_sigma=args.tolerance_sigma, tolerance_um=args.tolerance_um,
                  max_fraction=args.max_fraction, common_false_alarm=args.common_false_alarm)
    print(f"{args.lut_a} vs {args.lut_b}: {r.n_pixels} common pixels, z {r.z[0]:g} .. {r.z[-1]:g} mm"
          f" ({r.z.size} heights)")
    print(f"  models              {r.models[0]} | {r.models[1]}"
          + ("" if r.like_with_like else "  (UNLIKE: part of any difference is the models')"))
    print(f"  difference          RMS {r.rms_um:.3f} µm, 95th percentile {r.p95_um:.3f} µm, max {r.max_um:.3f} µm")
    if np.isfinite(r.predicted_rms_um):
        print(f"  predicted (sigma)   RMS {r.predicted_rms_um:.3f} µm; observed / predicted {r.ratio:.2f}")
    tol = f"{r.tolerance_sigma:g} sigma" + (f", at least {r.tolerance_um:g} µm" if r.tolerance_um else "")
    print(f"  beyond tolerance    {100 * r.fraction_beyond:.2f} % of the pixels ({tol}: per-pixel false-alarm"
          f" rate at most {100 * r.pixel_false_alarm:.2g} %; limit {100 * r.max_fraction:g} %)")
    for axis, c in (("x", r.common_x), ("y", r.common_y)):
        if not c.assessed:
            print(f"  common mode {axis}       mean shift {c.shift_um:+.3f} µm: not assessed (its standard error needs"
                  f" 4 x 4 blocks of {c.block_px} px at the LUTs' smoothing scale; the image is smaller)")
            continue
        print(f"  common mode {axis}       mean shift {c.shift_um:+.3f} µm, standard error {c.se_um:.3f} µm"
              f" ({c.n_blocks} blocks of {c.block_px} px): t = {c.t:+.2f}, limit {c.critical:.2f}"
              + (" FLAGGED" if c.flagged else ""))
    if r.height is not None:
        hd = r.height
        print(f"  height map Z        {hd.n_pixels} common pixels: RMS {hd.rms_um:.3f} µm, 95th percentile"
              f" {hd.p95_um:.3f} µm, max {hd.max_um:.3f} µm; predicted RMS {hd.predicted_rms_um:.3f} µm, observed /"
              f" predicted {hd.ratio:.2f}; {100 * hd.fraction_beyond:.2f} % beyond tolerance")
    print(f"  verdict             {r.verdict_words()} (common-mode false-alarm rate {100 * r.common_false_alarm:g} %)")
    if args.json:
        with atomic_path(args.json) as tmp:
            Path(tmp).write_text(json.dumps({"a": str(args.lut_a), "b": str(args.lut_b), **r.summary()}, indent=1))
    if args.png:
        diff_png(r, args.png, title=f"LUT difference per pixel: {Path(args.lut_a).name} vs {Path(args.lut_b).name}")
    return 0 if r.consistent else 1


def cmd_demo(args) -> int:
    if args.out:
        check_output_folder(args.out, force=args.force)
    workdir = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="ptp-demo-"))
    try:
        return _demo(args, workdir)
    finally:
        if not args.out:  # the simulated images of a temporary folder (169 MB for realistic) go
            shutil.rmtree(workdir, ignore_errors=True)


def _demo(args, workdir: Path) -> int:
    """Simulate into ``workdir``, calibrate on every second position through the one door, report the others."""
    from ptpcore.fit.settings import FitSettings
    from ptpcore.run.calibration import calibrate_session
    from ptpcore.run.session import new_session
    from ptpcore.simulate.virtual_rig import load_truth, preset, simulate_dataset

    rig, sim = preset(args.preset)
    k = rig.stage.n_positions
    cal, held = list(range(0, k, 2)), list(range(1, k, 2))
    settings = FitSettings.from_flags(args)
    if settings.stage_sigma_um == 0.0:  # the simulated stage's own error, as its datasheet would say
        settings = settings.with_changes(stage_sigma_um=float(sim.stage_error_um))
    where = str(workdir) if args.out else "a temporary folder (removed at the end)"
    print(f"simulating the '{args.preset}' rig ({rig.camera.width}x{rig.camera.height} px, {k} positions)"
          f" into {where} ...", flush=True)
    bar = progress_bar(args)
    try:
        simulate_dataset(workdir, rig, sim, seed=args.seed, progress=bar)
        print(f"calibrating on every second position ({len(cal)} of {k}) as `ptp calibrate` does ...", flush=True)
        session = new_session(workdir, settings, validate=False)
        # Every position decoded (the held-out ones are judged), the LUT fitted on the calibration ones.
        calibrate_session(session, stop_after="samples", progress=lambda f, m: bar(0.5 * f, m))
        session.positions = tuple(cal)
        result = calibrate_session(session, progress=lambda f, m: bar(0.5 + 0.5 * f, m))
    finally:
        bar.close()
    truth, sim, _ = load_truth(workdir)
    _demo_report(args, result, truth, sim, cal, held)
    if args.compare:
        _demo_compare(args, result, truth)
    return 0


def _demo_report(args, result, truth, sim, cal, held) -> None:
    """The demo's summary: the design check, the LUT (its model and why), its accuracy at the held-out positions."""
    from ptpcore.decode.patterns import design_check
    from ptpcore.evaluate.accuracy import held_out_accuracy
    from ptpcore.evaluate.lut_report import LutReport
    from ptpcore.fit.models import describe_lut

    session, lut = result.session, result.lut
    rig, samples = session.rig, session.samples
    k = rig.stage.n_positions
    # The LUT's own predicted 1-sigma per pixel (noise, stage and model parts; both axes pooled)
    pred = np.sqrt(0.5 * (lut.sigma_x ** 2 + lut.sigma_y ** 2)) if lut.sigma_x is not None else None
    acc = held_out_accuracy(lut, truth, rig.stage.z_mm, held, None if pred is None else [pred] * len(held))
    med_b = float(np.nanmedian(samples.modulation[samples.valid]))
    med_a = float(np.nanmedian(samples.background[samples.valid]))
    report = design_check(rig, modulation_dn=med_b, noise_dn=float(sim.noise_dn(rig.camera, med_a)))
    valid_frac = samples.valid.mean(axis=(1, 2))
    print()
    print(f"PTP demo: '{args.preset}' rig, camera {rig.camera.width}x{rig.camera.height} {rig.camera.bit_depth}-bit,"
          f" {k} positions z = {min(rig.stage.z_mm):g} .. {max(rig.stage.z_mm):g} mm")
    print(f"  design check        {'ok' if report.ok else 'PROBLEMS: ' + '; '.join(i.message for i in report.failures())}")
    print(f"  valid pixels        {100 * valid_frac.min():.1f} .. {100 * valid_frac.max():.1f} % per position")
    print(f"  median modulation   {med_b:.1f} grey levels")
    print(f"  LUT                 {describe_lut(lut)}; fitted on {len(cal)} positions, valid for"
          f" {100 * lut.valid.mean():.1f} % of pixels")
    print("\n".join(LutReport.of(lut).choice_lines()) or f"  (model {session.settings.model}: chosen by --model)")
    print(f"  held-out accuracy at {len(held)} positions against the simulator's exact rays,"
          " per-axis error (X and Y errors pooled):")
    print(f"    RMS {acc.rms_um:.2f} µm   95th percentile {acc.p95_um:.2f} µm   max {acc.max_um:.2f} µm")
    if acc.predicted_rms_um is not None:
        print(f"    predicted by the LUT's sigma maps: RMS {acc.predicted_rms_um:.2f} µm"
              f"  (observed / predicted = {acc.rms_um / acc.predicted_rms_um:.2f})")
    print("    per-axis RMS per position: " + "; ".join(f"{position_label(p, rig.stage.z_mm[p])}: {e:.2f} µm"
                                                         for p, e in zip(held, acc.per_position_rms_um)))


def _demo_compare(args, result, truth) -> None:
    from ptpcore.evaluate import compare, format_summary
    from ptpcore.fit.models import describe_lut

    session = result.session
    print()
    print(f"3DSTC comparison: each method fitted anew on every second position (PTP: plain poly; PTP smooth;"
          f" 3DSTC: pinhole + Brown); the demo's LUT above is {describe_lut(result.lut)}")
    from ptpcore.fit.corrected import correct_all

    # Every position corrected as cmd_compare corrects it (the glass, flatness, --refine-stage)
    samples = correct_all(session.samples, session.rig, refine=session.settings.refine_stage)[0]
    out = compare(samples, session.rig, truth=truth, seed=args.seed, degree=session.settings.degree)
    print(format_summary(out))


def cmd_compare(args) -> int:
    import json

    from ptpcore.atomic import write_text_atomic
    from ptpcore.evaluate import compare, format_summary
    from ptpcore.io.dataset import DatasetSource
    from ptpcore.errors import DatasetError
    from ptpcore.fit.corrected import correct_all
    from ptpcore.run.pipeline import collect_samples
    from ptpcore.simulate.virtual_rig import TRUTH_FILE, load_truth

    # --out passed the output guard (main) before this runs.
    source = DatasetSource(args.dataset_dir)
    truth = None
    truth_path = Path(args.dataset_dir) / TRUTH_FILE
    if truth_path.exists():
        try:
            truth, _, _ = load_truth(truth_path)
        except (OSError, KeyError, ValueError) as exc:
            raise DatasetError(f"{truth_path}: unreadable ground truth ({exc})") from None
    bar = progress_bar(args)
    try:
        samples = collect_samples(source, progress=bar)
        # The cover glass, a measured flatness and (--refine-stage) the stage pose, before any fit.
        samples = correct_all(samples, source.rig, refine=args.refine_stage)[0]
        result = compare(samples, source.rig, truth=truth, seed=args.seed, split=args.split,
                         n_points=args.points, rational=args.rational, model=args.model, degree=args.degree,
                         with_smooth=args.smooth, progress=bar)
    finally:
        bar.close()
    write_text_atomic(args.out, json.dumps(result.to_json_dict(), indent=1, allow_nan=False) + "\n")
    print(format_summary(result))
    print(f"report written to {args.out}" + ("" if truth is None else f" (with {TRUTH_FILE} as exact truth)"))
    return 0


# --------------------------------------------------------------------------- parser

def _add_diff_parser(sub) -> None:
    """The ``ptp diff`` subcommand."""
    df = sub.add_parser("diff", help="are two LUTs of one camera consistent within their predicted noise?",
                        description="Per-pixel difference of two ptp-lut/1 files over the pixels and heights"
                                    " both cover, against the difference their sigma maps predict, and the"
                                    " mean shift of the image against its standard error. Exit 0:"
                                    " consistent; 1: they differ; 2: bad input.")
    add_input(df, "lut_a", metavar="A.lut.h5", kind="lut", type=existing_file, help="the first LUT (ptp-lut/1)")
    add_input(df, "lut_b", metavar="B.lut.h5", kind="lut", type=existing_file,
              help="the second LUT, of the same camera (ptp-lut/1)")
    add_output(df, "--json", metavar="FILE", kind="report", help="write the numbers and the verdict as JSON")
    add_output(df, "--png", metavar="FILE", kind="png",
               help="write the difference map (in units of the tolerance) as PNG")
    df.add_argument("--tolerance-sigma", type=float, default=3.0, metavar="K",
                    help="a pixel is beyond tolerance above K predicted sigmas of the difference (default 3)")
    df.add_argument("--tolerance-um", type=float, default=0.0, metavar="U",
                    help="absolute floor of the tolerance in µm (needed for LUTs without sigma maps)")
    df.add_argument("--max-fraction", type=float, default=0.01, metavar="F",
                    help="the LUTs differ when more than this fraction of the pixels is beyond (default 0.01)")
    df.add_argument("--common-false-alarm", type=float, default=0.01, metavar="P",
                    help="false-alarm rate of the common-mode test (the mean shift of the image against its"
                         " standard error from block means, x and y together; default 0.01)")
    df.add_argument("--exact", action="store_true",
                    help="instead: are the two files identical, dataset by dataset and attribute by attribute (the"
                         " time of writing and the program's version aside)? Exit 0 identical, 1 not")
    df.add_argument("--ignore", action="append", default=[], metavar="NAME",
                    help="with --exact: also leave out this attribute or dataset (a name, or a path such as"
                         " /provenance@fit_settings); may be repeated")
    df.add_argument("--force", action="store_true", help=_FORCE)
    df.set_defaults(func=cmd_diff)



_FORCE = "replace an existing file of the same kind (never an input, nor a file of a dataset)"
_QUIET = "no progress bar"
_SESSION_EXISTS = "continue it with `ptp resume {path}`, choose another name, or add --force to replace it"


def build_parser() -> OneLineParser:
    """The ``ptp`` parser: every value checked by its type (one-line errors, exit 2)."""
    p = OneLineParser(prog="ptp", description="Point-to-point camera calibration (PTP Studio engine).")
    p.add_argument("--version", action="version", version=f"ptp {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND",
                           help="one of the commands below; `ptp COMMAND --help` for its options")
    _add_simulate(sub)
    _add_calibrate(sub)
    _add_resume_inspect(sub)
    _add_compare(sub)
    _add_reconstruct(sub)
    _add_acceptance(sub)
    _add_diff_parser(sub)
    _add_demo(sub)
    from ptpcore.cli.capture import add_parser as add_capture_parser

    add_capture_parser(sub)  # ptp capture (ptpcore/cli/capture.py)
    return p


def _add_simulate(sub) -> None:
    from ptpcore.simulate.scanner import SCANNER_PRESETS
    from ptpcore.simulate.virtual_rig import PRESETS

    s = sub.add_parser("simulate", help="render a ptp-dataset folder (/1, or /2 when the design needs it) with the virtual rig",
                       description="Render a ptp-dataset/1 or /2 folder (rig.toml, images, truth.h5) with the virtual rig.")
    add_output(s, "out_dir", metavar="OUT_DIR", kind="dataset",
               help="the dataset folder to write (created; its parent folder must exist)")
    s.add_argument("--preset", default="realistic", choices=list(PRESETS) + list(SCANNER_PRESETS),
                   help="rig preset (default realistic); scanner-mild and scanner-rough add the scanner's projector,"
                        " its height sweep and object scans (ptp-dataset/2 [projector], [height]; scans/*)")
    s.add_argument("--seed", type=seed, default=0, help="random seed 0 .. 2^32-1 (default 0)")
    s.add_argument("--width", type=positive_int, help="camera width in pixels, same field of view"
                                                      " (default: the preset's)")
    s.add_argument("--height", type=positive_int, help="camera height in pixels (default: keeps the aspect ratio)")
    s.add_argument("--positions", type=positive_int, help="number of stage positions (default: the preset's)")
    s.add_argument("--tiff", action="store_true", help="write TIFF instead of PNG")
    s.add_argument("--repeat", action="store_true",
                   help="show the first position again at the end (its own noise and stage error; rig.toml"
                        " [stage] repeat_z_mm, ptp-dataset/2): calibrate reports the drift")
    s.add_argument("--drift-um", nargs=2, type=float, metavar=("DX", "DY"),
                   help="with --repeat: the camera moved sideways by DX, DY µm (world X, Y) before the repeat")
    s.add_argument("--gray", type=positive_int, metavar="LEVELS",
                   help="Gray-code unwrapping (ptp-dataset/2, unwrap = \"gray\"): keep the finest LEVELS periods,"
                        " and as many Gray-code bits as cover the LCD")
    s.add_argument("--gray-inverse", action="store_true", help="with --gray: each Gray-code frame followed by its inverse")
    s.add_argument("--references", action="store_true",
                   help="with --gray: all-white and all-black frames at every position (threshold, clipping check)")
    s.add_argument("--heterodyne", type=_period_list_arg, metavar="T1,T2[,T3]",
                   help="heterodyne unwrapping (ptp-dataset/2, unwrap = \"heterodyne\"): two or three periods in LCD"
                        " px, any order, whose beat covers the LCD plus the carrier, e.g. 128,136.5,151.7")
    s.add_argument("--heterodyne-steps", type=positive_int, metavar="N",
                   help="with --heterodyne: phase steps per period (default: the preset's finest level's)")
    s.add_argument("--acceptance", action="store_true",
                   help="with a scanner preset: also the VDI/VDE 2634-2 acceptance scans (10 sphere positions, 7 ball"
                        " bar poses, 6 plane poses, sized against the measuring volume) in OUT_DIR/acceptance/")
    s.add_argument("--force", action="store_true", help="write into a folder that already holds a dataset")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_simulate)


def _period_list_arg(text: str) -> list[float]:
    """``T1,T2[,T3]``: two or three periods in LCD px."""
    try:
        vals = [float(t) for t in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected periods in px separated by commas, got {text!r}") from None
    if len(vals) not in (2, 3) or any(not (2.0 <= v < 1e6) for v in vals):
        raise argparse.ArgumentTypeError(f"expected two or three periods of at least 2 px, got {text!r}")
    return vals


def _add_calibrate(sub) -> None:
    from ptpcore.fit.settings import fit_arguments

    c = sub.add_parser("calibrate", help="images -> per-pixel LUT file",
                       description="Decode a ptp-dataset/1 or /2 folder and write a ptp-lut/1 file (with the"
                                   " scanner's height map in /height when the dataset has a height sweep). Exit"
                                   " 0: done; 2: bad input, nothing written; 3: partial, the XY LUT written but"
                                   " the height map failed (the reason printed).")
    add_input(c, "dataset_dir", metavar="DATASET_DIR", type=existing_dir, kind="dataset",
              help="the dataset folder (rig.toml and the images of every position)")
    add_output(c, "--out", required=True, metavar="FILE.lut.h5", kind="lut", help="the LUT file to write")
    fit_arguments(c)  # one flag per FitSettings field (ptpcore/fit/settings.py)
    add_output(c, "--session", metavar="FILE.ptps.h5", kind="session", hint=_SESSION_EXISTS,
               help="save a session file after each completed stage (continue it with `ptp resume`)")
    c.add_argument("--force", action="store_true", help=_FORCE)
    c.add_argument("-q", "--quiet", action="store_true", help=_QUIET)
    c.set_defaults(func=cmd_calibrate)


def _add_resume_inspect(sub) -> None:
    r = sub.add_parser("resume", help="continue a calibration session from its last completed stage",
                       description="Continue a ptp-session file from its last completed stage (decoding,"
                                   " LUT fit), saving it after each stage, then write the LUT file.")
    add_input(r, "session_file", metavar="FILE.ptps.h5", type=existing_file, kind="session",
              help="the session file (ptp-session/1) written by `ptp calibrate --session`")
    add_output(r, "--out", metavar="FILE.lut.h5", kind="lut",
               help="LUT file to write (default: the one the session names)")
    r.add_argument("--force", action="store_true", help=_FORCE)
    r.add_argument("-q", "--quiet", action="store_true", help=_QUIET)
    r.set_defaults(func=cmd_resume)

    de = sub.add_parser("decode", help="images -> decoded LCD coordinates (ptp-decoded/1)",
                        description="Decode some or all positions of a dataset folder (one or both directions; no"
                                    " heights needed, the z readings are not judged) and write the LCD coordinates"
                                    " every pixel sees as a ptp-decoded/1 file.")
    add_input(de, "dataset_dir", metavar="DATASET", type=existing_dir, kind="dataset",
              help="the dataset folder (rig.toml and the images of every position)")
    add_output(de, "--out", required=True, metavar="FILE.decoded.h5", kind="decoded",
               help="the ptp-decoded/1 file to write")
    de.add_argument("--positions", metavar="LIST", help="position indices, e.g. 0 or 0,2,5-7 (default all)")
    de.add_argument("--min-valid", type=float, default=10.0, metavar="PCT",
                    help="report positions keeping less than this percentage of their pixels (default 10)")
    de.add_argument("--compression", choices=("gzip", "none"), default="none",
                    help="the file's HDF5 filters: none (default: no filter, 28 bytes a pixel and position) or"
                         " gzip (shuffle + deflate level 1: about a third of the size for about twice the CPU"
                         " time of reading the images); any HDF5 reader reads both")
    de.add_argument("--force", action="store_true", help=_FORCE)
    de.add_argument("-q", "--quiet", action="store_true", help=_QUIET)
    de.set_defaults(func=cmd_decode)

    i = sub.add_parser("inspect", help="summarise a LUT file", description="Summarise a ptp-lut/1 file.")
    add_input(i, "lut_file", metavar="FILE.lut.h5", type=existing_file, kind="lut", help="the LUT file (ptp-lut/1)")
    i.set_defaults(func=cmd_inspect)

    a = sub.add_parser("apply", help="height map + LUT -> point cloud (PLY, .npy or .h5)",
                       description="Turn a height for every pixel (one number in mm, or a height map: 32-bit float"
                                   " TIFF or .npy, (H, W), mm, NaN = no measurement) into a point cloud through a"
                                   " ptp-lut/1 file. Pixels invalid in the LUT or outside their own calibrated"
                                   " z range are left out and counted.")
    add_input(a, "lut_file", metavar="FILE.lut.h5", type=existing_file, kind="lut", help="the LUT file (ptp-lut/1)")
    add_input(a, "--z", required=True, metavar="Z", kind="height",
              help="height in mm for every pixel, or a height-map file")
    add_output(a, "--out", required=True, metavar="OUT.ply|OUT.npy|OUT.h5", kind="points",
               help="binary little-endian PLY, a structured .npy array, or ptp-points/1 HDF5")
    a.add_argument("--extrapolate", action="store_true",
                   help="keep pixels whose height is outside their calibrated range (flagged `extrapolated`)")
    a.add_argument("--force", action="store_true", help="replace an existing point cloud")
    a.set_defaults(func=cmd_apply)


def _add_reconstruct(sub) -> None:
    r = sub.add_parser("reconstruct", help="scan folder + LUT with a height map -> point cloud (PLY, .npy or .h5)",
                       description="Decode a scan (ptp-scan/1) with the scanner's projector coordinate, take each"
                                   " pixel's Z from the LUT's height map and (X, Y) from its XY LUT at that Z;"
                                   " each point with its per-axis 1-sigma. Pixels without a decoded coordinate,"
                                   " or outside either map's calibrated range, have no point (never extrapolated).")
    add_input(r, "scan_dir", metavar="SCAN_DIR", type=existing_dir, kind="scans",
              help="the scan folder (ptp-scan/1: scan.toml and its images)")
    add_input(r, "--lut", required=True, metavar="F.lut.h5", type=existing_file, kind="lut",
              help="the scanner's LUT, with its height map (/height)")
    add_output(r, "--out", required=True, metavar="OUT.ply|OUT.npy|OUT.h5", kind="points",
               help="point cloud; a scan of several views writes OUT.view000.ply, ...")
    r.add_argument("--force", action="store_true", help="replace an existing point cloud")
    r.add_argument("-q", "--quiet", action="store_true", help=_QUIET)
    r.set_defaults(func=cmd_reconstruct)


def _add_acceptance(sub) -> None:
    a = sub.add_parser("acceptance", help="VDI/VDE 2634-2 acceptance of the scanner, PTP and conventional calibrations",
                       description="Reconstruct scans of a sphere, a ball bar and a plane with both scanner"
                                   " calibrations (the LUT's per-pixel height map and XY LUT; camera and projector as"
                                   " two pinholes calibrated from the same dataset) on the same decoded phases, and"
                                   " report the VDI/VDE 2634-2 figures PF, PS (sphere), SD (ball bar) and F (plane)"
                                   " per pose, their largest magnitudes and the verdicts against --mpe; up to 0.3 %"
                                   " of a fit's points are left out (the largest residuals). A scan names its"
                                   " artefact in artefact.toml (kind, diameter_mm, distance_mm) or, simulated, by its"
                                   " truth.h5, which adds the errors against the exact surface and the 3D distance"
                                   " errors.")
    add_input(a, "dataset_dir", metavar="DATASET", type=existing_dir, kind="dataset",
              help="the dataset the LUT was calibrated from (its height sweep calibrates the conventional model)")
    add_input(a, "scans", metavar="SCANS", nargs="+", kind="scans",
              help="ptp-scan/1 folders, or folders of them (e.g. DATASET/acceptance)")
    add_input(a, "--lut", required=True, metavar="F.lut.h5", type=existing_file, kind="lut",
              help="the scanner's LUT, with its height map (/height)")
    add_output(a, "--out", required=True, metavar="REPORT.json", kind="report", help="the report to write (JSON)")
    add_output(a, "--png", metavar="PAGE.png", kind="png",
               help="the page of plots (default: REPORT.png beside the report)")
    a.add_argument("--mpe", metavar="PF=..,PS=..,SD=..,F=..",
                   help="maximum permissible errors in mm (or µm with the unit, e.g. 12µm), any of PF, PS, SD, F")
    a.add_argument("--no-conventional", dest="conventional", action="store_false",
                   help="PTP only (no conventional camera-projector calibration)")
    a.add_argument("--seed", type=seed, default=0, help="seed of the 3D distance-error pairs (default 0)")
    a.add_argument("--force", action="store_true", help="replace an existing report and page")
    a.add_argument("-q", "--quiet", action="store_true", help=_QUIET)
    a.set_defaults(func=cmd_acceptance)


def _add_compare(sub) -> None:
    from ptpcore.io.lutfile import MODELS

    cm = sub.add_parser("compare", help="PTP against the 3DSTC pinhole calibration on held-out heights",
                        description="Calibrate a ptp-dataset/1 or /2 folder three ways (per-pixel LUT, smooth LUT and"
                                    " pinhole + Brown from feature points) on some positions, judge them at the others"
                                    " (docs/method.md section 7) and write the report as JSON. A truth.h5 in the"
                                    " folder (simulated data) adds errors against the exact truth.")
    add_input(cm, "dataset_dir", metavar="DATASET_DIR", type=existing_dir, kind="dataset",
              help="the dataset folder (rig.toml and the images of every position)")
    add_output(cm, "--out", required=True, metavar="REPORT.json", kind="report", help="the report to write (JSON)")
    cm.add_argument("--seed", type=seed, default=0, help="seed of the feature points and point pairs (default 0)")
    cm.add_argument("--points", type=positive_int, default=2000, metavar="M",
                    help="3DSTC feature points (default 2000)")
    cm.add_argument("--split", default="alternate", choices=["alternate", "loo"],
                    help="hold out every second position (default) or leave one position out")
    cm.add_argument("--rational", action="store_true", help="3DSTC also fits the rational k4..k6")
    cm.add_argument("--refine-stage", action="store_true",
                    help="estimate each position's stage pose and correct the samples before every method's fit")
    cm.add_argument("--model", default="auto", choices=["auto", *MODELS],
                    help="plain PTP LUT model; auto: poly of the degree 1-3 most accurate at positions held out of"
                         " each calibration (default auto)")
    cm.add_argument("--degree", type=int, default=3, choices=range(1, 6), metavar="D",
                    help="polynomial degree 1-5 (poly only, default 3; also the smooth LUT's upper bound)")
    cm.add_argument("--no-smooth", dest="smooth", action="store_false",
                    help="leave out the smooth LUT (compare only the plain LUT and 3DSTC)")
    cm.add_argument("--force", action="store_true", help="replace an existing report")
    cm.add_argument("-q", "--quiet", action="store_true", help=_QUIET)
    cm.set_defaults(func=cmd_compare)


def _add_demo(sub) -> None:
    from ptpcore.fit.settings import FitSettings, fit_arguments
    from ptpcore.simulate.virtual_rig import PRESETS

    d = sub.add_parser("demo", help="simulate, calibrate and report accuracy against the truth",
                       description="Simulate a rig, calibrate on every second position and report the accuracy"
                                   " at the others against the simulator's exact truth.")
    d.add_argument("--preset", default="realistic", choices=list(PRESETS), help="rig preset (default realistic)")
    d.add_argument("--seed", type=seed, default=0, help="random seed 0 .. 2^32-1 (default 0)")
    # The LUT is fitted as ptp calibrate fits it; the one difference: a poly LUT by default (seconds),
    # where calibrate's auto fits every candidate.
    fit_arguments(d, FitSettings(model="poly"), {"model": "the LUT's model as for ptp calibrate (default poly here,"
                                                          " for a quick first run; auto: the most accurate of poly"
                                                          " 1-3 and smooth at held-out positions)"})
    add_output(d, "--out", kind="dataset", help="keep the simulated dataset in this folder (default: a temporary"
                                                " folder, removed at the end)")
    d.add_argument("--force", action="store_true", help="write into an --out folder that already holds a dataset")
    d.add_argument("--no-compare", dest="compare", action="store_false", help="skip the 3DSTC comparison")
    d.add_argument("-q", "--quiet", action="store_true", help=_QUIET)
    d.set_defaults(func=cmd_demo)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Engine warnings (e.g. colour images converted to grey) as one ``ptp: warning:`` line."""
    print(f"ptp: warning: {message}", file=file or sys.stderr)


def main(argv=None) -> int:
    """Run one ``ptp`` command; return its exit code.

    0 done; 2 bad input or an output that cannot be written (one line on
    stderr); 3 partial (``calibrate``, ``resume``: the XY LUT written, the height
    map failed); 130 Ctrl-C; 143 SIGTERM; 141 standard output closed by its reader. Every temporary file is removed on the way out, whatever ended
    the command.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a bad argument (one line already printed)
        return exc.code if isinstance(exc.code, int) else EXIT_BAD_INPUT
    args.parser = parser  # _run applies the output guard over its marked arguments
    warnings.simplefilter("default")
    warnings.showwarning = _show_warning
    from ptpcore.store import remove_orphaned_spill_files

    remove_orphaned_spill_files()  # what killed runs left (only where spill files have names)
    with signals_as_interrupts():
        try:
            code = _run(args)
            if termination_requested() and code != EXIT_SIGTERM:  # SIGTERM lost after the last progress report
                print("ptp: terminated (SIGTERM) after the job had finished its last step", file=sys.stderr)
                return EXIT_SIGTERM
            sys.stdout.flush()
            return code
        except BrokenPipeError:
            return quiet_broken_pipe()
        finally:
            remove_temporaries()
            if termination_requested():
                gc.collect()  # objects the interrupted job left in cycles die while their errors stay quiet


def _run(args) -> int:
    """The output guard, then the command; failures turned into exit codes and one line each.

    Every output argument marked in the parser (:func:`ptpcore.cli.safety.add_output`) is checked
    against the command's marked inputs before the command runs (:func:`guard_arguments`), so no
    command decodes anything before it knows it can write its result.
    """
    try:
        if getattr(args, "parser", None) is not None:
            guard_arguments(args.parser, args)
        return args.func(args)
    except BrokenPipeError:
        raise
    except Cancelled:
        print("ptp: cancelled", file=sys.stderr)
        return EXIT_SIGINT
    except Terminated:
        print("ptp: terminated (SIGTERM); temporary files removed", file=sys.stderr)
        return EXIT_SIGTERM
    except KeyboardInterrupt:
        print("ptp: interrupted", file=sys.stderr)
        return EXIT_SIGINT
    except (PtpError, ValueError, OSError) as exc:
        print(f"ptp: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
