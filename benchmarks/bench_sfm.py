"""Structure from motion: our incremental pipeline against COLMAP's (pycolmap), on the same rendered images.

One run, one data set: the SfM module's default dataset (the "room" scene on a 120 degree orbit,
12 views at 640 x 480 by default, exact poses and K). The images are quantized to 8 bits and
written as PNG to a temporary folder; both pipelines read those same pixels.

* ours: every step of ``lab.modules.sfm`` with its defaults (SIFT and matching on all pairs, F/E
  verification, the initial pair, incremental registration with PnP, triangulation and bundle
  adjustment, a final bundle adjustment, filtering), the true K given;
* COLMAP: ``pycolmap.extract_features`` (one PINHOLE camera with the true K, converted to COLMAP's
  pixel convention: principal point + 0.5), ``match_exhaustive``, ``incremental_mapping`` with
  the intrinsics held fixed; the largest model is compared.

Both are scored the same way (:func:`lab.modules.sfm.pose_errors`): the registered cameras are
mapped onto the true ones by a similarity (Umeyama on the camera centres), then the mean rotation
error (degrees) and the mean camera-centre error as a fraction of the scene size (the largest
distance between two true camera centres). Mean reprojection error: the mean over all
observations of the pixel distance (COLMAP's ``compute_mean_reprojection_error``; ours from the
``bundle_adjust_all`` step). ``time_ratio`` = our wall time (all steps) / COLMAP's (the three calls).
pycolmap uses every core it finds; ours mostly one (NumPy's BLAS may use more).

    python benchmarks/bench_sfm.py [--views 12] [--width 640] [--height 480] [--scene room]

The last line is ``RESULT {json}`` with ``registered_ours``, ``registered_colmap``, ``views``,
``reproj_px_ours``, ``reproj_px_colmap``, ``rot_err_deg_ours``, ``rot_err_deg_colmap``,
``center_err_rel_ours``, ``center_err_rel_colmap``, ``time_ratio``, ``mean_track_length_ours``,
``mean_track_length_colmap`` (observations per 3D point), ``points_ours``, ``points_colmap`` and
extras (times, maxima).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np


def load(args):
    from lab.core import Image, ImageSet
    from lab.modules.sfm import rendered

    loaded = rendered(scene=args.scene, path="orbit", num_views=args.views, width=args.width,
                      height=args.height, arc_deg=args.arc)
    images = loaded.state["images"]
    quantized = [Image(np.round(np.clip(im.pixels, 0, 1) * 255).astype(np.uint8), name=im.name)
                 for im in images.images]
    state = dict(loaded.state, images=ImageSet(tuple(quantized)))
    return state, loaded.truth


def run_ours(state, truth, seed: int = 0):
    from lab.core import Loaded, Session
    from lab.modules.sfm import PIPELINE, pose_errors

    session = Session(PIPELINE, Loaded(dict(state), {}), dataset="rendered", seed=seed)
    start = time.perf_counter()
    seconds = {}
    for spec in PIPELINE.steps:
        t = time.perf_counter()
        session.run(spec.name)
        seconds[spec.name] = time.perf_counter() - t
    elapsed = time.perf_counter() - start
    s = session.state
    model = s["adjusted_model"]  # the final SparseModel
    reg = np.flatnonzero(model.registered)
    poses = model.poses
    errors = pose_errors(poses[reg, :, :3], poses[reg, :, 3], truth["R"][reg], truth["t"][reg],
                         truth["scene_size"])
    filtered = session.metrics["bundle_adjust_all"]
    return {"registered": len(reg), "reproj_px": filtered["reprojection_mean_px"],
            "track_length": filtered["mean_track_length"], "points": filtered["points_total"],
            "seconds": elapsed, "step_seconds": seconds, **errors}


def run_colmap(state, truth, folder: str):
    import cv2
    import pycolmap

    from lab.modules.sfm import pose_errors

    image_dir = os.path.join(folder, "images")
    os.makedirs(image_dir, exist_ok=True)
    images = state["images"]
    names = []
    for image in images.images:
        pixels = np.round(np.clip(image.pixels, 0, 1) * 255).astype(np.uint8)
        cv2.imwrite(os.path.join(image_dir, image.name), cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR))
        names.append(image.name)
    K = state["K"][0]
    database = os.path.join(folder, "database.db")
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    start = time.perf_counter()
    pycolmap.extract_features(database, image_dir, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, device=pycolmap.Device.cpu)
    t_extract = time.perf_counter()
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    t_match = time.perf_counter()
    models = pycolmap.incremental_mapping(database, image_dir, os.path.join(folder, "sparse"),
                                          options=options)
    elapsed = time.perf_counter() - start
    if not models:
        return {"registered": 0, "reproj_px": float("nan"), "track_length": 0.0, "points": 0,
                "seconds": elapsed, "rotation_error_deg": float("nan"),
                "rotation_error_max_deg": float("nan"), "center_error_rel": float("nan"),
                "center_error_max_rel": float("nan")}
    model = max(models.values(), key=lambda m: m.num_reg_images())
    found: list[int] = []
    R, t = [], []
    for image in model.images.values():
        if not image.has_pose:
            continue
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        matrix = pose.matrix()
        found.append(names.index(image.name))
        R.append(matrix[:, :3])
        t.append(matrix[:, 3])
    index = np.array(found)
    errors = pose_errors(np.array(R), np.array(t), truth["R"][index], truth["t"][index], truth["scene_size"])
    return {"registered": len(index), "reproj_px": float(model.compute_mean_reprojection_error()),
            "track_length": float(model.compute_mean_track_length()), "points": int(model.num_points3D()),
            "seconds": elapsed, "seconds_extract": t_extract - start, "seconds_match": t_match - t_extract,
            "seconds_map": elapsed - (t_match - start), **errors}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--arc", type=float, default=120.0)
    parser.add_argument("--scene", default="room")
    args = parser.parse_args()
    t = time.perf_counter()
    state, truth = load(args)
    print(f"rendered {args.views} views of {args.scene!r} at {args.width}x{args.height} in "
          f"{time.perf_counter() - t:.1f} s")
    with tempfile.TemporaryDirectory() as folder:
        colmap = run_colmap(state, truth, folder)
    print(f"COLMAP: {colmap['registered']}/{args.views} registered in {colmap['seconds']:.1f} s")
    ours = run_ours(state, truth)
    print(f"ours:   {ours['registered']}/{args.views} registered in {ours['seconds']:.1f} s")
    print("  our steps: " + ", ".join(f"{k} {v:.1f} s" for k, v in ours["step_seconds"].items()))
    rows = [("registered images", "registered", "{:d}"),
            ("mean reprojection error (px)", "reproj_px", "{:.3f}"),
            ("mean track length", "track_length", "{:.2f}"), ("points", "points", "{:d}"),
            ("rotation error, mean (deg)", "rotation_error_deg", "{:.4f}"),
            ("rotation error, max (deg)", "rotation_error_max_deg", "{:.4f}"),
            ("centre error, mean (% of scene)", "center_error_rel", "{:.4%}"),
            ("centre error, max (% of scene)", "center_error_max_rel", "{:.4%}"),
            ("wall time (s)", "seconds", "{:.1f}")]
    print(f"tracks: ours {ours['track_length']:.2f} images per point over {ours['points']} points, COLMAP "
          f"{colmap['track_length']:.2f} over {colmap['points']} points")
    print(f"{'':34s} {'ours':>12s} {'COLMAP':>12s} {'ratio':>8s}")
    for label, key, fmt in rows:
        a, b = ours[key], colmap[key]
        ratio = a / b if b else float("nan")
        print(f"{label:34s} {fmt.format(a):>12s} {fmt.format(b):>12s} {ratio:8.2f}")
    result = {
        "registered_ours": ours["registered"], "registered_colmap": colmap["registered"], "views": args.views,
        "reproj_px_ours": ours["reproj_px"], "reproj_px_colmap": colmap["reproj_px"],
        "rot_err_deg_ours": ours["rotation_error_deg"], "rot_err_deg_colmap": colmap["rotation_error_deg"],
        "center_err_rel_ours": ours["center_error_rel"], "center_err_rel_colmap": colmap["center_error_rel"],
        "time_ratio": ours["seconds"] / colmap["seconds"],
        "mean_track_length_ours": ours["track_length"], "mean_track_length_colmap": colmap["track_length"],
        "points_ours": ours["points"], "points_colmap": colmap["points"],
        # extras
        "track_length_ours": ours["track_length"], "track_length_colmap": colmap["track_length"],
        "rot_err_max_deg_ours": ours["rotation_error_max_deg"],
        "rot_err_max_deg_colmap": colmap["rotation_error_max_deg"],
        "center_err_max_rel_ours": ours["center_error_max_rel"],
        "center_err_max_rel_colmap": colmap["center_error_max_rel"],
        "seconds_ours": ours["seconds"], "seconds_colmap": colmap["seconds"],
        "width": args.width, "height": args.height, "scene": args.scene,
    }
    print("RESULT " + json.dumps({k: round(v, 6) if isinstance(v, float) else v for k, v in result.items()}))


if __name__ == "__main__":
    main()
