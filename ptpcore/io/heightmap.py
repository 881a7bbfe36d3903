"""The per-pixel height map ``u_p -> Z`` (docs/method.md section 9) in memory and in the LUT file's ``/height``.

``Z = (p_0 + p_1 s + ... + p_D s^D) / (1 + q_1 s)``, ``s = (u_p - u_center) / u_scale`` per pixel
(FORMATS.md, ``ptp-lut/1``). Fitting lives in :mod:`ptpcore.fit.height`; this module holds,
evaluates, writes and reads a map, so a scanner needs no fitting code.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from ptpcore.io.h5chunks import create_compressed

__all__ = ["HeightMap", "HeightEvaluation", "write_height_group", "read_height_group"]

RANGE_EPS_PX = 1e-6
RANGE_REL = 2.0 ** -23
"""``u_p`` is in a pixel's range when ``u_min - tol <= u_p <= u_max + tol``, ``tol = 1e-6 px + |bound| 2**-23``.

The bounds are stored as float32 (1000.3 px is kept as 1000.29998779): the relative part (two
float32 half-steps) keeps a value on the calibrated edge inside; the comparison is made in float64,
as the XY LUT's (``ptpcore.io.lutfile.RANGE_REL``). The C reader (readers/c/ptplut.c) uses the same rule.
"""


@dataclass
class HeightEvaluation:
    """Z of every pixel at its ``u_p``.

    Attributes
    ----------
    z : (H, W) float64, mm
        NaN where the pixel has no map, no ``u_p``, or ``u_p`` is outside its calibrated range.
    dz_du : (H, W) float64, mm per projector px
        The map's slope there (NaN like ``z``).
    in_range : (H, W) bool
        Valid map, finite ``u_p`` within ``[u_min, u_max]``.
    """

    z: np.ndarray
    dz_du: np.ndarray
    in_range: np.ndarray


@dataclass
class HeightMap:
    """A per-pixel rational height map, exactly what ``/height`` stores.

    Attributes
    ----------
    degree : int
        D, the numerator's degree.
    direction : {"x", "y"}
        The projector coordinate the map reads (``x``: ``u_p``).
    u_center, u_scale : (H, W) float64, projector px
    p : (D+1, H, W) float64
        Numerator coefficients, lowest power first (mm); NaN where invalid.
    q : (1, H, W) float64
        The denominator's ``q_1``; NaN where invalid.
    valid : (H, W) bool
    u_min, u_max : (H, W) float32, projector px
        The calibrated range of ``u_p``.
    rms_z, loo_z, sigma_z : (H, W) float32, mm
        Fit residual RMS, leave-one-position-out RMS, predicted 1-sigma of the map's Z (the
        propagated noise of its samples and its model error in quadrature, RMS over the range).
    n_positions : (H, W) uint16
    design : dict
        The projector's pattern design as decoded (``width``, ``height``, ``periods_px``, ``steps``,
        ``phase_origin_rad``, ``shift_sign``, ``unwrap``, ...).
    chosen_by : str
    sigma_model_z : (H, W) float32 or None
        The model's part of ``sigma_z``.
    n_rejected : (H, W) uint16 or None
        Samples the robust fit left out.
    provenance : dict
        JSON-able: the degree choice's held-out errors, the model error's estimate.
    camera_noise : (2,) float or None
        The camera's noise as the height sweep measured it: ``read_var`` (DN^2) and ``gain`` (DN),
        ``var = read_var + gain * level`` (attributes ``camera_noise_read_var``, ``camera_noise_gain``):
        a scan's own frames, a few hundred pixels of an object, measure it poorly.
    """

    degree: int
    direction: str
    u_center: np.ndarray
    u_scale: np.ndarray
    p: np.ndarray
    q: np.ndarray
    valid: np.ndarray
    u_min: np.ndarray
    u_max: np.ndarray
    rms_z: np.ndarray
    loo_z: np.ndarray
    sigma_z: np.ndarray
    n_positions: np.ndarray
    design: dict = field(default_factory=dict)
    chosen_by: str = ""
    sigma_model_z: np.ndarray | None = None
    n_rejected: np.ndarray | None = None
    provenance: dict = field(default_factory=dict)
    camera_noise: tuple[float, float] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape

    def evaluate(self, u) -> HeightEvaluation:
        """Z (mm) and dZ/du_p at projector coordinates ``u`` (H, W); never extrapolated.

        Raises
        ------
        ValueError
            ``u`` is not an ``(H, W)`` map.
        """
        u = np.asarray(u, dtype=float)
        if u.shape != self.shape:
            raise ValueError(f"u_p must be a {self.shape} map, got shape {u.shape}")
        lo = np.asarray(self.u_min, np.float64)
        hi = np.asarray(self.u_max, np.float64)
        with np.errstate(invalid="ignore"):
            in_range = (self.valid & np.isfinite(u) & (u >= lo - (RANGE_EPS_PX + np.abs(lo) * RANGE_REL))
                        & (u <= hi + (RANGE_EPS_PX + np.abs(hi) * RANGE_REL)))
        s = np.where(in_range, (u - self.u_center) / self.u_scale, 0.0)
        num = np.zeros(self.shape)
        dnum = np.zeros(self.shape)
        for i in range(self.degree, -1, -1):  # Horner, with the derivative
            dnum = dnum * s + num
            num = num * s + np.nan_to_num(self.p[i])
        q = np.nan_to_num(self.q[0])
        den = 1.0 + q * s
        z = num / den
        dz_ds = (dnum * den - num * q) / (den * den)
        z = np.where(in_range, z, np.nan)
        return HeightEvaluation(z, np.where(in_range, dz_ds / self.u_scale, np.nan), in_range)


def write_height_group(parent, hm: HeightMap) -> None:
    """Write ``hm`` as the ``/height`` group of an open LUT file or group (FORMATS.md)."""
    g = parent.create_group("height")
    g.attrs.update({"kind": "rational", "degree": int(hm.degree), "direction": hm.direction,
                    "chosen_by": hm.chosen_by})
    for key, val in hm.design.items():
        g.attrs[key] = val
    if hm.provenance:
        g.attrs["provenance"] = json.dumps(hm.provenance)
    if hm.camera_noise is not None:
        g.attrs["camera_noise_read_var"], g.attrs["camera_noise_gain"] = (float(v) for v in hm.camera_noise)
    create_compressed(g, "u_center", np.asarray(hm.u_center, np.float64))
    create_compressed(g, "u_scale", np.asarray(hm.u_scale, np.float64))
    create_compressed(g, "p", np.asarray(hm.p, np.float64))
    create_compressed(g, "q", np.asarray(hm.q, np.float64))
    create_compressed(g, "valid", hm.valid.astype(np.uint8))
    q = g.create_group("quality")
    for name in ("u_min", "u_max", "rms_z", "loo_z", "sigma_z"):
        create_compressed(q, name, np.asarray(getattr(hm, name), np.float32))
    create_compressed(q, "n_positions", np.asarray(hm.n_positions, np.uint16))
    if hm.sigma_model_z is not None:
        create_compressed(q, "sigma_model_z", np.asarray(hm.sigma_model_z, np.float32))
    if hm.n_rejected is not None:
        create_compressed(q, "n_rejected", np.minimum(hm.n_rejected, 65535).astype(np.uint16))


_DESIGN_KEYS = {"width": int, "height": int, "phase_origin_rad": float, "shift_sign": int, "unwrap": str,
                "offset": float, "amplitude": float, "gamma": float}


def read_height_group(rd, shape: tuple[int, int]) -> HeightMap:
    """Read and check ``/height`` through a LUT file's group reader (``ptpcore.io.lutfile._GroupReader``).

    Raises
    ------
    FileFormatError
        Naming the file and the dataset or attribute that is wrong.
    """
    kind = rd.attr("height", "kind", str)
    if kind != "rational":
        raise rd.fail(f"attribute 'kind' of {rd.name('height')} is {kind!r}, expected 'rational'")
    degree = rd.attr("height", "degree", int)
    if not 1 <= degree <= 5:
        raise rd.fail(f"attribute 'degree' of {rd.name('height')} must be 1 to 5, got {degree}")
    direction = rd.attr("height", "direction", str)
    if direction not in ("x", "y"):
        raise rd.fail(f"attribute 'direction' of {rd.name('height')} must be 'x' or 'y', got {direction!r}")
    design = {key: rd.attr("height", key, kind) for key, kind in _DESIGN_KEYS.items()
              if key in rd.group["height"].attrs or key in ("width", "height")}
    for key in ("periods_px", "steps"):
        if key not in rd.group["height"].attrs:
            raise rd.fail(f"missing attribute {key!r} of {rd.name('height')}")
        val = np.asarray(rd.group["height"].attrs[key])
        if val.ndim != 1 or val.size < 1 or val.dtype.kind not in "fiu" or not np.all(np.isfinite(val)):
            raise rd.fail(f"attribute {key!r} of {rd.name('height')} must be a list of numbers, got {val!r}"[:200])
        if key == "steps" and np.any(val != np.round(val)):
            raise rd.fail(f"attribute 'steps' of {rd.name('height')} must hold whole numbers, got {val!r}"[:200])
        design[key] = [float(v) for v in val] if key == "periods_px" else [int(v) for v in val]
    if len(design["periods_px"]) != len(design["steps"]):
        raise rd.fail(f"attributes 'periods_px' and 'steps' of {rd.name('height')} differ in length"
                      f" ({len(design['periods_px'])} and {len(design['steps'])})")
    hm = HeightMap(
        degree=degree, direction=direction,
        u_center=rd.array("height/u_center", 2), u_scale=rd.array("height/u_scale", 2),
        p=rd.array("height/p", 3), q=rd.array("height/q", 3), valid=rd.array("height/valid", 2),
        u_min=rd.array("height/quality/u_min", 2), u_max=rd.array("height/quality/u_max", 2),
        rms_z=rd.array("height/quality/rms_z", 2), loo_z=rd.array("height/quality/loo_z", 2),
        sigma_z=rd.array("height/quality/sigma_z", 2), n_positions=rd.array("height/quality/n_positions", 2),
        design=design, chosen_by=rd.attr("height", "chosen_by", str),
        sigma_model_z=(rd.array("height/quality/sigma_model_z", 2)
                       if "height/quality/sigma_model_z" in rd.group else None),
        n_rejected=rd.array("height/quality/n_rejected", 2) if "height/quality/n_rejected" in rd.group else None,
    )
    if "camera_noise_read_var" in rd.group["height"].attrs:
        noise = (rd.attr("height", "camera_noise_read_var", float), rd.attr("height", "camera_noise_gain", float))
        if min(noise) < 0:
            raise rd.fail(f"attributes 'camera_noise_read_var' and 'camera_noise_gain' of {rd.name('height')}"
                          f" must not be negative, got {noise}")
        hm.camera_noise = noise
    prov = rd.group["height"].attrs.get("provenance")
    if prov is not None:
        try:
            hm.provenance = json.loads(prov)
        except (TypeError, ValueError):
            raise rd.fail(f"attribute 'provenance' of {rd.name('height')} is not JSON") from None
    _check_height(rd, hm, shape)
    return hm


def _check_height(rd, hm: HeightMap, shape: tuple[int, int]) -> None:
    """Shapes against the camera, numbers where the map is valid, a denominator that never vanishes."""
    for name in ("u_center", "u_scale", "valid", "u_min", "u_max", "rms_z", "loo_z", "sigma_z", "n_positions"):
        if getattr(hm, name).shape != shape:
            raise rd.fail(f"{rd.name('height/' + name)} has shape {getattr(hm, name).shape}, expected {shape}")
    if hm.p.shape != (hm.degree + 1, *shape):
        raise rd.fail(f"{rd.name('height/p')} has shape {hm.p.shape}, expected {(hm.degree + 1, *shape)}")
    if hm.q.shape != (1, *shape):
        raise rd.fail(f"{rd.name('height/q')} has shape {hm.q.shape}, expected {(1, *shape)}")
    if np.any((hm.valid != 0) & (hm.valid != 1)):
        raise rd.fail(f"{rd.name('height/valid')} must hold only 0 and 1")
    v = hm.valid = hm.valid.astype(bool)
    for name, arr in (("p", hm.p[:, v]), ("q", hm.q[:, v]), ("u_center", hm.u_center[v]),
                      ("u_scale", hm.u_scale[v])):
        if not np.all(np.isfinite(arr)):
            raise rd.fail(f"{rd.name('height/' + name)} holds NaN or infinite values at valid pixels")
    if np.any(hm.u_scale[v] <= 0):
        raise rd.fail(f"{rd.name('height/u_scale')} must be positive at valid pixels")
    if np.any(np.abs(hm.q[0][v]) >= 1.0):
        raise rd.fail(f"{rd.name('height/q')}: the denominator 1 + q_1 s vanishes within a valid pixel's range"
                      " (|q_1| >= 1)")
