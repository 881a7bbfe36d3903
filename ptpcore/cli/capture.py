"""``ptp capture``: a live capture from the command line (wired into :mod:`ptpcore.cli`).

The command line has no screen to show patterns on (the LCD window is part of
the GUI, ``ptp-studio``), so its display is the simulated one and its camera
the simulated camera; the stage may be simulated, manual (a prompt) or serial
(``--config capture.toml``), which makes it the place to try a stage's
protocol and the resume logic without the GUI.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ptpcore.cli.progress import progress_bar
from ptpcore.cli.safety import (add_input, add_output, existing_file, nonneg_float, positive_float, positive_int,
                                seed)

__all__ = ["add_parser", "cmd_capture", "prompt_reading"]


def prompt_reading(z_mm: float, prompt: str) -> float | None:
    """Ask on the terminal for the stage reading (Enter: the planned value; q: stop)."""
    while True:
        try:
            text = input(f"{prompt} [{z_mm:g}] ").strip()
        except EOFError:
            return None
        if text.lower() in ("q", "quit", "stop"):
            return None
        if not text:
            return z_mm
        try:
            return float(text)
        except ValueError:
            print("  type the reading in mm, Enter for the planned value, or q to stop", file=sys.stderr)


def _stage(kind: str, config, args):
    from ptpcore.capture.devices import ManualStage, SerialStage, SimulatedStage
    from ptpcore.errors import ConfigError

    if kind == "sim":
        return SimulatedStage()
    if kind == "manual":
        return ManualStage(prompt_reading)
    if config is None or config.stage.serial is None:
        raise ConfigError("--stage serial needs --config FILE with a [stage.serial] table"
                          " (the controller's text protocol)")
    return SerialStage(config.stage.serial, port=args.port)


def cmd_capture(args) -> int:
    from ptpcore.capture.sequence import ExposureLimits, capture, capture_state, with_repeat_of_first
    from ptpcore.capture.devices import SimulatedCamera, SimulatedDisplay, simulated_meta
    from ptpcore.capture.devices.config import load_capture_config
    from ptpcore.errors import Cancelled, ConfigError
    from ptpcore.rig.rigfile import load_rig
    from ptpcore.simulate.virtual_rig import TRUTH_FILE, VirtualRig, preset, save_truth, scaled_preset

    # --out passed the output guard (ptpcore.cli.main): a folder, its parent writable, no dataset in it
    # unless --resume (what a capture to resume holds is capture()'s own check).
    config = load_capture_config(args.config) if args.config else None
    camera_kind = args.camera or (config.camera.kind if config else "sim")
    stage_kind = args.stage or (config.stage.kind if config else "sim")
    if camera_kind != "sim":
        raise ConfigError(f"--camera {camera_kind}: a real camera must see the patterns on the real LCD, which"
                          " only the GUI shows (ptp-studio, Acquire page); the command line captures with"
                          " --camera sim")
    rig, settings = preset(args.preset)
    if args.width or args.height or args.positions:
        rig, settings = scaled_preset(args.preset, args.width or rig.camera.width, args.height, args.positions)
    if args.rig:
        rig = load_rig(args.rig)
    if args.repeat_first:  # end the sweep at its first position again: calibrate reports the drift
        rig = with_repeat_of_first(rig)
    settle_ms = args.settle_ms if args.settle_ms is not None else (config.display.settle_ms if config else 0.0)
    exposure_us = args.exposure_us if args.exposure_us is not None else (config.camera.exposure_us if config
                                                                         else None)
    limits = ExposureLimits(**(config.exposure_check if config else {}))
    meta = simulated_meta(args.preset, args.seed, settings)

    out = Path(args.out)
    if args.resume:
        st = capture_state(out)
        if st is not None:
            print(f"{out}: resuming a capture with {st['done']} of {st['total']} positions done", flush=True)
    display = SimulatedDisplay(rig.lcd.width, rig.lcd.height, settle_ms / 1000.0)
    stage = _stage(stage_kind, config, args)
    vr = VirtualRig(rig, settings, args.seed)
    camera = SimulatedCamera(vr, display, stage)

    def on_exposure(report):
        print(f"exposure check: {report.message}", file=sys.stderr if not report.ok else sys.stdout, flush=True)

    bar = progress_bar(args)
    try:
        result = capture(out, rig, camera, stage, display, resume=args.resume, exposure_us=exposure_us,
                         check=not args.no_check, accept_exposure=args.ignore_exposure, limits=limits,
                         image_ext=".tif" if args.tiff else ".png", meta=meta, progress=bar,
                         on_exposure=on_exposure, measure_display=args.measure_display)
    except (Cancelled, KeyboardInterrupt):
        st = capture_state(out)
        if st is not None:
            print(f"{out}: {st['done']} of {st['total']} positions are saved; continue with --resume",
                  file=sys.stderr)
        raise
    finally:
        bar.close()
    if not (out / TRUTH_FILE).exists():
        save_truth(out / TRUTH_FILE, vr)
    n = result.rig.stage.n_positions
    kept = f", {len(result.kept)} kept from before" if result.kept else ""
    print(f"captured {len(result.captured)} of {n} positions{kept}"
          f" ({rig.camera.width}x{rig.camera.height}, {rig.fringes.frames_per_position} frames each,"
          f" simulated camera '{args.preset}' seed {args.seed}, {stage_kind} stage) to {out}")
    if result.rig.display is not None and args.measure_display:
        d = result.rig.display
        print("display response ([display] of rig.toml; the patterns went through its inverse): "
              + ", ".join(f"{lv:g}: {lum:.4f}" for lv, lum in zip(d.levels, d.luminance)))
    return 0


def add_parser(sub) -> argparse.ArgumentParser:
    """Add ``capture`` to the ``ptp`` sub-commands."""
    from ptpcore.simulate.virtual_rig import PRESETS

    p = sub.add_parser(
        "capture", help="capture a ptp-dataset folder (/1, or /2 when the design needs it) with (simulated) devices, resumable",
        description="Show every pattern, at every stage position, photograph it and write a ptp-dataset/1 (or /2)"
                    " folder as it goes (a crash loses at most one position; --resume continues). An exposure"
                    " check at the first position stops a bad exposure before the long run. The command line"
                    " uses the simulated display and camera (the real LCD window is the GUI's); the stage may be"
                    " simulated, manual (you type each reading) or serial (--config capture.toml).")
    add_output(p, "--out", required=True, metavar="DIR", kind="dataset", resume="resume",
               help="dataset folder (new or empty; or with --resume)")
    p.add_argument("--camera", choices=["sim", "opencv", "genicam", "pylon"],
                   help="camera (default: the config's, else sim; only sim works from the command line)")
    p.add_argument("--stage", choices=["sim", "manual", "serial"], help="stage (default: the config's, else sim)")
    add_input(p, "--config", metavar="capture.toml", type=existing_file, kind="config",
              help="devices and the serial stage's protocol")
    p.add_argument("--port", help="serial port (overrides stage.serial.port)")
    add_input(p, "--rig", metavar="rig.toml", type=existing_file, kind="rig",
              help="the rig to capture (default: the preset's)")
    p.add_argument("--preset", default="realistic", choices=list(PRESETS),
                   help="simulated rig and camera (default realistic)")
    p.add_argument("--seed", type=seed, default=0, help="simulator seed (default 0)")
    p.add_argument("--width", type=positive_int, help="camera width, same field of view (as ptp simulate)")
    p.add_argument("--height", type=positive_int, help="camera height (default keeps the aspect ratio)")
    p.add_argument("--positions", type=positive_int, help="number of stage positions (as ptp simulate)")
    p.add_argument("--exposure-us", type=positive_float, metavar="US", help="camera exposure in µs")
    p.add_argument("--settle-ms", type=nonneg_float, metavar="MS", help="wait after each pattern change (default 0)")
    p.add_argument("--ignore-exposure", action="store_true", help="capture even if the exposure check fails")
    p.add_argument("--no-check", action="store_true", help="skip the exposure check")
    p.add_argument("--measure-display", action="store_true",
                   help="measure the display's response at the first position (a ramp of uniform levels), store it"
                        " as rig.toml's [display] and show every pattern through its inverse")
    p.add_argument("--resume", action="store_true", help="continue the partial capture in --out")
    p.add_argument("--repeat-first", action="store_true",
                   help="end the sweep at its first position again ([stage] repeat_z_mm): calibrate reports the"
                        " drift in between")
    p.add_argument("--tiff", action="store_true", help="write TIFF instead of PNG")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_capture)
    return p
