"""Photos -> SfM -> NeRF (issue 17, done-when 3) and splatting from SfM's points (issue 18, done-when 4).

Protocol: a synthetic object (``--object``: the NeRF module's ``untuned`` scene or its ``object`` one) is
rendered in the NeRF-synthetic layout (``write_nerf_synthetic``: ``--size`` px, ``--train-views`` training
and ``--test-views`` held-out cameras on the upper hemisphere); the SfM module's pipeline runs on the
training images (8-bit, with their true K) through its own steps and exports its reconstruction as a
COLMAP text model (``PIPELINE.export("colmap")``); the NeRF dataset ``sfm_reconstruction`` reads it back,
the true held-out cameras brought into the SfM frame by the Umeyama similarity of the recovered training
cameras onto the true ones, the bounds from the SfM points. NeRF's grid variant (bench_nerf's ``fast``
configuration) then trains at the same budget on the SfM poses and on the true poses of the same
registered images (the true run's bounds: the same points box, aligned into the true frame, so that only
the poses differ), both read at ``--downscale`` (800 px / 8 = 100 px), and each is evaluated on the
held-out views. With ``--splatting``, splatting (``initialize_gaussians`` + ``train_splats`` at the same
budget, bench_splatting's controls) trains on the true poses of the registered views once from the SfM
points (carried into the true frame by the alignment) and once from as many true surface points
(``surface_points`` of the exact depths of the true training cameras), so that only the start differs;
and once more the whole chain, SfM's points on SfM's poses in the SfM frame.

Keys of ``RESULT {json}``: ``psnr_true_poses``, ``psnr_sfm_poses``, ``psnr_sfm_poses_minus_true`` (and
``ssim_*``), ``registered`` (of ``train_views``), ``sfm_points``, ``sfm_rotation_error_deg`` and
``sfm_center_error_rel`` (SfM's own evaluation after alignment), ``train_center_error`` (RMS centre error
after alignment, scene units), ``sfm_cpu_seconds``; with ``--splatting`` ``psnr_splat_true_points``,
``psnr_splat_sfm_points`` (both on the true poses), ``psnr_splat_sfm_minus_true``, ``psnr_splat_sfm_chain``
(SfM points and poses); ``budget``, ``clock``, ``torch_threads``,
``load_average_start`` and ``load_average`` (the 1-minute load when the run ended).

    python3 benchmarks/bench_nerf_sfm.py --budget 30 --threads 1 --cpu-clock --splatting
    python3 benchmarks/bench_nerf_sfm.py --budget 30 --threads 1 --cpu-clock --splatting --object object

Measured 2026-12-02 on the 2 shared cores (30 CPU-seconds a run, one torch thread, 800 px renders, NeRF
and splatting at 100 px, 8 held-out views). ``untuned`` (load 2.6-5.9): SfM registered 86 of 100 views,
3251 points, 0.20 deg rotation error, 379 s CPU; NeRF 28.93 dB on the true poses, 28.25 dB on SfM's
(-0.67 dB); splatting 32.29 dB from true points, 32.23 dB from SfM's (-0.06 dB), 31.79 dB for the whole
chain. ``object`` (load 2.5-5.0): 26 of 100 views registered (its textures are smooth), 447 points; NeRF
21.37 vs 20.85 dB (-0.52 dB); splatting 28.07 dB from true points vs 25.09 dB from the 447 SfM points
(-2.98 dB: too few points, all on the textured faces, to start from within 1 400 iterations).

Measured 2026-12-03 after held-out pixels became area means (4eea86d; random points fill the SfM start up to
``points``), ``untuned``, 30 CPU-s, load 1.1-4.1: 86 of 100 registered, 3251 points; NeRF 31.55 dB true
poses vs 31.28 SfM poses (-0.27 dB); splatting 32.25 dB from true points vs 32.08 from SfM's (-0.17 dB), the
whole chain 31.69 dB. ``object`` at ``--budget 120``: splatting 28.53 vs 28.21 (-0.32 dB).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import types
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from lab.core import Cameras, Image, ImageSet, Loaded, Session
from lab.geometry.alignment import apply_similarity
from lab.modules.nerf.datasets import (nerf_synthetic, object_scene, untuned_scene,
                                      write_nerf_synthetic)
from lab.modules.nerf.sfm_dataset import bounds_from_points, sfm_reconstruction


def run_sfm(folder: str, views: int, out: str) -> dict:
    """The SfM pipeline on the training images of ``folder`` (their true K), exported as COLMAP text to
    ``out``; returns its numbers."""
    from lab.modules.sfm import PIPELINE, pose_errors, scene_extent

    loaded = nerf_synthetic(path=folder, downscale=1, train_views=views, test_views=1)
    cameras = loaded.state["cameras"]
    images = ImageSet(tuple(Image(np.round(np.clip(im.pixels, 0, 1) * 255).astype(np.uint8),
                                  name=f"r_{i}.png") for i, im in enumerate(loaded.state["images"].images)))
    state = {"images": images, "K": cameras.K.copy()}
    session = Session(PIPELINE, Loaded(state, {}), dataset="photos", seed=0)
    cpu = time.process_time()
    for spec in PIPELINE.steps:
        session.run(spec.name)
    cpu = time.process_time() - cpu
    PIPELINE.export("colmap").write(session.state, session.metrics, Path(out))
    model = session.state["adjusted_model"]
    reg = np.flatnonzero(model.registered)
    errors = pose_errors(model.poses[reg, :, :3], model.poses[reg, :, 3], cameras.R[reg], cameras.t[reg],
                         scene_extent(cameras.centers))
    return {"registered": len(reg), "sfm_points": len(model.points), "sfm_cpu_seconds": cpu,
            "sfm_rotation_error_deg": errors["rotation_error_deg"],
            "sfm_center_error_rel": errors["center_error_rel"]}


def true_pose_dataset(folder: str, sfm: Loaded, *, views: int, test_views: int, downscale: int) -> Loaded:
    """The same registered training images with their true cameras, the same held-out views, bounds from
    the SfM points carried into the true frame by the dataset's alignment."""
    full = nerf_synthetic(path=folder, downscale=downscale, train_views=views, test_views=test_views)
    names = [f"r_{i}.png" for i in range(views)]
    pick = np.array([names.index(name) for name in sfm.state["images"].names])
    train: Cameras = full.state["cameras"]
    cameras = Cameras(train.K[pick], train.R[pick], train.t[pick], train.width, train.height, image="images")
    images = ImageSet(tuple(full.state["images"].images[i] for i in pick))
    points = apply_similarity(sfm.truth["alignment"], sfm.state["sfm_points"].xyz)
    bounds = bounds_from_points(points, cameras.R, cameras.t)
    cloud = replace(sfm.state["sfm_points"], xyz=points)
    state = {**full.state, "images": images, "cameras": cameras, "bounds": bounds, "sfm_points": cloud}
    return Loaded(state, full.truth, f"true poses of the {len(pick)} registered views")


