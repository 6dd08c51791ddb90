"""lab.modules.diffusion: schedules, the forward process, the updates against diffusers, samplers, training,
errors.

diffusers is a test-only dependency: its DDPMScheduler / DDIMScheduler are the reference of our updates.
Models here are tiny (a 32-wide MLP, a few hundred iterations) so the file runs in seconds.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from diffusers import DDIMScheduler, DDPMScheduler

from lab.core import InvalidControl, InvalidValue, PointCloud
from lab.core.codecs import decode_json, to_json
from lab.core.pipeline import open_session
from lab.modules import MODULES, get_pipeline
from lab.modules import diffusion as D
from lab.modules.diffusion import PIPELINE

TINY = {"iterations": 200, "hidden": 32, "layers": 2, "batch_size": 128}


@pytest.fixture(scope="module")
def moons():
    """A session on two moons with a tiny trained epsilon model."""
    session = open_session(PIPELINE, "two_moons", {"count": 400, "held_out": 400}, seed=3)
    session.run("noise_schedule", {"timesteps": 200})
    session.run("train_denoiser", {**TINY, "iterations": 500})
    return session


@pytest.fixture(scope="module")
def flow_moons():
    session = open_session(PIPELINE, "two_moons", {"count": 400, "held_out": 400}, seed=3)
    session.run("noise_schedule", {"timesteps": 200})
    session.run("train_denoiser", {**TINY, "objective": "flow"})
    return session


def test_registered():
    assert "diffusion" in MODULES and get_pipeline("diffusion") is PIPELINE
    first = ["noise_schedule", "forward_noising", "train_denoiser", "sample"]
    assert [s.name for s in PIPELINE.steps][:4] == first
    assert PIPELINE.step("train_denoiser").is_generator and PIPELINE.step("sample").is_generator


def test_views_are_values_the_steps_write():
    """The viewer's scrubber reads ``trace`` and ``model`` by name: the pipeline declares and writes both."""
    written = {name for spec in PIPELINE.steps for name in spec.writes}
    assert PIPELINE.views == {"trace", "model"} and PIPELINE.views <= written
    assert PIPELINE.producer("trace").name == "sample" and PIPELINE.producer("model").name == "train_denoiser"


# --- datasets -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("dataset,dim", [("shape_3d", 3), ("two_moons", 2), ("swiss_roll", 3)])
def test_point_datasets_shapes_and_held_out(dataset, dim):
    spec = PIPELINE.dataset(dataset)
    loaded = spec.load({"count": 300, "held_out": 200})
    data = loaded.state["training_data"]
    assert data.x.shape == (300, dim) and data.kind == "points" and data.labels is None
    assert loaded.truth["held_out"].shape == (200, dim)
    assert isinstance(loaded.state["points"], PointCloud) and loaded.state["points"].xyz.shape == (300, 3)
    again = spec.load({"count": 300, "held_out": 200})
    np.testing.assert_array_equal(again.state["training_data"].x, data.x)  # seeded


def test_torus_points_lie_on_the_surface():
    x = PIPELINE.dataset("shape_3d").load({"count": 500}).state["training_data"].x
    ring = np.hypot(x[:, 0], x[:, 1]) - 1.0  # trimesh's torus: major radius 1 in the xy plane, minor 0.35
    np.testing.assert_allclose(np.hypot(ring, x[:, 2]), 0.35, atol=0.02)


def test_digits_dataset_labels_and_classifier():
    loaded = PIPELINE.dataset("digits").load({})
    data = loaded.state["training_data"]
    assert data.x.shape[1] == 64 and data.classes == 10 and set(np.unique(data.labels)) == set(range(10))
    assert data.x.min() >= 0.0 and data.x.max() <= 1.0
    held, labels = loaded.truth["held_out"], loaded.truth["held_out_labels"]
    assert len(held) + len(data.x) == 1797
    accuracy = np.mean(loaded.truth["classifier"].predict(held) == labels)
    assert accuracy > 0.9
    metrics = D.digit_metrics(held, labels, loaded.truth)
    assert metrics["digit_accuracy"] == pytest.approx(accuracy) and metrics["diversity"] == pytest.approx(1.0)


