"""Diffusion sampling: samplers on a 3D shape, our updates against diffusers', guidance on digits.

In one run:
1. train an epsilon-prediction denoiser and a flow-matching one (same MLP, same iterations) on points
   sampled on a torus (lab.modules.diffusion.shape_3d), timing the training;
2. sample 2000 points with DDPM-1000, DDIM-{10, 20, 50, 100}, the probability-flow ODE (Euler / Heun)
   and flow matching (Euler / Heun at 10, 20, 50 steps), and the SDE sampler: Chamfer distance and
   MMD to 2000 held-out points, sampling time;
3. our ``ddpm_step`` / ``ddim_step`` against diffusers' ``DDPMScheduler.step`` / ``DDIMScheduler.step``
   on the same model outputs and samples (recorded along a real sampling run): max |difference| and
   time ratio (ours / diffusers);
4. a class-conditional digits model sampled with classifier-free guidance w = 0, 1, 3: the accuracy of
   the module's digit classifier on the requested classes, and the diversity of the samples.

The last line is ``RESULT {json}``. Run: ``python benchmarks/bench_diffusion.py [--quick] [--threads N]``.
Timings depend on the machine's load; torch runs with ``--threads`` threads (default 1).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import numpy as np
import torch

from lab.core.pipeline import open_session
from lab.modules import diffusion as D


def train(session, **params) -> tuple[D.DenoiserCheckpoint, float]:
    record = session.run("train_denoiser", params)
    return session.state["model"], float(record.metrics["train_seconds"])


def run_sampler(session, **params) -> dict[str, float]:
    started = time.perf_counter()
    record = session.run("sample", params)
    seconds = time.perf_counter() - started
    return {"chamfer": record.metrics["chamfer"], "mmd": record.metrics["mmd"], "seconds": seconds,
            "evaluations": record.metrics["evaluations"]}


def _updates(name: str, scheduler, alphas: np.ndarray, ratio: int) -> tuple[Callable, Callable]:
    """Our update and diffusers' ``step`` for sampler ``name``, both ``(t, x_t, model output) -> x_prev``."""

    def ours(t, x_t, output):  # the same abar_t as diffusers' (float32 cumprod): the same inputs
        abar, abar_prev = float(alphas[t]), (float(alphas[t - ratio]) if t - ratio >= 0 else 1.0)
        if name == "ddim":
            return D.ddim_step(x_t, output, abar, abar_prev)
        x0 = D.predicted_x0_from_eps(x_t, output, abar)
        if t == 0:
            return D.ddpm_step(x_t, x0, abar, abar_prev)
        noise = torch.randn(x_t.shape, generator=torch.Generator().manual_seed(t), dtype=x_t.dtype)
        return D.ddpm_step(x_t, x0, abar, abar_prev, noise=noise)

    def theirs(t, x_t, output):
        if name == "ddim":
            return scheduler.step(output, t, x_t, eta=0.0).prev_sample
        return scheduler.step(output, t, x_t, generator=torch.Generator().manual_seed(t)).prev_sample

    return ours, theirs