def nerf_run(loaded: Loaded, budget: float) -> dict:
    """bench_nerf's ``fast`` configuration for ``budget`` seconds through the NeRF pipeline's steps."""
    from bench_nerf import CONFIGS

    from lab.modules.nerf import PIPELINE

    session = Session(PIPELINE, loaded, dataset="sfm_reconstruction", seed=0)
    session.run("generate_rays")
    session.run("encode_positions")
    train = session.run("train_nerf", {**CONFIGS["fast"], "budget_seconds": budget, "iterations": 1_000_000,
                                       "preview_every": 100_000})
    held = session.run("render_held_out")
    return {"psnr": held.metrics["psnr"], "ssim": held.metrics["ssim"],
            "iterations": train.metrics["iterations"]}


def splat_run(loaded: Loaded, budget: float) -> dict:
    """Splatting from ``loaded``'s ``sfm_points`` for ``budget`` seconds (bench_splatting's controls)."""
    from bench_splatting import SPLAT_INIT, SPLAT_TRAIN

    from lab.modules.splatting import PIPELINE

    session = Session(PIPELINE, loaded, dataset="object_with_points", seed=0)
    session.run("initialize_gaussians", {**SPLAT_INIT, "source": "points"})
    train = session.run("train_splats", {**SPLAT_TRAIN, "budget_seconds": budget})
    held = session.run("render_held_out")
    return {"psnr": held.metrics["psnr"], "ssim": held.metrics["ssim"],
            "iterations": train.metrics["iterations"]}