# --- schedules and the forward process ------------------------------------------------------------------
def test_linear_schedule_known_answers_and_diffusers():
    schedule = D.make_schedule("linear", 1000)
    assert schedule.betas[0] == pytest.approx(1e-4) and schedule.betas[-1] == pytest.approx(0.02)
    assert schedule.alphas_cumprod[0] == pytest.approx(1 - 1e-4)
    # prod (1 - beta) with beta linear: about exp(-sum beta) = exp(-10.05)
    assert schedule.alphas_cumprod[-1] == pytest.approx(4.04e-5, rel=0.01)
    reference = DDPMScheduler(num_train_timesteps=1000,
                              beta_schedule="linear").alphas_cumprod.double().numpy()
    np.testing.assert_allclose(schedule.alphas_cumprod, reference, rtol=1e-5)
    # other T: the betas scale by 1000 / T, so abar_T stays about the same
    short = D.make_schedule("linear", 100)
    assert short.betas[0] == pytest.approx(1e-3) and short.betas[-1] == pytest.approx(0.2)
    assert short.alphas_cumprod[-1] < 1e-4


def test_cosine_schedule_matches_its_formula_and_diffusers():
    schedule = D.make_schedule("cosine", 1000)
    f = lambda t: math.cos((t / 1000 + 0.008) / 1.008 * math.pi / 2) ** 2  # noqa: E731
    assert schedule.alphas_cumprod[499] == pytest.approx(f(500) / f(0), rel=1e-9)
    assert schedule.betas.max() <= 0.999
    reference = DDPMScheduler(num_train_timesteps=1000,
                              beta_schedule="squaredcos_cap_v2").alphas_cumprod.double()
    np.testing.assert_allclose(schedule.alphas_cumprod, reference.numpy(), rtol=1e-5, atol=1e-9)


def test_snr_known_answer_and_monotone():
    np.testing.assert_allclose(D.signal_to_noise(np.array([0.5, 0.8, 0.2])), [1.0, 4.0, 0.25])
    for kind in ("linear", "cosine"):
        result = D.noise_schedule(schedule=kind, timesteps=100)
        assert np.all(np.diff(result.snr_plot.y[0]) < 0)  # noise only grows
        assert result.schedule_plot.y.shape == (4, 100) and result.snr_plot.y.shape == (1, 100)
        final_snr = D.signal_to_noise(result.schedule.alphas_cumprod[-1:])[0]
        assert result.final_snr_db == pytest.approx(10 * np.log10(final_snr))


def test_schedule_errors():
    with pytest.raises(InvalidControl, match="beta_start < beta_end"):
        D.make_schedule("linear", 100, 0.02, 0.01)
    with pytest.raises(InvalidControl, match="timesteps"):
        D.make_schedule("linear", 1)


def test_forward_noising_keeps_the_data_at_t0_and_destroys_it_at_T():
    session = open_session(PIPELINE, "two_moons", {"count": 500}, seed=0)
    session.run("noise_schedule")
    session.run("forward_noising", {"t": 0})
    x = session.state["training_data"].x
    np.testing.assert_allclose(session.state["noised"].xyz[:, :2], x, atol=0.05)
    record = session.run("forward_noising", {"t": 999})
    mean, scale = D.normalization(session.state["training_data"])
    normalized = (session.state["noised"].xyz[:, :2] - mean) / scale
    assert abs(normalized.std() - 1.0) < 0.1 and record.metrics["signal_fraction"] < 0.01
    with pytest.raises(InvalidControl, match="t"):
        session.run("forward_noising", {"t": 1000})


def test_flow_matching_pair_known_answer():
    x1, x0 = torch.tensor([[2.0, 4.0]]), torch.tensor([[0.0, 1.0]])
    xt, u = D.flow_matching_pair(x1, x0, torch.tensor([[0.25]]))
    np.testing.assert_allclose(xt.numpy(), [[0.5, 1.75]])
    np.testing.assert_allclose(u.numpy(), [[2.0, 3.0]])


# --- the updates against diffusers ----------------------------------------------------------------------
def _inputs(seed: int, shape=(256, 3)):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(shape, generator=g), torch.randn(shape, generator=g), torch.randn(shape, generator=g)


