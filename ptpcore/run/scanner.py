"""The whole scanner (docs/method.md section 9): the height sweep's map, and a scan's point cloud.

- :func:`decode_projector`: the projector coordinate ``u_p`` and its predicted sigma at every
  position of a height sweep or a scan, with the calibration's own decoder;
- :func:`calibrate_height`: a dataset's height sweep -> :class:`~ptpcore.io.heightmap.HeightMap`;
- :func:`reconstruct`: a scan folder + a LUT with ``/height`` -> points, each with its per-axis sigma.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ptpcore.decode.noise import NoiseAccumulator, NoiseModel
from ptpcore.decode.phase import DecodeOptions
from ptpcore.errors import ConfigError, DatasetError
from ptpcore.fit.height import fit_height_map
from ptpcore.io.heightmap import HeightMap
from ptpcore.io.pointcloud import PointCloud
from ptpcore.progress import Progress
from ptpcore.rig.rigfile import Rig, load_rig, load_scan

__all__ = ["ProjectorDecode", "decode_projector", "calibrate_height", "ScanResult", "reconstruct",
           "check_scan_design"]


@dataclass
class ProjectorDecode:
    """Decoded projector coordinates of every position of a height sweep (or the views of a scan).

    Attributes
    ----------
    z_mm : (K,) float64
        The positions' readings (a scan's: its view index).
    u : (K, H, W) float32, projector px
        ``u_p``; NaN where invalid (float32: 1e-4 px at 1280 px, far below the noise; half the memory).
    sigma_u : (K, H, W) float32, projector px
        Predicted 1-sigma of ``u_p`` (the camera's noise model and the display's integer levels).
    reasons : (K, H, W) uint8
        The decoder's reason bits (0 valid).
    noise_source : str
    noise : NoiseModel or None
        The camera noise model ``sigma_u`` came from (None: the neighbourhood's spread).
    v, sigma_v : (K, H, W) float32, projector px, or None
        ``v_p`` and its predicted 1-sigma when direction ``y`` was decoded (``directions=("x", "y")``),
        valid where ``u`` is (a pixel is valid where both directions are); None otherwise.
    """

    z_mm: np.ndarray
    u: np.ndarray
    sigma_u: np.ndarray
    reasons: np.ndarray
    noise_source: str
    noise: NoiseModel | None = None
    v: np.ndarray | None = None
    sigma_v: np.ndarray | None = None


def _position_arrays(k: int, shape, spill: bool, with_v: bool = False) -> dict:
    """The decode's ``(K, H, W)`` arrays: in memory, or as maps of one temporary file
    (:class:`ptpcore.store.SpillStore`: reserved up front, gone with the arrays) on a big sensor.
    ``with_v``: also ``v_p``'s (direction ``y``)."""
    fields = {"u": np.float32, "sigma_u": np.float32, "bg": np.float32, "mod": np.float32, "reasons": np.uint8}
    fill = {"u": np.nan, "sigma_u": np.nan, "bg": 0, "mod": 0, "reasons": 0}
    if with_v:
        fields.update({"v": np.float32, "sigma_v": np.float32, "bg_v": np.float32, "mod_v": np.float32})
        fill.update({"v": np.nan, "sigma_v": np.nan, "bg_v": 0, "mod_v": 0})
    if not spill:
        return {name: np.full((k, *shape), fill[name], dt) for name, dt in fields.items()}
    from ptpcore.store import SpillStore

    arrays = SpillStore(k, shape, fields, fill).arrays()
    for name, a in arrays.items():
        a[...] = fill[name]
    return arrays


def decode_projector(source, *, options: DecodeOptions = DecodeOptions(), progress: Progress | None = None,
                     noise: NoiseModel | None = None, spill: bool | None = None,
                     directions: tuple[str, ...] = ("x",)) -> ProjectorDecode:
    """Decode ``u_p`` (and ``v_p``) at every position of a projector rig's frames (:meth:`ptpcore.rig.Rig.height_rig`).

    The noise model is measured over all positions (the harmonic-free N-step residuals of direction
    ``x``, as the LCD sweep's), unless one is given (a scan: the height sweep's, measured on every
    pixel of the plate, where an object's few hundred pixels bias a fit weighted by their own scatter
    low); ``sigma_u`` (``sigma_v``) follows from it, the finest level's background and modulation.
    ``spill``: keep the ``(K, H, W)`` arrays in a temporary file (default: when they would pass
    :data:`ptpcore.run.pipeline.SPILL_BYTES`, as the LCD sweep's samples do).

    Parameters
    ----------
    directions : ("x",) or ("x", "y")
        What to decode: ``x`` alone (the height map's ``u_p``; the frames of other directions are not
        read, so a pixel's validity is its ``x`` decode's), or ``x`` and ``y`` (``u_p`` and ``v_p``, valid
        where both are: the conventional calibration, :mod:`ptpcore.run.structured_light`).

    Raises
    ------
    ConfigError
        ``directions`` asks for a direction the source's ``[projector]`` does not show.
    DatasetError
        No pixel valid at any position.
    """
    from ptpcore.run.pipeline import SPILL_BYTES, decode_positions

    source = _showing(source, directions)
    rig: Rig = source.rig
    k_total = rig.stage.n_positions
    h, w = rig.camera.shape
    with_v = "y" in directions
    if spill is None:
        spill = k_total * h * w * (33 if with_v else 17) > SPILL_BYTES
    arrays = _position_arrays(k_total, (h, w), spill, with_v)
    accumulated = NoiseAccumulator(rig.camera.max_level)
    fallback = []
    with contextlib.closing(decode_positions(source, range(k_total), options)) as decoded:
        for k in range(k_total):
            if progress:
                progress(k / k_total, f"decoding projector position {k} ({k + 1} of {k_total})")
            _keep_position(next(decoded), k, arrays, accumulated, fallback)
    u = arrays["u"]
    if not np.any(np.isfinite(u)):
        raise DatasetError("no pixel decodes the projector's coordinate at any position")
    model = noise if noise is not None else accumulated.model()
    source_name = _sigma_u(rig, model, arrays["bg"], arrays["mod"], fallback, arrays["sigma_u"], "x")
    if with_v:
        _sigma_u(rig, model, arrays["bg_v"], arrays["mod_v"], fallback, arrays["sigma_v"], "y")
    for k in range(k_total):
        arrays["sigma_u"][k][~np.isfinite(u[k])] = np.nan
        if with_v:
            arrays["sigma_v"][k][~np.isfinite(u[k])] = np.nan
    if progress:
        progress(1.0, "projector decoded")
    return ProjectorDecode(np.asarray(rig.stage.z_mm, float), u, arrays["sigma_u"], arrays["reasons"], source_name,
                           model, arrays.get("v"), arrays.get("sigma_v"))


def _keep_position(pos, k: int, arrays: dict, accumulated: NoiseAccumulator, fallback: list) -> None:
    """One decoded position into the ``(K, H, W)`` arrays (``k``), its noise samples into ``accumulated``
    (direction ``x``) and its neighbourhood sigma into ``fallback``."""
    valid = pos.reasons == 0
    arrays["reasons"][k] = pos.reasons
    arrays["u"][k] = np.where(valid, pos.u, np.nan)
    fine = pos.directions["x"].wrapped[-1]
    arrays["bg"][k], arrays["mod"][k] = fine.background, fine.modulation
    if "v" in arrays:
        arrays["v"][k] = np.where(valid, pos.v, np.nan)
        fine = pos.directions["y"].wrapped[-1]
        arrays["bg_v"][k], arrays["mod_v"][k] = fine.background, fine.modulation
    part = pos.info.get("noise_samples", {}).get("x")
    if part is not None:
        sub = valid[part["rows"]][:, part["cols"]].ravel()
        accumulated.add(part["background"], part["var"], sub & np.isfinite(part["var"]), part["dof"])
    used = pos.info.get("sigma", {}).get("x")
    if used is not None:
        fallback.append(float(np.nanmedian(used)) if np.ndim(used) else float(used))


class _Showing:
    """A frame source passing on only the frames of its rig's directions (any source without
    a ``showing`` method of its own)."""

    def __init__(self, source, rig: Rig):
        self.source, self.rig = source, rig

    def frames(self, k: int):
        shown = self.rig.fringes.directions
        for key, img in self.source.frames(k):
            if key[0] in shown:
                yield key, img


def _showing(source, directions: tuple[str, ...]):
    """``source`` read for ``directions`` only: a dataset folder reads no other frame; a source with a
    ``showing(directions)`` method (the simulator's) renders no other.

    Raises
    ------
    ConfigError
        A direction the source's design does not show, or ``directions`` without ``x``.
    """
    from ptpcore.io.dataset import DatasetSource

    directions = tuple(directions)
    shown = tuple(source.rig.fringes.directions)
    if "x" not in directions or not set(directions) <= {"x", "y"}:
        raise ConfigError(f"decode_projector: directions must be ('x',) or ('x', 'y'), got {directions!r}")
    missing = [d for d in directions if d not in shown]
    if missing:
        raise ConfigError(f"the projector's design shows directions {list(shown)}, not {missing[0]!r}:"
                          f" key 'projector.directions' needs {list(directions)}")
    if shown == directions:
        return source
    rig = replace(source.rig, fringes=replace(source.rig.fringes, directions=directions))
    if type(source) is DatasetSource:
        return DatasetSource(source.folder, source.workers, rig=rig)
    if hasattr(source, "showing"):
        return source.showing(directions)
    return _Showing(source, rig)


def _sigma_u(rig: Rig, model: NoiseModel | None, bg: np.ndarray, mod: np.ndarray, fallback: list,
             sigma_u: np.ndarray, direction: str = "x") -> str:
    """Predicted 1-sigma of ``u_p`` (``v_p`` for ``direction`` ``y``) into ``sigma_u`` (K, H, W) from the
    noise model and the direction's finest level's background and modulation
    (:func:`ptpcore.decode.position.coordinate_sigma`, as the LCD sweep's), or the neighbourhood's spread
    without a model; returns where it came from."""
    from ptpcore.decode.position import coordinate_sigma

    f = rig.fringes
    if model is not None:
        for k in range(bg.shape[0]):
            rows = coordinate_sigma(model, SimpleNamespace(background=bg[k], modulation=mod[k]),
                                    f.steps_of(direction)[-1], f.amplitude, f.periods(direction)[-1])
            sigma_u[k] = rows(0, bg.shape[1])
        return model.source
    if fallback:
        sigma_u[:] = float(np.median(fallback))
        return "neighbourhood"
    raise DatasetError("the projector's frames give no noise estimate (no level of 5 steps or more,"
                       " and no neighbourhood to measure it from)")


def calibrate_height(dataset_dir, *, degree: int | None = None, positions=None,
                     options: DecodeOptions = DecodeOptions(), progress: Progress | None = None,
                     decoded: ProjectorDecode | None = None) -> HeightMap:
    """A dataset's height sweep -> the per-pixel height map (docs/method.md section 9).

    Parameters
    ----------
    dataset_dir : path
        A ``ptp-dataset/2`` folder with ``[projector]`` and ``[height]``.
    degree : int, optional
        Numerator degree (default: chosen by held-out positions).
    positions : sequence of int, optional
        Fit only these heights.
    decoded : ProjectorDecode, optional
        The sweep already decoded (:func:`decode_projector`).

    Raises
    ------
    ConfigError
        The dataset has no height sweep.
    """
    from ptpcore.io.dataset import DatasetSource

    folder = Path(dataset_dir)
    rig = load_rig(folder)
    if rig.projector is None or rig.height is None:
        raise ConfigError(f"{folder / 'rig.toml'}: no height sweep ([projector] and [height], FORMATS.md)")
    if decoded is None:
        decoded = decode_projector(DatasetSource(folder, rig=rig.height_rig()), options=options, progress=progress)
    hm = fit_height_map(decoded.u, decoded.sigma_u, decoded.z_mm, degree=degree, positions=positions,
                        design=rig.projector.design_attrs, direction="x")
    hm.provenance["noise_source"] = decoded.noise_source
    if decoded.noise is not None:
        hm.camera_noise = (decoded.noise.read_var, decoded.noise.gain)
    return hm


def check_scan_design(scan_design: dict, lut_design: dict, where: str) -> None:
    """A scan's projector design must be the one the height map was calibrated with (FORMATS.md).

    Raises
    ------
    ConfigError
        Naming the scan's ``scan.toml`` and the first key that differs.
    """
    for key in ("width", "height", "periods_px", "steps", "phase_origin_rad", "shift_sign", "unwrap"):
        a, b = scan_design.get(key), lut_design.get(key)
        if b is None:
            continue
        same = np.allclose(a, b) if key in ("periods_px", "phase_origin_rad") else a == b
        if not same:
            raise ConfigError(f"{where}: key 'projector.{key}' is {a!r}, but the height map was calibrated"
                              f" with {b!r}")


@dataclass
class ScanResult:
    """One view of a scan: per pixel maps and the cloud.

    Attributes
    ----------
    cloud : PointCloud
        The valid points, each with its per-axis sigma.
    u, sigma_u : (H, W) float64
        Decoded ``u_p`` and its predicted sigma (NaN where invalid).
    x, y, z : (H, W) float64, mm
        NaN where the pixel has no point.
    sigma_x, sigma_y, sigma_z : (H, W) float64, mm
        Per-axis 1-sigma of each point: ``sigma_z`` is u_p's noise through dZ/du_p and the height
        map's sigma in quadrature; ``sigma_x`` adds the XY LUT's own sigma to ``slope_x * sigma_z``.
    slope_x, slope_y : (H, W) float64
        dX/dZ, dY/dZ of the XY LUT at the point: a Z error moves the point along the ray (so the
        axes' errors are correlated; :func:`ptpcore.evaluate.scanner.scan_accuracy` uses it).
    sigma_lut_x, sigma_lut_y : (H, W) float64, mm
        The XY LUT's own sigma (0 where the LUT has none).
    """

    cloud: PointCloud
    u: np.ndarray
    sigma_u: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    sigma_z: np.ndarray
    slope_x: np.ndarray
    slope_y: np.ndarray
    sigma_lut_x: np.ndarray
    sigma_lut_y: np.ndarray


def reconstruct(scan_dir, lut, *, options: DecodeOptions = DecodeOptions(),
                progress: Progress | None = None) -> list[ScanResult]:
    """A scan folder (``ptp-scan/1``) through a LUT with a height map -> one point cloud per view.

    Per pixel: ``u_p`` decoded as the height sweep was, ``Z`` from the height map, ``(X, Y)`` from
    the XY LUT at that ``Z``. A pixel without ``u_p``, outside its height map's calibrated ``u_p``
    range or its LUT's ``z`` range has no point (never extrapolated). Each point's 1-sigma:
    ``sigma_Z^2 = (dZ/du_p sigma_u)^2 + sigma_map^2``; ``sigma_X^2 = sigma_LUT,X^2 + (dX/dZ sigma_Z)^2``
    (and Y).

    Raises
    ------
    ConfigError
        A bad ``scan.toml``; a LUT without ``/height``; a camera or pattern design that differs.
    """
    from ptpcore.io.dataset import DatasetSource

    folder = Path(scan_dir)
    spec = load_scan(folder)
    where = str(folder / "scan.toml")
    hm: HeightMap | None = lut.height
    if hm is None:
        raise ConfigError("the LUT has no height map (/height): calibrate with a dataset that has a height sweep"
                          " ([projector] and [height])")
    if spec.camera.shape != lut.shape:
        raise ConfigError(f"{where}: camera {spec.camera.width}x{spec.camera.height}, but the LUT's is"
                          f" {lut.shape[1]}x{lut.shape[0]}")
    check_scan_design(spec.projector.design_attrs, hm.design, where)
    noise = None if hm.camera_noise is None else NoiseModel(*hm.camera_noise, source="height sweep")
    dec = decode_projector(DatasetSource(folder, rig=spec.rig()), options=options, progress=progress, noise=noise)
    return [_points(dec.u[k], dec.sigma_u[k], hm, lut) for k in range(spec.views)]


def _points(u: np.ndarray, sigma_u: np.ndarray, hm: HeightMap, lut) -> ScanResult:
    """One view's points from its decoded ``u_p`` (H, W)."""
    ev = hm.evaluate(u)
    z = ev.z
    sigma_z = np.sqrt((ev.dz_du * sigma_u) ** 2 + hm.sigma_z.astype(float) ** 2)
    xy = lut.evaluate(np.where(np.isfinite(z), z, lut.z_min))
    dz = 1e-3 * max(lut.z_max - lut.z_min, 1e-3)
    # the LUT's slope: a central difference (extrapolating by dz at the range's ends is harmless)
    hi = lut.evaluate(np.where(np.isfinite(z), z + dz, lut.z_min), extrapolate=True)
    lo = lut.evaluate(np.where(np.isfinite(z), z - dz, lut.z_min), extrapolate=True)
    slope_x, slope_y = (hi.x - lo.x) / (2 * dz), (hi.y - lo.y) / (2 * dz)
    h, w = lut.shape
    sx_lut = lut.sigma_x.astype(float) if lut.sigma_x is not None else np.zeros((h, w))
    sy_lut = lut.sigma_y.astype(float) if lut.sigma_y is not None else np.zeros((h, w))
    sigma_x = np.sqrt(sx_lut ** 2 + (slope_x * sigma_z) ** 2)
    sigma_y = np.sqrt(sy_lut ** 2 + (slope_y * sigma_z) ** 2)
    has_u = np.isfinite(u)
    has_z = np.isfinite(z)
    keep = has_z & lut.valid & xy.in_range & np.isfinite(xy.x) & np.isfinite(xy.y)
    rows, cols = np.nonzero(keep)
    x_map, y_map, z_map = (np.where(keep, a, np.nan) for a in (xy.x, xy.y, z))
    cloud = PointCloud(
        x=xy.x[keep], y=xy.y[keep], z=z[keep], row=rows.astype(np.int32), col=cols.astype(np.int32),
        sigma_x=sigma_x[keep].astype(np.float32), sigma_y=sigma_y[keep].astype(np.float32),
        extrapolated=np.zeros(keep.sum(), bool), shape=(h, w),
        n_no_height=int(np.count_nonzero(~has_u)), n_invalid=int(np.count_nonzero(has_u & ~(hm.valid & lut.valid))),
        n_out_of_range=int(np.count_nonzero(has_z & lut.valid & ~xy.in_range)),
        n_no_value=int(np.count_nonzero(has_z & lut.valid & xy.in_range & ~(np.isfinite(xy.x) & np.isfinite(xy.y)))),
        sigma_z=sigma_z[keep].astype(np.float32),
        n_out_of_height_range=int(np.count_nonzero(has_u & hm.valid & lut.valid & ~ev.in_range)),
    )
    return ScanResult(cloud, u, sigma_u, x_map, y_map, z_map, sigma_x, sigma_y, sigma_z, slope_x, slope_y,
                      sx_lut, sy_lut)
