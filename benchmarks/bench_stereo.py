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

Full resolution (issue 19): two pairs of about 1.4 megapixels written to a folder (``left.png``,
``right.png``, ``disp0.pfm``, no calibration: taken as rectified) and run by the command line,
``vision-lab run stereo --dataset FOLDER --set cost_volume.max_disparity=0 --json``, in a child process
whose peak resident memory (``ru_maxrss``) is read when it ends:

- ``synthetic``: the lab's rendered table scene at 1280 x 1024 with a 0.32 m baseline, true
  disparities 82 to 208 px, every pixel with truth;
- ``moto2x``: scikit-image's motorcycle pair upsampled 2 times (1482 x 1000, bilinear; its truth
  doubled, nearest), disparities 14 to 120 px.

Each runs the default settings with ``max_disparity = 0`` (auto: the range estimated from matched
SIFT features, reported as ``auto_max_disparity``); its volume (over 2**26 costs) is aggregated by
rows (``lab.modules.stereo.lean``). Peak memory is that of the whole process (Python, NumPy, OpenCV,
Numba and the pair included); ``*_base_mb`` is the same process stopped after rectification. Tuned
``cv2.StereoSGBM`` runs on the same 8-bit pair over the same range (``numDisparities`` the auto range
rounded up to 16): modes SGBM, HH (8 paths) and 3-way, block 3, 5 or 7, P1 = 8 * 3 * b^2, P2 =
32 * 3 * b^2, disp12MaxDiff 1, uniquenessRatio 10, speckle 100 / 2; the lowest bad-2 is reported.

Real time (issue 19 item 3): :func:`lab.modules.stereo.block_match_realtime` (winner-take-all 8-bit SAD,
9 x 9 blocks, 32 disparities, running sums) on a sequence of 320 x 240 grey frames (the motorcycle pair
and the synthetic table rig, each resized to 320 x 240, taken in turn), ``--realtime-frames`` frames
after a warm-up, on one thread and on the lab's kernel thread pool (bands of rows), in frames per
second, beside ``cv2.StereoBM_create(numDisparities=32, blockSize=9)`` on the same frames (OpenCV's
threads, and one thread), and the seeds' table: SRI SVS 30 fps, Point Grey Triclops 20 fps, PARTS
FPGA 42 fps.

    python benchmarks/bench_stereo.py [--repeat 7] [--skip-full-resolution] [--realtime-frames 300]

The last line is ``RESULT {json}`` with the keys issue 5 names: sgm_bad2_all, sgbm_bad2_all,
sgm_bad2_pred, sgbm_bad2_pred, sgm_time_ratio (ours / SGBM), census_bad2_pred, stereobm_bad2_pred;
and issue 19's, for the synthetic pair: lean_peak_mb, bad2_lab, bad2_sgbm (holes counted as errors),
auto_max_disparity, true_max_disparity, lean_seconds, sgbm_seconds (and the same with the prefix
``moto2x_`` for the motorcycle pair); and the real-time frames per second, realtime_fps (ours on the
thread pool) and stereobm_realtime_fps (StereoBM, OpenCV's threads). The line before, ``DETAILS {json}``,
adds every method's bad-1/2/4 rates, coverage, end-point error and time, census_time_ratio (ours /
StereoBM), the StereoBM block size chosen, the SGBM setting chosen per pair, the CPU count, and the
one-thread frames per second and the load average of the real-time run.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import timeit
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from lab.core import Image
from lab.modules.stereo import (aggregate_costs, block_match_realtime, cost_volume, disparity_errors,
                                filter_disparity, left_right_check, motorcycle, refine_subpixel,
                                winner_take_all)

MAX_DISPARITY = 63  # 64 disparities, OpenCV's numDisparities = 64

#: The keys of the RESULT line, exactly those issue 5 names (rates as fractions; the ratio is ours / SGBM).
RESULT_KEYS = ("sgm_bad2_all", "sgbm_bad2_all", "sgm_bad2_pred", "sgbm_bad2_pred", "sgm_time_ratio",
               "census_bad2_pred", "stereobm_bad2_pred")
#: Issue 19's keys, per full-resolution pair (the motorcycle's with the prefix moto2x_).
FULL_RESOLUTION_KEYS = ("lean_peak_mb", "bad2_lab", "bad2_sgbm", "auto_max_disparity", "true_max_disparity",
                        "lean_seconds", "sgbm_seconds")
#: Issue 19 item 3's keys: frames per second at 320 x 240 with 32 disparities.
REALTIME_KEYS = ("realtime_fps", "stereobm_realtime_fps")
#: The seeds' real-time stereo table (320 x 240, 32 disparities, SAD block matching), frames per second.
SEED_REALTIME_FPS = {"SRI SVS (Pentium III)": 30.0, "Point Grey Triclops": 20.0, "PARTS FPGA": 42.0}


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


