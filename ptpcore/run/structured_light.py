"""The conventional structured-light calibration of a dataset (docs/method.md section 9, "The comparison").

The same sweeps as the per-pixel calibration, the same decoders, the same noise:

- **Feature points**: a sparse grid of camera pixels (every ``grid_step_px``, default about 40 across
  the image whatever its size), kept where the pixel is valid at every LCD position and every plate
  height, so that each feature pixel is one fixed ray seen through the whole volume.
- **Camera**: the LCD sweep's decoded coordinates at those pixels (:func:`ptpcore.run.pipeline.collect_samples`
  with the cover-glass and flatness corrections of :func:`ptpcore.fit.corrected.correct_all`, as
  ``ptp compare`` gives 3DSTC), world ``(X, Y, z_k)``: the translated planes as one non-coplanar
  target, DLT start and Levenberg-Marquardt (a planar Zhang calibration is degenerate for them).
- **Projector**: at each plate height ``z_h`` the feature pixel's ray meets the plate at
  ``(X, Y, z_h)`` and the projector lights it at the decoded ``(u_p, v_p)``
  (:func:`ptpcore.run.scanner.decode_projector` with directions ``x`` and ``y``). ``X, Y``: from the LCD
  decode where the plate height is one of the LCD's readings (the same datum, FORMATS.md): that is a
  measurement of where the ray meets ``Z = z_h``, micrometres of noise and no model error. With at
  least :data:`MIN_LCD_HEIGHTS` such heights only those are used (the presets' 21 plate heights hold
  the LCD's 11); otherwise every height, ``X, Y`` from the calibrated camera's ray (its model error then
  enters the projector's points). Which heights and which source: the result's ``provenance``.
- The two fits and OpenCV's stereo cross-check: :mod:`ptpcore.pinhole.structured_light`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ptpcore.decode.phase import DecodeOptions
from ptpcore.errors import ConfigError, DatasetError
from ptpcore.io.samples import SampleStack
from ptpcore.pinhole.camera import fit_pinhole
from ptpcore.pinhole.structured_light import ConventionalCalibration, fit_conventional, opencv_stereo_check
from ptpcore.progress import Progress, sub_progress
from ptpcore.rig.rigfile import Rig, load_rig

__all__ = ["calibrate_conventional", "calibrate_conventional_from", "check_conventional_rig", "feature_grid",
           "reconstruct_conventional"]

# Plate heights within this of an LCD reading (mm) take that position's decoded X, Y.
_SAME_HEIGHT_MM = 1e-6
# At least this many plate heights on the LCD's readings: the projector is fitted on those alone
# (3: the DLT needs two planes, a third checks them).
MIN_LCD_HEIGHTS = 3


def check_conventional_rig(rig: Rig, where: str) -> None:
    """The dataset must have a height sweep showing both projector directions.

    Raises
    ------
    ConfigError
        Naming ``where`` (the ``rig.toml``) and the missing table or key.
    """
    if rig.projector is None or rig.height is None:
        raise ConfigError(f"{where}: no height sweep ([projector] and [height], FORMATS.md): the conventional"
                          " calibration needs the plate's sweep")
    shown = list(rig.projector.fringes.directions)
    if "y" not in shown:
        raise ConfigError(f"{where}: key 'projector.directions' is {shown}: the conventional calibration needs"
                          " [\"x\", \"y\"] (the projector's v_p as well as u_p)")


def calibrate_conventional(dataset_dir, *, progress: Progress | None = None, grid_step_px: int | None = None,
                           options: DecodeOptions = DecodeOptions(), samples: SampleStack | None = None,
                           decoded=None) -> ConventionalCalibration:
    """A ``ptp-dataset/2`` with an LCD sweep and a height sweep in ``x`` and ``y`` -> camera and projector pinholes.

    Parameters
    ----------
    dataset_dir : path
        The dataset folder (``rig.toml`` with ``[projector] directions = ["x", "y"]`` and ``[height]``).
    progress : callable, optional
        ``progress(fraction, message)``; may raise to cancel.
    grid_step_px : int, optional
        Feature grid spacing (camera px); default :func:`feature_grid`'s.
    options : DecodeOptions
    samples : SampleStack, optional
        The LCD sweep already decoded and corrected (:func:`ptpcore.fit.corrected.correct_all`), e.g. by the
        caller's own ``ptp calibrate`` run: not decoded again.
    decoded : ProjectorDecode, optional
        The height sweep already decoded with ``directions=("x", "y")``: not decoded again.

    Returns
    -------
    ConventionalCalibration

    Raises
    ------
    ConfigError
        No height sweep, or one without direction ``y`` (naming ``rig.toml`` and the key).
    DatasetError
        Too few feature pixels valid at every position and height.
    """
    from ptpcore.io.dataset import DatasetSource

    folder = Path(dataset_dir)
    where = str(folder / "rig.toml")
    rig = load_rig(folder)
    check_conventional_rig(rig, where)
    return calibrate_conventional_from(rig, DatasetSource(folder, rig=rig),
                                       DatasetSource(folder, rig=rig.height_rig()), progress=progress,
                                       grid_step_px=grid_step_px, options=options, where=where, samples=samples,
                                       decoded=decoded)


def calibrate_conventional_from(rig: Rig, lcd_source, height_source, *, progress: Progress | None = None,
                                grid_step_px: int | None = None, options: DecodeOptions = DecodeOptions(),
                                where: str = "rig", samples: SampleStack | None = None,
                                decoded=None) -> ConventionalCalibration:
    """:func:`calibrate_conventional` from frame sources (a dataset's, or the simulator's rendered on demand).

    Parameters
    ----------
    rig : Rig
        With ``[projector]`` (directions ``x`` and ``y``) and ``[height]``.
    lcd_source, height_source : frame sources
        The LCD sweep (its ``rig``: the LCD's) and the height sweep (:meth:`ptpcore.rig.Rig.height_rig`).
    where : str
        Names the rig in error messages.
    samples, decoded : optional
        As :func:`calibrate_conventional`'s.

    Raises
    ------
    ValueError
        ``decoded`` without ``v_p`` (decoded with direction ``x`` alone).
    """
    from ptpcore.fit.corrected import correct_all
    from ptpcore.run.pipeline import collect_samples
    from ptpcore.run.scanner import decode_projector

    check_conventional_rig(rig, where)
    report = progress or (lambda f, m: None)
    if decoded is not None and decoded.v is None:
        raise ValueError("calibrate_conventional: the height sweep was decoded without v_p:"
                         " decode_projector(..., directions=('x', 'y'))")
    if samples is None:
        samples = collect_samples(lcd_source, options=options, progress=sub_progress(progress, 0.0, 0.45))
        samples = correct_all(samples, lcd_source.rig)[0]
    dec = decoded if decoded is not None else decode_projector(
        height_source, options=options, directions=("x", "y"), progress=sub_progress(progress, 0.45, 0.9))
    report(0.9, "conventional calibration: fitting camera and projector")
    rows, cols = feature_grid(samples, dec.u, dec.v, grid_step_px)
    cam_world, cam_px = _camera_points(samples, rows, cols)
    camera_fit = fit_pinhole(cam_world, cam_px)  # first: the plate's points may need the camera's rays
    proj_world, proj_uv, proj_cam_px, info = _projector_points(samples, dec, rows, cols, camera_fit.model)
    provenance = {"grid_step_px": _step(samples.x.shape[1:], grid_step_px), "n_feature_pixels": int(rows.size),
                  "lcd_z_mm": [float(z) for z in samples.z], "plate_z_mm": [float(z) for z in dec.z_mm],
                  "noise_source": dec.noise_source, "corrections": sorted(samples.corrections), **info}
    if dec.noise is not None:  # the camera noise model u_p's sigma came from: a scan's decode can reuse it
        provenance["camera_noise"] = [float(dec.noise.read_var), float(dec.noise.gain)]
    cal = fit_conventional(cam_world, cam_px, proj_world, proj_uv, camera_fit=camera_fit, provenance=provenance)
    cal.opencv_check = opencv_stereo_check(cal, proj_world, proj_cam_px, proj_uv,
                                           (rig.camera.width, rig.camera.height),
                                           (rig.projector.width, rig.projector.height))
    report(1.0, "conventional calibration done")
    return cal


def _predicted_rms(dec, heights: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> float:
    """RMS of the decoded ``u_p``, ``v_p``'s predicted 1-sigma over the projector's feature points (projector
    px): what the projector's reprojection RMS should be when the pinhole model fits."""
    sig = np.concatenate([dec.sigma_u[heights][:, rows, cols].ravel(),
                          dec.sigma_v[heights][:, rows, cols].ravel()]).astype(float)
    return float(np.sqrt(np.mean(sig ** 2)))


def _step(shape, grid_step_px: int | None) -> int:
    """The feature grid's spacing (camera px): given, or about 40 feature pixels across the image."""
    return int(grid_step_px) if grid_step_px else max(1, int(round(shape[1] / 40)))


def feature_grid(samples: SampleStack, u: np.ndarray, v: np.ndarray, grid_step_px: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The feature pixels: a grid every ``grid_step_px`` (from half a step in), valid everywhere.

    Parameters
    ----------
    samples : SampleStack
        The LCD sweep's (K LCD positions).
    u, v : (K_h, H, W) float32
        Decoded ``u_p``, ``v_p`` of the height sweep (NaN where invalid).
    grid_step_px : int, optional
        Default: about 40 pixels across the image.

    Returns
    -------
    rows, cols : (M,) int64
        Grid pixels valid at every LCD position and every plate height.

    Raises
    ------
    DatasetError
        Fewer than 20 such pixels.
    """
    h, w = samples.x.shape[1:]
    step = _step((h, w), grid_step_px)
    r, c = np.meshgrid(np.arange(step // 2, h, step), np.arange(step // 2, w, step), indexing="ij")
    r, c = r.ravel(), c.ravel()
    ok = np.all(np.isfinite(samples.x[:, r, c]) & np.isfinite(samples.y[:, r, c]), axis=0)
    ok &= np.all(np.isfinite(u[:, r, c]) & np.isfinite(v[:, r, c]), axis=0)
    if np.count_nonzero(ok) < 20:
        raise DatasetError(f"the conventional calibration needs feature pixels valid at every LCD position and"
                           f" plate height: {np.count_nonzero(ok)} of {r.size} grid pixels (every {step} px) are")
    return r[ok], c[ok]


def _camera_points(samples: SampleStack, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera's feature points: world (K M, 3) mm, each feature pixel at every LCD position, and their
    pixels (K M, 2) ``(col, row)``."""
    k = samples.z.size
    x = samples.x_ref[rows, cols] + samples.x[:, rows, cols].astype(np.float64)
    y = samples.y_ref[rows, cols] + samples.y[:, rows, cols].astype(np.float64)
    z = np.broadcast_to(np.asarray(samples.z, float)[:, None], x.shape)
    world = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    pixels = np.tile(np.stack([cols, rows], axis=1).astype(np.float64), (k, 1))
    return world, pixels


def _plate_heights(samples: SampleStack, plate_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which plate heights give the projector's points, and the LCD position each one's X, Y comes from.

    The plate heights on the LCD's readings (within :data:`_SAME_HEIGHT_MM`), when there are at least
    :data:`MIN_LCD_HEIGHTS`: their X, Y are the LCD decode's, a measurement with no model error, and the
    other heights are left out rather than mixed in with the camera model's error (on a lens that Brown
    does not describe, tens of um: more than ``u_p``'s noise). Otherwise every height, X, Y from the
    camera's fit (LCD position -1).

    Returns
    -------
    heights : (K_u,) int64
        Indices into ``plate_z``.
    lcd_position : (K_u,) int64
        The LCD position of each, or -1 for the camera model.
    """
    lcd_z = np.asarray(samples.z, float)
    match = np.array([np.flatnonzero(np.abs(lcd_z - z) < _SAME_HEIGHT_MM)[:1].tolist() or [-1] for z in plate_z])[:, 0]
    on_lcd = np.flatnonzero(match >= 0)
    if on_lcd.size >= MIN_LCD_HEIGHTS:
        return on_lcd, match[on_lcd]
    return np.arange(plate_z.size), np.full(plate_z.size, -1)


def _projector_points(samples: SampleStack, dec, rows: np.ndarray, cols: np.ndarray, camera):
    """The projector's feature points at the plate heights :func:`_plate_heights` picks.

    Returns
    -------
    world : (K_u M, 3) float64, mm
        ``(X, Y, z_h)``: X, Y from the LCD position at the same reading, or from ``camera``'s ray.
    uv : (K_u M, 2) float64
        Decoded ``(u_p, v_p)`` (projector px).
    camera_px : (K_u M, 2) float64
        The feature pixels ``(col, row)``.
    info : dict
        ``plate_xy_from``: per plate height used (``"%g"`` mm), ``"lcd decode"`` or ``"camera model"``;
        ``projector_sigma_rms_px``: :func:`_predicted_rms` of these points.
    """
    plate_z = np.asarray(dec.z_mm, float)
    heights, lcd_position = _plate_heights(samples, plate_z)
    world, xy_from = [], {}
    for h, k in zip(heights, lcd_position):
        if k >= 0:
            x = samples.x_ref[rows, cols] + samples.x[k, rows, cols].astype(np.float64)
            y = samples.y_ref[rows, cols] + samples.y[k, rows, cols].astype(np.float64)
        else:
            x, y = camera.pixel_to_world_at_z(cols.astype(float), rows.astype(float), plate_z[h])
        world.append(np.stack([x, y, np.full(rows.shape, plate_z[h])], axis=1))
        xy_from[f"{plate_z[h]:g}"] = "lcd decode" if k >= 0 else "camera model"
    uv = np.stack([dec.u[heights][:, rows, cols].ravel(), dec.v[heights][:, rows, cols].ravel()], axis=1)
    camera_px = np.tile(np.stack([cols, rows], axis=1).astype(np.float64), (heights.size, 1))
    info = {"plate_xy_from": xy_from, "projector_sigma_rms_px": _predicted_rms(dec, heights, rows, cols)}
    return np.concatenate(world), uv.astype(np.float64), camera_px, info


def reconstruct_conventional(scan_dir, cal: ConventionalCalibration, *, options: DecodeOptions = DecodeOptions(),
                             progress: Progress | None = None) -> list:
    """A scan folder (``ptp-scan/1``) through the conventional calibration -> one point cloud per view.

    ``u_p`` is decoded as :func:`ptpcore.run.scanner.reconstruct` decodes it (the height sweep's camera noise
    model, ``cal.provenance["camera_noise"]``, for its sigma); each pixel's point is
    :meth:`~ptpcore.pinhole.structured_light.ConventionalCalibration.points_from_up`. Its 1-sigma per axis is
    ``|dP/du_p| sigma_u`` (the point moves along the camera ray as ``u_p`` varies; the calibration's own
    parameter uncertainty is not included).

    Returns
    -------
    list of PointCloud
        Valid points only (``n_no_height``: pixels without ``u_p``; ``n_no_value``: pixels whose ray does not
        meet the surface of their ``u_p``).
    """
    from ptpcore.decode.noise import NoiseModel
    from ptpcore.io.dataset import DatasetSource
    from ptpcore.rig.rigfile import load_scan
    from ptpcore.run.scanner import decode_projector

    spec = load_scan(scan_dir)
    noise = cal.provenance.get("camera_noise")
    noise = None if noise is None else NoiseModel(*noise, source="height sweep")
    dec = decode_projector(DatasetSource(scan_dir, rig=spec.rig()), options=options, progress=progress, noise=noise)
    return [_cloud(cal, dec.u[k], dec.sigma_u[k]) for k in range(spec.views)]


def _cloud(cal: ConventionalCalibration, u: np.ndarray, sigma_u: np.ndarray):
    """One view's points from its decoded ``u_p`` (H, W), each with ``|dP/du_p| sigma_u`` per axis."""
    from ptpcore.io.pointcloud import PointCloud

    rows, cols = np.nonzero(np.isfinite(u))
    up = u[rows, cols].astype(float)
    p = cal.points_from_up(cols, rows, up)
    step = 0.01  # projector px: the surface of constant u_p moves smoothly on this scale
    slope = (cal.points_from_up(cols, rows, up + step) - cal.points_from_up(cols, rows, up - step)) / (2 * step)
    sigma = np.abs(slope) * sigma_u[rows, cols].astype(float)[:, None]
    ok = np.all(np.isfinite(p), axis=1)
    s32 = sigma[ok].astype(np.float32)
    return PointCloud(x=p[ok, 0], y=p[ok, 1], z=p[ok, 2], row=rows[ok].astype(np.int32), col=cols[ok].astype(np.int32),
                      sigma_x=s32[:, 0], sigma_y=s32[:, 1], extrapolated=np.zeros(int(ok.sum()), bool), shape=u.shape,
                      n_no_height=int(np.count_nonzero(~np.isfinite(u))), n_no_value=int(np.count_nonzero(~ok)),
                      sigma_z=s32[:, 2])
