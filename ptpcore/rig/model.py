"""The rig as data: camera, LCD, stage, fringe design, image layout, the scanner's projector.

Frozen dataclasses, the in-memory form of a ``ptp-dataset/1`` or ``/2`` ``rig.toml`` and of a
``ptp-scan/1`` ``scan.toml`` (FORMATS.md). They hold values already checked:
:mod:`ptpcore.rig.reading` builds them from a file with every validation,
:mod:`ptpcore.rig.writing` writes them back.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from ptpcore.errors import ConfigError

__all__ = [
    "DATASET_FORMAT",
    "DATASET_FORMAT_2",
    "SCAN_FORMAT",
    "DEFAULT_TEMPLATE",
    "Camera",
    "Lcd",
    "Stage",
    "Display",
    "DirectionFringes",
    "FringeDesign",
    "DecodeSettings",
    "FrameEntry",
    "Rig",
    "Projector",
    "HeightSweep",
    "ScanSpec",
    "projector_rig",
    "format_period",
    "heterodyne_beats",
]

DATASET_FORMAT = "ptp-dataset/1"
DATASET_FORMAT_2 = "ptp-dataset/2"
SCAN_FORMAT = "ptp-scan/1"
DEFAULT_TEMPLATE = "z{pos:03d}/{dir}_T{period}_n{step:02d}.png"


@dataclass(frozen=True)
class Camera:
    """The camera's sensor: ``width`` x ``height`` pixels, ``bit_depth`` bits per sample."""

    width: int = 640
    height: int = 480
    bit_depth: int = 8
    bit_shift: int = 0  # ptp-dataset/2: samples stored MSB-aligned; value >> bit_shift = counts

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``: the shape of every image and per-pixel map."""
        return (self.height, self.width)

    @property
    def max_level(self) -> int:
        """Largest grey level the sensor can report."""
        return (1 << self.bit_depth) - 1


@dataclass(frozen=True)
class Lcd:
    """The LCD: ``width`` x ``height`` pixels with pitch ``(x, y)`` in mm."""

    width: int = 3840
    height: int = 2160
    pitch_mm: tuple[float, float] = (0.05, 0.05)
    # ptp-dataset/2 (kept here for the corrections that use them):
    cover_glass_mm: float | None = None  # None: the key is absent (a bare panel assumed); 0: no glass, declared
    cover_glass_index: float = 1.52
    cover_glass_mm_sigma: float = 0.0
    cover_glass_index_sigma: float = 0.0
    flatness_u_px: tuple[float, ...] = ()
    flatness_v_px: tuple[float, ...] = ()
    flatness_um: tuple[tuple[float, ...], ...] = ()  # [v][u], um


@dataclass(frozen=True)
class Stage:
    """Stage readings ``z_mm`` (capture order) and travel direction ``(a, b, 1)``."""

    z_mm: tuple[float, ...] = tuple(float(4 * k) for k in range(11))
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    repeat_z_mm: tuple[float, ...] = ()  # ptp-dataset/2: readings captured again after the sweep

    @property
    def n_positions(self) -> int:
        return len(self.z_mm)


@dataclass(frozen=True)
class Display:
    """ptp-dataset/2 ``[display]``: measured relative luminance at some levels (monotonic)."""

    levels: tuple[float, ...] = ()
    luminance: tuple[float, ...] = ()


@dataclass(frozen=True)
class DirectionFringes:
    """ptp-dataset/2 ``[fringes.x]`` / ``[fringes.y]``: what differs for one direction (None: as ``[fringes]``)."""

    periods_px: tuple[float, ...] | None = None
    steps: tuple[int, ...] | None = None
    phase_origin_rad: float | None = None
    shift_sign: int | None = None
    gray_bits: int | None = None


@dataclass(frozen=True)
class FringeDesign:
    """What the LCD shows at every position (docs/method.md section 3).

    ``periods_px`` run coarse to fine (fractional in ``ptp-dataset/2``);
    ``steps[j]`` is N for ``periods_px[j]``. ``per_direction`` holds the
    overrides of ``[fringes.x]``/``[fringes.y]``: use :meth:`periods`,
    :meth:`steps_of`, :meth:`origin`, :meth:`sign` and :meth:`bits` for the
    values of one direction.
    """

    directions: tuple[str, ...] = ("x", "y")
    periods_px: tuple[float, ...] = (4096, 512, 64, 16)
    steps: tuple[int, ...] = (4, 4, 4, 8)
    offset: float = 127.5
    amplitude: float = 100.0
    carrier_px_per_mm: tuple[float, float] = (0.0, 0.0)
    gamma: float = 1.0
    phase_origin_rad: float = 0.0
    shift_sign: int = 1
    unwrap: str = "periods"
    gray_bits: int = 0
    gray_inverse: bool = False
    per_direction: tuple[tuple[str, DirectionFringes], ...] = ()

    def carrier(self, direction: str) -> float:
        """Carrier displacement (LCD px per mm of z) for ``direction``."""
        return self.carrier_px_per_mm[0 if direction == "x" else 1]

    def _override(self, direction: str, name: str):
        for d, o in self.per_direction:
            if d == direction and getattr(o, name) is not None:
                return getattr(o, name)
        return getattr(self, name)

    def periods(self, direction: str) -> tuple[float, ...]:
        """Periods (LCD px, coarse to fine) of ``direction``."""
        return self._override(direction, "periods_px")

    def steps_of(self, direction: str) -> tuple[int, ...]:
        """Steps N of every period of ``direction``."""
        return self._override(direction, "steps")

    def origin(self, direction: str) -> float:
        """``phase_origin_rad`` of ``direction``."""
        return float(self._override(direction, "phase_origin_rad"))

    def sign(self, direction: str) -> int:
        """``shift_sign`` of ``direction``."""
        return int(self._override(direction, "shift_sign"))

    def bits(self, direction: str) -> int:
        """Gray-code bits of ``direction`` (0 unless ``unwrap = "gray"``)."""
        return int(self._override(direction, "gray_bits")) if self.unwrap == "gray" else 0

    @property
    def is_plain(self) -> bool:
        """True for a ``ptp-dataset/1`` design: integer periods and steps shared by both
        directions, phase origin 0, shift sign +1, unwrapping by periods (the fast paths)."""
        return (not self.per_direction and self.phase_origin_rad == 0.0 and self.shift_sign == 1
                and self.unwrap == "periods" and all(float(t).is_integer() for t in self.periods_px))

    def frames(self):
        """Yield ``(direction, level, period, step, n_steps)`` of the phase-shifted frames in capture order."""
        for d in self.directions:
            for j, (t, n) in enumerate(zip(self.periods(d), self.steps_of(d))):
                for s in range(n):
                    yield d, j, t, s, n

    def gray_frames(self):
        """Yield ``(direction, bit, inverse)`` of the Gray-code frames (none unless ``unwrap = "gray"``)."""
        for d in self.directions:
            for b in range(self.bits(d)):
                yield d, b, False
                if self.gray_inverse:
                    yield d, b, True

    @property
    def frames_per_position(self) -> int:
        return sum(sum(self.steps_of(d)) for d in self.directions) + sum(1 for _ in self.gray_frames())


@dataclass(frozen=True)
class DecodeSettings:
    """ptp-dataset/2 ``[decode]`` thresholds; None: the engine's default."""

    min_modulation: float | None = None
    border_margin_px: int | None = None
    unwrap_tolerance: float | None = None