def compare_with_diffusers(model: D.DenoiserCheckpoint, schedule: D.NoiseSchedule, *, count: int, repeats: int
                           ) -> dict[str, float]:
    """Record (t, x_t, model output) along diffusers' own DDIM-50 and DDPM-1000 runs; apply both updates."""
    from diffusers import DDIMScheduler, DDPMScheduler

    denoiser = D.Denoiser(model, schedule)
    results: dict[str, float] = {}
    for name in ("ddim", "ddpm"):
        if name == "ddim":
            scheduler = DDIMScheduler(num_train_timesteps=schedule.timesteps, beta_schedule="linear",
                                      clip_sample=False, set_alpha_to_one=True, steps_offset=0,
                                      timestep_spacing="leading")
            scheduler.set_timesteps(50)
        else:
            scheduler = DDPMScheduler(num_train_timesteps=schedule.timesteps, beta_schedule="linear",
                                      clip_sample=False, timestep_spacing="leading")
            scheduler.set_timesteps(schedule.timesteps)
        ratio = schedule.timesteps // scheduler.num_inference_steps
        x = torch.randn((count, model.dim), generator=torch.Generator().manual_seed(0))
        records = []
        for t in scheduler.timesteps.tolist():
            output = denoiser.output(x, t)
            records.append((t, x, output))
            if name == "ddim":
                x = scheduler.step(output, t, x, eta=0.0).prev_sample
            else:
                x = scheduler.step(output, t, x, generator=torch.Generator().manual_seed(t)).prev_sample

        alphas = scheduler.alphas_cumprod.double().numpy()
        results["schedule_max_rel_diff"] = float(np.max(np.abs(alphas - schedule.alphas_cumprod) / alphas))

        ours, theirs = _updates(name, scheduler, alphas, ratio)
        diff = max(float((ours(*r) - theirs(*r)).abs().max()) for r in records)
        times = {}
        for label, update in (("ours", ours), ("diffusers", theirs)):
            best = np.inf
            for _ in range(repeats):
                started = time.perf_counter()
                for r in records:
                    update(*r)
                best = min(best, time.perf_counter() - started)
            times[label] = best
        results[f"{name}_max_abs_diff"] = diff
        results[f"{name}_time_ratio"] = times["ours"] / times["diffusers"]
        print(f"{name.upper()} updates vs diffusers over {len(records)} steps of {count} samples: max |diff| "
              f"{diff:.2e}, ours {times['ours'] * 1e3:.1f} ms, diffusers {times['diffusers'] * 1e3:.1f} ms, "
              f"ratio {times['ours'] / times['diffusers']:.2f}")
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer iterations and samples (a smoke run)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--iterations", type=int, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    iterations = args.iterations or (300 if args.quick else 3000)
    count = 500 if args.quick else 2000
    result: dict[str, float] = {}

    # --- 1. training on the 3D shape -----------------------------------------------------------------
    session = open_session(D.PIPELINE, "shape_3d", {"count": 2000, "held_out": count}, seed=1)
    session.run("noise_schedule", {"schedule": "linear"})
    eps_model, result["train_seconds"] = train(session, objective="epsilon", iterations=iterations,
                                               batch_size=512)
    print(f"torus, {iterations} iterations: epsilon model trained in {result['train_seconds']:.1f} s "
          f"(loss {session.metrics['train_denoiser']['final_loss']:.4f})")

    # --- 2. samplers -----------------------------------------------------------------------------------
    rows = []
    runs = [("ddpm", 1000), ("ddim", 10), ("ddim", 20), ("ddim", 50), ("ddim", 100), ("euler", 20),
            ("heun", 20), ("sde", 100)]
    if args.quick:
        runs = [("ddpm", 1000), ("ddim", 10), ("ddim", 50), ("heun", 20)]
    for sampler, steps in runs:
        row = run_sampler(session, sampler=sampler, steps=steps, count=count)
        rows.append((f"diffusion {sampler}-{steps}", row))
        key = {"ddpm": "ddpm", "ddim": "ddim", "euler": "pfode_euler", "heun": "pfode_heun",
               "sde": "sde"}[sampler]
        result[f"chamfer_{key}{steps}"] = row["chamfer"]
        result[f"seconds_{key}{steps}"] = row["seconds"]
    diffusion_session = session
    flow_session = open_session(D.PIPELINE, "shape_3d", {"count": 2000, "held_out": count}, seed=1)
    flow_session.run("noise_schedule", {"schedule": "linear"})
    _, result["flow_train_seconds"] = train(flow_session, objective="flow", iterations=iterations,
                                            batch_size=512)
    print(f"flow-matching model trained in {result['flow_train_seconds']:.1f} s "
          f"(loss {flow_session.metrics['train_denoiser']['final_loss']:.4f})")
    flow_runs = [("euler", 10), ("heun", 10), ("euler", 20), ("heun", 20), ("euler", 50), ("heun", 50),
                 ("sde", 50)]
    if args.quick:
        flow_runs = [("euler", 20), ("heun", 20)]
    for sampler, steps in flow_runs:
        row = run_sampler(flow_session, sampler=sampler, steps=steps, count=count)
        rows.append((f"flow {sampler}-{steps}", row))
        result[f"chamfer_{'flow_' if sampler == 'sde' else ''}{sampler}{steps}"] = row["chamfer"]
        result[f"seconds_{'flow_' if sampler == 'sde' else ''}{sampler}{steps}"] = row["seconds"]
    print(f"\n{'sampler':<24}{'NFE':>6}{'Chamfer':>10}{'MMD':>9}{'seconds':>9}")
    for name, row in rows:
        print(f"{name:<24}{row['evaluations']:>6}{row['chamfer']:>10.4f}{row['mmd']:>9.4f}{row['seconds']:>9.2f}")
    held = np.asarray(diffusion_session.truth["held_out"])
    floor = D.chamfer_distance(np.asarray(diffusion_session.state["training_data"].x)[:count], held)
    result["chamfer_data_floor"] = floor
    print(f"{'training data itself':<24}{'':>6}{floor:>10.4f}")
    print(f"DDIM-50 / DDPM-1000 Chamfer: {result['chamfer_ddim50'] / result['chamfer_ddpm1000']:.3f} "
          f"(done when <= 1.10); flow Heun-20 / DDIM-50: "
          f"{result['chamfer_heun20'] / result['chamfer_ddim50']:.3f} "
          "(done when <= 1.0)")

    # --- 3. our updates vs diffusers' ---------------------------------------------------------------------
    compared = compare_with_diffusers(eps_model, diffusion_session.state["schedule"], count=count,
                                      repeats=3 if args.quick else 5)
    result.update(compared)
    result["diffusers_max_abs_diff"] = max(compared["ddim_max_abs_diff"], compared["ddpm_max_abs_diff"])
    result["diffusers_time_ratio"] = max(compared["ddim_time_ratio"], compared["ddpm_time_ratio"])

    # --- 4. guidance on digits ---------------------------------------------------------------------------
    digits = open_session(D.PIPELINE, "digits", seed=2)
    digits.run("noise_schedule", {"schedule": "cosine"})
    _, result["digits_train_seconds"] = train(digits, objective="epsilon", conditional=True,
                                              label_dropout=0.2, iterations=max(300, iterations * 2 // 3),
                                              batch_size=256, hidden=256)
    # DDIM-50 on the conditional model; diversity is within each class, against held-out digits of that
    # class
    for w in (0.0, 1.0, 3.0):
        record = digits.run("sample", {"sampler": "ddim", "steps": 50, "guidance_scale": w, "count": 500})
        result[f"digit_accuracy_w{w:g}"] = record.metrics["digit_accuracy"]
        result[f"digit_diversity_w{w:g}"] = record.metrics["diversity"]
        print(f"digits, guidance w = {w:g}: classifier accuracy {record.metrics['digit_accuracy']:.3f}, "
              f"diversity {record.metrics['diversity']:.3f}")
    print("RESULT " + json.dumps({k: float(f"{float(v):.6g}") for k, v in result.items()}))


if __name__ == "__main__":
    main()
