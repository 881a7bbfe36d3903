"""Reading ``rig.toml`` (``ptp-dataset/1`` and ``/2``) and ``scan.toml`` (``ptp-scan/1``) into the model.

All validation happens here, at load time: once a :class:`~ptpcore.rig.model.Rig` exists, the
numerics downstream can trust it. Every error is one :class:`~ptpcore.errors.ConfigError` line
naming the file and the key ("section.key") and what was expected (FORMATS.md); a
``ptp-dataset/2`` key in a file that declares ``/1`` names the format that has it (:data:`V2_KEYS`).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from ptpcore.errors import ConfigError

from .fringe_reading import check_heterodyne_span, read_fringes
from .model import (DATASET_FORMAT, DATASET_FORMAT_2, DEFAULT_TEMPLATE, SCAN_FORMAT, Camera, DecodeSettings, Display,
                    FrameEntry, HeightSweep, Lcd, Projector, Rig, ScanSpec, Stage, format_period)
from .templates import GRAY_TEMPLATE_FIELDS, REFERENCE_TEMPLATE_FIELDS, needed_fields, validate_template
from .toml_fields import Section, convert, read_text, short_repr, tname, toml_document

__all__ = ["MAX_POSITIONS", "V2_KEYS", "load_rig", "rig_from_toml", "load_scan"]

MAX_POSITIONS = 10_000
V2_KEYS: dict[str, tuple[str, ...]] = {
    "": ("display", "decode", "projector", "height"),
    "camera": ("bit_shift",),
    "lcd": ("cover_glass_mm", "cover_glass_index", "cover_glass_mm_sigma", "cover_glass_index_sigma",
            "flatness_u_px", "flatness_v_px", "flatness_um"),
    "stage": ("repeat_z_mm",),
    "fringes": ("phase_origin_rad", "shift_sign", "unwrap", "gray_bits", "gray_inverse", "x", "y"),
    "images": ("gray_template", "white_template", "black_template", "frames"),
}
"""The keys only ``ptp-dataset/2`` has, by table ("": top-level tables); in a ``/1`` file each is an
error naming ``/2`` (FORMATS.md)."""


def load_rig(path: str | Path) -> Rig:
    """Read and validate a ``rig.toml`` file (or the one inside a dataset folder)."""
    path = Path(path)
    if path.is_dir():
        path = path / "rig.toml"
    return rig_from_toml(read_text(path), str(path))


def rig_from_toml(text: str, source: str = "rig.toml") -> Rig:
    """Parse and validate the text of a ``rig.toml`` (``ptp-dataset/1`` or ``/2``).

    Raises
    ------
    ConfigError
        Naming the key and what was expected.
    """
    known = {"format", "camera", "lcd", "stage", "fringes", "images"}
    doc = toml_document(text, source, (DATASET_FORMAT, DATASET_FORMAT_2), known | set(V2_KEYS[""]))
    v2 = doc["format"] == DATASET_FORMAT_2
    if not v2:
        _refuse_v2_keys(doc, source)

    camera = _camera_section(doc, source, v2)
    lcd = _lcd_section(doc, source, v2)
    stage = _stage_section(doc, source, v2)
    fringes = read_fringes(doc, source, v2)
    display = _display_section(doc, source, v2)
    decode = _decode_section(doc, source, v2)
    rig = _images_section(doc, source, v2, camera, lcd, stage, fringes, display, decode)
    if fringes.unwrap == "heterodyne":
        check_heterodyne_span(rig, source)
    if v2 and ("projector" in doc or "height" in doc):
        if "projector" not in doc or "height" not in doc:
            missing = "projector" if "projector" not in doc else "height"
            raise ConfigError(f"{source}: a height sweep needs both [projector] and [height]; [{missing}] is missing")
        rig = replace(rig, projector=_projector_section(doc, source), height=_height_section(doc, source))
        h_rig = rig.height_rig()
        validate_template(rig.height.template, source, key="height.template",
                          needed=needed_fields(("pos", "dir", "period", "step"), h_rig.fringes, h_rig.stage))
    return rig


def _refuse_v2_keys(doc: dict, source: str) -> None:
    """In a ``ptp-dataset/1`` document, the first :data:`V2_KEYS` key (in the file's order) is an
    error naming the format that has it."""
    for section, value in doc.items():
        if section in V2_KEYS[""]:
            found = [(section, value)]
        elif section in V2_KEYS and isinstance(value, dict):
            found = [(f"{section}.{k}", v) for k, v in value.items() if k in V2_KEYS[section]]
        else:
            continue
        for name, v in found[:1]:
            if isinstance(v, dict):
                what = f"table [{name}] is a {DATASET_FORMAT_2} table"
            elif isinstance(v, list) and v and all(isinstance(e, dict) for e in v):
                what = f"table [[{name}]] is a {DATASET_FORMAT_2} table"
            else:
                what = f"key '{name}' is a {DATASET_FORMAT_2} key"
            raise ConfigError(f"{source}: {what}: set format = \"{DATASET_FORMAT_2}\"")


def _camera_section(doc: dict, source: str, v2: bool) -> Camera:
    """``[camera]``: size 1..100000 px, bit depth 8..16, bit_shift within the stored bits (/2)."""
    s = Section(doc, "camera", source)
    camera = Camera(s.get("width", "int"), s.get("height", "int"), s.get("bit_depth", "int", 8),
                    s.get("bit_shift", "int", 0) if v2 else 0)
    s.finish()
    for key, v in (("width", camera.width), ("height", camera.height)):
        if not 1 <= v <= 100_000:
            raise ConfigError(f"{source}: key 'camera.{key}' must be between 1 and 100000, got {v}")
    if not 8 <= camera.bit_depth <= 16:
        raise ConfigError(f"{source}: key 'camera.bit_depth' must be 8 to 16, got {camera.bit_depth}")
    stored_bits = 8 if camera.bit_depth == 8 else 16
    if not 0 <= camera.bit_shift <= stored_bits - camera.bit_depth:
        raise ConfigError(f"{source}: key 'camera.bit_shift' must be 0 to {stored_bits - camera.bit_depth}"
                          f" for a {camera.bit_depth}-bit camera, got {camera.bit_shift}")
    return camera


def _lcd_section(doc: dict, source: str, v2: bool) -> Lcd:
    """``[lcd]``: size, pitch (mm), and for /2 the cover glass, its tolerances and the flatness grid."""
    s = Section(doc, "lcd", source)
    lcd_w, lcd_h = s.get("width", "int"), s.get("height", "int")
    pitch = s.get("pitch_mm", "list[float]")
    extra = {}
    if v2:
        extra = dict(
            cover_glass_mm=_nonneg_or_none(s.get("cover_glass_mm", "float", None), f"{source}: key 'lcd.cover_glass_mm'"),
            cover_glass_index=s.get("cover_glass_index", "float", 1.52),
            cover_glass_mm_sigma=_nonneg(s.get("cover_glass_mm_sigma", "float", 0.0),
                                         f"{source}: key 'lcd.cover_glass_mm_sigma'"),
            cover_glass_index_sigma=_nonneg(s.get("cover_glass_index_sigma", "float", 0.0),
                                            f"{source}: key 'lcd.cover_glass_index_sigma'"),
            flatness_u_px=tuple(s.get("flatness_u_px", "list[float]", [])),
            flatness_v_px=tuple(s.get("flatness_v_px", "list[float]", [])),
        )
        rows = s.table.get("flatness_um", [])
        s.used.add("flatness_um")
        if not isinstance(rows, list):
            raise ConfigError(f"{source}: key 'lcd.flatness_um' must be a list of rows, got {tname(rows)}")
        extra["flatness_um"] = tuple(tuple(convert(r, "list[float]", f"{source}: key 'lcd.flatness_um[{i}]'"))
                                     for i, r in enumerate(rows))
    s.finish()
    if len(pitch) != 2 or min(pitch) <= 0:
        raise ConfigError(f"{source}: key 'lcd.pitch_mm' must be two positive numbers [x, y],"
                          f" got {short_repr(pitch)}")
    for key, v in (("width", lcd_w), ("height", lcd_h)):
        if not 1 <= v <= 1_000_000:
            raise ConfigError(f"{source}: key 'lcd.{key}' must be between 1 and 1000000, got {short_repr(v)}")
    if v2:
        if not 1.0 <= extra["cover_glass_index"] <= 3.0:
            raise ConfigError(f"{source}: key 'lcd.cover_glass_index' must be 1 to 3, got {extra['cover_glass_index']}")
        fu, fv, fz = extra["flatness_u_px"], extra["flatness_v_px"], extra["flatness_um"]
        if fu or fv or fz:
            for key, grid in (("flatness_u_px", fu), ("flatness_v_px", fv)):
                if len(grid) < 2 or any(b <= a for a, b in zip(grid, grid[1:])):
                    raise ConfigError(f"{source}: key 'lcd.{key}' must list at least 2 increasing LCD coordinates,"
                                      f" got {short_repr(list(grid))}")
            if len(fz) != len(fv) or any(len(r) != len(fu) for r in fz):
                raise ConfigError(f"{source}: key 'lcd.flatness_um' must have {len(fv)} rows of {len(fu)} values"
                                  " ([v][u], one per flatness_v_px and flatness_u_px)")
    lcd = Lcd(lcd_w, lcd_h, (pitch[0], pitch[1]), **extra)
    return lcd


def _stage_section(doc: dict, source: str, v2: bool) -> Stage:
    """``[stage]``: readings strictly monotonic (mm), travel direction ``[a, b, 1]``, repeat readings (/2)."""
    s = Section(doc, "stage", source)
    z = s.get("z_mm", "list[float]")
    direction = s.get("direction", "list[float]", [0.0, 0.0, 1.0])
    repeat = s.get("repeat_z_mm", "list[float]", []) if v2 else []
    s.finish()
    min_positions = 1 if v2 else 2
    if len(z) < min_positions:
        hint = f" (one position needs format = \"{DATASET_FORMAT_2}\")" if not v2 and len(z) == 1 else ""
        raise ConfigError(f"{source}: key 'stage.z_mm' needs at least {min_positions} position"
                          f"{'s' if min_positions > 1 else ''}, got {len(z)}{hint}")
    if len(z) + len(repeat) > MAX_POSITIONS:
        raise ConfigError(f"{source}: key 'stage.z_mm' lists {len(z)} positions, at most {MAX_POSITIONS}")
    dz = [b - a for a, b in zip(z, z[1:])]
    if dz and not (all(d > 0 for d in dz) or all(d < 0 for d in dz)):
        i = next(i for i, d in enumerate(dz) if d == 0 or (d > 0) != (dz[0] > 0))
        what = "a duplicate position" if dz[i] == 0 else "a change of direction"
        raise ConfigError(
            f"{source}: key 'stage.z_mm' must be strictly monotonic; {what} at index {i + 1}"
            f" ({z[i]} -> {z[i + 1]})"
        )
    if len(direction) != 3 or direction[2] != 1.0:
        raise ConfigError(f"{source}: key 'stage.direction' must be [a, b, 1.0], got {short_repr(direction)}")
    stage = Stage(tuple(z), (direction[0], direction[1], 1.0), tuple(repeat))
    return stage


def _display_section(doc: dict, source: str, v2: bool):
    """``[display]`` (/2): a measured response, levels strictly increasing in 0..255 and luminance monotonic; or None."""
    display = None
    if v2 and "display" in doc:
        s = Section(doc, "display", source)
        levels = s.get("levels", "list[float]")
        lum = s.get("luminance", "list[float]")
        s.finish()
        if len(levels) < 2 or len(levels) != len(lum):
            raise ConfigError(f"{source}: keys 'display.levels' and 'display.luminance' must have the same"
                              f" length (at least 2), got {len(levels)} and {len(lum)}")
        if any(b <= a for a, b in zip(levels, levels[1:])) or not 0 <= levels[0] or levels[-1] > 255:
            raise ConfigError(f"{source}: key 'display.levels' must increase strictly within 0..255,"
                              f" got {short_repr(levels)}")
        if any(b < a for a, b in zip(lum, lum[1:])) or lum[-1] <= lum[0]:
            raise ConfigError(f"{source}: key 'display.luminance' must be monotonic (increasing),"
                              f" got {short_repr(lum)}")
        display = Display(tuple(levels), tuple(lum))
    return display


def _decode_section(doc: dict, source: str, v2: bool) -> DecodeSettings:
    """``[decode]`` (/2): thresholds, each None where the engine's default applies."""
    decode = DecodeSettings()
    if v2 and "decode" in doc:
        s = Section(doc, "decode", source)
        decode = DecodeSettings(s.get("min_modulation", "float", None), s.get("border_margin_px", "int", None),
                                s.get("unwrap_tolerance", "float", None))
        s.finish()
        if decode.min_modulation is not None and not 0 <= decode.min_modulation < 1:
            raise ConfigError(f"{source}: key 'decode.min_modulation' must be 0 to 1 (a fraction of full scale),"
                              f" got {decode.min_modulation}")
        if decode.border_margin_px is not None and not 0 <= decode.border_margin_px <= 1000:
            raise ConfigError(f"{source}: key 'decode.border_margin_px' must be 0 to 1000, got {decode.border_margin_px}")
        if decode.unwrap_tolerance is not None and not 0 < decode.unwrap_tolerance <= 0.5:
            raise ConfigError(f"{source}: key 'decode.unwrap_tolerance' must be above 0 and at most 0.5 (periods),"
                              f" got {decode.unwrap_tolerance}")
    return decode


def _images_section(doc: dict, source: str, v2: bool, camera: Camera, lcd: Lcd, stage: Stage, fringes,
                    display, decode: DecodeSettings) -> Rig:
    """``[images]``: the templates (or, /2, the frames named one by one), checked against the design; the whole rig."""
    s = Section(doc, "images", source, required=False)
    template = s.get("template", "str", DEFAULT_TEMPLATE)
    gray_t = white_t = black_t = None
    frames_raw = []
    if v2:
        gray_t = s.get("gray_template", "str", None)
        white_t = s.get("white_template", "str", None)
        black_t = s.get("black_template", "str", None)
        frames_raw = s.table.get("frames", [])
        s.used.add("frames")
    s.finish()
    rig = Rig(camera, lcd, stage, fringes, template, display, decode, gray_t, white_t, black_t)
    if v2 and frames_raw:
        return replace(rig, frame_list=_frame_list(frames_raw, rig, source))
    validate_template(template, source, needed=needed_fields(("pos", "dir", "period", "step"), fringes, stage))
    for d in fringes.directions:
        for j, t in enumerate(fringes.periods(d)):
            try:
                template.format(pos=0, dir=d, period=format_period(t), step=0, steps=3, period_index=j)
            except (ValueError, TypeError) as exc:
                raise ConfigError(f"{source}: key 'images.template' cannot name period {format_period(t)} px"
                                  f" ({exc}); use {{period}} without an integer format spec, or {{period_index}}")\
                    from None
    if fringes.unwrap == "gray":
        if gray_t is None:
            raise ConfigError(f"{source}: key 'images.gray_template' is needed with fringes.unwrap = \"gray\""
                              " (or name the frames in [[images.frames]])")
        needed = needed_fields(("pos", "dir", "bit") + (("inverse",) if fringes.gray_inverse else ()), fringes, stage)
        validate_template(gray_t, source, key="images.gray_template", fields=GRAY_TEMPLATE_FIELDS, needed=needed)
    elif gray_t is not None:
        raise ConfigError(f"{source}: key 'images.gray_template' is given but fringes.unwrap is not \"gray\"")
    if (white_t is None) != (black_t is None):
        raise ConfigError(f"{source}: keys 'images.white_template' and 'images.black_template' go together")
    for key, t in (("images.white_template", white_t), ("images.black_template", black_t)):
        if t is not None:
            validate_template(t, source, key=key, fields=REFERENCE_TEMPLATE_FIELDS,
                              needed=needed_fields(("pos",), fringes, stage))
    return rig


_FRAME_KEYS = {"pos", "dir", "period_index", "step", "gray_bit", "inverse", "reference", "file"}


def _frame_list(raw, rig: Rig, source: str) -> tuple[FrameEntry, ...]:
    """``[[images.frames]]``: every entry valid, every frame the design needs named exactly once."""
    if not isinstance(raw, list) or not all(isinstance(e, dict) for e in raw):
        raise ConfigError(f"{source}: key 'images.frames' must be an array of tables [[images.frames]]")
    f = rig.fringes
    k_total = rig.stage.n_positions
    out = []
    seen: dict = {}
    for i, e in enumerate(raw):
        where = f"{source}: [[images.frames]] entry {i + 1}"
        unknown = sorted(set(e) - _FRAME_KEYS)
        if unknown:
            raise ConfigError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(_FRAME_KEYS))})")

        def get(key, kind, default=...):
            if key not in e:
                if default is ...:
                    raise ConfigError(f"{where}: missing key {key!r}")
                return default
            if kind == "bool":
                if not isinstance(e[key], bool):
                    raise ConfigError(f"{where}: key {key!r} must be true or false, got {short_repr(e[key])}")
                return e[key]
            return convert(e[key], kind, f"{where}: key {key!r}")

        file = get("file", "str")
        try:
            validate_template(file, source, key=f"images.frames[{i}].file", fields=(), needed=())
        except ConfigError as exc:
            raise ConfigError(str(exc)) from None
        pos = get("pos", "int", 0)
        if not 0 <= pos < k_total:
            raise ConfigError(f"{where}: key 'pos' must be 0 to {k_total - 1}, got {pos}")
        ref = get("reference", "str", None)
        if ref is not None:
            if ref not in ("white", "black"):
                raise ConfigError(f"{where}: key 'reference' must be \"white\" or \"black\", got {short_repr(ref)}")
            extra = sorted(set(e) & {"dir", "period_index", "step", "gray_bit", "inverse"})
            if extra:
                raise ConfigError(f"{where}: a reference frame takes no key {extra[0]!r}")
            entry = FrameEntry(file, pos, reference=ref)
        else:
            d = get("dir", "str", None)
            if d is None and len(f.directions) == 1:
                d = f.directions[0]
            if d not in f.directions:
                raise ConfigError(f"{where}: key 'dir' must be one of {list(f.directions)}, got {short_repr(d)}")
            if "gray_bit" in e:
                if f.unwrap != "gray":
                    raise ConfigError(f"{where}: a Gray-code frame, but fringes.unwrap is not \"gray\"")
                bit = get("gray_bit", "int")
                if not 0 <= bit < f.bits(d):
                    raise ConfigError(f"{where}: key 'gray_bit' must be 0 to {f.bits(d) - 1}, got {bit}")
                inv = get("inverse", "bool", False)
                if inv and not f.gray_inverse:
                    raise ConfigError(f"{where}: an inverse Gray-code frame, but fringes.gray_inverse is false")
                if "period_index" in e or "step" in e:
                    raise ConfigError(f"{where}: a Gray-code frame takes no 'period_index' or 'step'")
                entry = FrameEntry(file, pos, d, gray_bit=bit, inverse=inv)
            else:
                j = get("period_index", "int")
                n_levels = len(f.periods(d))
                if not 0 <= j < n_levels:
                    raise ConfigError(f"{where}: key 'period_index' must be 0 to {n_levels - 1}, got {j}")
                n = f.steps_of(d)[j]
                step = get("step", "int")
                if not 0 <= step < n:
                    raise ConfigError(f"{where}: key 'step' must be 0 to {n - 1}, got {step}")
                if "inverse" in e:
                    raise ConfigError(f"{where}: key 'inverse' belongs to Gray-code frames")
                entry = FrameEntry(file, pos, d, period_index=j, step=step)
        if entry.key in seen:
            raise ConfigError(f"{where}: the same frame as entry {seen[entry.key] + 1}")
        seen[entry.key] = i
        out.append(entry)
    rig = replace(rig, frame_list=tuple(out))
    for k in range(k_total):
        for d, j, _t, s_, _n in f.frames():
            if (k, "phase", d, j, s_) not in seen:
                raise ConfigError(f"{source}: [[images.frames]] names no frame for pos = {k}, dir = {d!r},"
                                  f" period_index = {j}, step = {s_}")
        for d, b, inv in f.gray_frames():
            if (k, "gray", d, b, inv) not in seen:
                raise ConfigError(f"{source}: [[images.frames]] names no Gray-code frame for pos = {k},"
                                  f" dir = {d!r}, gray_bit = {b}" + (", inverse = true" if inv else ""))
        refs = {r for r in ("white", "black") if (k, "ref", r) in seen}
        if len(refs) == 1:
            raise ConfigError(f"{source}: [[images.frames]] has a {next(iter(refs))} reference frame for"
                              f" pos = {k} but not its {'black' if 'white' in refs else 'white'} one")
    return tuple(out)