@pytest.mark.parametrize("prediction", ["epsilon", "v_prediction", "sample"])
@pytest.mark.parametrize("steps", [1000, 50])
def test_ddpm_step_matches_diffusers(prediction, steps):
    scheduler = DDPMScheduler(num_train_timesteps=1000, beta_schedule="linear", clip_sample=False,
                              prediction_type=prediction)
    scheduler.set_timesteps(steps)
    alphas = scheduler.alphas_cumprod.double().numpy()
    pairs = D.leading_timesteps(1000, steps)
    assert [t for t, _ in pairs] == scheduler.timesteps.tolist()
    for t, t_prev in pairs[:: max(1, len(pairs) // 12)] + pairs[-3:]:
        x, out, _ = _inputs(t)
        abar, abar_prev = alphas[t], (alphas[t_prev] if t_prev >= 0 else 1.0)
        theirs = scheduler.step(out, t, x, generator=torch.Generator().manual_seed(t))
        a = torch.tensor(abar, dtype=torch.float32).sqrt()
        b = torch.tensor(1 - abar, dtype=torch.float32).sqrt()
        x0 = {"epsilon": D.predicted_x0_from_eps(x, out, abar), "v_prediction": a * x - b * out,
              "sample": out}[prediction]
        noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(t)) if t > 0 else None
        ours = D.ddpm_step(x, x0, abar, abar_prev, noise=noise)
        assert float((ours - theirs.prev_sample).abs().max()) < 1e-5, t
        assert float((x0 - theirs.pred_original_sample).abs().max()) < 1e-5, t


@pytest.mark.parametrize("eta", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("steps", [10, 50])
def test_ddim_step_matches_diffusers(eta, steps):
    scheduler = DDIMScheduler(num_train_timesteps=1000, beta_schedule="linear", clip_sample=False,
                              set_alpha_to_one=True, steps_offset=0, timestep_spacing="leading")
    scheduler.set_timesteps(steps)
    alphas = scheduler.alphas_cumprod.double().numpy()
    pairs = D.leading_timesteps(1000, steps)
    assert [t for t, _ in pairs] == scheduler.timesteps.tolist()
    for t, t_prev in pairs:
        x, eps, noise = _inputs(t)
        abar, abar_prev = alphas[t], (alphas[t_prev] if t_prev >= 0 else 1.0)
        theirs = scheduler.step(eps, t, x, eta=eta, variance_noise=noise).prev_sample
        ours = D.ddim_step(x, eps, abar, abar_prev, eta=eta, noise=noise)
        assert float((ours - theirs).abs().max()) < 1e-5, t
        # the lesson's numpy step computes the same in float64
        lesson = D.ddim_update(x.double().numpy(), eps.double().numpy(), np.array([abar, abar_prev]),
                               noise.double().numpy(), eta=eta)
        np.testing.assert_allclose(lesson, theirs.double().numpy(), atol=2e-4)


def test_ddim_with_eta_one_has_ddpm_variance():
    x, eps, noise = _inputs(1, (4000, 2))
    abar, abar_prev = 0.3, 0.5
    x0 = D.predicted_x0_from_eps(x, eps, abar)
    ddim = D.ddim_step(x, eps, abar, abar_prev, eta=1.0, noise=noise) \
        - D.ddim_step(x, eps, abar, abar_prev, eta=1.0, noise=torch.zeros_like(noise))
    ddpm = D.ddpm_step(x, x0, abar, abar_prev, noise=noise) - D.ddpm_step(x, x0, abar, abar_prev)
    np.testing.assert_allclose(ddim.numpy(), ddpm.numpy(), atol=1e-5)  # the same sigma_t (Song et al. eq. 16)
    # and the same mean: DDPM's posterior mean is DDIM's eta = 1 mean
    np.testing.assert_allclose(
        D.ddim_step(x, eps, abar, abar_prev, eta=1.0, noise=torch.zeros_like(noise)).numpy(),
        D.ddpm_step(x, x0, abar, abar_prev).numpy(), atol=1e-5)


def test_deterministic_ddim_two_kernel_form_equals_the_equation():
    x, eps, _ = _inputs(4)
    for abar, abar_prev in ((4e-5, 0.01), (0.5, 0.7), (0.99, 1.0)):
        x0 = D.predicted_x0_from_eps(x, eps, abar)
        np.testing.assert_allclose(D.ddim_step(x, eps, abar, abar_prev).numpy(),
                                   D.ddim_step(x, eps, abar, abar_prev, x0=x0).numpy(), atol=2e-5)


def test_the_sde_sampler_is_stochastic(moons):
    moons.run("sample", {"sampler": "ddim", "steps": 20, "count": 100})
    ddim = moons.state["generated"].copy()
    moons.run("sample", {"sampler": "sde", "steps": 20, "count": 100})
    assert np.abs(moons.state["generated"] - ddim).mean() > 1e-3


def test_ddim_last_step_returns_the_predicted_x0():
    x, eps, _ = _inputs(2)
    np.testing.assert_allclose(D.ddim_step(x, eps, 0.9, 1.0).numpy(),
                               D.predicted_x0_from_eps(x, eps, 0.9).numpy(), atol=1e-6)


def test_combine_guidance_known_answers():
    c, u = np.array([[1.0, 2.0]]), np.array([[0.0, 1.0]])
    np.testing.assert_allclose(D.combine_guidance(c, u, guidance_scale=0.0), c)
    np.testing.assert_allclose(D.combine_guidance(c, u, guidance_scale=2.0), [[3.0, 4.0]])
    # diffusers' convention: eps_u + s (eps_c - eps_u) with s = 1 + w
    np.testing.assert_allclose(D.combine_guidance(c, u, guidance_scale=2.0), u + 3.0 * (c - u))


def test_ddim_update_errors():
    with pytest.raises(InvalidControl, match="eta"):
        D.ddim_update(np.zeros((2, 2)), np.zeros((2, 2)), np.array([0.5, 0.6]), np.zeros((2, 2)), eta=1.5)


# --- training and sampling ------------------------------------------------------------------------------
def test_short_training_lowers_the_loss():
    session = open_session(PIPELINE, "two_moons", {"count": 400}, seed=5)
    session.run("noise_schedule", {"timesteps": 200})
    untrained = session.run("train_denoiser", {**TINY, "iterations": 1}).metrics["final_loss"]
    losses = []
    record = session.run("train_denoiser", {**TINY, "iterations": 300},
                         on_progress=lambda step, p: losses.append(p.loss))
    assert len(losses) == 6 and losses[-1] <= losses[0]
    assert record.metrics["final_loss"] < 0.7 * untrained  # predicting eps = 0 costs about 1
    model = session.state["model"]
    assert model.dataset == "two_moons" and model.objective == "epsilon" and not model.conditional
    assert session.state["loss_curve"].y.shape[1] > 0


@pytest.mark.parametrize("objective", ["x0", "v"])
def test_other_objectives_train(objective):
    session = open_session(PIPELINE, "two_moons", {"count": 300}, seed=5)
    session.run("noise_schedule", {"timesteps": 100})
    record = session.run("train_denoiser", {**TINY, "iterations": 100, "objective": objective})
    assert np.isfinite(record.metrics["final_loss"])
    session.run("sample", {"sampler": "ddim", "steps": 10, "count": 50})
    assert np.all(np.isfinite(session.state["generated"]))


@pytest.mark.parametrize(("sampler", "steps"),
                         [("ddpm", 200), ("ddim", 20), ("euler", 20), ("heun", 10), ("sde", 20)])
def test_every_sampler_yields_every_step_and_approaches_the_data(moons, sampler, steps):
    previews = []
    record = moons.run("sample", {"sampler": sampler, "steps": steps, "count": 300},
                       on_progress=lambda step, p: previews.append(p))
    assert len(previews) == steps and previews[-1].iteration == steps
    assert set(previews[-1].values) == {"samples", "predicted_x0"}
    assert sum(bool(p.values) for p in previews) == min(steps, 100)
    generated = moons.state["generated"]
    assert generated.shape == (300, 2) and np.all(np.isfinite(generated))
    trace = moons.state["trace"]
    assert trace.frames == min(steps, 100) + 1 and trace.x_t.shape[1:] == (256, 2) and trace.step[-1] == steps
    np.testing.assert_allclose(trace.x_t[-1], generated[:256], atol=1e-5)
    assert np.isinf(trace.noise_level[0]) and trace.noise_level[-1] == 0.0
    # samples much nearer the moons than the initial noise
    held = moons.truth["held_out"]
    assert record.metrics["mmd"] < 0.75 * D.mmd_rbf(trace.x_t[0], held)
    assert record.metrics["chamfer"] < D.chamfer_distance(trace.x_t[0], held)
    assert record.metrics["evaluations"] == (2 * steps - 1 if sampler == "heun" else steps)


def test_sampler_generator_yields_x_t_and_x0_per_step(moons):
    denoiser = D.Denoiser(moons.state["model"], moons.state["schedule"])
    states = list(D.sample_ddim(denoiser, torch.randn(10, 2), steps=5,
                                generator=torch.Generator().manual_seed(0)))
    assert [s.step for s in states] == [0, 1, 2, 3, 4, 5]
    assert all(s.x_t.shape == (10, 2) and s.x0.shape == (10, 2) for s in states)
    # abar_prev = 1 at the end
    np.testing.assert_allclose(states[-1].x_t.numpy(), states[-1].x0.numpy(), atol=1e-5)


def test_euler_on_the_probability_flow_ode_is_ddim(moons):
    denoiser = D.Denoiser(moons.state["model"], moons.state["schedule"])
    x_T = torch.randn(50, 2, generator=torch.Generator().manual_seed(1))
    *_, ddim = D.sample_ddim(denoiser, x_T, steps=10, generator=torch.Generator())
    *_, euler = D.sample_ode(denoiser, x_T, steps=10, method="euler")
    np.testing.assert_allclose(euler.x_t.numpy(), ddim.x_t.numpy(), atol=1e-4)


def test_sampling_is_reproducible_and_the_seed_matters(moons):
    moons.run("sample", {"sampler": "ddpm", "steps": 50, "count": 100})
    first = moons.state["generated"].copy()
    moons.run("sample", {"sampler": "ddpm", "steps": 50, "count": 100})
    np.testing.assert_array_equal(moons.state["generated"], first)
    other = open_session(PIPELINE, "two_moons", {"count": 400, "held_out": 400}, seed=4)
    other.state.update({k: moons.state[k] for k in ("schedule", "model")})
    other.run("sample", {"sampler": "ddpm", "steps": 50, "count": 100})
    assert not np.allclose(other.state["generated"], first)


def test_flow_model_samplers(flow_moons):
    heun = flow_moons.run("sample", {"sampler": "heun", "steps": 10, "count": 300})
    assert heun.metrics["evaluations"] == 20  # Heun on the flow ODE: two evaluations every step
    assert flow_moons.state["trace"].noise_level[-1] == 0.0
    flow_moons.run("sample", {"sampler": "sde", "steps": 10, "count": 300})
    assert np.all(np.isfinite(flow_moons.state["generated"]))
    with pytest.raises(InvalidControl, match="flow matching"):
        flow_moons.run("sample", {"sampler": "ddim"})


def test_ancestral_step_with_eta_one_is_ddpm_variance():
    x0, eps, z = (t.double() for t in _inputs(3, (2000, 2)))
    abar, abar_prev = 0.2, 0.6
    sigma = math.sqrt((1 - abar) / abar)
    got = D.ancestral_step(x0, eps, math.sqrt(abar_prev), math.sqrt(1 - abar_prev), sigma, eta=1.0, noise=z)
    x_t = math.sqrt(abar) * x0 + math.sqrt(1 - abar) * eps
    want = D.ddim_step(x_t, eps, abar, abar_prev, eta=1.0, noise=z)
    np.testing.assert_allclose(got.numpy(), want.numpy(), atol=1e-9)


# --- guidance on digits and the lesson steps --------------------------------------------------------------
@pytest.fixture(scope="module")
def digits_session():
    session = open_session(PIPELINE, "digits", seed=1)
    session.run("noise_schedule", {"timesteps": 100})
    session.run("train_denoiser", {**TINY, "conditional": True, "iterations": 100})
    return session


def test_conditional_sampling_reports_accuracy_and_diversity(digits_session):
    record = digits_session.run("sample", {"sampler": "ddim", "steps": 5, "guidance_scale": 2.0, "count": 40})
    assert 0.0 <= record.metrics["digit_accuracy"] <= 1.0 and record.metrics["diversity"] > 0
    np.testing.assert_array_equal(digits_session.state["generated_labels"], np.arange(40) % 10)
    generated = digits_session.state["generated"]
    assert generated.shape == (40, 64) and generated.min() >= 0 and generated.max() <= 1
    assert digits_session.state["samples"].pixels.shape == (37, 91)  # 4 rows x 10 columns of 8 x 8 with gaps
    digits_session.run("sample", {"sampler": "ddim", "steps": 5, "label": 7, "count": 10})
    assert set(digits_session.state["generated_labels"]) == {7}


def test_lesson_steps_chain(digits_session):
    digits_session.run("prepare_update", {"timestep": 50, "stride": 10, "count": 16})
    state = digits_session.state
    assert state["x_t"].shape == (16, 64)
    assert not np.allclose(state["eps_conditional"], state["eps_unconditional"])
    schedule = state["schedule"]
    np.testing.assert_allclose(state["step_alphas"],
                               [schedule.alphas_cumprod[50], schedule.alphas_cumprod[40]])
    digits_session.run("combine_guidance", {"guidance_scale": 1.5})
    np.testing.assert_allclose(state["eps_conditional"] * 2.5 - 1.5 * state["eps_unconditional"],
                               digits_session.state["eps_guided"])
    digits_session.run("ddim_update", {"eta": 0.0})
    x_prev = digits_session.state["x_prev"]
    assert x_prev.shape == (16, 64) and np.all(np.isfinite(x_prev))


# --- errors ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("params", "field"), [
    ({"steps": 0}, "steps"), ({"eta": 1.5}, "eta"), ({"eta": -0.1}, "eta"),
    ({"guidance_scale": 2.0}, "guidance_scale"), ({"label": 3}, "label"), ({"steps": 201}, "steps")])
