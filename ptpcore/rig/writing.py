"""Writing the model back: ``rig.toml`` and ``scan.toml`` text, and ``rig.toml`` saved atomically.

A rig that uses no ``ptp-dataset/2`` key is written as ``/1``, so older readers keep reading it;
the text round-trips through :func:`ptpcore.rig.reading.rig_from_toml`.
"""

from __future__ import annotations

from pathlib import Path

import tomli_w

from ptpcore.atomic import write_text_atomic

from .model import DATASET_FORMAT, DATASET_FORMAT_2, SCAN_FORMAT, Lcd, Projector, Rig, ScanSpec, format_period

__all__ = ["rig_to_toml", "save_rig", "scan_to_toml"]


def rig_to_toml(rig: Rig) -> str:
    """The ``rig.toml`` text of ``rig`` (round-trips through :func:`rig_from_toml`).

    ``ptp-dataset/1`` unless the rig uses a ``/2`` key (only those that differ
    from their defaults are written).
    """
    f = rig.fringes
    v2: dict = {}  # section -> {key: value} of the /2 keys in use

    def put(section: str, key: str, value) -> None:
        v2.setdefault(section, {})[key] = value

    c, lcd, st = rig.camera, rig.lcd, rig.stage
    if c.bit_shift:
        put("camera", "bit_shift", c.bit_shift)
    d = Lcd()
    if lcd.cover_glass_mm is not None:  # 0 too: "no glass" declared is not a bare panel assumed
        put("lcd", "cover_glass_mm", float(lcd.cover_glass_mm))
    for key in ("cover_glass_index", "cover_glass_mm_sigma", "cover_glass_index_sigma"):
        if getattr(lcd, key) != getattr(d, key):
            put("lcd", key, float(getattr(lcd, key)))
    if lcd.flatness_um:
        put("lcd", "flatness_u_px", [float(x) for x in lcd.flatness_u_px])
        put("lcd", "flatness_v_px", [float(x) for x in lcd.flatness_v_px])
        put("lcd", "flatness_um", [[float(x) for x in r] for r in lcd.flatness_um])
    if st.repeat_z_mm:
        put("stage", "repeat_z_mm", [float(z) for z in st.repeat_z_mm])
    if any(isinstance(t, float) for t in f.periods_px):
        put("fringes", "periods_px", [format_period(t) if isinstance(t, int) else float(t) for t in f.periods_px])
    if f.phase_origin_rad != 0.0:
        put("fringes", "phase_origin_rad", float(f.phase_origin_rad))
    if f.shift_sign != 1:
        put("fringes", "shift_sign", int(f.shift_sign))
    if f.unwrap != "periods":
        put("fringes", "unwrap", f.unwrap)
    if f.gray_bits:
        put("fringes", "gray_bits", int(f.gray_bits))
    if f.gray_inverse:
        put("fringes", "gray_inverse", True)
    for dname, o in f.per_direction:
        sub = {}
        if o.periods_px is not None:
            sub["periods_px"] = [t if isinstance(t, int) else float(t) for t in o.periods_px]
        if o.steps is not None:
            sub["steps"] = list(o.steps)
        for key in ("phase_origin_rad", "shift_sign", "gray_bits"):
            if getattr(o, key) is not None:
                sub[key] = getattr(o, key)
        if sub:
            put("fringes", dname, sub)
    if rig.display is not None:
        v2["display"] = {"levels": [float(x) for x in rig.display.levels],
                         "luminance": [float(x) for x in rig.display.luminance]}
    dec = {k: v for k, v in (("min_modulation", rig.decode.min_modulation),
                             ("border_margin_px", rig.decode.border_margin_px),
                             ("unwrap_tolerance", rig.decode.unwrap_tolerance)) if v is not None}
    if dec:
        v2["decode"] = dec
    for key in ("gray_template", "white_template", "black_template"):
        if getattr(rig, key) is not None:
            put("images", key, getattr(rig, key))
    if rig.frame_list:
        frames = []
        for e in rig.frame_list:
            t = {"pos": e.pos}
            if e.reference is not None:
                t["reference"] = e.reference
            elif e.gray_bit is not None:
                t.update({"dir": e.dir, "gray_bit": e.gray_bit, "inverse": e.inverse})
            else:
                t.update({"dir": e.dir, "period_index": e.period_index, "step": e.step})
            t["file"] = e.file
            frames.append(t)
        put("images", "frames", frames)
    if st.n_positions < 2:
        v2.setdefault("stage", {})
    if rig.projector is not None and rig.height is not None:
        v2["projector"] = _projector_table(rig.projector)
        v2["height"] = {"z_mm": [float(z) for z in rig.height.z_mm], "template": rig.height.template}

    doc = {
        "format": DATASET_FORMAT_2 if v2 else DATASET_FORMAT,
        "camera": {"width": c.width, "height": c.height, "bit_depth": c.bit_depth},
        "lcd": {"width": lcd.width, "height": lcd.height, "pitch_mm": list(lcd.pitch_mm)},
        "stage": {"z_mm": [float(z) for z in st.z_mm], "direction": list(st.direction)},
        "fringes": {
            "directions": list(f.directions),
            "periods_px": list(f.periods_px),
            "steps": list(f.steps),
            "offset": f.offset,
            "amplitude": f.amplitude,
            "carrier_px_per_mm": list(f.carrier_px_per_mm),
            "gamma": f.gamma,
        },
        "images": {"template": rig.template},
    }
    for section, keys in v2.items():
        doc.setdefault(section, {}).update(keys)
    # Sub-tables after plain keys (TOML needs [fringes.y] after the keys of [fringes]).
    fr = doc["fringes"]
    doc["fringes"] = {k: v for k, v in fr.items() if not isinstance(v, dict)} | \
        {k: v for k, v in fr.items() if isinstance(v, dict)}
    return tomli_w.dumps(doc)


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write ``rig.toml`` atomically."""
    write_text_atomic(path, rig_to_toml(rig))


def scan_to_toml(spec: ScanSpec) -> str:
    """The ``scan.toml`` text of ``spec`` (round-trips through :func:`load_scan`)."""
    c = spec.camera
    camera = {"width": c.width, "height": c.height, "bit_depth": c.bit_depth}
    if c.bit_shift:
        camera["bit_shift"] = c.bit_shift
    return tomli_w.dumps({"format": SCAN_FORMAT, "camera": camera, "projector": _projector_table(spec.projector),
                          "images": {"template": spec.template}})


def _projector_table(p: Projector) -> dict:
    """``[projector]`` of ``rig.toml`` or ``scan.toml``: size and design (keys at their defaults left out)."""
    f = p.fringes
    t: dict = {"width": p.width, "height": p.height, "directions": list(f.directions),
               "periods_px": [float(v) for v in f.periods_px], "steps": list(f.steps),
               "offset": float(f.offset), "amplitude": float(f.amplitude), "gamma": float(f.gamma)}
    if f.phase_origin_rad != 0.0:
        t["phase_origin_rad"] = float(f.phase_origin_rad)
    if f.shift_sign != 1:
        t["shift_sign"] = int(f.shift_sign)
    if f.unwrap != "periods":
        t["unwrap"] = f.unwrap
    for dname, o in f.per_direction:
        sub = {}
        if o.periods_px is not None:
            sub["periods_px"] = [float(v) for v in o.periods_px]
        if o.steps is not None:
            sub["steps"] = list(o.steps)
        for key in ("phase_origin_rad", "shift_sign"):
            if getattr(o, key) is not None:
                sub[key] = getattr(o, key)
        if sub:
            t[dname] = sub
    return t
