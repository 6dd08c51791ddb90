"""Synthetic scenes: time to render a 640 x 480 view of each named scene, and SIFT features per view.

For each scene in ``SCENE_NAMES`` the scene is built once (timed separately: it is cached), then
``--views`` cameras on a 40 degree arc of its default orbit (starting at its home viewpoint) are
rendered at 640 x 480 with ``--supersample`` (default 2), each ``--repeat`` times; the table shows
the median time per view, the share of pixels that see a surface and the median number of SIFT
keypoints (``cv2.SIFT_create().detect``) per view.

    python benchmarks/bench_render.py [--views 4] [--repeat 3] [--supersample 2]

The last line is ``RESULT {json}`` with ``seconds_per_view_640x480`` (median over every render of
every scene), ``sift_features_median`` (median over every view), and per-scene entries.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import cv2
import numpy as np

from lab.data.scenes import SCENE_NAMES, named_scene, orbit_cameras, render


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--supersample", type=int, default=2)
    args = parser.parse_args()

    sift = cv2.SIFT_create()
    all_times: list[float] = []
    all_features: list[int] = []
    per_scene: dict[str, dict[str, float]] = {}
    print(f"{'scene':<8} {'build s':>8} {'s/view':>8} {'min s':>7} {'mask %':>7} {'SIFT':>6}")
    for name in SCENE_NAMES:
        start = time.perf_counter()
        scene = named_scene(name)
        build = time.perf_counter() - start
        cameras = orbit_cameras(scene, num_views=args.views, arc_deg=40.0, width=640, height=480)
        times, features, coverage = [], [], []
        for index in range(len(cameras)):
            for _ in range(args.repeat):
                start = time.perf_counter()
                view = render(scene, cameras, index, supersample=args.supersample)
                times.append(time.perf_counter() - start)
            gray = np.clip(view.image.gray() * 255.0 + 0.5, 0, 255).astype(np.uint8)
            features.append(len(sift.detect(gray, None)))
            coverage.append(float(view.mask.mean()))
        median = statistics.median(times)
        per_scene[name] = {"build_seconds": round(build, 3), "seconds_per_view": round(median, 4),
                           "sift_features_median": statistics.median(features),
                           "mask_fraction": round(statistics.mean(coverage), 3)}
        print(f"{name:<8} {build:>8.2f} {median:>8.3f} {min(times):>7.3f} {100 * statistics.mean(coverage):>7.1f} "
              f"{statistics.median(features):>6.0f}")
        all_times += times
        all_features += features
    result = {"seconds_per_view_640x480": round(statistics.median(all_times), 4),
              "sift_features_median": statistics.median(all_features), "supersample": args.supersample,
              "views_per_scene": args.views, "repeat": args.repeat, "scenes": per_scene}
    print(f"all      {'':>8} {result['seconds_per_view_640x480']:>8.3f} {min(all_times):>7.3f} {'':>7} "
          f"{result['sift_features_median']:>6.0f}")
    print("RESULT " + json.dumps(result))


if __name__ == "__main__":
    main()