@dataclass(frozen=True)
class FrameEntry:
    """One ``[[images.frames]]`` entry: a phase step, a Gray-code bit or a reference frame."""

    file: str
    pos: int = 0
    dir: str | None = None
    period_index: int | None = None
    step: int | None = None
    gray_bit: int | None = None
    inverse: bool = False
    reference: str | None = None

    @property
    def key(self) -> tuple:
        if self.reference is not None:
            return (self.pos, "ref", self.reference)
        if self.gray_bit is not None:
            return (self.pos, "gray", self.dir, self.gray_bit, self.inverse)
        return (self.pos, "phase", self.dir, self.period_index, self.step)


@dataclass(frozen=True)
class Projector:
    """ptp-dataset/2 ``[projector]``: the scanner's own fringe source, fixed to the camera (docs/method.md section 9).

    ``width`` x ``height`` projector pixels: the range of the decoded projector coordinate ``u_p``
    (and ``v_p``). ``fringes`` is its pattern design, as ``[fringes]`` but without a carrier.
    """

    width: int = 1280
    height: int = 800
    fringes: FringeDesign = field(default_factory=lambda: FringeDesign(("x",), (1280.0, 160.0, 20.0), (4, 4, 8)))

    @property
    def design_attrs(self) -> dict:
        """The pattern design a scanner needs to decode ``u_p`` as the calibration did
        (the ``/height`` attributes of ``ptp-lut/1``; direction ``x``)."""
        f = self.fringes
        return {"width": int(self.width), "height": int(self.height),
                "periods_px": [float(t) for t in f.periods("x")], "steps": [int(n) for n in f.steps_of("x")],
                "phase_origin_rad": float(f.origin("x")), "shift_sign": int(f.sign("x")), "unwrap": f.unwrap,
                "offset": float(f.offset), "amplitude": float(f.amplitude), "gamma": float(f.gamma)}


