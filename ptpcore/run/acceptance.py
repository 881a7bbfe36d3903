"""The acceptance scans through both scanner calibrations (docs/method.md section 9, issue 35).

Every scan is decoded once (:func:`ptpcore.run.scanner.reconstruct`, the height sweep's decoder and
noise model); the same decoded ``u_p`` of every pixel then goes through

- **ptp**: the LUT's per-pixel height map and XY LUT (the point :func:`reconstruct` gives);
- **conventional**: camera and projector as two pinholes with Brown distortion
  (:func:`ptpcore.run.structured_light.calibrate_conventional` on the same dataset), the camera
  ray intersected with the projector's surface of constant ``u_p``.

The result is plain arrays per scan (pixels, each method's points, the exact points when the scan is
simulated); :mod:`ptpcore.evaluate.vdi2634` judges them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptpcore.decode.phase import DecodeOptions
from ptpcore.errors import ConfigError
from ptpcore.progress import Progress, sub_progress

__all__ = ["ACCEPTANCE_METHODS", "ScanPoints", "scan_folders", "conventional_calibration", "reconstruct_scans"]

ACCEPTANCE_METHODS = ("ptp", "conventional")


@dataclass
class ScanPoints:
    """One scan (its first view) reconstructed by every method, on the same pixels.

    Attributes
    ----------
    name : str
        The scan folder's name.
    scan_dir : Path
    rows, cols : (N,) int64
        The camera pixels with a decoded ``u_p``.
    u : (N,) float64, projector px
        Their decoded ``u_p``.
    points : dict of method -> (N, 3) float64, mm
        Each method's point of each pixel (NaN rows: the method gives none there).
    truth_xyz : (N, 3) float64 or None, mm
        The exact point of each pixel's centre ray on the simulated object (NaN off it).
    truth_object : ScanObject or None
        The simulated object (:class:`ptpcore.simulate.scanner.ScanObject`).
    counts : dict
        Pixels decoded, and points per method.
    """

    name: str
    scan_dir: Path
    rows: np.ndarray
    cols: np.ndarray
    u: np.ndarray
    points: dict
    truth_xyz: np.ndarray | None = None
    truth_object: object | None = None
    counts: dict = field(default_factory=dict)

    def common(self) -> np.ndarray:
        """(N,) bool: pixels where every method gives a point."""
        ok = np.ones(self.rows.size, bool)
        for p in self.points.values():
            ok &= np.all(np.isfinite(p), axis=1)
        return ok


def scan_folders(paths) -> list[Path]:
    """The scans named by ``paths``: each a scan folder (``scan.toml``) or a folder of them (every
    sub-folder with a ``scan.toml``, sorted by name), in the order given.

    Raises
    ------
    ValueError
        A path that is not a folder, or a folder with no scan in it or under it (named).
    """
    out = []
    for text in paths:
        folder = Path(text)
        if not folder.is_dir():
            raise ValueError(f"{folder}: not a folder (a ptp-scan/1 folder, or a folder of them)")
        if (folder / "scan.toml").is_file():
            out.append(folder)
            continue
        inner = sorted(p for p in folder.iterdir() if (p / "scan.toml").is_file())
        if not inner:
            raise ValueError(f"{folder}: no scan.toml in it or in its sub-folders")
        out += inner
    return out


def conventional_calibration(dataset_dir, progress: Progress | None = None):
    """The conventional camera-projector calibration of ``dataset_dir``
    (:func:`ptpcore.run.structured_light.calibrate_conventional`: camera and projector pinholes with
    Brown distortion from the same LCD and height sweeps).

    Raises
    ------
    ConfigError, DatasetError
        The dataset cannot calibrate it (e.g. a height sweep without direction ``y``; named by it).
    """
    from ptpcore.run.structured_light import calibrate_conventional

    return calibrate_conventional(dataset_dir, progress=progress)


def reconstruct_scans(scans, lut, *, conventional=None, options: DecodeOptions = DecodeOptions(),
                      progress: Progress | None = None) -> list[ScanPoints]:
    """Decode every scan once and reconstruct it with PTP (``lut``) and, when given, ``conventional``.

    Parameters
    ----------
    scans : sequence of path
        ``ptp-scan/1`` folders; a scan of several views contributes its first.
    lut : Lut
        With ``/height`` (:func:`ptpcore.io.load_lut`).
    conventional : object with ``points_from_up(cols, rows, u_p) -> (N, 3)``, optional
        The conventional calibration (:func:`conventional_calibration`).

    Returns
    -------
    list of ScanPoints, in the order of ``scans``.

    Raises
    ------
    ConfigError, DatasetError
        A scan that :func:`ptpcore.run.scanner.reconstruct` refuses (named by it).
    """
    from ptpcore.run.scanner import reconstruct

    out = []
    n = len(scans)
    for i, scan in enumerate(scans):
        folder = Path(scan)
        part = sub_progress(progress, i / n, (i + 1) / n, f"{folder.name}: ")
        view = reconstruct(folder, lut, options=options, progress=part)[0]
        rows, cols = np.nonzero(np.isfinite(view.u))
        u = view.u[rows, cols].astype(np.float64)
        points = {"ptp": np.stack([view.x[rows, cols], view.y[rows, cols], view.z[rows, cols]], axis=1)}
        if conventional is not None:
            points["conventional"] = _conventional_points(conventional, cols, rows, u)
        counts = {"decoded": int(rows.size),
                  **{m: int(np.all(np.isfinite(p), axis=1).sum()) for m, p in points.items()}}
        sp = ScanPoints(folder.name, folder, rows.astype(np.int64), cols.astype(np.int64), u, points, counts=counts)
        _attach_truth(sp)
        out.append(sp)
    if progress:
        progress(1.0, "scans reconstructed")
    return out


def _conventional_points(cal, cols: np.ndarray, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``cal.points_from_up`` checked: (N, 3) float64, NaN rows where it gives no point."""
    if cols.size == 0:
        return np.zeros((0, 3))
    p = np.asarray(cal.points_from_up(cols.astype(np.float64), rows.astype(np.float64), u), float)
    if p.shape != (cols.size, 3):
        raise ValueError(f"the conventional calibration returned points of shape {p.shape}, expected ({cols.size}, 3)")
    return p


def _attach_truth(sp: ScanPoints) -> None:
    """A simulated scan's exact points and object (``truth.h5``), when the folder has them."""
    from ptpcore.simulate.scanner import SCAN_TRUTH_FILE, load_scan_truth

    if not (sp.scan_dir / SCAN_TRUTH_FILE).exists():
        return
    obj, truth = load_scan_truth(sp.scan_dir)
    xyz = truth["xyz"]
    if xyz.shape[:2] == (0, 0) or sp.rows.size and (sp.rows.max() >= xyz.shape[0] or sp.cols.max() >= xyz.shape[1]):
        raise ConfigError(f"{sp.scan_dir / SCAN_TRUTH_FILE}: its camera is not the scan's")
    sp.truth_xyz = xyz[sp.rows, sp.cols].astype(np.float64)
    sp.truth_object = obj