def _projector_section(doc: dict, source: str) -> Projector:
    """``[projector]`` (/2): the projector's size and its pattern design, as ``[fringes]`` without a carrier.

    Unwrapping by periods or heterodyne (a height sweep names no Gray-code frames); direction ``x``
    (what heights need) must be shown.
    """
    table = doc["projector"]
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: 'projector' must be a table [projector], got {tname(table)}")
    size = {}
    for key in ("width", "height"):
        if key not in table:
            raise ConfigError(f"{source}: missing key 'projector.{key}' (expected int)")
        size[key] = convert(table[key], "int", f"{source}: key 'projector.{key}'")
        if not 1 <= size[key] <= 100_000:
            raise ConfigError(f"{source}: key 'projector.{key}' must be between 1 and 100000, got {size[key]}")
    if "carrier_px_per_mm" in table:
        raise ConfigError(f"{source}: key 'projector.carrier_px_per_mm' is not allowed (the projector has no carrier)")
    rest = {k: v for k, v in table.items() if k not in ("width", "height")}
    rest.setdefault("directions", ["x"])
    f = read_fringes({"projector": rest}, source, True, name="projector")
    if f.unwrap == "gray":
        raise ConfigError(f"{source}: key 'projector.unwrap' = \"gray\" is not supported (a height sweep names"
                          " no Gray-code frames); use \"periods\" or \"heterodyne\"")
    if "x" not in f.directions:
        raise ConfigError(f"{source}: key 'projector.directions' must include \"x\" (heights come from u_p),"
                          f" got {short_repr(list(f.directions))}")
    for d in f.directions:
        extent = size["width"] if d == "x" else size["height"]
        if f.unwrap == "periods" and float(f.periods(d)[0]) < extent:
            raise ConfigError(f"{source}: key 'projector.periods_px': the coarsest period of direction {d}"
                              f" ({format_period(f.periods(d)[0])} px) must span the projector's {extent} px")
    return Projector(size["width"], size["height"], f)


