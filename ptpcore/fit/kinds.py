"""One LUT of a named kind, fitted as it is: ``poly``, ``pchip``, ``linear`` or ``smooth``.

Below the choices that fit several of them (:mod:`ptpcore.fit.choice`'s ``auto``, the outlier
screening of :mod:`ptpcore.fit.robust`) and :func:`ptpcore.fit.models.fit_model`, which dispatches to
all three: every one of them fits its LUTs here, so none imports another back.
"""

from __future__ import annotations

from typing import Callable

from ptpcore.fit.perpixel import fit_lut
from ptpcore.fit.sigma import MODEL_MAP_WORDS
from ptpcore.fit.smooth import fit_smooth_lut, poly_model_variance, poly_sigma_maps, sigma_scale
from ptpcore.io.lutfile import Lut
from ptpcore.io.samples import SampleStack
from ptpcore.rig.rigfile import Rig, rig_to_toml

__all__ = ["LUT_KINDS", "fit_kind"]

LUT_KINDS = ("poly", "pchip", "linear", "smooth")


def fit_kind(samples: SampleStack, rig: Rig, model: str = "poly", degree: int = 3, positions=None,
             progress: Callable[[float, str], None] | None = None, *, stage_sigma_mm: float = 0.0,
             level_bias: bool = True, footprint: bool = True, uncertainty: bool = True,
             smooth_scales_px=None, smooth_global_fit=None) -> Lut:
    """Fit one LUT of kind ``model`` (one of :data:`LUT_KINDS`) to decoded samples.

    Parameters and result as :func:`ptpcore.fit.models.fit_model` (without ``auto`` and ``robust``).
    Plain ``poly`` LUTs get their predicted sigma maps when the samples carry a noise model.
    ``smooth_scales_px``: the smooth fit's candidate smoothing scales (default its own ladder); one
    scale fixes it (the model choice's folds use the scale chosen on all positions).
    ``smooth_global_fit``: the smooth fit's global model on these positions, to reuse
    (:func:`ptpcore.fit.smooth.smooth_global_fit`).
    """
    if model not in LUT_KINDS:
        raise ValueError(f"model must be one of {', '.join(LUT_KINDS)}, got {model!r}")
    toml = rig_to_toml(rig)
    if model == "smooth":
        scales = {} if smooth_scales_px is None else {"scales_px": tuple(float(v) for v in smooth_scales_px)}
        lut, _info = fit_smooth_lut(samples, rig, degree, positions, rig_toml=toml, progress=progress,
                                    stage_sigma_mm=stage_sigma_mm, level_bias=level_bias, footprint=footprint,
                                    uncertainty=uncertainty, global_fit=smooth_global_fit, **scales)
        return lut
    with_sigma = model == "poly" and uncertainty and samples.noise is not None and samples.modulation is not None
    scale = None
    if with_sigma:
        # Before the LUT: the scale fits a degree-2 LUT of its own, and the two LUTs were the
        # run's peak of memory when held together (1.3 GB at 5 MP, 2.6 GB at 12 MP).
        if progress:
            progress(0.0, f"fitting LUT ({model}): the noise scale")
        scale = sigma_scale(samples, rig, positions)
    lut = fit_lut(samples, model, degree, positions=positions, rig_toml=toml, progress=progress)
    if with_sigma:
        lut.sigma_x, lut.sigma_y = poly_sigma_maps(samples, rig, lut, positions, stage_sigma_mm, scale=scale)
        _add_poly_model_part(lut, samples, rig, positions, stage_sigma_mm, scale)
    return lut


def _add_poly_model_part(lut: Lut, samples: SampleStack, rig: Rig, positions, stage_sigma_mm: float,
                         scale: float) -> None:
    """The model's own error (:func:`ptpcore.fit.smooth.poly_model_variance`) into the poly LUT's sigma
    maps in quadrature, its part as ``sigma_model_x``, ``_y`` and how in ``/provenance`` ``model_error``."""
    import json

    import numpy as np

    var, info = poly_model_variance(samples, rig, lut, positions, stage_sigma_mm, scale)
    for a in "xy":
        noise = getattr(lut, f"sigma_{a}").astype(np.float64)
        setattr(lut, f"sigma_{a}", np.sqrt(noise * noise + var[a]).astype(np.float32))
        setattr(lut, f"sigma_model_{a}", np.sqrt(var[a]).astype(np.float32))
    valid = lut.valid.astype(bool)
    rms = float(np.sqrt(np.mean([np.nanmean(var[a][valid]) for a in "xy"]))) if valid.any() else 0.0
    lut.provenance["model_error"] = json.dumps({
        "method": "poly leave-one-position-out (r_k / (1 - h_kk), closed form): per interior sample, its square"
                  " minus its predicted noise variance (sum_j (I - H)_kj^2 sigma_j^2 / (1 - h_kk)^2); "
                  + MODEL_MAP_WORDS + "; added to the noise in quadrature",
        "scale_px": {a: float(v) for a, v in info["scale_px"].items()}, "rms_um": round(1e3 * rms, 6),
        "resolved_limit_um": {a: round(1e3 * v, 6) for a, v in info["resolved_limit_mm"].items()},
        "n_samples": info["n_samples"],
        "spatial": any(np.isfinite(v) for v in info["scale_px"].values())})