@dataclass(frozen=True)
class HeightSweep:
    """ptp-dataset/2 ``[height]``: the matte plate's heights (same datum as ``[stage] z_mm``) and its frames."""

    z_mm: tuple[float, ...] = ()
    template: str = "h{pos:03d}/{dir}_T{period}_n{step:02d}.png"


def format_period(period) -> int | float:
    """A period as ``{period}`` shows it: its shortest decimal form (``67.5``; ``120`` for ``120.0``)."""
    p = float(period)
    return int(p) if p.is_integer() else p


@dataclass(frozen=True)
class Rig:
    """Everything ``rig.toml`` describes."""

    camera: Camera = field(default_factory=Camera)
    lcd: Lcd = field(default_factory=Lcd)
    stage: Stage = field(default_factory=Stage)
    fringes: FringeDesign = field(default_factory=FringeDesign)
    template: str = DEFAULT_TEMPLATE
    display: Display | None = None
    decode: DecodeSettings = field(default_factory=DecodeSettings)
    gray_template: str | None = None
    white_template: str | None = None
    black_template: str | None = None
    frame_list: tuple[FrameEntry, ...] = ()
    projector: Projector | None = None  # ptp-dataset/2 [projector] (docs/method.md section 9)
    height: HeightSweep | None = None   # ptp-dataset/2 [height]: the plate's sweep

    def height_rig(self) -> "Rig":
        """The height sweep as a rig the decoder reads: the projector in the LCD's place (its
        pixels, pitch 1), the plate's heights as the stage's, no carrier, the ``[height]`` template.

        Raises
        ------
        ConfigError
            The dataset has no ``[projector]`` and ``[height]``.
        """
        if self.projector is None or self.height is None:
            raise ConfigError("the dataset has no height sweep ([projector] and [height], FORMATS.md)")
        return projector_rig(self.camera, self.projector, self.height.z_mm, self.height.template, self.decode)

    def image_name(self, pos: int, direction: str, period, step: int, steps: int,
                   period_index: int | None = None) -> str:
        """Relative path of one phase-shifted image (``[[images.frames]]`` or ``template``)."""
        if period_index is None:
            ps = self.fringes.periods(direction)
            period_index = next((j for j, t in enumerate(ps) if float(t) == float(period)), 0)
        if self.frame_list:
            return self._listed((pos, "phase", direction, period_index, step))
        return self.template.format(pos=pos, dir=direction, period=format_period(period), step=step,
                                    steps=steps, period_index=period_index)

    def gray_name(self, pos: int, direction: str, bit: int, inverse: bool) -> str:
        """Relative path of one Gray-code image."""
        if self.frame_list:
            return self._listed((pos, "gray", direction, bit, bool(inverse)))
        return (self.gray_template or "").format(pos=pos, dir=direction, bit=bit, inverse=int(bool(inverse)))

    def reference_name(self, pos: int, which: str) -> str | None:
        """Relative path of the all-white or all-black frame of ``pos``, or None without one."""
        if self.frame_list:
            for e in self.frame_list:
                if e.key == (pos, "ref", which):
                    return e.file
            return None
        t = self.white_template if which == "white" else self.black_template
        return None if t is None else t.format(pos=pos)

    @property
    def has_references(self) -> bool:
        """Whether the dataset has white and black reference frames."""
        if self.frame_list:
            return any(e.reference == "white" for e in self.frame_list) and \
                any(e.reference == "black" for e in self.frame_list)
        return self.white_template is not None and self.black_template is not None

    def _listed(self, key: tuple) -> str:
        for e in self.frame_list:
            if e.key == key:
                return e.file
        raise KeyError(f"no [[images.frames]] entry for {key}")

    def with_z(self, z_mm) -> "Rig":
        """A copy with other stage positions."""
        return replace(self, stage=replace(self.stage, z_mm=tuple(float(z) for z in z_mm)))