def test_bad_sampling_controls_are_clear_errors_and_keep_the_state(moons, params, field):
    moons.run("sample", {"sampler": "ddim", "steps": 5, "count": 20})
    before = moons.state["generated"]
    with pytest.raises(InvalidControl) as error:
        moons.run("sample", {"sampler": "ddim", **params})
    assert error.value.field == field
    assert moons.state["generated"] is before


def test_sampler_functions_check_their_arguments(moons):
    denoiser = D.Denoiser(moons.state["model"], moons.state["schedule"])
    with pytest.raises(InvalidControl, match="at least one step"):
        D.run_sampler("ddim", denoiser, torch.zeros(2, 2), steps=0, eta=0.0, generator=torch.Generator())
    with pytest.raises(InvalidControl, match="eta"):
        list(D.sample_ddim(denoiser, torch.zeros(2, 2), steps=2, eta=2.0, generator=torch.Generator()))
    with pytest.raises(InvalidControl, match="trained without labels"):
        D.Denoiser(moons.state["model"], moons.state["schedule"], guidance_scale=1.0)


def test_a_checkpoint_for_another_dataset_is_refused(moons):
    torus = open_session(PIPELINE, "shape_3d", {"count": 200, "held_out": 200}, seed=0)
    torus.run("noise_schedule", {"timesteps": 200})
    torus.put("model", moons.state["model"])
    with pytest.raises(InvalidValue, match="trained on dataset 'two_moons'"):
        torus.run("sample", {"steps": 5})
    assert "generated" not in torus.state


