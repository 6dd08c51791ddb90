"""Stereo: our block matching and semi-global matching against cv2.StereoBM and cv2.StereoSGBM.

One run on the Middlebury 2014 motorcycle pair shipped with scikit-image (741 x 500, disparities
7 to 60 px, about 7 % of the pixels without truth). All methods search the same 64 disparities
(0 to 63). Rows:

- ours SGM: the stereo module's steps with their defaults (census over 5 x 5 windows, SGM with
  8 paths, P1 = 0.05, P2 = 1.0, left-right check, parabola refinement, 3 x 3 median, uniqueness
  0.05, peak removal 100 px / 2 px, no hole filling);
- cv2.StereoSGBM tuned as asked: 3-way mode, block size 3, P1 = 8 * 3 * b^2, P2 = 32 * 3 * b^2,
  disp12MaxDiff 1, uniquenessRatio 10, speckleWindowSize 100, speckleRange 2 (colour input);
- ours census BM: the same steps with ``aggregate_costs(method="none")`` (block matching);
- cv2.StereoBM: OpenCV's defaults (prefilter, texture threshold 10, uniqueness 15), block size
  chosen from 5 to 21 for the lowest bad-2 with holes counted (gray input); and, for context, a
  strict StereoBM (block 5, uniqueness 30, speckle 100 / 2, disp12MaxDiff 1) that shows how far the
  rate on predicted pixels alone drops when a method leaves more holes.

Metrics over the pixels with a true disparity (rates as fractions): bad-2 counting holes as
errors, bad-2 over predicted pixels only, coverage, end-point error. Times are medians of
``--repeat`` runs after a warm-up (which compiles the Numba kernels), from images in memory to
the final disparity map; our kernels and OpenCV both use every CPU of the process.

    python benchmarks/bench_stereo.py [--repeat 7]

The last line is ``RESULT {json}`` with exactly the keys issue 5 names: sgm_bad2_all, sgbm_bad2_all,
sgm_bad2_pred, sgbm_bad2_pred, sgm_time_ratio (ours / SGBM), census_bad2_pred, stereobm_bad2_pred.
The line before, ``DETAILS {json}``, adds every method's bad-1/2/4 rates, coverage, end-point error
and time, census_time_ratio (ours / StereoBM), the StereoBM block size chosen and the CPU count.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import timeit
from typing import Literal

import cv2
import numpy as np

from lab.core import Image
from lab.modules.stereo import (aggregate_costs, cost_volume, disparity_errors, filter_disparity,
                                left_right_check, motorcycle, refine_subpixel, winner_take_all)

MAX_DISPARITY = 63  # 64 disparities, OpenCV's numDisparities = 64

#: The keys of the RESULT line, exactly those issue 5 names (rates as fractions; the ratio is ours / SGBM).
RESULT_KEYS = ("sgm_bad2_all", "sgbm_bad2_all", "sgm_bad2_pred", "sgbm_bad2_pred", "sgm_time_ratio",
               "census_bad2_pred", "stereobm_bad2_pred")


def ours(left: Image, right: Image, *, method: Literal["sgm", "none"]) -> np.ndarray:
    """The module's steps with their defaults, from the rectified pair to the filtered disparity."""
    volume = cost_volume(left, right, max_disparity=MAX_DISPARITY)
    aggregated = aggregate_costs(volume, method=method)
    winners = winner_take_all(aggregated)
    consistent = left_right_check(aggregated, winners)
    refined = refine_subpixel(aggregated, winners)
    return filter_disparity(refined, consistent, aggregated).disparity


