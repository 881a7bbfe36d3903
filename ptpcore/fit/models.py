"""One entry point for every LUT kind the product offers.

``auto`` (the default) chooses among ``poly`` degrees 1 to 3 and ``smooth`` by
their error at held-out positions (:mod:`ptpcore.fit.choice`). ``poly``, ``pchip`` and ``linear`` are the paper's per-pixel models
(:mod:`ptpcore.io.lutfile`); ``smooth`` is the regularised per-pixel model
(:mod:`ptpcore.fit.smooth`), written as ``poly`` coefficients. Plain ``poly`` LUTs
also get their predicted sigma maps when the samples carry a noise model.

This module dispatches; the fits are :func:`ptpcore.fit.kinds.fit_kind` (one named kind),
:func:`ptpcore.fit.choice.fit_auto` and :func:`ptpcore.fit.robust.fit_robust`, which fit their LUTs
with :func:`~ptpcore.fit.kinds.fit_kind` too (none of them imports this module).
"""

from __future__ import annotations

from typing import Callable

from ptpcore.fit.choice import fit_auto
from ptpcore.fit.kinds import fit_kind
from ptpcore.fit.robust import fit_robust
from ptpcore.io.lutfile import Lut
from ptpcore.io.samples import SampleStack
from ptpcore.rig.rigfile import Rig

__all__ = ["LUT_MODELS", "fit_model", "lut_model", "describe_lut", "describe_model", "positions_needed", "check_positions_for_model"]

LUT_MODELS = ("auto", "poly", "pchip", "linear", "smooth")


def positions_needed(model: str, degree: int = 3) -> int:
    """Fewest calibration positions a model can be fitted (and checked) on: ``degree + 2`` for
    ``poly`` and ``smooth`` (one more than its coefficients), 3 for ``auto`` (it judges its
    candidates at a position held out between two others), 2 for the tables."""
    if model == "auto":
        return 3
    return int(degree) + 2 if model in ("poly", "smooth") else 2


def check_positions_for_model(model: str, degree: int, n_positions: int, source: str = "the dataset") -> None:
    """Refuse, before any decoding, a model that needs more positions than there are.

    Raises
    ------
    ValueError
        One line naming the model, the number it needs and the number available.
    """
    need = positions_needed(model, degree)
    if n_positions < need:
        what = f"{model} of degree {degree}" if model in ("poly", "smooth") else model
        lower = (f"; choose --degree {max(1, n_positions - 2)}" if model in ("poly", "smooth") and n_positions >= 3
                 else "; choose --model linear" if n_positions >= 2 else "")
        raise ValueError(f"{source}: model {what} needs at least {need} positions, the dataset has"
                         f" {n_positions}{lower} or capture more positions")


def fit_model(samples: SampleStack, rig: Rig, model: str = "poly", degree: int = 3, positions=None,
              progress: Callable[[float, str], None] | None = None, *, stage_sigma_mm: float = 0.0,
              level_bias: bool = True, footprint: bool = True, robust: bool = False,
              uncertainty: bool = True) -> Lut:
    """Fit a LUT of any kind to decoded samples.

    Parameters
    ----------
    samples : SampleStack
    rig : Rig
    model : {"auto", "poly", "pchip", "linear", "smooth"}
        ``auto``: :func:`ptpcore.fit.choice.fit_auto` (``degree`` is not used).
    degree : int
        Polynomial degree for ``poly`` and ``smooth`` (1 to 5).
    positions : sequence of int, optional
        Calibration positions (default all).
    progress : callable, optional
        ``progress(fraction, message)``; may raise to cancel.
    stage_sigma_mm : float
        1-sigma error of the stage readings (mm, the stage's specification):
        part of the predicted sigma maps (``poly`` and ``smooth``).
    level_bias : bool
        ``smooth``: remove the display's level bias first (:mod:`ptpcore.decode.display`).
    footprint : bool
        ``smooth``: move samples from the footprint centroid to the centre ray
        (:func:`ptpcore.fit.smooth.footprint_bias`).

    robust : bool
        Leave out the samples far outside their pixel's curve first (:func:`ptpcore.fit.robust.fit_robust`;
        ``n_rejected`` and ``provenance["robust"]`` on the LUT).
    uncertainty : bool
        ``smooth``: the honest sigma maps and the real leave-one-out
        (:func:`ptpcore.fit.smooth.fit_smooth_lut`); off for fits judged only by
        their predictions (auto's held-out candidates).

    Returns
    -------
    Lut
        ``smooth`` comes back with ``kind == "poly"`` and
        ``extra_attrs["method"] == "smooth"``.
    """
    if model not in LUT_MODELS:
        raise ValueError(f"model must be one of {', '.join(LUT_MODELS)}, got {model!r}")
    if robust:  # screen the samples for outliers, then this same fit without them
        return fit_robust(samples, rig, model, degree, positions, stage_sigma_mm=stage_sigma_mm, progress=progress,
                          level_bias=level_bias, footprint=footprint)[0]
    if model == "auto":
        return fit_auto(samples, rig, positions, stage_sigma_mm=stage_sigma_mm, level_bias=level_bias,
                        footprint=footprint, progress=progress)[0]
    return fit_kind(samples, rig, model, degree, positions, progress, stage_sigma_mm=stage_sigma_mm,
                    level_bias=level_bias, footprint=footprint, uncertainty=uncertainty)


def lut_model(lut: Lut) -> str:
    """The model name a LUT was fitted with (one of :data:`LUT_MODELS`).

    A ``smooth`` LUT is stored as ``kind = "poly"``; its ``/model`` attribute
    ``method = "smooth"`` tells it apart.
    """
    method = lut.extra_attrs.get("method") if lut.extra_attrs else None
    if isinstance(method, bytes):
        method = method.decode("utf-8", "replace")
    return "smooth" if lut.kind == "poly" and str(method) == "smooth" else lut.kind


def describe_lut(lut: Lut) -> str:
    """A short description of a LUT's model, e.g. ``"smooth, poly degree 2, smoothing scale 16 px"``.

    A LUT whose model was chosen (``/model`` attribute ``chosen_by``) says so at the end.
    """
    text = _describe(lut)
    chosen_by = lut.extra_attrs.get("chosen_by") if lut.extra_attrs else None
    if isinstance(chosen_by, bytes):
        chosen_by = chosen_by.decode("utf-8", "replace")
    return f"{text}, chosen by {chosen_by}" if chosen_by else text


def describe_model(lut: Lut) -> str:
    """The model, degree and smoothing scale of a LUT (:func:`describe_lut` without how it was chosen):
    two LUTs with equal descriptions were fitted alike."""
    return _describe(lut)


def _describe(lut: Lut) -> str:
    model = lut_model(lut)
    if model == "smooth":
        text = f"smooth, poly degree {lut.degree}"
        scale = lut.extra_attrs.get("smoothing_scale_px")
        try:
            scale = float(scale)
        except (TypeError, ValueError):
            return text
        return text + (f", smoothing scale {scale:g} px" if scale > 0 else ", not smoothed (scale 0 px)")
    return f"poly degree {lut.degree}" if lut.kind == "poly" else lut.kind
