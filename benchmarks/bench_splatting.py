"""Gaussian splatting on a CPU: the fast rasterizer against its reference, and training against the NeRF
module's accelerated variant at the same wall-clock budget.

Protocol (issue 18 item 6):

1. Rasterizer: a random scene of the awkward cases the tests use (overlapping, tiny, huge, behind the
   camera, straddling the edges, opaque stacks), float64, rendered by the fast path (:func:`render`) and the
   per-pixel reference (:func:`render_reference`): forward and backward times, their ratios, the largest
   image difference and the largest gradient difference over every parameter.
2. Training: the synthetic 100 x 100 object scene (``synthetic_object``: 40 training and 8 held-out views
   on white), or with ``--scene PATH`` a NeRF-synthetic folder (shrunk to 100 px); splatting trains through
   its pipeline's steps (``initialize_gaussians``, ``train_splats`` with ``budget_seconds``,
   ``render_held_out``), NeRF's grid variant through bench_nerf's ``fast`` configuration at the same budget;
   both then render held-out camera 0 at 200 x 200 for the render time. Training clocks count optimizer
   steps only (previews off); on a machine shared with other jobs every number in seconds is pessimistic.

Keys of the last line ``RESULT {json}``: ``psnr_splat_<budget>s``, ``ssim_splat_<budget>s``,
``iterations_splat_<budget>s``, ``gaussians_splat_<budget>s``, ``psnr_nerf_<budget>s``,
``ssim_nerf_<budget>s``, ``render_seconds_200_splat``, ``render_seconds_200_nerf``,
``render_cpu_seconds_200_splat``, ``render_cpu_seconds_200_nerf``, ``render_speedup_vs_nerf`` and
``render_speedup_vs_nerf_cpu`` (NeRF's 200 x 200 render time over splatting's, wall and CPU: both timed on
one core, every thread of the process pinned to one CPU and torch on one thread, the best of 5 after a
warm-up render, no gradient), ``rasterizer_max_abs_diff``, ``grad_max_abs_diff``,
``rasterizer_forward_speedup``, ``rasterizer_backward_speedup`` (reference time over fast), ``scene``,
``clock`` (``cpu`` with ``--cpu-clock``: the training budgets in CPU seconds), ``torch_threads``,
``load_average_start`` and ``load_average`` (the 1-minute load when the run started and ended).

    python3 benchmarks/bench_splatting.py                    # 120 s each
    python3 benchmarks/bench_splatting.py --budget 20 --no-nerf
    python3 benchmarks/bench_splatting.py --scene ~/data/nerf_synthetic/lego
    python3 benchmarks/bench_splatting.py --cpu-clock --scene /tmp/untuned --downscale 2   # the untuned
        # scene, written first by lab.modules.nerf.datasets: write_nerf_synthetic("/tmp/untuned",
        # untuned_scene(0)) (200 px, read at 100)
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
import types
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch

from lab.core import open_session
from lab.modules.nerf import FieldRenderer, cameras_rays, scaled_cameras
from lab.modules.splatting import PIPELINE, View, render, render_model, render_reference

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "modules" / "splatting"))

#: The splatting run's controls (beyond the budget).
SPLAT_INIT = {"points": 1000}
SPLAT_TRAIN = {"iterations": 1_000_000, "preview_every": 100_000}
NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh")


def rasterizer_comparison(seed: int = 0) -> dict:
    """Fast against reference on one awkward random scene (float64): times, ratios, largest differences."""
    from test_splatting_rasterizer import camera, random_scene

    scene = random_scene(seed, count=40)
    view: View = camera(48, 32)
    background = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    weights = torch.randn(32, 48, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def timed(draw) -> tuple[torch.Tensor, dict, float, float]:
        params = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
        started = time.perf_counter()
        image = draw(*(params[k] for k in NAMES), view, sh_degree=3, background=background)
        image = getattr(image, "image", image)
        forward = time.perf_counter() - started
        (image * weights).sum().backward()
        backward = time.perf_counter() - started - forward
        return image.detach(), {k: params[k].grad for k in NAMES}, forward, backward

    timed(render)                                           # compiles (or loads) the float64 kernels
    slow, slow_grads, slow_forward, slow_backward = timed(render_reference)
    runs = [timed(render) for _ in range(3)]
    fast, fast_grads = runs[0][:2]
    numbers: dict = {"fast_forward_seconds": min(r[2] for r in runs),
                     "fast_backward_seconds": min(r[3] for r in runs),
                     "reference_forward_seconds": slow_forward, "reference_backward_seconds": slow_backward}
    numbers["rasterizer_max_abs_diff"] = float((fast - slow).abs().max())
    numbers["grad_max_abs_diff"] = max(float((fast_grads[k] - slow_grads[k]).abs().max()) for k in NAMES)
    numbers["grad_max_rel_diff"] = max(float(((fast_grads[k] - slow_grads[k]).abs()
                                              / slow_grads[k].abs().clamp_min(1.0)).max()) for k in NAMES)
    numbers["rasterizer_forward_speedup"] = (numbers["reference_forward_seconds"]
                                             / numbers["fast_forward_seconds"])
    numbers["rasterizer_backward_speedup"] = (numbers["reference_backward_seconds"]
                                              / numbers["fast_backward_seconds"])
    return numbers


@contextlib.contextmanager
def one_core() -> Iterator[None]:
    """Every thread of this process (the kernels' pool included) on one CPU, torch on one thread: the fair
    render figure on a shared 2-core machine (the pool's bands then take turns on that core)."""
    tasks = [int(t) for t in os.listdir("/proc/self/task")]
    saved = {t: os.sched_getaffinity(t) for t in tasks}
    threads = torch.get_num_threads()
    cpu = min(os.sched_getaffinity(0))
    try:
        for t in tasks:
            with contextlib.suppress(OSError):      # a thread that ended meanwhile
                os.sched_setaffinity(t, {cpu})
        torch.set_num_threads(1)
        yield
    finally:
        for t, cpus in saved.items():
            with contextlib.suppress(OSError):
                os.sched_setaffinity(t, cpus)
        torch.set_num_threads(threads)


def render_times(draw: Callable[[], object], repeats: int = 5) -> tuple[float, float]:
    """Best wall and best CPU seconds (``time.process_time``: every thread of the process) of ``draw()``
    over ``repeats`` calls after one warm-up call, on one core (:func:`one_core`)."""
    with one_core():
        draw()
        wall = cpu = float("inf")
        for _ in range(repeats):
            started, started_cpu = time.perf_counter(), time.process_time()
            draw()
            wall = min(wall, time.perf_counter() - started)
            cpu = min(cpu, time.process_time() - started_cpu)
    return wall, cpu


def splat_run(session_args: tuple, budget: float) -> dict:
    """Train splatting for ``budget`` seconds through its steps, evaluate, time a 200 x 200 view."""
    session = open_session(PIPELINE, session_args[0], session_args[1], seed=0)
    session.run("initialize_gaussians", SPLAT_INIT)
    train = session.run("train_splats", {**SPLAT_TRAIN, "budget_seconds": budget})
    if train.status != "ok":
        raise SystemExit(f"train_splats failed: {train.error}")
    held = session.run("render_held_out")
    model, test = session.state["model"], session.state["test_cameras"]
    big = scaled_cameras(test, 200 / test.width)
    wall, cpu = render_times(lambda: render_model(model, big, 0))
    return {"psnr": held.metrics["psnr"], "ssim": held.metrics["ssim"],
            "iterations": train.metrics["iterations"],
            "gaussians": train.metrics["gaussians_count"], "render_seconds_200": wall,
            "render_cpu_seconds_200": cpu}


def nerf_run(session_args: tuple, budget: float) -> dict:
    """NeRF's accelerated (grid) variant for ``budget`` seconds, as bench_nerf runs its ``fast`` config;
    held-out camera 0 at 200 x 200 rendered as bench_nerf's ``render_seconds_200`` does (the compiled grid
    march, no gradient), timed like splatting's on one core."""
    from bench_nerf import CONFIGS, run_config

    from lab.modules.nerf import PIPELINE as NERF

    numbers = run_config((NERF, *session_args), CONFIGS["fast"], budget)
    first = scaled_cameras(numbers["test_cameras"], 200 / numbers["test_cameras"].width)
    one = type(first)(first.K[:1], first.R[:1], first.t[:1], first.width, first.height)
    renderer = FieldRenderer(numbers["model"], "cpu")
    if renderer.net is not None:
        raise SystemExit("the NeRF fast configuration trained an MLP, not the grid")
    origins, directions = cameras_rays(one)
    wall, cpu = render_times(lambda: renderer.image(origins[0], directions[0], (one.height, one.width)))
    return {"psnr": numbers["psnr"], "ssim": numbers["ssim"], "iterations": numbers["iterations"],
            "render_seconds_200": wall, "render_cpu_seconds_200": cpu}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--budget", type=float, default=120.0, help="training seconds of each method")
    parser.add_argument("--scene", default="", help="a NeRF-synthetic folder (default: the synthetic object)")
    parser.add_argument("--downscale", type=int, default=8,
                        help="--scene's images shrunk this many times (the Blender scenes: 800 px / 8)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (the machine is shared)")
    parser.add_argument("--cpu-clock", action="store_true",
                        help="budgets in this process's CPU seconds, not wall-clock ones (both training "
                             "loops' clock replaced, as bench_nerf's --cpu-clock): comparable figures on a "
                             "machine shared with other jobs")
    parser.add_argument("--no-nerf", action="store_true", help="skip the NeRF run")
    parser.add_argument("--no-training", action="store_true", help="only the rasterizer comparison")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.cpu_clock:
        from lab.modules.nerf import grid
        from lab.modules.nerf import training as nerf_training
        from lab.modules.splatting import training as splat_training

        for module in (grid, nerf_training, splat_training):
            module.time = types.SimpleNamespace(perf_counter=time.process_time)  # type: ignore[attr-defined]
    result: dict = {"scene": args.scene or "synthetic_object", "torch_threads": args.threads,
                    "clock": "cpu" if args.cpu_clock else "wall",
                    "load_average_start": os.getloadavg()[0]}
    raster = rasterizer_comparison()
    result.update(raster)
    print(f"rasterizer: forward {raster['fast_forward_seconds'] * 1e3:.1f} ms vs reference "
          f"{raster['reference_forward_seconds']:.2f} s ({raster['rasterizer_forward_speedup']:.0f}x), "
          f"backward "
          f"{raster['fast_backward_seconds'] * 1e3:.1f} ms vs {raster['reference_backward_seconds']:.2f} s "
          f"({raster['rasterizer_backward_speedup']:.0f}x); "
          f"max |image diff| {raster['rasterizer_max_abs_diff']:.2e}, "
          f"max |grad diff| {raster['grad_max_abs_diff']:.2e}", flush=True)
    if not args.no_training:
        if args.scene:
            session_args: tuple = ("nerf_synthetic", {"path": args.scene, "downscale": args.downscale})
        else:
            session_args = ("synthetic_object", {"train_views": 40, "test_views": 8})
        tag = f"{args.budget:g}s"
        runs = {"splat": splat_run(session_args, args.budget)}
        if not args.no_nerf:
            runs["nerf"] = nerf_run(session_args, args.budget)
        for name, numbers in runs.items():
            for key in ("psnr", "ssim", "iterations", "gaussians"):
                if key in numbers:
                    result[f"{key}_{name}_{tag}"] = numbers[key]
            result[f"render_seconds_200_{name}"] = numbers["render_seconds_200"]
            result[f"render_cpu_seconds_200_{name}"] = numbers["render_cpu_seconds_200"]
            print(f"{name} {tag}: held-out PSNR {numbers['psnr']:.2f} dB, SSIM {numbers['ssim']:.3f}, "
                  f"{numbers['iterations']} iterations, 200 x 200 view on one core in "
                  f"{numbers['render_seconds_200'] * 1e3:.1f} ms wall, "
                  f"{numbers['render_cpu_seconds_200'] * 1e3:.1f} ms CPU (load {os.getloadavg()[0]:.1f})",
                  flush=True)
        if "nerf" in runs:
            for key, suffix in (("render_seconds_200", ""), ("render_cpu_seconds_200", "_cpu")):
                result[f"render_speedup_vs_nerf{suffix}"] = runs["nerf"][key] / runs["splat"][key]
            print(f"render speed-up vs NeRF grid: {result['render_speedup_vs_nerf']:.1f}x wall, "
                  f"{result['render_speedup_vs_nerf_cpu']:.1f}x CPU", flush=True)
    result["load_average"] = os.getloadavg()[0]
    rounded = {k: (float(f"{v:.4g}") if isinstance(v, float) and np.isfinite(v) else v)
               for k, v in result.items()}
    print("RESULT " + json.dumps(rounded))


if __name__ == "__main__":
    main()
