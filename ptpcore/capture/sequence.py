"""Live capture: every fringe pattern on the LCD, at every stage position, photographed.

:func:`capture` drives a :class:`~ptpcore.capture.devices.display.Display`, a
:class:`~ptpcore.capture.devices.camera.Camera` and a
:class:`~ptpcore.capture.devices.stage.Stage` through the rig's plan and writes a
``ptp-dataset/1`` folder as it goes:

1. the folder gets ``capture-state.json`` first (the plan: the rig as
   ``rig.toml`` text, and per position its state and stage reading), updated
   atomically after every position;
2. at the first position it captures, an exposure check photographs the
   brightest and the darkest level the patterns use (uniform screens) and
   judges saturated and too-dark pixels (:func:`check_exposure`); a failing
   verdict stops before the long run unless accepted; with
   ``measure_display`` a ramp of uniform levels follows, the camera's mean
   response per level becomes the dataset's ``[display]`` curve
   (:func:`measure_display_response`) and every pattern is generated through
   its inverse (:func:`ptpcore.decode.patterns.display_inverse`);
3. per position: move, read the stage (the reading is what ``rig.toml``
   records, and what the patterns' carrier uses), record it, then for every
   pattern show, settle, grab (dropped frames are asked for again) and write
   the image atomically (:mod:`ptpcore.atomic`);
4. ``rig.toml`` is written last, with the readings: a folder without it is
   visibly an unfinished capture.

A crash, a kill or a device error loses at most the position being captured.
``capture(..., resume=True)`` continues: positions recorded as done whose
images all read back correctly are kept, everything else is captured again.
Every device failure ends as a :class:`~ptpcore.errors.DeviceError` whose
message names the device and says how much is saved.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import warnings
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ptpcore.atomic import write_bytes_atomic, write_text_atomic
from ptpcore.io.dataset import check_calibration_design, read_image
from ptpcore.capture.devices import describe
from ptpcore.capture.devices.camera import FrameError
from ptpcore.errors import CaptureError, ConfigError, DeviceError, PtpError
from ptpcore.rig import position_label
from ptpcore.decode.patterns import fringe_profile, gray_profile, reference_profile
from ptpcore.progress import Progress
from ptpcore.rig.rigfile import Display, FringeDesign, Rig, rig_from_toml, rig_to_toml, save_rig

__all__ = [
    "STATE_FILE",
    "ExposureLimits",
    "ExposureReport",
    "ExposureError",
    "CaptureResult",
    "display_levels",
    "exposure_report",
    "check_exposure",
    "measure_display_response",
    "display_from_means",
    "DISPLAY_RAMP",
    "with_repeat_of_first",
    "capture",
    "capture_state",
    "pattern_image",
    "extra_frames",
    "frames_per_position",
]

STATE_FILE = "capture-state.json"
STATE_FORMAT = "ptp-capture-state/1"


class ExposureError(CaptureError):
    """The exposure check failed (and was not accepted)."""


# --------------------------------------------------------------------------- exposure

@dataclass(frozen=True)
class ExposureLimits:
    """Thresholds of the exposure check (fractions).

    Attributes
    ----------
    max_saturated : float
        Pixels at full scale on the brightest pattern, at most (they would
        clip every fringe's crest).
    min_signal : float
        The 99th percentile of the contrast (brightest minus darkest pattern)
        must reach this fraction of full scale.
    max_clipped_black : float
        Pixels that see the LCD but read 0 on the darkest pattern, at most.
    dark_contrast : float
        A pixel whose contrast is below this fraction of full scale is too
        dark to decode (bezel, vignetted corner, or underexposed).
    max_dark : float
        Too-dark pixels, at most (more means the camera barely sees the LCD).
    """

    max_saturated: float = 0.001
    min_signal: float = 0.2
    max_clipped_black: float = 0.01
    dark_contrast: float = 0.05
    max_dark: float = 0.9

    def validate(self, source: str = "exposure limits") -> "ExposureLimits":
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.0 <= v <= 1.0):
                raise ConfigError(f"{source}: key '{f.name}' must be a fraction between 0 and 1, got {v!r}")
        return self


@dataclass
class ExposureReport:
    """The verdict of the exposure check.

    Attributes
    ----------
    ok : bool
    verdict : {"ok", "overexposed", "no signal", "underexposed", "black clipped"}
    message : str
        One line: what was found and what to do.
    saturated_fraction, clipped_black_fraction, dark_fraction : float
        Fractions of all pixels (clipped black: of the pixels that see the LCD).
    signal : float
        99th percentile of the contrast, fraction of full scale.
    exposure_us : float or None
        The exposure it was taken with (None: the camera's own).
    suggested_exposure_us : float or None
        A better exposure, when one can be said.
    levels : (int, int)
        The darkest and brightest displayed levels photographed.
    bright, dark : (H, W) arrays
        The two frames.
    """

    ok: bool
    verdict: str
    message: str
    saturated_fraction: float
    clipped_black_fraction: float
    dark_fraction: float
    signal: float
    exposure_us: float | None
    suggested_exposure_us: float | None
    levels: tuple[int, int]
    bright: np.ndarray = field(repr=False)
    dark: np.ndarray = field(repr=False)

    def summary(self) -> dict:
        """The numbers (no frames), JSON-ready."""
        d = {k: v for k, v in asdict(self).items() if k not in ("bright", "dark")}
        d["levels"] = list(self.levels)
        return d


def display_levels(design: FringeDesign) -> tuple[int, int]:
    """The darkest and brightest grey levels the design's patterns put on the LCD."""
    from ptpcore.rig.rigfile import Lcd

    lo, hi = 255, 0
    for d, _j, t, s, n in design.frames():
        p = fringe_profile(Lcd(max(t, 3), 1, (1.0, 1.0)), design, "x", t, s, n, 0.0)
        lo, hi = min(lo, int(p.min())), max(hi, int(p.max()))
    return lo, hi


def _pct(v: float) -> str:
    return f"{100 * v:.2f} %" if v < 0.1 else f"{100 * v:.0f} %"


def exposure_report(bright, dark, max_level: int, limits: ExposureLimits = ExposureLimits(),
                    exposure_us: float | None = None, levels: tuple[int, int] = (0, 255)) -> ExposureReport:
    """Judge two frames: the brightest and the darkest displayed level.

    Parameters
    ----------
    bright, dark : (H, W) uint8 or uint16
    max_level : int
        The camera's full scale (``2**bit_depth - 1``).
    limits : ExposureLimits
    exposure_us : float, optional
        The exposure used (for a suggestion).

    Returns
    -------
    ExposureReport
    """
    bright = np.asarray(bright)
    dark = np.asarray(dark)
    contrast = bright.astype(np.float64) - dark
    full = float(max_level)
    saturated = float(np.mean(bright >= max_level))
    seeing = contrast >= limits.dark_contrast * full
    dark_fraction = 1.0 - float(seeing.mean())
    clipped = float(np.mean(dark[seeing] <= 0)) if seeing.any() else 0.0
    signal = float(np.percentile(contrast, 99)) / full
    top = float(np.percentile(bright, 99.9)) / full
    suggest = None
    if exposure_us is not None and top > 0:
        suggest = float(exposure_us) * min(0.8 / top, 10.0) if top < 1.0 else float(exposure_us) * 0.7
    hint = f" (e.g. {suggest:.0f} µs)" if suggest is not None else ""
    if saturated > limits.max_saturated:
        verdict = "overexposed"
        message = (f"overexposed: {_pct(saturated)} of the pixels saturate on the brightest pattern"
                   f" (at most {_pct(limits.max_saturated)}): shorten the exposure{hint}"
                   " or lower the fringe amplitude")
    elif dark_fraction > limits.max_dark:
        verdict = "no signal"
        message = (f"no signal: {_pct(dark_fraction)} of the pixels change by less than"
                   f" {_pct(limits.dark_contrast)} of full scale between the darkest and the brightest"
                   " pattern: is the camera looking at the LCD, the lens open, the LCD showing the patterns?")
    elif signal < limits.min_signal:
        verdict = "underexposed"
        message = (f"underexposed: the contrast between the darkest and the brightest pattern reaches only"
                   f" {_pct(signal)} of full scale (at least {_pct(limits.min_signal)}):"
                   f" lengthen the exposure{hint}")
    elif clipped > limits.max_clipped_black:
        verdict = "black clipped"
        message = (f"black level clipped: {_pct(clipped)} of the pixels that see the LCD read 0 on the darkest"
                   " pattern: raise the camera's black level (offset) or the exposure")
    else:
        verdict = "ok"
        message = (f"exposure ok: contrast {_pct(signal)} of full scale, {_pct(saturated)} saturated,"
                   f" {_pct(dark_fraction)} of the pixels too dark to decode")
    return ExposureReport(verdict == "ok", verdict, message, saturated, clipped, dark_fraction, signal,
                          exposure_us, suggest if verdict != "ok" else None, tuple(levels), bright, dark)


def _uniform(rig: Rig, level: int) -> np.ndarray:
    return np.broadcast_to(np.uint8(level), (rig.lcd.height, rig.lcd.width))


def check_exposure(rig: Rig, camera, display, *, limits: ExposureLimits = ExposureLimits(),
                   exposure_us: float | None = None, retries: int = 2) -> ExposureReport:
    """Photograph the brightest and darkest levels the patterns use, and judge the exposure.

    The devices must be open; the stage stays where it is.

    Raises
    ------
    DeviceError
    """
    lo, hi = display_levels(rig.fringes)
    frames = []
    for level in (hi, lo):
        _call(display, "show", _uniform(rig, level))
        _call(display, "settle")
        frames.append(_check_frame(_grab(camera, f"the exposure check (level {level})", retries), rig, camera))
    return exposure_report(frames[0], frames[1], rig.camera.max_level, limits, exposure_us, (lo, hi))


DISPLAY_RAMP = tuple(range(0, 256, 16)) + (255,)
"""The uniform levels :func:`measure_display_response` shows (17: every 16th and full white)."""


def display_from_means(levels, means) -> Display:
    """A ``[display]`` response from the camera's mean level at each displayed level.

    The camera is linear: ``(mean - mean[0]) / (mean[-1] - mean[0])`` is the
    display's relative luminance (offset and gain cancel), made monotone
    (a running maximum: noise at nearly equal levels).

    Raises
    ------
    CaptureError
        The brightest level is not brighter than the darkest (the camera does not see the LCD).
    """
    m = np.asarray(means, dtype=float)
    if not m[-1] > m[0]:
        raise CaptureError(f"display response: the camera reads {m[-1]:.1f} at level {levels[-1]} and"
                           f" {m[0]:.1f} at level {levels[0]}: it does not see the LCD light up")
    rel = np.maximum.accumulate((m - m[0]) / (m[-1] - m[0]))
    return Display(tuple(float(v) for v in levels), tuple(float(v) for v in np.clip(rel, 0.0, 1.0)))


def measure_display_response(rig: Rig, camera, display, *, levels=DISPLAY_RAMP, retries: int = 2,
                             ) -> tuple[Display, np.ndarray, int]:
    """Show a ramp of uniform levels and measure the camera's mean response to each.

    The devices must be open; the stage stays where it is. The mean is taken
    over the pixels that see the LCD (full white minus black above half its
    99th percentile) and are not saturated at full white.

    Returns
    -------
    display : Display
        ``[display]`` levels and relative luminance (:func:`display_from_means`).
    means : (L,) float64
        The camera's mean level at each displayed level (grey levels).
    n_pixels : int
        Camera pixels averaged.

    Raises
    ------
    DeviceError, CaptureError
    """
    frames = []
    for level in levels:
        _call(display, "show", _uniform(rig, int(level)))
        _call(display, "settle")
        frames.append(_check_frame(_grab(camera, f"the display response (level {level})", retries), rig,
                                   camera).astype(np.float64))
    diff = frames[-1] - frames[0]
    seen = (diff > 0.5 * np.percentile(diff, 99)) & (frames[-1] < rig.camera.max_level)
    if not seen.any():
        raise CaptureError("display response: no camera pixel sees the LCD light up without saturating")
    means = np.array([f[seen].mean() for f in frames])
    return display_from_means(levels, means), means, int(seen.sum())


# --------------------------------------------------------------------------- helpers

def pattern_image(rig: Rig, direction: str, period: int, step: int, n_steps: int, z_mm: float) -> np.ndarray:
    """The LCD image ``(lcd.height, lcd.width)`` uint8 of one pattern (a read-only broadcast view)."""
    prof = fringe_profile(rig.lcd, rig.fringes, direction, period, step, n_steps, z_mm, rig.display)
    shape = (rig.lcd.height, rig.lcd.width)
    return np.broadcast_to(prof[None, :] if direction == "x" else prof[:, None], shape)


def extra_frames(rig: Rig, k: int, z_mm: float):
    """The frames of position ``k`` besides the phase steps (ptp-dataset/2): Gray-code bits and
    their inverses (``unwrap = "gray"``), then the white and black reference frames when the rig
    names them.

    Yields
    ------
    name : str
        The frame's path relative to the dataset folder (``rig.gray_name`` / ``rig.reference_name``).
    image : (lcd.height, lcd.width) uint8
        What the LCD shows (a read-only broadcast view).
    what : str
        The frame in words, for progress and messages.
    """
    shape = (rig.lcd.height, rig.lcd.width)
    for d, b, inv in rig.fringes.gray_frames():
        prof = gray_profile(rig.lcd, rig.fringes, d, b, inv, z_mm)
        yield (rig.gray_name(k, d, b, inv),
               np.broadcast_to(prof[None, :] if d == "x" else prof[:, None], shape),
               f"{d} Gray-code bit {b}{' inverse' if inv else ''}")
    if rig.has_references:
        for which in ("white", "black"):
            yield (rig.reference_name(k, which),
                   np.broadcast_to(reference_profile(rig.lcd, rig.fringes, which)[None, :], shape), f"{which} frame")


def frames_per_position(rig: Rig) -> int:
    """Frames captured at each position: phase steps, Gray-code frames and reference frames."""
    return rig.fringes.frames_per_position + 2 * bool(rig.has_references)


def _call(device, method: str, *args):
    """Call a device method; anything but our own errors becomes a DeviceError naming the device."""
    try:
        return getattr(device, method)(*args)
    except PtpError:
        raise
    except Exception as exc:  # noqa: BLE001 - drivers raise anything
        raise DeviceError(f"{describe(device)}: {method} failed ({type(exc).__name__}: {exc})") from exc


def _grab(camera, what: str, retries: int) -> np.ndarray:
    last = "no frame"
    for _ in range(retries + 1):
        try:
            frame = _call(camera, "grab")
        except FrameError as exc:
            last = str(exc)
            continue
        if frame is None:
            last = "no frame delivered"
            continue
        return frame
    raise FrameError(f"{describe(camera)}: no frame for {what} after {retries + 1} tries ({last})")


def _check_frame(frame, rig: Rig, camera) -> np.ndarray:
    frame = np.asarray(frame)
    if frame.ndim == 3 and frame.shape[2] == 1:
        frame = frame[:, :, 0]
    want = np.uint8 if rig.camera.bit_depth == 8 else np.uint16
    h, w = rig.camera.shape
    if frame.shape != (h, w):
        raise DeviceError(f"{describe(camera)}: delivers frames of shape {frame.shape},"
                          f" but rig.toml says camera {w}x{h} (a grey image of {h} rows, {w} columns)")
    if frame.dtype != want:
        raise DeviceError(f"{describe(camera)}: delivers {frame.dtype} frames, but rig.toml says"
                          f" camera.bit_depth = {rig.camera.bit_depth} ({np.dtype(want).name} expected)")
    if rig.camera.bit_depth not in (8, 16) and int(frame.max()) > rig.camera.max_level:
        raise DeviceError(f"{describe(camera)}: frame values up to {int(frame.max())}, above the"
                          f" {rig.camera.bit_depth}-bit full scale {rig.camera.max_level} (rig.toml"
                          " camera.bit_depth): set the camera's pixel format to match")
    return np.ascontiguousarray(frame)


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


# --------------------------------------------------------------------------- state file

def _read_state(folder: Path) -> dict | None:
    path = folder / STATE_FILE
    if not path.exists():
        return None
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{path}: unreadable capture state ({exc})") from None
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        raise CaptureError(f"{path}: not a capture state file (expected format \"{STATE_FORMAT}\")")
    if not isinstance(state.get("positions"), list) or not isinstance(state.get("rig_toml"), str):
        raise CaptureError(f"{path}: capture state is incomplete (no plan or positions)")
    return state


def _write_state(folder: Path, state: dict) -> None:
    state["updated"] = _now()
    write_text_atomic(folder / STATE_FILE, json.dumps(state, indent=1) + "\n")


def capture_state(folder) -> dict | None:
    """What a folder holds of a capture: ``None`` if no capture was started there.

    Returns
    -------
    dict with ``done`` (positions recorded as captured), ``total``,
    ``complete`` (bool), ``meta`` and ``rig`` (the planned Rig).
    """
    folder = Path(folder)
    state = _read_state(folder)
    if state is None:
        return None
    rig = rig_from_toml(state["rig_toml"], str(folder / STATE_FILE))
    return {"done": _done_count(state), "total": len(state["positions"]), "complete": bool(state.get("complete")),
            "meta": state.get("meta") or {}, "rig": rig}


def _done_count(state: dict) -> int:
    """Positions a capture state records as captured."""
    return sum(1 for p in state["positions"] if isinstance(p, dict) and p.get("state") == "done")


def _first_difference(a: str, b: str) -> str:
    for la, lb in zip(a.splitlines(), b.splitlines()):
        if la != lb:
            return f"'{la.strip()}' then, '{lb.strip()}' now"
    return "different length"


# --------------------------------------------------------------------------- capture

@dataclass
class CaptureResult:
    """What :func:`capture` did.

    Attributes
    ----------
    folder : Path
        The ``ptp-dataset/1`` folder (complete).
    rig : Rig
        Its ``rig.toml`` (stage readings as recorded).
    captured : list of int
        Positions captured by this call.
    kept : list of int
        Positions already complete (resume), verified and kept.
    exposure : ExposureReport or None
    display_means : (L,) float64 or None
        The camera's mean level at each level of the display ramp (``measure_display``),
        whose curve is ``rig.display``.
    """

    folder: Path
    rig: Rig
    captured: list
    kept: list
    exposure: ExposureReport | None = None
    display_means: np.ndarray | None = None


def _with_image_ext(rig: Rig, image_ext: str) -> Rig:
    """``rig`` with every image template (fringes, Gray code, white, black) ending in ``image_ext``."""
    for key in ("template", "gray_template", "white_template", "black_template"):
        t = getattr(rig, key)
        if t is not None and Path(t).suffix != image_ext:
            rig = replace(rig, **{key: str(Path(t).with_suffix(image_ext))})
    return rig


def capture(out_dir, rig: Rig, camera, stage, display, *, resume: bool = False,
            exposure_us: float | None = None, check: bool = True, accept_exposure: bool = False,
            limits: ExposureLimits = ExposureLimits(), retries: int = 2, home: bool = True,
            position_tolerance_mm: float | None = None, image_ext: str = ".png", meta: dict | None = None,
            measure_display: bool = False,
            progress: Progress | None = None, on_frame: Callable | None = None,
            on_exposure: Callable[[ExposureReport], None] | None = None,
            on_position: Callable[[int, str], None] | None = None) -> CaptureResult:
    """Capture a whole ``ptp-dataset/1`` folder with live (or simulated) devices.

    Parameters
    ----------
    out_dir : path
        The dataset folder: new or empty, or (``resume=True``) a partial capture.
    rig : Rig
        The plan: camera, LCD, fringes, and the stage heights ``z_mm`` to visit; with
        ``[stage] repeat_z_mm`` (see :func:`with_repeat_of_first`) those heights are visited
        again after the sweep (positions K, K+1, ...: they measure drift).
    camera, stage, display
        Unopened devices (:mod:`ptpcore.capture.devices`); opened here and closed at the end.
    resume : bool
        Continue the partial capture in ``out_dir``.
    exposure_us : float, optional
        Set the camera's exposure first.
    check : bool
        Run the exposure check at the first position captured.
    accept_exposure : bool
        Go on when the exposure check fails (its verdict is still reported).
    limits : ExposureLimits
    retries : int
        Dropped frames asked for again, per pattern, before giving up.
    home : bool
        Home the stage first.
    position_tolerance_mm : float, optional
        How far a stage reading may be from the planned height (default a
        quarter of the smallest step between positions).
    image_ext : {".png", ".tif"}
    meta : dict, optional
        Anything JSON can hold that a resumed capture must match (e.g. the
        simulator settings); stored in the state file.
    measure_display : bool
        At the first position, after the exposure check, measure the display's
        response (:func:`measure_display_response`), write it to ``rig.toml``'s
        ``[display]`` and show every pattern through its inverse (the rig's own
        ``[display]``, when it has one, is replaced). A resumed capture keeps the
        response it measured (stored in the state file).
    progress : callable, optional
        ``progress(fraction, message)``; may raise :class:`Cancelled` (the
        capture stops, resumable).
    on_frame : callable, optional
        ``on_frame(k, (dir, level, period, step, N), frame)`` after each frame is written.
    on_exposure : callable, optional
        ``on_exposure(report)`` after the exposure check.
    on_position : callable, optional
        ``on_position(k, state)`` with state ``"kept"``, ``"capturing"`` or ``"done"``.

    Returns
    -------
    CaptureResult

    Raises
    ------
    ConfigError
        The rig cannot be calibrated (checked before anything moves).
    CaptureError
        The folder holds something else, or a partial capture of another plan.
    ExposureError
        The exposure check failed (nothing of that position was written).
    DeviceError
        A device failed; the message says what is saved and that the capture resumes.
    Cancelled
    """
    out = Path(out_dir)
    if image_ext not in (".png", ".tif", ".tiff"):
        raise ValueError(f"image_ext must be .png or .tif, got {image_ext!r}")
    rig = _with_image_ext(rig, image_ext)
    check_calibration_design(rig, "rig")
    limits.validate()
    plan_toml = rig_to_toml(rig)
    meta = json.loads(json.dumps(meta or {}))
    z_plan = [float(z) for z in rig.stage.z_mm] + [float(z) for z in rig.stage.repeat_z_mm]
    n_sweep, n_pos = rig.stage.n_positions, len(z_plan)
    if position_tolerance_mm is None:
        position_tolerance_mm = 0.25 * min(abs(b - a) for a, b in zip(z_plan, z_plan[1:]))

    def report(fraction, message):
        if progress is not None:
            progress(min(max(fraction, 0.0), 1.0), message)

    state = _prepare_folder(out, resume, plan_toml, meta, n_pos)
    if state is None:
        state = {"format": STATE_FORMAT, "software": "ptp-studio", "started": _now(), "rig_toml": plan_toml,
                 "meta": meta, "complete": False, "exposure": None,
                 "positions": [{"state": "pending", "z_mm": None} for _ in range(n_pos)]}
        out.mkdir(parents=True, exist_ok=True)
        _write_state(out, state)
    elif state.get("complete") and (out / "rig.toml").is_file():
        report(1.0, "capture already complete")
        from ptpcore.rig.rigfile import load_rig

        return CaptureResult(out, load_rig(out), [], list(range(n_pos)), None)

    kept = _verify_kept_positions(out, rig, state, report, on_position) if resume else []
    run = _CaptureRun(out, rig, camera, stage, display, state, image_ext, retries, report, on_frame, on_position)
    run.display_from_state(measure_display and not kept)
    todo = [k for k in range(n_pos) if k not in kept]
    state["devices"] = {"camera": describe(camera), "stage": describe(stage), "display": describe(display)}
    exposure = run.run(todo, z_plan, position_tolerance_mm, home, exposure_us,
                       (limits, accept_exposure, on_exposure) if check else None)

    final = _with_readings(run.rig, [p["z_mm"] for p in state["positions"]], n_sweep)
    save_rig(final, out / "rig.toml")
    state["complete"] = True
    _write_state(out, state)
    report(1.0, "capture complete")
    return CaptureResult(out, final, run.captured, kept, exposure, run.display_means)


def _with_readings(rig: Rig, readings: list, n_sweep: int) -> Rig:
    """``rig`` with the captured stage readings: the sweep's, then its repeats' (``[stage] repeat_z_mm``)."""
    out = rig.with_z(readings[:n_sweep])
    if len(readings) > n_sweep:
        out = replace(out, stage=replace(out.stage, repeat_z_mm=tuple(float(z) for z in readings[n_sweep:])))
    return out


def with_repeat_of_first(rig: Rig) -> Rig:
    """The plan ``rig`` ending its sweep at its first position again (``[stage] repeat_z_mm``,
    ptp-dataset/2): ``ptp calibrate`` compares the two captures of that height and reports the drift
    (:mod:`ptpcore.fit.drift`)."""
    return replace(rig, stage=replace(rig.stage, repeat_z_mm=(float(rig.stage.z_mm[0]),)))


def _verify_kept_positions(out: Path, rig: Rig, state: dict, report, on_position) -> list[int]:
    """Resume: keep the positions whose readings are recorded and whose images all read back.

    Stale temporary files are removed; every other position is marked pending again.
    """
    for stale in out.rglob(".*.part"):
        with contextlib.suppress(OSError):
            stale.unlink()
    kept = []
    n_pos = len(state["positions"])
    for k, pos in enumerate(state["positions"]):
        report(0.0, f"verifying position {k} (0 … {n_pos - 1})")
        if pos.get("state") == "done" and _position_complete(out, rig, k):
            kept.append(k)
            if on_position:
                on_position(k, "kept")
        else:
            pos.update(state="pending")
    _write_state(out, state)
    return kept


class _CaptureRun:
    """The devices' part of one capture: open them, visit the positions, write every frame, close them.

    ``state`` (the capture-state document) is updated and written after every
    change, so that a crash loses at most the position being captured.
    """

    def __init__(self, out: Path, rig: Rig, camera, stage, display, state: dict, image_ext: str, retries: int,
                 report, on_frame, on_position):
        self.out, self.rig, self.state = out, rig, state
        self.camera, self.stage, self.display = camera, stage, display
        self.image_ext, self.retries, self.report = image_ext, retries, report
        self.on_frame, self.on_position = on_frame, on_position
        self.n_pos = len(state["positions"])
        self.captured: list[int] = []
        self.done_frames = 0
        self.total = 1
        self.measure_display = False
        self.display_means: np.ndarray | None = None

    def saved_note(self) -> str:
        """What is saved so far, for every error message."""
        done = [k for k, p in enumerate(self.state["positions"]) if p.get("state") == "done"]
        if not done:
            return f"nothing is captured yet in {self.out}; resume the capture once fixed"
        return (f"{len(done)} of {self.n_pos} positions are saved in {self.out}; fix the cause and resume the"
                " capture to get the rest")

    def run(self, todo: list[int], z_plan: list[float], tolerance_mm: float, home: bool, exposure_us,
            exposure_check) -> ExposureReport | None:
        """Capture positions ``todo``; ``exposure_check`` = (limits, accept, on_exposure) or None to skip it.

        Returns the exposure check's report (None when not run). Device, exposure and
        folder errors are re-raised with :meth:`saved_note` appended.
        """
        self.total = max(1, len(todo) * frames_per_position(self.rig))
        exposure = None
        opened = []
        try:
            for dev in (self.display, self.camera, self.stage):
                _call(dev, "open")
                opened.append(dev)
            if exposure_us is not None:
                _call(self.camera, "set_exposure", float(exposure_us))
            if home and todo:
                self.report(0.0, "homing the stage")
                _call(self.stage, "home")
            for i, k in enumerate(todo):
                z = self.move_to(k, z_plan[k], tolerance_mm)
                if i == 0 and exposure_check is not None:
                    exposure = self.check_exposure_at(z, exposure_us, *exposure_check)
                if i == 0 and self.measure_display:
                    self.measure_display_at()
                self.capture_position(k, z)
        except DeviceError as exc:
            raise type(exc)(f"{exc} — {self.saved_note()}") from exc
        except ExposureError as exc:
            raise ExposureError(f"{exc} — {self.saved_note()}") from None
        except OSError as exc:  # the folder: disk full, permissions, a vanished drive
            raise CaptureError(f"{exc} — {self.saved_note()}") from exc
        finally:
            for dev in reversed(opened):
                try:
                    _call(dev, "close")
                except PtpError as exc:
                    warnings.warn(str(exc), stacklevel=2)
        return exposure

    def move_to(self, k: int, z_planned: float, tolerance_mm: float) -> float:
        """Move the stage to position ``k``; its reading (mm), checked against the plan."""
        self.report(self.done_frames / self.total,
                    f"position {k} (0 … {self.n_pos - 1}): moving the stage to z = {z_planned:g} mm")
        _call(self.stage, "move_to", z_planned)
        z = float(_call(self.stage, "position"))
        if not math.isfinite(z) or abs(z - z_planned) > tolerance_mm:
            raise DeviceError(f"{describe(self.stage)}: reads z = {z:g} mm after the move to {z_planned:g} mm"
                              f" (more than {tolerance_mm:g} mm away)")
        return z

    def check_exposure_at(self, z: float, exposure_us, limits: ExposureLimits, accept: bool,
                          on_exposure) -> ExposureReport:
        """The exposure check at the first position captured (recorded in the state)."""
        self.report(self.done_frames / self.total, "checking the exposure")
        exposure = check_exposure(self.rig, self.camera, self.display, limits=limits, exposure_us=exposure_us,
                                  retries=self.retries)
        self.state["exposure"] = exposure.summary()
        _write_state(self.out, self.state)
        if on_exposure:
            on_exposure(exposure)
        if not exposure.ok and not accept:
            raise ExposureError(f"exposure check at z = {z:g} mm: {exposure.message}")
        return exposure

    def display_from_state(self, measure: bool) -> None:
        """A response measured when the capture started (its patterns went through it), else measure it
        at the first position when ``measure``."""
        d = self.state.get("display")
        if d:
            self.rig = replace(self.rig, display=Display(tuple(d["levels"]), tuple(d["luminance"])))
            if d.get("camera_means"):
                self.display_means = np.asarray(d["camera_means"], dtype=float)
        self.measure_display = bool(measure) and not d

    def measure_display_at(self) -> None:
        """The display response at the first position captured: into the rig and the state."""
        self.report(self.done_frames / self.total, "measuring the display's response (a ramp of uniform levels)")
        resp, self.display_means, n_pix = measure_display_response(self.rig, self.camera, self.display,
                                                                   retries=self.retries)
        self.rig = replace(self.rig, display=resp)
        self.state["display"] = {"levels": list(resp.levels), "luminance": list(resp.luminance),
                                 "camera_means": [float(v) for v in self.display_means], "camera_pixels": n_pix}
        _write_state(self.out, self.state)

    def capture_position(self, k: int, z: float) -> None:
        """Show every pattern at position ``k`` (stage reading ``z``), grab and write each frame."""
        state, out = self.state, self.out
        state["positions"][k] = {"state": "capturing", "z_mm": z}
        _write_state(out, state)
        if self.on_position:
            self.on_position(k, "capturing")
        hint = getattr(self.camera, "position_hint", None)  # simulated cameras: a repeat is another position
        if callable(hint):
            hint(k)
        for spec in self.rig.fringes.frames():
            self.capture_frame(k, z, spec)
        for name, image, what in extra_frames(self.rig, k, z):
            self.capture_image(k, z, name, image, what)
        state["positions"][k] = {"state": "done", "z_mm": z}
        _write_state(out, state)
        self.captured.append(k)
        if self.on_position:
            self.on_position(k, "done")

    def capture_frame(self, k: int, z: float, spec) -> None:
        """One pattern ``spec = (dir, level, period, step, N)``: show, settle, grab, check, write atomically."""
        rig = self.rig
        d, _j, t, s, big_n = spec
        self.report(self.done_frames / self.total, f"{position_label(k, z)} (0 … {self.n_pos - 1}): {d} period"
                                                   f" {t} px, step {s + 1}/{big_n}")
        _call(self.display, "show", pattern_image(rig, d, t, s, big_n, z))
        _call(self.display, "settle")
        frame = _check_frame(_grab(self.camera, f"position {k}, {d} period {t} step {s + 1}", self.retries),
                             rig, self.camera)
        ok, buf = cv2.imencode(self.image_ext, frame)
        if not ok:
            raise OSError(f"could not encode the frame of position {k} as {self.image_ext}")
        path = self.out / rig.image_name(k, d, t, s, big_n)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(path, buf.tobytes())
        self.done_frames += 1
        if self.on_frame:
            self.on_frame(k, spec, frame)


    def capture_image(self, k: int, z: float, name: str, image: np.ndarray, what: str) -> None:
        """One frame besides the phase steps (:func:`extra_frames`): show, settle, grab, check, write atomically."""
        self.report(self.done_frames / self.total, f"{position_label(k, z)} (0 … {self.n_pos - 1}): {what}")
        _call(self.display, "show", image)
        _call(self.display, "settle")
        frame = _check_frame(_grab(self.camera, f"position {k}, {what}", self.retries), self.rig, self.camera)
        ok, buf = cv2.imencode(self.image_ext, frame)
        if not ok:
            raise OSError(f"could not encode the frame of position {k} as {self.image_ext}")
        path = self.out / name
        path.parent.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(path, buf.tobytes())
        self.done_frames += 1


def _prepare_folder(out: Path, resume: bool, plan_toml: str, meta: dict, n_pos: int) -> dict | None:
    """Check what ``out`` holds; return the state to resume (or None to start afresh)."""
    if out.exists() and not out.is_dir():
        raise CaptureError(f"{out}: exists and is not a folder")
    state = _read_state(out) if out.is_dir() else None
    if state is None:
        if (out / "rig.toml").exists():
            raise CaptureError(f"{out}: already holds a dataset (rig.toml); choose another folder")
        if out.is_dir() and any(out.iterdir()):
            raise CaptureError(f"{out}: folder is not empty and holds no capture to "
                               f"{'resume' if resume else 'continue'}; choose a new or empty folder")
        return None
    done = _done_count(state)
    total = len(state["positions"])
    if not resume:
        if state.get("complete"):
            raise CaptureError(f"{out}: holds a complete capture; choose another folder")
        raise CaptureError(f"{out}: holds a partial capture ({done} of {total} positions); resume it"
                           " or choose another folder")
    if state["rig_toml"] != plan_toml:
        raise CaptureError(f"{out}: the partial capture was started with another rig"
                           f" ({_first_difference(state['rig_toml'], plan_toml)}); resume it with the same rig")
    if (state.get("meta") or {}) != meta:
        old = state.get("meta") or {}
        keys = sorted(k for k in set(old) | set(meta) if old.get(k) != meta.get(k))
        diffs = ", ".join(f"{k}: {old.get(k)!r} then, {meta.get(k)!r} now" for k in keys)
        raise CaptureError(f"{out}: the partial capture was started with other settings ({diffs});"
                           " resume it with the same settings")
    if total != n_pos:
        raise CaptureError(f"{out / STATE_FILE}: lists {total} positions, the plan has another number")
    return state


def _position_complete(out: Path, rig: Rig, k: int) -> bool:
    """Every image of position ``k`` exists and decodes to the camera's size and depth."""
    names = [rig.image_name(k, d, t, s, big_n) for d, _j, t, s, big_n in rig.fringes.frames()]
    names += [name for name, _img, _what in extra_frames(rig, k, rig.stage.z_mm[k])]
    for name in names:
        try:
            read_image(out / name, rig)
        except PtpError:
            return False
    return True