def true_surface_points(scene, loaded: Loaded, count: int) -> Loaded:
    """``loaded`` with ``sfm_points`` replaced by ``count`` true surface points seen by its training
    cameras (exact depths of the shared renderer at their pixel centres, drawn as splatting's dataset
    does)."""
    from lab.data.scenes import render
    from lab.modules.splatting.datasets import surface_points

    cameras: Cameras = loaded.state["cameras"]
    depths = np.stack([render(scene, cameras, i, supersample=1).depth for i in range(len(cameras))])
    images = np.stack([im.pixels for im in loaded.state["images"].images])
    cloud = surface_points(cameras, depths, images, count, np.random.default_rng(0))
    return Loaded({**loaded.state, "sfm_points": cloud}, loaded.truth, loaded.description)


def report(tag: str, numbers: dict, result: dict) -> None:
    for key, value in numbers.items():
        result[f"{key}_{tag}"] = value
    print(f"{tag}: held-out PSNR {numbers['psnr']:.2f} dB, SSIM {numbers['ssim']:.3f}, "
          f"{numbers['iterations']} iterations (load {os.getloadavg()[0]:.1f})", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--object", choices=("object", "untuned"), default="untuned",
                        help="the scene: untuned (wood, a photograph: SfM registers 86 of 100 views) or "
                             "object (smooth noise and flat shapes: 26 of 100)")
    parser.add_argument("--size", type=int, default=800, help="rendered image side (SfM runs at this size)")
    parser.add_argument("--downscale", type=int, default=8,
                        help="NeRF reads the images shrunk this many times")
    parser.add_argument("--train-views", type=int, default=100)
    parser.add_argument("--test-views", type=int, default=8)
    parser.add_argument("--budget", type=float, default=30.0, help="training seconds of each run")
    parser.add_argument("--splatting", action="store_true", help="also splatting from SfM vs true points")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (the machine is shared)")
    parser.add_argument("--cpu-clock", action="store_true",
                        help="budgets in this process's CPU seconds (the training loops' clock replaced)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.cpu_clock:
        from lab.modules.nerf import grid
        from lab.modules.nerf import training as nerf_training
        from lab.modules.splatting import training as splat_training

        for module in (grid, nerf_training, splat_training):
            module.time = types.SimpleNamespace(perf_counter=time.process_time)  # type: ignore[attr-defined]
    result: dict = {"object": args.object, "budget": args.budget, "torch_threads": args.threads,
                    "clock": "cpu" if args.cpu_clock else "wall", "train_views": args.train_views,
                    "load_average_start": os.getloadavg()[0]}
    scene = (object_scene if args.object == "object" else untuned_scene)(0)
    with tempfile.TemporaryDirectory() as root:
        folder = write_nerf_synthetic(os.path.join(root, "scene"), scene, size=args.size,
                                      views=(args.train_views, 1, args.test_views))
        sparse = os.path.join(root, "sparse")
        result.update(run_sfm(folder, args.train_views, sparse))
        print(f"SfM: {result['registered']} of {args.train_views} views registered, {result['sfm_points']} "
              f"points, rotation error {result['sfm_rotation_error_deg']:.3f} deg, centre error "
              f"{result['sfm_center_error_rel']:.4f} of the path, {result['sfm_cpu_seconds']:.0f} s CPU",
              flush=True)
        sfm = sfm_reconstruction(path=sparse, images=os.path.join(folder, "train"), reference=folder,
                                 downscale=args.downscale, test_views=args.test_views)
        result["train_center_error"] = sfm.truth["train_center_error"]
        true = true_pose_dataset(folder, sfm, views=args.train_views, test_views=args.test_views,
                                 downscale=args.downscale)
        report("true_poses", nerf_run(true, args.budget), result)
        report("sfm_poses", nerf_run(sfm, args.budget), result)
        result["psnr_sfm_poses_minus_true"] = result["psnr_sfm_poses"] - result["psnr_true_poses"]
        if args.splatting:
            count = len(sfm.state["sfm_points"])
            true_points = true_surface_points(scene, true, count)
            report("splat_true_points", splat_run(true_points, args.budget), result)
            report("splat_sfm_points", splat_run(true, args.budget), result)
            report("splat_sfm_chain", splat_run(sfm, args.budget), result)
            result["psnr_splat_sfm_minus_true"] = (result["psnr_splat_sfm_points"]
                                                   - result["psnr_splat_true_points"])
    result["load_average"] = os.getloadavg()[0]
    print("RESULT " + json.dumps(result))


if __name__ == "__main__":
    main()
