"""Calibration: our Zhang pipeline against cv2.calibrateCamera on the same detected corners.

Two data sets, in one run: OpenCV's 13 sample photos (``../shared/data/opencv-samples/left*.jpg``)
and the default synthetic set (15 views, 0.2 px corner noise, exact truth). For each, the corners
are detected once (our ``detect_corners``); then "ours" is the whole calibration from those corners
(homographies, closed-form intrinsics and poses, linear distortion, Levenberg-Marquardt) and
"OpenCV" is ``cv2.calibrateCamera`` with default flags on the same corners. Each is timed
``--repeat`` times and the median is reported; a last row compares the sub-pixel refinement with
``cv2.cornerSubPix``.

    python benchmarks/bench_calibration.py [--repeat 15]

The last line is ``RESULT {json}`` with rms_ours, rms_opencv, fx_rel_diff and time_ratio
(ours / OpenCV) for the real photos, and the same keys prefixed ``synthetic_``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from lab.core import Points2D, open_session
from lab.modules.calibration import (PIPELINE, estimate_distortion, estimate_extrinsics,
                                     estimate_homographies, estimate_intrinsics, refine_calibration,
                                     refine_corners)

SAMPLES = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "opencv-samples"


def calibrate_ours(corners: Points2D, board_points: np.ndarray):
    """The whole calibration from detected corners, as the pipeline runs it."""
    H = estimate_homographies(corners, board_points)
    K_init = estimate_intrinsics(H)
    poses = estimate_extrinsics(H, K_init)
    dist_init = estimate_distortion(corners, board_points, K_init, poses.R_init, poses.t_init)
    generator = refine_calibration(corners, board_points, K_init, dist_init, poses.R_init, poses.t_init)
    try:
        while True:
            next(generator)
    except StopIteration as stop:
        return stop.value


def calibrate_opencv(corners: Points2D, board_points: np.ndarray, size: tuple[int, int]):
    views = np.unique(corners.view)
    object_points = [board_points[corners.ids[corners.view == v]].astype(np.float32) for v in views]
    image_points = [corners.xy[corners.view == v].astype(np.float32) for v in views]
    return cv2.calibrateCamera(object_points, image_points, size, None, None)


def median_seconds(func, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def compare(name: str, session, repeat: int) -> dict[str, float]:
    session.run("detect_corners")
    corners, board_points = session.state["corners"], session.state["board_points"]
    image = session.state["images"][0]
    size = (image.width, image.height)
    ours = calibrate_ours(corners, board_points)
    rms_cv, K_cv, dist_cv, _, _ = calibrate_opencv(corners, board_points, size)
    t_ours = median_seconds(lambda: calibrate_ours(corners, board_points), repeat)
    t_cv = median_seconds(lambda: calibrate_opencv(corners, board_points, size), repeat)
    row = {"rms_ours": ours.rms_px, "rms_opencv": float(rms_cv), "fx_ours": ours.fx,
           "fx_opencv": float(K_cv[0, 0]), "fx_rel_diff": abs(ours.fx - K_cv[0, 0]) / K_cv[0, 0],
           "time_ours_s": t_ours, "time_opencv_s": t_cv, "time_ratio": t_ours / t_cv,
           "iterations": ours.iterations, "views": len(np.unique(corners.view))}
    truth = session.truth
    if "K" in truth:
        K_true = truth["K"]
        row["fx_error_ours"] = abs(ours.fx - K_true[0, 0]) / K_true[0, 0]
        row["fx_error_opencv"] = abs(K_cv[0, 0] - K_true[0, 0]) / K_true[0, 0]
        row["k1_error_ours"] = abs(ours.k1 - truth["dist"][0])
        row["k1_error_opencv"] = abs(dist_cv.ravel()[0] - truth["dist"][0])
    print(f"{name:<10} {len(np.unique(corners.view)):>5} {ours.rms_px:>10.6f} {rms_cv:>10.6f} "
          f"{ours.fx:>10.3f} {K_cv[0, 0]:>10.3f} {1000 * t_ours:>9.2f} {1000 * t_cv:>9.2f} "
          f"{t_ours / t_cv:>6.2f}")
    return row


def compare_subpixel(session, repeat: int) -> dict[str, float]:
    images = session.state["images"]
    grays, starts = [], []
    for image in images.images:
        gray = image.gray()
        found, xy = cv2.findChessboardCorners(np.clip(gray * 255 + 0.5, 0, 255).astype(np.uint8), (9, 6))
        if found:
            grays.append(gray)
            starts.append(xy.reshape(-1, 2))
    stack, start = np.stack(grays), np.concatenate(starts)
    view = np.repeat(np.arange(len(grays)), 54)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)

    def opencv():
        refined = [cv2.cornerSubPix(g, s.reshape(-1, 1, 2).copy(), (5, 5), (-1, -1), criteria)
                   for g, s in zip(grays, starts, strict=True)]
        return np.concatenate(refined).reshape(-1, 2)

    difference = np.abs(refine_corners(stack, start, view, window=5) - opencv()).max()
    t_ours = median_seconds(lambda: refine_corners(stack, start, view, window=5), repeat)
    t_cv = median_seconds(opencv, repeat)
    gap = "max |ours - cv2.cornerSubPix| = " + f"{difference:.2e} px"
    print(f"{'subpixel':<10} {len(grays):>5} {gap:>43} "
          f"{1000 * t_ours:>9.2f} {1000 * t_cv:>9.2f} {t_ours / t_cv:>6.2f}")
    return {"subpixel_max_diff_px": float(difference), "subpixel_time_ratio": t_ours / t_cv}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=15, help="timings per method (the median is reported)")
    args = parser.parse_args()
    print(f"{'data':<10} {'views':>5} {'rms ours':>10} {'rms cv':>10} {'fx ours':>10} {'fx cv':>10} "
          f"{'ours ms':>9} {'cv ms':>9} {'ratio':>6}")
    real = open_session(PIPELINE, "folder", {"path": str(SAMPLES), "pattern": "left*.jpg"})
    result = compare("real", real, args.repeat)
    synthetic = open_session(PIPELINE, "synthetic", seed=0)
    result.update({f"synthetic_{k}": v for k, v in compare("synthetic", synthetic, args.repeat).items()})
    result.update(compare_subpixel(real, args.repeat))
    rounded = {k: (round(v, 8) if isinstance(v, float) else v) for k, v in result.items()}
    print("RESULT " + json.dumps(rounded))


if __name__ == "__main__":
    main()