def sgbm(bgr_left: np.ndarray, bgr_right: np.ndarray) -> np.ndarray:
    block = 3
    matcher = cv2.StereoSGBM.create(minDisparity=0, numDisparities=MAX_DISPARITY + 1, blockSize=block,
                                    P1=8 * 3 * block * block, P2=32 * 3 * block * block, disp12MaxDiff=1,
                                    uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                    mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    return _from_fixed_point(matcher.compute(bgr_left, bgr_right))


def stereobm(gray_left: np.ndarray, gray_right: np.ndarray, *, block: int,
             strict: bool = False) -> np.ndarray:
    matcher = cv2.StereoBM.create(numDisparities=MAX_DISPARITY + 1, blockSize=block)
    if strict:
        matcher.setUniquenessRatio(30)
        matcher.setSpeckleWindowSize(100)
        matcher.setSpeckleRange(2)
        matcher.setDisp12MaxDiff(1)
    return _from_fixed_point(matcher.compute(gray_left, gray_right))


def _from_fixed_point(disparity16: np.ndarray) -> np.ndarray:
    """OpenCV's disparities come in 1/16 px, negative where invalid: to pixels with -1 holes."""
    disparity = disparity16.astype(np.float64) / 16.0
    return np.where(disparity >= 0, disparity, -1.0)


def median_seconds(func, repeat: int) -> float:
    return statistics.median(timeit.repeat(func, number=1, repeat=repeat))


def row(name: str, errors: dict[str, float], seconds: float) -> str:
    return (f"{name:<34s} {100 * errors['bad2_all']:9.2f} {100 * errors['bad2_pred']:10.2f} "
            f"{100 * errors['coverage']:9.1f} {errors['epe_px']:7.3f} {1000 * seconds:9.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=7, help="timed runs per method (median reported)")
    args = parser.parse_args()

    loaded = motorcycle()
    left, right = loaded.state["left_raw"], loaded.state["right_raw"]
    truth = loaded.truth["disparity"]
    rgb8 = [np.clip(image.pixels * 255.0 + 0.5, 0, 255).astype(np.uint8) for image in (left, right)]
    bgr = [cv2.cvtColor(p, cv2.COLOR_RGB2BGR) for p in rgb8]
    gray = [cv2.cvtColor(p, cv2.COLOR_RGB2GRAY) for p in rgb8]

    ours(left, right, method="sgm")  # warm-up: compiles (or loads) the Numba kernels
    ours(left, right, method="none")
    results = {}
    results["sgm"] = (disparity_errors(ours(left, right, method="sgm"), truth),
                      median_seconds(lambda: ours(left, right, method="sgm"), args.repeat))
    results["sgbm"] = (disparity_errors(sgbm(*bgr), truth), median_seconds(lambda: sgbm(*bgr), args.repeat))
    results["census"] = (disparity_errors(ours(left, right, method="none"), truth),
                         median_seconds(lambda: ours(left, right, method="none"), args.repeat))
    blocks = {block: disparity_errors(stereobm(*gray, block=block), truth) for block in range(5, 22, 2)}
    best_block = min(blocks, key=lambda b: blocks[b]["bad2_all"])
    results["stereobm"] = (blocks[best_block],
                           median_seconds(lambda: stereobm(*gray, block=best_block), args.repeat))
    results["stereobm_strict"] = (disparity_errors(stereobm(*gray, block=5, strict=True), truth),
                                  median_seconds(lambda: stereobm(*gray, block=5, strict=True), args.repeat))

    cpus = len(os.sched_getaffinity(0))
    print(f"motorcycle {left.width} x {left.height}, disparities 0..{MAX_DISPARITY}, {cpus} CPU(s); "
          "rates in % of the pixels with a true disparity")
    print(f"{'method':<34s} {'bad2 all':>9s} {'bad2 pred':>10s} {'coverage':>9s} {'EPE px':>7s} "
          f"{'time ms':>9s}")
    names = {"sgm": "ours SGM (census 5x5, 8 paths)", "sgbm": "cv2.StereoSGBM (3-way, block 3)",
             "census": "ours census BM (5x5)", "stereobm": f"cv2.StereoBM (block {best_block})",
             "stereobm_strict": "cv2.StereoBM strict (block 5)"}
    for key, name in names.items():
        print(row(name, *results[key]))
    sgm_ratio = results["sgm"][1] / results["sgbm"][1]
    census_ratio = results["census"][1] / results["stereobm"][1]
    print(f"time ratio ours / OpenCV: SGM {sgm_ratio:.2f}, block matching {census_ratio:.2f}")

    details = {}
    for key in ("sgm", "sgbm", "census", "stereobm", "stereobm_strict"):
        errors, seconds = results[key]
        details.update({f"{key}_bad2_all": errors["bad2_all"], f"{key}_bad2_pred": errors["bad2_pred"],
                        f"{key}_bad1_all": errors["bad1_all"], f"{key}_bad4_all": errors["bad4_all"],
                        f"{key}_coverage": errors["coverage"], f"{key}_epe_px": errors["epe_px"],
                        f"{key}_time_s": seconds})
    details.update({"sgm_time_ratio": sgm_ratio, "census_time_ratio": census_ratio,
                    "stereobm_block": best_block, "cpus": cpus})
    details = {k: round(v, 6) if isinstance(v, float) else v for k, v in details.items()}
    print("DETAILS " + json.dumps(details))
    print("RESULT " + json.dumps({key: details[key] for key in RESULT_KEYS}))


if __name__ == "__main__":
    main()