# ----------------------------------------------------------------------------------------------------
# Full resolution (issue 19): folders, the command line in a child process, tuned SGBM
# ----------------------------------------------------------------------------------------------------
def write_pair(directory: Path, rgb_left: np.ndarray, rgb_right: np.ndarray, truth: np.ndarray) -> None:
    """``left.png``, ``right.png`` (8-bit) and ``disp0.pfm`` (float32, inf where unknown) in ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    for name, rgb in (("left", rgb_left), ("right", rgb_right)):
        cv2.imwrite(str(directory / f"{name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(directory / "disp0.pfm"), np.where(truth >= 0, truth, np.inf).astype(np.float32))


def synthetic_pair(directory: Path) -> None:
    from lab.modules.stereo import synthetic

    loaded = synthetic(scene="table", width=1280, height=1024, baseline=0.32)
    left, right = (np.clip(loaded.state[n].pixels * 255.0 + 0.5, 0, 255).astype(np.uint8)
                   for n in ("left_raw", "right_raw"))
    write_pair(directory, left, right, loaded.truth["disparity"])


def motorcycle_2x_pair(directory: Path) -> None:
    from skimage import data

    left, right, disparity = data.stereo_motorcycle()
    size = (2 * left.shape[1], 2 * left.shape[0])
    up = [cv2.resize(image, size, interpolation=cv2.INTER_LINEAR) for image in (left, right)]
    truth = np.where(np.isfinite(disparity), 2.0 * disparity, -1.0).astype(np.float32)
    write_pair(directory, *up, cv2.resize(truth, size, interpolation=cv2.INTER_NEAREST).astype(np.float64))


def run_cli(folder: Path, *extra: str) -> tuple[dict[str, Any], float, float]:
    """``vision-lab run stereo --dataset FOLDER --json`` in a child: (its summary, seconds, peak MB)."""
    code = ("import resource, subprocess, sys, json; r = subprocess.run(sys.argv[1:], capture_output=True, "
            "text=True); print(json.dumps({'rc': r.returncode, 'out': r.stdout, 'err': r.stderr[-3000:], "
            "'peak_kb': resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))")
    command = [sys.executable, "-c", code, sys.executable, "-c", "from lab.cli import app; app()", "run",
               "stereo", "--dataset", str(folder), "--set", "cost_volume.max_disparity=0", "--json", *extra]
    started = time.monotonic()
    wrapper = json.loads(subprocess.run(command, capture_output=True, text=True, check=True).stdout)
    seconds = time.monotonic() - started
    if wrapper["rc"] != 0:
        raise RuntimeError(f"vision-lab run failed:\n{wrapper['err']}")
    return json.loads(wrapper["out"]), seconds, wrapper["peak_kb"] / 1024.0


def tuned_sgbm(bgr_left: np.ndarray, bgr_right: np.ndarray, truth: np.ndarray,
               disparities: int) -> tuple[dict[str, float], float, str]:
    """The lowest bad-2 (holes counted) of SGBM's modes and block sizes: (errors, seconds, setting)."""
    modes = {"SGBM": cv2.STEREO_SGBM_MODE_SGBM, "HH": cv2.STEREO_SGBM_MODE_HH,
             "3WAY": cv2.STEREO_SGBM_MODE_SGBM_3WAY}
    best: tuple[dict[str, float], float, str] | None = None
    for mode_name, mode in modes.items():
        for block in (3, 5, 7):
            matcher = cv2.StereoSGBM.create(minDisparity=0, numDisparities=disparities, blockSize=block,
                                            P1=8 * 3 * block * block, P2=32 * 3 * block * block,
                                            disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                                            speckleRange=2, mode=mode)
            started = time.monotonic()
            disparity = _from_fixed_point(matcher.compute(bgr_left, bgr_right))
            seconds = time.monotonic() - started
            errors = disparity_errors(disparity, truth)
            if best is None or errors["bad2_all"] < best[0]["bad2_all"]:
                best = (errors, seconds, f"{mode_name}, block {block}")
    assert best is not None
    return best


