"""How good a texture is: its statistics against the sample's, its visible seams, and the evaluations
against a dataset's truth (the procedural textures' known statistics, where a query window was cut).

The first two are the metrics the synthesis steps report; :data:`EVALUATIONS` is the pipeline's
``evaluations`` (step name -> function of state and truth).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from lab.core import InvalidValue
from lab.core.pipeline import Evaluation
from lab.modules.texture._common import as_hwc, channel_count, luminance
from lab.modules.texture.parametric import build_pyramid


def quantiles(values: np.ndarray, count: int = 64) -> np.ndarray:
    """The ``count`` quantiles ``(k + 0.5) / count`` of all of ``values``."""
    return np.quantile(values.ravel(), (np.arange(count) + 0.5) / count)


def _pyramid_levels_for(shape: tuple[int, ...], wanted: int = 3) -> int:
    side = min(shape[:2])
    return int(max(1, min(wanted, math.floor(math.log2(max(side, 2) / 8.0)) + 1)))


def texture_statistics_distance(output: np.ndarray, sample: np.ndarray, *, levels: int = 3,
                                orientations: int = 4) -> float:
    """How far the texture statistics of ``output`` are from those of ``sample`` (0 = the same), any sizes.

    Two terms, averaged: (1) subband histograms: the 1D Wasserstein distance between the value
    distributions of every band of an oriented pyramid (:func:`build_pyramid`) of the luminance, and
    of every colour channel's pixels, each divided by the sample band's standard deviation (the mean
    absolute difference of 64 quantiles); (2) Gram matrices of filter responses: per pyramid level,
    ``G = F^T F / n`` of the oriented bands and their magnitudes, relative Frobenius difference
    (Gatys et al. 2015 with a fixed filter bank in place of a CNN's). Heeger–Bergen matches the
    histograms of its own pyramid exactly, so it is favoured by term (1); term (2) sees the
    joint statistics that it does not copy.

    ``output``, ``sample``: ``(H, W)`` or ``(H, W, 3)`` images in [0, 1]. ``levels`` shrinks for small images.
    """
    out, ref = np.asarray(output, dtype=np.float64), np.asarray(sample, dtype=np.float64)
    if channel_count(out) != channel_count(ref):
        raise InvalidValue("output", f"has {channel_count(out)} channel(s) but the sample "
                                     f"{channel_count(ref)}")
    levels = min(levels, _pyramid_levels_for(out.shape), _pyramid_levels_for(ref.shape))
    hist_terms = []
    for c in range(channel_count(ref)):
        a, b = as_hwc(out)[:, :, c], as_hwc(ref)[:, :, c]
        hist_terms.append(np.abs(quantiles(a) - quantiles(b)).mean() / (b.std() + 1e-3))
    bands_out = build_pyramid(luminance(out), levels=levels, orientations=orientations)
    bands_ref = build_pyramid(luminance(ref), levels=levels, orientations=orientations)
    for a, b in zip(bands_out, bands_ref, strict=True):
        hist_terms.append(np.abs(quantiles(a) - quantiles(b)).mean() / (b.std() + 1e-3))
    gram_terms = []
    for level in range(levels):
        chunk = slice(level * orientations, (level + 1) * orientations)
        grams = []
        for bands in (bands_out[chunk], bands_ref[chunk]):
            features = np.stack([b.ravel() for b in bands] + [np.abs(b).ravel() for b in bands], axis=1)
            grams.append(features.T @ features / len(features))
        gram_terms.append(np.linalg.norm(grams[0] - grams[1]) / (np.linalg.norm(grams[1]) + 1e-12))
    return float(0.5 * np.mean(hist_terms) + 0.5 * np.mean(gram_terms))


def seam_score(output: np.ndarray, source: np.ndarray, sample: np.ndarray) -> float:
    """Visible seams: contrast across seams relative to the texture's own contrast (about 1: invisible).

    ``source`` ``(H, W, 2)`` int: the sample pixel each output pixel was copied from. A pair of
    4-neighbours is *across a seam* when their sources are not neighbours in the same way (the
    copy jumps). The score is the mean squared difference of the pairs across seams divided by the
    mean squared difference of all neighbour pairs of the sample; 1.0 when there is no seam.
    Seams a viewer sees are differences larger than the texture's usual ones (Efros & Freeman 2001,
    figure 2's visible block edges).
    """
    out = as_hwc(output)
    ref = as_hwc(sample)
    source = np.asarray(source)
    jumps, base = [], []
    for axis, step in ((0, (1, 0)), (1, (0, 1))):
        a = np.take(out, range(out.shape[axis] - 1), axis=axis)
        b = np.take(out, range(1, out.shape[axis]), axis=axis)
        sa = np.take(source, range(source.shape[axis] - 1), axis=axis)
        sb = np.take(source, range(1, source.shape[axis]), axis=axis)
        seam = np.any(sb - sa != np.array(step), axis=2)
        jumps.append(((a - b) ** 2).sum(axis=2)[seam])
        ra = np.take(ref, range(ref.shape[axis] - 1), axis=axis)
        rb = np.take(ref, range(1, ref.shape[axis]), axis=axis)
        base.append(((ra - rb) ** 2).sum(axis=2).ravel())
    across = np.concatenate(jumps)
    typical = np.concatenate(base).mean()
    if len(across) == 0:
        return 1.0
    return float(across.mean() / max(typical, 1e-12))


def evaluate_match(state: Mapping[str, Any], truth: Mapping[str, Any]) -> dict[str, float]:
    """``match_error_px``: how far the chosen window is from where the query was cut."""
    if "chosen_match" not in state or "query_origin" not in state:
        return {}
    return {"match_error_px": float(np.hypot(*(state["chosen_match"] - state["query_origin"])))}


def _statistics_evaluation(name: str) -> Evaluation:
    def evaluate(state: Mapping[str, Any], truth: Mapping[str, Any]) -> dict[str, float]:
        if name not in state or "mean" not in truth:
            return {}
        pixels = state[name].pixels
        return {"mean_error": float(abs(pixels.mean() - truth["mean"])),
                "std_ratio": float(pixels.std() / truth["std"])}

    evaluate.__name__ = f"evaluate_{name}"
    evaluate.__doc__ = (f"``mean_error`` and ``std_ratio`` of {name!r} against the procedural texture's "
                        "true statistics.")
    return evaluate


evaluate_parametric = _statistics_evaluation("parametric")
evaluate_efros_leung = _statistics_evaluation("efros_leung")
evaluate_quilting = _statistics_evaluation("quilting")

#: The pipeline's evaluations: step name -> what its outputs are compared with.
EVALUATIONS: dict[str, Evaluation] = {
    "match_window": evaluate_match, "synthesize_parametric": evaluate_parametric,
    "synthesize_efros_leung": evaluate_efros_leung, "quilt": evaluate_quilting}