def test_conditional_training_needs_labels(moons):
    with pytest.raises(InvalidControl, match="no labels"):
        moons.run("train_denoiser", {**TINY, "conditional": True})


# --- values and codecs --------------------------------------------------------------------------------------
def test_checkpoint_round_trips_through_json(moons):
    model = moons.state["model"]
    encoded = json.loads(json.dumps(to_json(model)))
    assert encoded["type"] == "DenoiserCheckpoint" and encoded["dataset"] == "two_moons"
    decoded = decode_json(encoded, D.DenoiserCheckpoint, name="model")
    for key, value in model.weights.items():
        np.testing.assert_array_equal(decoded.weights[key], value)
    net = D.network_from(decoded)
    assert sum(p.numel() for p in net.parameters()) == sum(v.size for v in model.weights.values())
    json.dumps(to_json(moons.state["trace"]))  # every state value encodes for REST
    json.dumps(to_json(moons.state["schedule"]))
    json.dumps(to_json(moons.state["training_data"]))


def test_checkpoint_validation():
    with pytest.raises(InvalidValue, match="weights"):
        D.DenoiserCheckpoint({}, "x", 2, "epsilon", 8, 1, 0, 10, np.zeros(2), 1.0)
    with pytest.raises(InvalidValue, match="objective"):
        D.DenoiserCheckpoint({"a": np.zeros(1)}, "x", 2, "score", 8, 1, 0, 10, np.zeros(2), 1.0)


# --- metrics ----------------------------------------------------------------------------------------------
def test_chamfer_and_mmd_known_answers():
    a = np.random.default_rng(0).standard_normal((300, 3))
    assert D.chamfer_distance(a, a) == 0.0
    assert D.chamfer_distance(np.zeros((1, 3)), np.array([[0.0, 0.0, 2.0]])) == pytest.approx(4.0)
    assert D.mmd_rbf(a, a) == pytest.approx(0.0, abs=1e-6)
    assert D.mmd_rbf(a + 3.0, a) > 0.5 > D.mmd_rbf(a + 0.1, a)
    assert D.diversity_score(np.zeros((10, 4)), a) == 0.0