def full_resolution(name: str, make: Any, workdir: Path) -> dict[str, Any]:
    """One full-resolution pair: ours by the command line (auto range, rows) against tuned SGBM."""
    from lab.modules.stereo import read_disparity

    folder = workdir / name
    make(folder)
    truth = read_disparity(str(folder / "disp0.pfm"))
    bgr = [cv2.imread(str(folder / f"{side}.png")) for side in ("left", "right")]
    _, _, base_mb = run_cli(folder, "--until", "rectify_pair")
    result, seconds, peak_mb = run_cli(folder)
    metrics = result["metrics"]
    steps = {step["name"]: step for step in result["steps"]}
    auto = int(metrics["auto_max_disparity"])
    sgbm_errors, sgbm_seconds, setting = tuned_sgbm(*bgr, truth, 16 * -(-(auto + 1) // 16))
    height, width = truth.shape
    print(f"{name}: {width} x {height}, true disparities {truth[truth >= 0].min():.1f} to "
          f"{truth.max():.1f} px, auto range 0..{auto} ({metrics['range_matches']} matched features)")
    print(f"  ours (CLI, rows): bad-2 {100 * metrics['bad2_all']:.2f} % (holes counted), coverage "
          f"{100 * metrics['coverage']:.1f} %, {seconds:.1f} s in all (aggregation "
          f"{steps['aggregate_costs']['seconds']:.1f} s), peak {peak_mb:.0f} MB (after rectification "
          f"{base_mb:.0f} MB)")
    print(f"  cv2.StereoSGBM tuned ({setting}): bad-2 {100 * sgbm_errors['bad2_all']:.2f} %, coverage "
          f"{100 * sgbm_errors['coverage']:.1f} %, {sgbm_seconds:.2f} s")
    return {"lean_peak_mb": round(peak_mb, 1), "base_mb": round(base_mb, 1), "bad2_lab": metrics["bad2_all"],
            "bad2_sgbm": sgbm_errors["bad2_all"], "auto_max_disparity": auto,
            "true_max_disparity": round(float(truth.max()), 2), "lean_seconds": round(seconds, 2),
            "aggregate_seconds": steps["aggregate_costs"]["seconds"], "sgbm_seconds": round(sgbm_seconds, 3),
            "coverage_lab": metrics["coverage"], "coverage_sgbm": sgbm_errors["coverage"],
            "sgbm_setting": setting, "range_matches": metrics["range_matches"]}


# ----------------------------------------------------------------------------------------------------
# Real time (issue 19 item 3): 320 x 240, 32 disparities, frames per second
# ----------------------------------------------------------------------------------------------------
def realtime_frames() -> list[tuple[np.ndarray, np.ndarray]]:
    """The motorcycle pair and the synthetic table rig as 320 x 240 8-bit grey pairs."""
    from lab.modules.stereo import synthetic

    frames = []
    for loaded in (motorcycle(), synthetic(scene="table", width=320, height=240)):
        pair = []
        for name in ("left_raw", "right_raw"):
            gray = np.clip(loaded.state[name].gray() * 255.0 + 0.5, 0, 255).astype(np.uint8)
            pair.append(cv2.resize(gray, (320, 240), interpolation=cv2.INTER_AREA))
        frames.append((pair[0], pair[1]))
    return frames


def frames_per_second(match: Any, frames: list[tuple[np.ndarray, np.ndarray]], count: int) -> float:
    """``count`` frames through ``match(left, right)``, the pairs in turn, after one warm-up frame each."""
    for left, right in frames:
        match(left, right)
    started = time.perf_counter()
    for index in range(count):
        match(*frames[index % len(frames)])
    return count / (time.perf_counter() - started)


def realtime(count: int) -> dict[str, float]:
    frames = realtime_frames()
    matcher = cv2.StereoBM.create(numDisparities=32, blockSize=9)
    threads = cv2.getNumThreads()
    pool = functools.partial(block_match_realtime, max_disparity=31, block=9)
    single = functools.partial(block_match_realtime, max_disparity=31, block=9, parallel=False)
    fps = {"realtime_fps": frames_per_second(pool, frames, count),
           "realtime_fps_1thread": frames_per_second(single, frames, count),
           "stereobm_realtime_fps": frames_per_second(matcher.compute, frames, count)}
    cv2.setNumThreads(1)
    try:
        fps["stereobm_realtime_fps_1thread"] = frames_per_second(matcher.compute, frames, count)
    finally:
        cv2.setNumThreads(threads)
    load = os.getloadavg()[0]
    print(f"real time: 320 x 240, 32 disparities, 9 x 9 SAD, {count} frames (2 pairs in turn), load average "
          f"{load:.1f}")
    print(f"  ours block_match_realtime: {fps['realtime_fps']:.0f} fps (kernel thread pool), "
          f"{fps['realtime_fps_1thread']:.0f} fps (1 thread)")
    print(f"  cv2.StereoBM: {fps['stereobm_realtime_fps']:.0f} fps (OpenCV's {threads} threads), "
          f"{fps['stereobm_realtime_fps_1thread']:.0f} fps (1 thread)")
    seeds = ", ".join(f"{name} {value:.0f} fps" for name, value in SEED_REALTIME_FPS.items())
    print(f"  the seeds' table: {seeds}")
    return {**fps, "realtime_load_average": load}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=7, help="timed runs per method (median reported)")
    parser.add_argument("--skip-full-resolution", action="store_true",
                        help="only the 741 x 500 motorcycle comparison (issue 5)")
    parser.add_argument("--realtime-frames", type=int, default=300,
                        help="frames timed per method at 320 x 240 (issue 19 item 3)")
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
    details.update(realtime(args.realtime_frames))
    keys = list(RESULT_KEYS) + list(REALTIME_KEYS)
    if not args.skip_full_resolution:
        with tempfile.TemporaryDirectory(prefix="bench-stereo-") as workdir:
            for prefix, make in (("", synthetic_pair), ("moto2x_", motorcycle_2x_pair)):
                measured = full_resolution(prefix.rstrip("_") or "synthetic", make, Path(workdir))
                details.update({prefix + k: v for k, v in measured.items()})
                keys += [prefix + k for k in FULL_RESOLUTION_KEYS]
    details = {k: round(v, 6) if isinstance(v, float) else v for k, v in details.items()}
    print("DETAILS " + json.dumps(details))
    print("RESULT " + json.dumps({key: details[key] for key in keys}))


if __name__ == "__main__":
    main()