def _height_section(doc: dict, source: str) -> HeightSweep:
    """``[height]`` (/2): the plate's heights (at least 3, strictly monotonic) and its frames' template."""
    s = Section(doc, "height", source)
    z = s.get("z_mm", "list[float]")
    template = s.get("template", "str", HeightSweep().template)
    s.finish()
    if len(z) < 3:
        raise ConfigError(f"{source}: key 'height.z_mm' needs at least 3 heights, got {len(z)}")
    if len(z) > MAX_POSITIONS:
        raise ConfigError(f"{source}: key 'height.z_mm' lists {len(z)} heights, at most {MAX_POSITIONS}")
    dz = [b - a for a, b in zip(z, z[1:])]
    if not (all(d > 0 for d in dz) or all(d < 0 for d in dz)):
        i = next(i for i, d in enumerate(dz) if d == 0 or (d > 0) != (dz[0] > 0))
        raise ConfigError(f"{source}: key 'height.z_mm' must be strictly monotonic; at index {i + 1}"
                          f" ({z[i]} -> {z[i + 1]})")
    return HeightSweep(tuple(float(v) for v in z), template)


def load_scan(folder) -> ScanSpec:
    """Read and validate a scan folder's ``scan.toml`` (FORMATS.md ``ptp-scan/1``).

    Raises
    ------
    ConfigError
        A missing or invalid ``scan.toml`` (naming the key), or a template naming no frame present.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"{folder}: scan folder not found")
    path = folder / "scan.toml"
    source = str(path)
    doc = toml_document(read_text(path), source, SCAN_FORMAT, {"format", "camera", "projector", "images"})
    camera = _camera_section(doc, source, True)
    if "projector" not in doc:
        raise ConfigError(f"{source}: missing section [projector]")
    projector = _projector_section(doc, source)
    s = Section(doc, "images", source)
    template = s.get("template", "str")
    s.finish()
    needed = ("period", "step") + (("dir",) if len(projector.fringes.directions) > 1 else ())
    validate_template(template, source, needed=needed)
    spec = ScanSpec(camera, projector, template)
    if "{pos" not in template:
        return spec
    first = next(iter(spec.rig().fringes.frames()))
    d, j, t, n, big_n = first
    views = 0
    while (folder / template.format(pos=views, dir=d, period=format_period(t), step=n, steps=big_n,
                                    period_index=j)).is_file() and views < MAX_POSITIONS:
        views += 1
    if views == 0:
        raise ConfigError(f"{source}: key 'images.template' names no frame present (first:"
                          f" {template.format(pos=0, dir=d, period=format_period(t), step=n, steps=big_n, period_index=j)})")
    return replace(spec, views=views)


def _nonneg(v: float, where: str) -> float:
    if v < 0:
        raise ConfigError(f"{where} must be >= 0, got {v}")
    return v


def _nonneg_or_none(v: float | None, where: str) -> float | None:
    """``v`` checked >= 0; None (an absent key) stays None."""
    return None if v is None else _nonneg(v, where)
