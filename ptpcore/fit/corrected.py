"""One call from decoded samples to a LUT with every correction of docs/method.md section 8.

Every front end fits through :func:`fit_corrected`, called by the composer's fit stage
(:mod:`ptpcore.run.calibration`): the cover glass and a
measured flatness (:func:`ptpcore.fit.glass.correct_samples`), optionally the
stage pose (:mod:`ptpcore.fit.stage_pose`), then the fit; what cannot be
measured enters the sigma maps (the glass's datasheet tolerances, the pose
estimates' uncertainty) and every correction is recorded in the LUT's
``/provenance``.
"""

from __future__ import annotations

from dataclasses import dataclass

from ptpcore.fit.glass import add_tolerances_to_sigma, correct_samples, corrections_json, pixel_slopes
from ptpcore.fit.models import fit_model
from ptpcore.fit.settings import FitSettings
from ptpcore.fit.sigma import add_stage_pose_sigma
from ptpcore.fit.stage_pose import StagePose, apply_stage_pose, refine_stage
from ptpcore.io.lutfile import Lut
from ptpcore.io.samples import SampleStack
from ptpcore.progress import Progress
from ptpcore.rig.rigfile import Rig

__all__ = ["CorrectedFit", "fit_corrected", "correct_all", "samples_as_fitted"]


@dataclass
class CorrectedFit:
    """A LUT fitted to corrected samples.

    Attributes
    ----------
    lut : Lut
        With ``/provenance`` ``corrections``, ``stage_pose`` (when refined) and the
        sigma maps widened by what no data can reveal.
    samples : SampleStack
        The samples the LUT was fitted to (every correction applied).
    applied : dict
        Name -> correction object (:func:`ptpcore.fit.glass.correct_samples`).
    pose : StagePose or None
        The stage pose estimates (``refine_stage``).
    """

    lut: Lut
    samples: SampleStack
    applied: dict
    pose: StagePose | None = None


def correct_all(samples: SampleStack, rig: Rig, positions=None, *, refine: bool = False, seed: int = 0,
                progress: Progress | None = None,
                ) -> tuple[SampleStack, dict, StagePose | None, tuple]:
    """The samples with the glass, the flatness and (``refine``) the stage pose removed.

    Returns
    -------
    corrected : SampleStack
    applied : dict
    pose : StagePose or None
    slopes : (2,) tuple of (H, W) float64, or None
        Every pixel's ``dX/dZ``, ``dY/dZ`` (of the glass-corrected samples); None unless ``refine``
        (nothing else reads them).
    """
    samples, applied = correct_samples(samples, rig, positions)
    slopes = pixel_slopes(samples, positions) if refine else None
    pose = None
    if refine:
        if progress:
            progress(0.0, "refining the stage pose of every position")
        pose = refine_stage(samples, rig, n_pixels=1500, seed=seed)
        samples = apply_stage_pose(samples, rig, pose, slopes)
    return samples, applied, pose, slopes


def samples_as_fitted(samples: SampleStack, rig: Rig, lut: Lut | None, positions=None) -> SampleStack:
    """The samples a LUT was fitted to: the corrections ``rig.toml`` asks for, and the LUT's stored stage pose.

    For residuals and per-pixel plots of a fitted (or reopened) LUT: the pose is
    the one in ``lut.stage_pose`` (not estimated again).

    Parameters
    ----------
    samples : SampleStack
        As decoded.
    rig : Rig
    lut : Lut or None
    positions : sequence of int, optional
        Positions whose samples give each pixel's slope (default all).

    Returns
    -------
    SampleStack
    """
    fixed, _applied = correct_samples(samples, rig, positions)
    if lut is not None and lut.stage_pose is not None and len(lut.stage_pose) == len(samples.z):
        sigma = lut.stage_pose_sigma if lut.stage_pose_sigma is not None else lut.stage_pose * 0.0
        fixed = apply_stage_pose(fixed, rig, StagePose(lut.stage_pose, sigma, 0.0, 0), pixel_slopes(fixed, positions))
    return fixed


def fit_corrected(samples: SampleStack, rig: Rig, settings: FitSettings = FitSettings(), positions=None, *,
                  progress: Progress | None = None) -> CorrectedFit:
    """Correct the samples (docs/method.md section 8), fit the LUT, record the corrections and their uncertainty.

    Parameters
    ----------
    samples : SampleStack
        As decoded (not modified).
    rig : Rig
    settings : FitSettings
        The model and every fit option, passed whole (``refine_stage``: estimate every position's pose
        errors and correct the samples first, :func:`ptpcore.fit.stage_pose.refine_stage`; their 1-sigma
        enters the sigma maps, :func:`ptpcore.fit.sigma.add_stage_pose_sigma`).
    positions : sequence of int, optional
        Calibration positions (default all).
    progress : callable, optional

    Returns
    -------
    CorrectedFit
    """
    fixed, applied, pose, slopes = correct_all(samples, rig, positions, refine=settings.refine_stage,
                                               progress=progress)
    lut = fit_model(fixed, rig, settings.model, settings.degree, positions=positions, progress=progress,
                    stage_sigma_mm=settings.stage_sigma_mm, level_bias=settings.level_bias,
                    footprint=settings.footprint, robust=settings.robust)
    lut.provenance["corrections"] = corrections_json(fixed)
    add_tolerances_to_sigma(lut, applied)
    if pose is not None:
        lut.stage_pose, lut.stage_pose_sigma = pose.pose, pose.sigma
        add_stage_pose_sigma(lut, fixed, rig, pose.sigma, slopes, positions)
    return CorrectedFit(lut, fixed, applied, pose)