def projector_rig(camera: Camera, projector: Projector, z_mm, template: str,
                  decode: DecodeSettings = DecodeSettings()) -> Rig:
    """A rig the decoder reads for frames of the scanner's projector (a height sweep or a scan).

    The projector stands in the LCD's place: its pixels (pitch 1, so world X of a decoded position
    is ``u_p`` itself), the heights ``z_mm`` as stage readings (one 0 for a scan), no carrier.
    """
    fringes = replace(projector.fringes, carrier_px_per_mm=(0.0, 0.0))
    return Rig(camera, Lcd(projector.width, projector.height, (1.0, 1.0)),
               Stage(tuple(float(v) for v in z_mm)), fringes, template, None, decode)


@dataclass(frozen=True)
class ScanSpec:
    """A scan to reconstruct (``scan.toml``, ``ptp-scan/1``): camera, projector design, frames' template.

    ``views``: how many views the folder holds (``{pos}`` in the template: counted from the files
    present, 0, 1, ... while a view's first frame exists; 1 without ``{pos}``).
    """

    camera: Camera
    projector: Projector
    template: str
    views: int = 1

    def rig(self) -> Rig:
        """The rig the decoder reads for this scan's frames (:func:`projector_rig`), one position per view."""
        return projector_rig(self.camera, self.projector, tuple(float(k) for k in range(self.views)), self.template)


def heterodyne_beats(periods) -> dict:
    """The beats of a heterodyne design (FORMATS.md ``unwrap = "heterodyne"``).

    Parameters
    ----------
    periods : sequence of 2 or 3 float
        LCD px, any order.

    Returns
    -------
    dict
        ``periods``: sorted ``T1 < T2 (< T3)``; ``steps``: the cascade as
        ``(name, beat period, period it unwraps)`` from the absolute beat down to
        ``T1``; ``absolute``: the beat whose phase is taken as absolute (``T12``
        for two periods, ``T123`` for three), LCD px.

    Raises
    ------
    ValueError
        Not 2 or 3 distinct periods, or (three) equal beats ``T12 = T23``.
    """
    ts = sorted(float(t) for t in periods)
    if len(ts) not in (2, 3) or len(set(ts)) != len(ts):
        raise ValueError(f"heterodyne unwrapping needs two or three different periods, got {list(periods)}")
    t12 = ts[0] * ts[1] / (ts[1] - ts[0])
    if len(ts) == 2:
        return {"periods": ts, "absolute": t12, "steps": [("T12", t12, ts[0])]}
    t23 = ts[1] * ts[2] / (ts[2] - ts[1])
    if abs(t23 - t12) <= 1e-9 * t12:
        raise ValueError(f"periods {', '.join(f'{t:g}' for t in ts)} px have equal beats T12 = T23 ="
                         f" {t12:g} px: their beat is infinite and unwraps nothing")
    t123 = t12 * t23 / abs(t23 - t12)
    return {"periods": ts, "absolute": t123, "t23": t23,
            "steps": [("T123", t123, t12), ("T12", t12, ts[0])]}
