"""Comparisons of rendered held-out views with the truth: PSNR, SSIM (scikit-image) and depth error.

The pipeline runs :func:`evaluate_held_out` after ``render_held_out``; it returns ``{}`` when the truth
has no held-out images (a user's own data without a test split), and leaves the depth error out when
the truth has no depths (photos, NeRF-synthetic folders).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lab.core import ImageSet, InvalidValue
from lab.core.pipeline import Evaluation


def psnr_from_mse(mse: float) -> float:
    """Peak signal-to-noise ratio of images in [0, 1]: ``-10 log10(MSE)`` dB (inf for a perfect fit)."""
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)


def image_psnr(rendered: np.ndarray, truth: np.ndarray) -> float:
    """:func:`psnr_from_mse` of two images in [0, 1]."""
    difference = np.asarray(rendered, np.float64) - np.asarray(truth, np.float64)
    return psnr_from_mse(float(np.mean(difference ** 2)))


def image_ssim(rendered: np.ndarray, truth: np.ndarray) -> float:
    """Structural similarity (Wang et al. 2004) of two ``(H, W, 3)`` images in [0, 1]:
    ``skimage.metrics.structural_similarity`` with its default 7 x 7 window, per channel, averaged."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(np.asarray(rendered, np.float64), np.asarray(truth, np.float64),
                                       channel_axis=-1, data_range=1.0))


def depth_error(rendered: np.ndarray, truth: np.ndarray) -> float:
    """Mean absolute depth error ``(H, W)`` over the pixels whose true depth is finite (that see a
    surface); NaN when none does."""
    seen = np.isfinite(truth)
    if not seen.any():
        return float("nan")
    return float(np.mean(np.abs(np.asarray(rendered, np.float64)[seen] - truth[seen])))


def evaluate_held_out(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Mean PSNR and SSIM of ``test_renders`` against the truth's ``test_images``, and the mean absolute
    error of ``test_depth`` against ``test_depths`` where the truth has them."""
    if "test_images" not in truth or "test_renders" not in state:
        return {}
    renders: ImageSet = state["test_renders"]
    images = np.asarray(truth["test_images"])
    if len(renders) != len(images):
        raise InvalidValue("test_renders", f"{len(renders)} renders for {len(images)} held-out images")
    pairs = [(r.pixels, im) for r, im in zip(renders.images, images, strict=True)]
    metrics = {"psnr": float(np.mean([image_psnr(r, im) for r, im in pairs])),
               "ssim": float(np.mean([image_ssim(r, im) for r, im in pairs]))}
    if "test_depths" in truth and "test_depth" in state:
        errors = [depth_error(d, t) for d, t in zip(state["test_depth"], truth["test_depths"], strict=True)]
        metrics["depth_mae"] = float(np.nanmean(errors))
    return metrics


EVALUATIONS: dict[str, Evaluation] = {"render_held_out": evaluate_held_out}

__all__ = ["EVALUATIONS", "depth_error", "evaluate_held_out", "image_psnr", "image_ssim", "psnr_from_mse"]
