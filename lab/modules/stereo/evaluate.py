"""Evaluation against the truth (run after a step; the truth may be empty) and what the viewer inspects.

The bad-pixel metrics of Scharstein and Szeliski (2002), section 5.1 (Middlebury 2014's "bad 2.0"
and "avgerr"), the viewer's error map, and the cost curves of a clicked pixel.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np

from lab.core import Curve, Image, InvalidControl, InvalidValue
from lab.geometry.camera import project
from lab.geometry.rectification import StereoCalibration, rectify_pixels, stereo_rectify
from lab.modules.stereo._checks import check_max_disparity, check_pair, check_window
from lab.modules.stereo.costs import COSTS, Cost
from lab.modules.stereo.lean import RowWinners
from lab.modules.stereo.steps import cost_volume

#: Error thresholds (pixels) of the bad-pixel rates.
BAD_THRESHOLDS: tuple[float, ...] = (1.0, 2.0, 4.0)


def disparity_errors(disparity: np.ndarray, truth: np.ndarray, *,
                     thresholds: tuple[float, ...] = BAD_THRESHOLDS) -> dict[str, float]:
    """Bad-pixel rates, coverage and end-point error of a disparity map against the truth (fractions, pixels).

    Over the pixels with a true disparity (``truth >= 0``): ``bad{t}_all`` counts a hole (-1) or an
    error above ``t`` px as bad; ``bad{t}_pred`` is the same rate over the pixels that have a
    disparity; ``coverage`` is the fraction that has one; ``epe_px`` the mean absolute error over
    them (Scharstein and Szeliski 2002, section 5.1; Middlebury 2014's "bad 2.0" and "avgerr").
    Returns {} when the truth has no valid pixel.
    """
    d = np.asarray(disparity, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if d.shape != t.shape:
        raise InvalidValue("disparity", f"shape {d.shape} differs from the truth's {t.shape}")
    valid = t >= 0
    if not valid.any():
        return {}
    predicted = valid & (d >= 0)
    error = np.abs(d - t)
    count = int(predicted.sum())
    out: dict[str, float] = {}
    for threshold in thresholds:
        bad = error > threshold
        key = f"{threshold:g}".replace(".", "_")
        out[f"bad{key}_all"] = float(np.mean(~predicted[valid] | bad[valid]))
        out[f"bad{key}_pred"] = float(np.mean(bad[predicted])) if count else 1.0
    out["coverage"] = float(count / valid.sum())
    out["epe_px"] = float(np.mean(error[predicted])) if count else 0.0
    return out


def error_map(disparity: np.ndarray, truth: np.ndarray, *, threshold: float = 2.0) -> Image:
    """Where a disparity map is right and wrong, as an Image for the viewer.

    Green: error at most ``threshold`` px; red, brighter with the error: wrong; blue: a hole where
    the truth has a disparity; black: no truth.
    """
    d = np.asarray(disparity, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if d.shape != t.shape:
        raise InvalidValue("disparity", f"shape {d.shape} differs from the truth's {t.shape}")
    valid = t >= 0
    predicted = valid & (d >= 0)
    error = np.abs(d - t)
    rgb = np.zeros((*d.shape, 3), np.float32)
    good = predicted & (error <= threshold)
    bad = predicted & (error > threshold)
    rgb[good] = (0.1, 0.75, 0.2)
    strength = np.clip(0.5 + 0.5 * (error - threshold) / (4.0 * max(threshold, 1e-9)), 0.5, 1.0)
    rgb[bad] = np.stack([strength[bad], 0.1 * np.ones(bad.sum()), 0.1 * np.ones(bad.sum())], axis=1)
    rgb[valid & ~predicted] = (0.15, 0.35, 1.0)
    return Image(rgb, name=f"error map (bad > {threshold:g} px)")


def _truth_disparity(state: dict[str, Any], truth: dict[str, Any]) -> np.ndarray | None:
    reference = truth.get("disparity")
    left = state.get("left")
    if reference is None or not isinstance(left, Image) or np.shape(reference) != (left.height, left.width):
        return None
    return np.asarray(reference, dtype=np.float64)


def evaluate_rectification(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``epipolar_error_px``: mean (and max) vertical distance between the rectified projections of true 3D
    points."""
    points = truth.get("points")
    calibration = state.get("calibration")
    if points is None or not isinstance(calibration, StereoCalibration) or len(points) == 0:
        return {}
    left = state["left"]
    rect = stereo_rectify(calibration.K_left, calibration.dist_left, calibration.K_right,
                          calibration.dist_right, (left.width, left.height), calibration.R, calibration.T)
    points = np.asarray(points, dtype=np.float64)
    in_right = points @ calibration.R.T + calibration.T
    x_l = rectify_pixels(project(points, calibration.K_left, calibration.dist_left), calibration.K_left,
                         calibration.dist_left, rect.R_left, rect.P_left)
    x_r = rectify_pixels(project(in_right, calibration.K_right, calibration.dist_right), calibration.K_right,
                         calibration.dist_right, rect.R_right, rect.P_right)
    dy = np.abs(x_l[:, 1] - x_r[:, 1])
    return {"epipolar_error_px": float(dy.mean()), "epipolar_error_max_px": float(dy.max())}


def evaluate_winner_take_all(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Bad-pixel rates of the raw winner-take-all disparities (every pixel predicted)."""
    reference = _truth_disparity(state, truth)
    return {} if reference is None else disparity_errors(state["disparity_wta"], reference)


def evaluate_left_right(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """``consistent_fraction``; with truth, ``removed_wrong``: the fraction of removed pixels that were wrong
    (bad-2), and ``kept_wrong``: the fraction of kept ones that are."""
    mask = np.asarray(state["consistent"], dtype=bool)
    out = {"consistent_fraction": float(mask.mean())}
    reference = _truth_disparity(state, truth)
    if reference is not None:
        valid = reference >= 0
        wrong = np.abs(np.asarray(state["disparity_wta"], dtype=np.float64) - reference) > 2.0
        removed, kept = valid & ~mask, valid & mask
        out["removed_wrong"] = float(wrong[removed].mean()) if removed.any() else 0.0
        out["kept_wrong"] = float(wrong[kept].mean()) if kept.any() else 0.0
    return out


def evaluate_subpixel(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """End-point error and bad-pixel rates of the refined disparities (every pixel predicted)."""
    reference = _truth_disparity(state, truth)
    return {} if reference is None else disparity_errors(state["disparity_subpixel"], reference)


def evaluate_disparity(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Bad-1/2/4 over all pixels with a truth (holes count as errors) and over predicted pixels, coverage,
    EPE."""
    reference = _truth_disparity(state, truth)
    return {} if reference is None else disparity_errors(state["disparity"], reference)


def evaluate_depth(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """With a true depth: median relative depth error and the fraction of depths within 3 ``u_z`` of the
    truth."""
    reference = truth.get("depth")
    depth = np.asarray(state["depth"])
    if reference is None or np.shape(reference) != depth.shape:
        return {}
    reference = np.asarray(reference, dtype=np.float64)
    both = (depth > 0) & (reference > 0)
    if not both.any():
        return {}
    error = np.abs(depth[both] - reference[both])
    return {"depth_rel_error": float(np.median(error / reference[both])),
            "within_3u": float(np.mean(error <= 3.0 * np.asarray(state["depth_uncertainty"])[both]))}


# ----------------------------------------------------------------------------------------------------
# Inspection: the costs of one pixel
# ----------------------------------------------------------------------------------------------------
def cost_curves(left: Image, right: Image, x: int, y: int, *, costs: tuple[str, ...] = COSTS,
                window: int = 5, max_disparity: int = 64,
                aggregated_cost: np.ndarray | RowWinners | None = None) -> Curve:
    """The cost of left pixel ``(x, y)`` at every disparity, one series per cost (what the viewer plots on a
    click).

    Each cost is computed by :func:`cost_volume` on a crop around the pixel (rows ``y +- r``, columns
    ``x - max_disparity - r .. x + r``, ``r`` the reach of the window and of the census/rank
    transform), so a click costs milliseconds; the values equal those of the full volume.
    ``aggregated_cost`` (the state's volume, optional) adds its curve at the pixel, labelled
    "aggregated" (not for a volume aggregated by rows, which keeps no curves); rank and census are left
    out when ``window`` is 1 (they need neighbours).
    Returns a :class:`Curve` over ``d = 0 .. max_disparity``.
    """
    left, right = check_pair(left, right)
    if not (0 <= int(x) < left.width and 0 <= int(y) < left.height):
        raise InvalidValue("x", f"pixel ({x}, {y}) lies outside the {left.width} x {left.height} image")
    x, y = int(x), int(y)
    window = check_window(window)
    max_disparity = check_max_disparity(max_disparity, left.width)
    reach = 2 * (window // 2) + 1  # a transform (census, rank, local mean) then a window sum
    y0, y1 = max(0, y - reach), min(left.height, y + reach + 1)
    x0, x1 = max(0, x - max_disparity - reach), min(left.width, x + reach + 1)
    crop_l = Image(left.pixels[y0:y1, x0:x1])
    crop_r = Image(right.pixels[y0:y1, x0:x1])
    disparities = np.arange(max_disparity + 1, dtype=np.float64)
    series, labels = [], []
    for name in costs:
        if name not in COSTS:
            raise InvalidControl("costs", f"unknown cost {name!r}; costs are {list(COSTS)}")
        if window < 3 and name in ("rank", "census"):
            continue  # these compare a pixel with its neighbours: a 1 x 1 window has none
        usable = min(max_disparity, crop_l.width - 1)
        volume = cost_volume(crop_l, crop_r, cost=cast(Cost, name), window=window, max_disparity=usable)
        if not isinstance(volume, np.ndarray):  # a crop's volume is small enough to be kept whole
            raise InvalidValue("max_disparity", f"the volume of a {crop_l.width} x {crop_l.height} crop was "
                                                "not kept whole")
        curve = np.full(max_disparity + 1, volume[y - y0, x - x0, -1], dtype=np.float64)
        curve[:usable + 1] = volume[y - y0, x - x0]
        series.append(curve)
        labels.append(name)
    if aggregated_cost is not None and not isinstance(aggregated_cost, RowWinners):  # rows keep no curves
        volume = np.asarray(aggregated_cost)
        if volume.ndim != 3 or volume.shape[:2] != (left.height, left.width):
            raise InvalidValue("aggregated_cost", f"expected ({left.height}, {left.width}, D), got "
                                                  f"{volume.shape}")
        curve = np.full(max_disparity + 1, np.nan)
        count = min(volume.shape[2], max_disparity + 1)
        curve[:count] = volume[y, x, :count]
        curve[count:] = curve[count - 1]
        series.append(curve)
        labels.append("aggregated")
    return Curve(disparities, np.array(series), kind="line", title=f"matching costs at ({x}, {y})",
                 xlabel="disparity (px)", ylabel="cost", labels=tuple(labels))


def volume_curve(volume: np.ndarray, x: int, y: int, *, label: str = "cost") -> Curve:
    """One pixel's column of a cost volume as a :class:`Curve` over the disparities."""
    volume = np.asarray(volume)
    if volume.ndim != 3:
        raise InvalidValue("volume", f"a cost volume is (H, W, D), got shape {volume.shape}")
    if not (0 <= int(x) < volume.shape[1] and 0 <= int(y) < volume.shape[0]):
        raise InvalidValue("x", f"pixel ({x}, {y}) lies outside the {volume.shape[1]} x {volume.shape[0]} "
                                "volume")
    return Curve(np.arange(volume.shape[2], dtype=np.float64), volume[int(y), int(x)].astype(np.float64),
                 kind="line", title=f"{label} at ({x}, {y})", xlabel="disparity (px)", ylabel=label,
                 labels=(label,))
