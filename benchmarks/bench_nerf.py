"""NeRF on a CPU: the accelerated grid variant against the vanilla NeRF MLP, at the same wall-clock budgets.

Protocol (issue 17 item 7): the synthetic 100 x 100 object scene (``synthetic_object``: 40 training and 8
held-out views on white), or with ``--scene PATH`` a folder in the NeRF-synthetic layout (shrunk to
100 px); every configuration trains through the pipeline's own steps (``generate_rays``,
``encode_positions``, ``train_nerf`` with ``budget_seconds``, ``render_held_out``) on this machine, then
renders one 200 x 200 view (held-out camera 0 at twice the resolution) for the render time. The training
clock counts optimizer steps only (previews are off), so budgets are comparable; on a machine shared with
other jobs every number in seconds is pessimistic.

Configurations: ``fast`` (method grid: 96^3 finest grid, 2048 rays a batch, learning rate 0.15, total
variation 1e-3);
``vanilla`` (the classic course project's NeRF: 6 frequencies, 32 samples per ray, a 4 x 64 MLP, 4096 rays
a batch, learning rate 5e-3); ``vanilla_small_batch`` (the same with 1024 rays a batch).

Keys of the last line ``RESULT {json}``: ``psnr_<config>_<budget>s``, ``ssim_<config>_<budget>s``,
``iterations_<config>_<budget>s``, ``rays_per_second_<config>_<budget>s``,
``samples_per_ray_<config>_<budget>s``; ``render_seconds_200_<config>`` and
``render_cpu_seconds_200_<config>`` (wall and CPU time, from the longest budget's model);
``psnr_fast_minus_vanilla_<budget>s``; ``render_speedup_200_wall`` and ``render_speedup_200_cpu``
(vanilla's render time over fast's) and ``render_speedup_200``, the CPU-time one where the load average
was above 1 (the machine shared), else the wall one; with ``--untuned``, the fast configuration's keys on
the untuned scene (``psnr_untuned_<budget>s`` ...) and ``psnr_untuned_minus_tuned_<budget>s``;
``psnr_sfm_poses_minus_true`` (null: the SfM chain, issue 17 item 4d, is not built yet); ``scene``,
``torch_threads``, ``load_average`` (the 1-minute load when the run ended).

    python3 benchmarks/bench_nerf.py                       # budgets 10 s and 120 s, every configuration
    python3 benchmarks/bench_nerf.py --budgets 10 --configs fast
    python3 benchmarks/bench_nerf.py --scene ~/data/nerf_synthetic/lego
    python3 benchmarks/bench_nerf.py --budgets 10,120 --configs fast,vanilla --threads 1 --cpu-clock --untuned

The held-out views are rendered as the pipeline's ``render_held_out`` does by default: each pixel the mean
of the rays through an s x s grid of points inside it, s the dataset's ``pixel_supersample`` (the synthetic
object's images are 2 x 2 supersampled, a NeRF-synthetic folder shrunk f times has f x f, at most 4 x 4
taken), as the truth's pixels are area means; one ray through each pixel centre scores even the exact scene
at only 30.6 dB on the synthetic object. Every configuration is evaluated so. The 200 x 200 timing stays a
plain render, one ray through each pixel centre: it measures render speed.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
import types

import torch

from lab.core import open_session
from lab.modules.nerf import PIPELINE, FieldRenderer, cameras_rays, render_image, scaled_cameras
from lab.modules.nerf import grid, training
from lab.modules.nerf.datasets import untuned_scene, write_nerf_synthetic

#: Above this 1-minute load average other jobs share the cores: the render speed-up is read from CPU time
#: (``time.process_time`` on one thread), which the other jobs do not inflate, rather than wall time.
LOADED = 1.0

CONFIGS = {
    "fast": {"method": "grid", "grid_resolution": 96, "batch_rays": 2048, "grid_learning_rate": 0.15,
             "grid_tv": 1e-3},
    "vanilla": {"method": "mlp", "samples": 32, "hidden": 64, "layers": 4, "batch_rays": 4096,
                "learning_rate": 5e-3},
    "vanilla_small_batch": {"method": "mlp", "samples": 32, "hidden": 64, "layers": 4, "batch_rays": 1024,
                            "learning_rate": 5e-3},
}


def run_config(session_args: tuple, controls: dict, budget: float) -> dict:
    """Train one configuration for ``budget`` seconds and evaluate it; returns its numbers and model."""
    session = open_session(*session_args[:2], session_args[2], seed=0)
    session.run("generate_rays")
    session.run("encode_positions")
    cpu = time.process_time()
    train = session.run("train_nerf", {**controls, "budget_seconds": budget, "iterations": 1_000_000,
                                       "preview_every": 100_000})
    cpu = time.process_time() - cpu
    if train.status != "ok":
        raise SystemExit(f"train_nerf failed: {train.error}")
    held = session.run("render_held_out")
    numbers = {key: held.metrics[key] for key in ("psnr", "ssim")}
    numbers.update({key: train.metrics[key] for key in ("iterations", "rays_per_second", "samples_per_ray")})
    numbers["cpu_share"] = cpu / max(train.metrics["train_seconds"], 1e-9)
    return {**numbers, "model": session.state["model"], "test_cameras": session.state["test_cameras"]}


def render_seconds_200(model, test_cameras, *, repeats: int = 3) -> tuple[float, float]:
    """Wall and CPU seconds (this process's, ``time.process_time``) to render held-out camera 0 at
    200 x 200 (twice the 100 px training resolution): each the best of ``repeats`` after one warm-up render
    (compiled kernels loaded, torch's allocator warm), no gradient; the MLP at its fastest chunk of rays
    (of 2048, 8192 and the whole view)."""
    first = scaled_cameras(test_cameras, 200 / test_cameras.width)
    one = type(first)(first.K[:1], first.R[:1], first.t[:1], first.width, first.height)
    renderer = FieldRenderer(model, "cpu")
    origins, directions = cameras_rays(one)
    shape = (one.height, one.width)
    if renderer.net is None:
        renderings = [lambda: renderer.image(origins[0], directions[0], shape)]
    else:
        renderings = [lambda chunk=chunk: render_image(renderer.net, origins[0], directions[0], model.bounds,
                                                       shape, background=renderer.background, chunk=chunk)
                      for chunk in (2048, 8192, shape[0] * shape[1])]
    wall = cpu = float("inf")
    for render in renderings:
        render()
        for _ in range(repeats):
            started, started_cpu = time.perf_counter(), time.process_time()
            render()
            wall = min(wall, time.perf_counter() - started)
            cpu = min(cpu, time.process_time() - started_cpu)
    return wall, cpu


def report(tag: str, numbers: dict, result: dict) -> None:
    """Record one run's numbers under ``<key>_<tag>`` and print them."""
    for key in ("psnr", "ssim", "iterations", "rays_per_second", "samples_per_ray", "cpu_share"):
        result[f"{key}_{tag}"] = numbers[key]
    print(f"{tag}: held-out PSNR {numbers['psnr']:.2f} dB, SSIM {numbers['ssim']:.3f}, "
          f"{numbers['iterations']} iterations, {numbers['rays_per_second']:.0f} rays/s, "
          f"{numbers['samples_per_ray']:.1f} samples/ray, CPU share {numbers['cpu_share']:.2f} "
          f"(load {os.getloadavg()[0]:.1f})", flush=True)


def render_speedup(renders: dict[str, tuple[float, float]], result: dict) -> None:
    """Vanilla's 200 x 200 render time over fast's, in wall and in CPU time; ``render_speedup_200`` is the
    CPU-time ratio where the load average was above :data:`LOADED` at the start or the end, else the wall
    one (said in the output)."""
    result["render_speedup_200_wall"] = renders["vanilla"][0] / renders["fast"][0]
    result["render_speedup_200_cpu"] = renders["vanilla"][1] / renders["fast"][1]
    loaded = max(result["load_average_start"], os.getloadavg()[0]) > LOADED
    result["render_speedup_200"] = result["render_speedup_200_cpu" if loaded else "render_speedup_200_wall"]
    why = (f"the load average was above {LOADED:g}: other jobs shared the cores, and CPU time is what the "
           "renders themselves took" if loaded else f"the load average stayed at most {LOADED:g}")
    print(f"render speed-up at 200 x 200: {result['render_speedup_200_wall']:.1f}x wall, "
          f"{result['render_speedup_200_cpu']:.1f}x CPU time; render_speedup_200 is the "
          f"{'CPU-time' if loaded else 'wall'} ratio ({why})", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--budgets", default="10,120", help="training budgets in seconds, comma-separated")
    parser.add_argument("--configs", default=",".join(CONFIGS), help=f"of {', '.join(CONFIGS)}")
    parser.add_argument("--scene", default="", help="a NeRF-synthetic folder (default: the synthetic object)")
    parser.add_argument("--downscale", type=int, default=8,
                        help="--scene's images shrunk this many times (the Blender scenes: 800 px / 8)")
    parser.add_argument("--untuned", action="store_true",
                        help="also run the fast configuration on a scene nothing was tuned on "
                             "(datasets.untuned_scene written in the NeRF-synthetic layout to a temporary "
                             "folder, 200 px read at downscale 2): keys psnr_untuned_<budget>s")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (the machine is shared)")
    parser.add_argument("--cpu-clock", action="store_true",
                        help="budgets in this process's CPU seconds, not wall-clock ones (the training "
                             "loops' clock replaced): comparable figures on a machine shared with other jobs")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.cpu_clock:
        for module in (grid, training):
            module.time = types.SimpleNamespace(perf_counter=time.process_time)  # type: ignore[assignment]
    budgets = [float(b) for b in args.budgets.split(",")]
    if args.scene:
        session_args = (PIPELINE, "nerf_synthetic", {"path": args.scene, "downscale": args.downscale})
    else:
        session_args = (PIPELINE, "synthetic_object", {"train_views": 40, "test_views": 8})
    result: dict = {"scene": args.scene or "synthetic_object", "torch_threads": args.threads,
                    "clock": "cpu" if args.cpu_clock else "wall", "load_average_start": os.getloadavg()[0]}
    renders: dict[str, tuple[float, float]] = {}
    for name in args.configs.split(","):
        for budget in budgets:
            numbers = run_config(session_args, CONFIGS[name], budget)
            report(f"{name}_{budget:g}s", numbers, result)
            if budget == max(budgets):
                renders[name] = render_seconds_200(numbers["model"], numbers["test_cameras"])
                wall, cpu = renders[name]
                result[f"render_seconds_200_{name}"], result[f"render_cpu_seconds_200_{name}"] = wall, cpu
                print(f"{name}: 200 x 200 view in {wall:.3f} s wall, {cpu:.3f} s CPU", flush=True)
    if args.untuned:
        with tempfile.TemporaryDirectory() as folder:
            write_nerf_synthetic(folder, untuned_scene(0), size=200)
            untuned = (PIPELINE, "nerf_synthetic", {"path": folder, "downscale": 2})
            for budget in budgets:
                report(f"untuned_{budget:g}s", run_config(untuned, CONFIGS["fast"], budget), result)
    for budget in budgets:
        fast, vanilla = result.get(f"psnr_fast_{budget:g}s"), result.get(f"psnr_vanilla_{budget:g}s")
        if fast is not None and vanilla is not None:
            result[f"psnr_fast_minus_vanilla_{budget:g}s"] = fast - vanilla
        if fast is not None and f"psnr_untuned_{budget:g}s" in result:
            result[f"psnr_untuned_minus_tuned_{budget:g}s"] = result[f"psnr_untuned_{budget:g}s"] - fast
    if "fast" in renders and "vanilla" in renders:
        render_speedup(renders, result)
    result["psnr_sfm_poses_minus_true"] = None
    result["load_average"] = os.getloadavg()[0]
    rounded = {k: round(v, 4) if isinstance(v, float) else v for k, v in result.items()}
    print("RESULT " + json.dumps(rounded))


if __name__ == "__main__":
    main()
