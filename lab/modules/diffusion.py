"""Diffusion sampling made watchable: forward noising, DDPM, DDIM, flow matching, ODE and SDE samplers, guidance.

References (equation numbers as in the papers):
- J. Ho, A. Jain, P. Abbeel, "Denoising diffusion probabilistic models", NeurIPS 2020 (DDPM):
  the forward process ``q(x_t | x_0) = N(sqrt(abar_t) x_0, (1 - abar_t) I)`` (eq. 4), the
  epsilon objective (eq. 14, "L_simple"), the posterior mean ``mu~_t(x_t, x_0)`` and variance
  ``beta~_t`` (eqs. 6-7) used by the ancestral sampler (Algorithm 2); the linear beta schedule
  (section 4: 1e-4 .. 0.02 over T = 1000).
- A. Nichol, P. Dhariwal, "Improved denoising diffusion probabilistic models", ICML 2021: the
  cosine schedule ``abar(t) = cos^2(((t/T + s) / (1 + s)) pi/2)``, betas clipped at 0.999 (eq. 17).
- J. Song, C. Meng, S. Ermon, "Denoising diffusion implicit models", ICLR 2021 (DDIM): the update
  of eq. 12 with ``sigma_t(eta)`` of eq. 16; eta = 0 is deterministic, eta = 1 is DDPM's variance.
- T. Salimans, J. Ho, "Progressive distillation", ICLR 2022: the v objective
  ``v = sqrt(abar) eps - sqrt(1 - abar) x_0`` (section 4).
- Y. Lipman, R. T. Q. Chen, H. Ben-Hamu, M. Nickel, M. Le, "Flow matching for generative
  modeling", ICLR 2023: conditional flow matching with the linear (optimal-transport) path
  ``x_t = (1 - (1 - sigma_min) t) x_noise + t x_data`` and its velocity
  ``u_t = x_data - (1 - sigma_min) x_noise`` (eqs. 20-23; here sigma_min = 0); t = 0 is noise,
  t = 1 is data; samples solve ``dx/dt = v(x, t)`` from 0 to 1.
- T. Karras, M. Aittala, T. Aila, S. Laine, "Elucidating the design space of diffusion-based
  generative models", NeurIPS 2022 (EDM): the probability-flow ODE in ``sigma`` with
  ``x~ = x / sqrt(abar)``, ``sigma = sqrt((1 - abar) / abar)``, ``dx~/dsigma = eps_hat`` (eq. 4
  with s = 1), Euler and Heun's second-order method (Algorithm 1); Euler on it is DDIM with eta = 0.
- Y. Song et al., "Score-based generative modeling through SDEs", ICLR 2021: the reverse SDE;
  the stochastic sampler here is its ancestral discretization (k-diffusion's ``euler_ancestral``).
- J. Ho, T. Salimans, "Classifier-free diffusion guidance", 2022: one model trained with labels
  dropped with probability ``p_uncond`` (Algorithm 1) and sampled with
  ``eps~ = (1 + w) eps(x, c) - w eps(x, null)`` (eq. 6; w = 0 is the plain conditional model).

Every noise path here is ``x_t = a_t x_0 + b_t eps``: diffusion ``a = sqrt(abar_t)``,
``b = sqrt(1 - abar_t)``; flow matching ``a = t``, ``b = 1 - t``. Samplers turn the model's output
into a predicted clean sample ``x0_hat`` and noise ``eps_hat`` with ``x_t = a x0_hat + b eps_hat``
and step from one noise level to the next.

Conventions: points are float64 ``(N, 2)`` / ``(N, 3)`` (2D points are drawn at z = 0); digits
are 8 x 8 images with values in [0, 1] flattened to 64 values. Networks run in float32 on
``device``; data are normalized (mean 0, about unit spread; digits to [-1, 1]) and samples mapped
back. The DDPM and DDIM updates follow diffusers' ``DDPMScheduler`` / ``DDIMScheduler`` (leading
timestep spacing, ``set_alpha_to_one``) and match their ``step`` to float32 rounding.

State names:
    training_data       TrainingData        the samples a model learns (points or digits, labels)
    points              PointCloud          the training points (digits: absent)
    digits              Image               a grid of training digits (points: absent)
    schedule            NoiseSchedule       betas and abar_t of the forward process
    schedule_plot       Curve               beta_t, abar_t, sqrt(abar_t), sqrt(1 - abar_t) over t
    snr_plot            Curve               log10 SNR(t) = log10(abar_t / (1 - abar_t))
    noised              PointCloud | Image  a draw of q(x_t | x_0) at the chosen t
    model               DenoiserCheckpoint  the trained network's weights and configuration
    loss_curve          Curve               training loss over iterations
    samples             PointCloud | Image  the sampler's output (digits: a grid)
    predicted_x0        PointCloud | Image  the model's x0 prediction at the last step
    generated           (N, D)              the samples in data units (points, or flattened digits)
    generated_labels    (N,) int            the class each sample was asked for (-1: none)
    trace               SamplingTrace       x_t and x0_hat at every step (at most 101 frames)
    x_t, eps_conditional, eps_unconditional, step_alphas, update_noise   [lesson helpers]
    eps_guided          (N, D)              the classifier-free-guidance combination  [lesson]
    x_prev              (N, D)              one DDIM update  [lesson]
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from typing import Annotated, Any, Generator, Iterator, Literal

import numpy as np
import torch

from lab.core.step import step_result
from lab.core import Curve, Image, InvalidControl, InvalidValue, Mesh, Pipeline, PointCloud, Progress, Range, metric
from lab.core.pipeline import Loaded

Objective = Literal["epsilon", "x0", "v", "flow"]
SamplerName = Literal["ddpm", "ddim", "euler", "heun", "sde"]
DIFFUSION_OBJECTIVES = ("epsilon", "x0", "v")

#: Frames of x_t / x0_hat kept in a trace (evenly spaced over the steps, first and last included).
MAX_TRACE_FRAMES = 101
#: Samples kept in a trace (points / digits).
TRACE_POINTS = 256
TRACE_DIGITS = 100
#: Scale of the time fed to the network's sinusoidal embedding (flow time t in [0, 1] is multiplied by it).
TIME_SCALE = 1000.0
DIGIT_SHAPE = (8, 8)


# ----------------------------------------------------------------------------------------------------
# Values
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class TrainingData:
    """Samples to learn: ``x`` float64 ``(N, D)`` in data units, ``labels`` ``(N,)`` int or None.

    ``kind`` is "points" (D = 2 or 3) or "digits" (D = 64, 8 x 8 images in [0, 1]); ``name``
    identifies the dataset (a checkpoint trained on another name is refused); ``classes`` is the
    number of labels (0 without labels).
    """

    x: np.ndarray
    kind: str
    name: str
    labels: np.ndarray | None = None
    classes: int = 0

    def __post_init__(self) -> None:
        x = np.asarray(self.x, dtype=np.float64)
        if x.ndim != 2 or len(x) < 2:
            raise InvalidValue("training_data.x", f"expected (N, D) samples with N >= 2, got shape {x.shape}")
        if not np.all(np.isfinite(x)):
            raise InvalidValue("training_data.x", "contains NaN or infinite entries")
        if self.kind not in ("points", "digits"):
            raise InvalidValue("training_data.kind", f"must be 'points' or 'digits', got {self.kind!r}")
        object.__setattr__(self, "x", x)
        if self.labels is not None:
            labels = np.asarray(self.labels, dtype=np.int64)
            if labels.shape != (len(x),):
                raise InvalidValue("training_data.labels", f"expected ({len(x)},) labels, got {labels.shape}")
            object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "classes", int(self.classes))

    @property
    def dim(self) -> int:
        return int(self.x.shape[1])


@dataclass(frozen=True, eq=False)
class NoiseSchedule:
    """The forward process: ``betas`` float64 ``(T,)`` and ``alphas_cumprod`` ``abar_t = prod_{s<=t} (1 - beta_s)``."""

    betas: np.ndarray
    alphas_cumprod: np.ndarray
    kind: str = "linear"

    def __post_init__(self) -> None:
        betas = np.asarray(self.betas, dtype=np.float64)
        abar = np.asarray(self.alphas_cumprod, dtype=np.float64)
        if betas.ndim != 1 or abar.shape != betas.shape or len(betas) < 2:
            raise InvalidValue("schedule", f"betas and alphas_cumprod must be (T,) with T >= 2, "
                                           f"got {betas.shape}, {abar.shape}")
        if not (np.all(betas > 0) and np.all(betas < 1)):
            raise InvalidValue("schedule.betas", "every beta must lie in (0, 1)")
        object.__setattr__(self, "betas", betas)
        object.__setattr__(self, "alphas_cumprod", abar)

    @property
    def timesteps(self) -> int:
        return len(self.betas)

    def abar(self, t: int) -> float:
        """``abar_t``; 1.0 for t < 0 (the clean sample, diffusers' ``set_alpha_to_one``)."""
        return 1.0 if t < 0 else float(self.alphas_cumprod[t])


@dataclass(frozen=True, eq=False)
class DenoiserCheckpoint:
    """A trained denoiser: ``weights`` (the network's state_dict as float32 numpy arrays) and its configuration.

    ``dataset`` and ``dim`` name the data it was trained on (sampling refuses other data);
    ``objective`` is what the network predicts ("epsilon", "x0", "v" or "flow" velocity);
    ``classes`` > 0 for a class-conditional model (label ``classes`` is the null label);
    ``mean`` ``(D,)`` and ``scale`` map data to the normalized space the network sees:
    ``x_norm = (x - mean) / scale``; ``clip`` > 0 clamps predicted clean samples to
    ``[-clip, clip]`` there (digits: 1, their pixel range). ``timesteps`` is the length of the
    schedule a diffusion model was trained with.
    """

    weights: dict[str, np.ndarray]
    dataset: str
    dim: int
    objective: str
    hidden: int
    layers: int
    classes: int
    timesteps: int
    mean: np.ndarray
    scale: float
    clip: float = 0.0
    label_dropout: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.weights, dict) or not self.weights:
            raise InvalidValue("model.weights", "a checkpoint needs the network's weights (a dict of arrays)")
        weights = {str(k): np.asarray(v, dtype=np.float32) for k, v in self.weights.items()}
        object.__setattr__(self, "weights", weights)
        if self.objective not in ("epsilon", "x0", "v", "flow"):
            raise InvalidValue("model.objective", f"must be epsilon, x0, v or flow, got {self.objective!r}")
        object.__setattr__(self, "mean", np.asarray(self.mean, dtype=np.float64).reshape(int(self.dim)))
        for name in ("dim", "hidden", "layers", "classes", "timesteps"):
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "scale", float(self.scale))
        object.__setattr__(self, "clip", float(self.clip))

    @property
    def conditional(self) -> bool:
        return self.classes > 0

    @property
    def is_flow(self) -> bool:
        return self.objective == "flow"


@dataclass(frozen=True, eq=False)
class SamplingTrace:
    """What a sampler did, for scrubbing: ``x_t`` and ``x0`` float32 ``(F, M, D)`` in data units at ``F`` frames.

    ``step`` ``(F,)`` is the sampler step of each frame (0: the initial noise), ``noise_level``
    ``(F,)`` is ``b_t / a_t`` (``sigma``; inf at pure noise) of the state in the frame; ``labels``
    ``(M,)`` the requested class of each traced sample (-1: none); ``kind`` "points" or "digits".
    """

    x_t: np.ndarray
    x0: np.ndarray
    step: np.ndarray
    noise_level: np.ndarray
    labels: np.ndarray
    kind: str
    sampler: str = ""
    steps: int = 0

    def __post_init__(self) -> None:
        x_t = np.asarray(self.x_t, dtype=np.float32)
        if x_t.ndim != 3:
            raise InvalidValue("trace.x_t", f"expected (F, M, D), got {x_t.shape}")
        object.__setattr__(self, "x_t", x_t)
        object.__setattr__(self, "x0", np.asarray(self.x0, dtype=np.float32).reshape(x_t.shape))
        object.__setattr__(self, "step", np.asarray(self.step, dtype=np.int64).reshape(len(x_t)))
        object.__setattr__(self, "noise_level", np.asarray(self.noise_level, dtype=np.float64).reshape(len(x_t)))
        object.__setattr__(self, "labels", np.asarray(self.labels, dtype=np.int64).reshape(x_t.shape[1]))

    @property
    def frames(self) -> int:
        return int(len(self.x_t))


# ----------------------------------------------------------------------------------------------------
# Datasets
# ----------------------------------------------------------------------------------------------------
def _points_loaded(x: np.ndarray, held: np.ndarray, name: str, description: str, mesh: Mesh | None = None) -> Loaded:
    state: dict[str, Any] = {"training_data": TrainingData(x, "points", name), "points": PointCloud(_as_3d(x))}
    if mesh is not None:
        state["mesh"] = mesh
    return Loaded(state=state, truth={"held_out": held}, description=description)


def shape_3d(*, shape: Literal["torus", "capsule", "box", "icosphere"] = "torus",
             count: Annotated[int, Range(100, 20000)] = 2000, held_out: Annotated[int, Range(100, 20000)] = 2000,
             seed: int = 0) -> Loaded:
    """Points on the surface of a trimesh mesh (``trimesh.sample.sample_surface``), about unit size.

    Args:
        shape: the mesh: a torus (radii 1 and 0.35), a capsule, a box or an icosphere.
        count: training points.
        held_out: points kept apart to measure samples against (Chamfer, MMD).
        seed: seed of the surface sampling.
    """
    import trimesh

    makers = {"torus": lambda: trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=48,
                                                       minor_sections=24),
              "capsule": lambda: trimesh.creation.capsule(height=1.2, radius=0.45),
              "box": lambda: trimesh.creation.box(extents=(1.6, 1.0, 0.6)),
              "icosphere": lambda: trimesh.creation.icosphere(subdivisions=3, radius=1.0)}
    mesh = makers[shape]()
    rng = np.random.default_rng(seed)
    x, _ = trimesh.sample.sample_surface(mesh, int(count) + int(held_out), seed=rng)
    x = np.asarray(x, dtype=np.float64)[rng.permutation(int(count) + int(held_out))]
    return _points_loaded(x[:count], x[count:], f"shape_3d:{shape}",
                          f"{count} points on a {shape} surface ({held_out} held out)",
                          Mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)))


def two_moons(*, count: Annotated[int, Range(100, 20000)] = 2000, held_out: Annotated[int, Range(100, 20000)] = 2000,
              noise: Annotated[float, Range(0.0, 0.5)] = 0.05, seed: int = 0) -> Loaded:
    """Two interleaving half circles in 2D (``sklearn.datasets.make_moons``), drawn at z = 0.

    Args:
        count: training points.
        held_out: points kept apart to measure samples against.
        noise: standard deviation of the Gaussian noise added to the points.
        seed: seed of the draw.
    """
    from sklearn.datasets import make_moons

    x, _ = make_moons(int(count) + int(held_out), noise=float(noise), random_state=int(seed) % 2**32)
    return _points_loaded(x[:count], x[count:], "two_moons", f"{count} two-moons points, noise {noise}")


def swiss_roll(*, count: Annotated[int, Range(100, 20000)] = 2000, held_out: Annotated[int, Range(100, 20000)] = 2000,
               noise: Annotated[float, Range(0.0, 2.0)] = 0.2, dimensions: Literal[2, 3] = 3, seed: int = 0) -> Loaded:
    """A swiss roll (``sklearn.datasets.make_swiss_roll``), in 3D or its 2D spiral (x, z), scaled by 1/10.

    Args:
        count: training points.
        held_out: points kept apart to measure samples against.
        noise: standard deviation of the noise (before the 1/10 scaling).
        dimensions: 3 for the roll, 2 for the spiral.
        seed: seed of the draw.
    """
    from sklearn.datasets import make_swiss_roll

    x, _ = make_swiss_roll(int(count) + int(held_out), noise=float(noise), random_state=int(seed) % 2**32)
    x = x / 10.0 if dimensions == 3 else x[:, [0, 2]] / 10.0
    return _points_loaded(x[:count], x[count:], f"swiss_roll_{dimensions}d",
                          f"{count} swiss-roll points in {dimensions}D")


def digits(*, held_out_fraction: Annotated[float, Range(0.05, 0.5)] = 0.2, seed: int = 0) -> Loaded:
    """scikit-learn's 1797 handwritten 8 x 8 digits (``sklearn.datasets.load_digits``, offline) with labels 0-9.

    Pixels are scaled to [0, 1]. A held-out part trains the small digit classifier that scores
    samples (:func:`train_digit_classifier`) and measures their diversity.

    Args:
        held_out_fraction: the fraction of the digits kept apart.
        seed: seed of the split.
    """
    from sklearn.datasets import load_digits

    bunch = load_digits()
    x = np.asarray(bunch.data, dtype=np.float64) / 16.0
    labels = np.asarray(bunch.target, dtype=np.int64)
    order = np.random.default_rng(seed).permutation(len(x))
    held = int(round(len(x) * float(held_out_fraction)))
    train, test = order[held:], order[:held]
    data = TrainingData(x[train], "digits", "digits", labels[train], 10)
    truth = {"held_out": x[test], "held_out_labels": labels[test],
             "classifier": _cached_digit_classifier(int(seed), float(held_out_fraction))}
    return Loaded(state={"training_data": data, "digits": digit_grid(x[train][:100])}, truth=truth,
                  description=f"{len(train)} 8x8 digits with labels ({held} held out)")


# ----------------------------------------------------------------------------------------------------
# Schedules and the forward process
# ----------------------------------------------------------------------------------------------------
def linear_betas(timesteps: int, beta_start: float = 1e-4, beta_end: float = 0.02) -> np.ndarray:
    """``(T,)`` betas evenly spaced from ``beta_start`` to ``beta_end`` (Ho et al. 2020, section 4), given for
    T = 1000 and scaled by ``1000 / T`` for other T (Nichol & Dhariwal 2021's ``get_named_beta_schedule``),
    so that ``abar_T`` stays near 0; at most 0.999. For T = 1000 this is diffusers' "linear" schedule."""
    scale = 1000.0 / int(timesteps)
    return np.minimum(np.linspace(beta_start * scale, beta_end * scale, int(timesteps), dtype=np.float64), 0.999)


def cosine_betas(timesteps: int, *, offset: float = 0.008, max_beta: float = 0.999) -> np.ndarray:
    """``(T,)`` betas of the cosine schedule (Nichol & Dhariwal 2021, eq. 17; diffusers' "squaredcos_cap_v2").

    ``beta_t = min(1 - abar(t + 1) / abar(t), max_beta)`` with ``abar(t) = cos^2((t/T + s)/(1 + s) pi/2)``.
    """
    steps = np.arange(int(timesteps) + 1, dtype=np.float64) / int(timesteps)
    abar = np.cos((steps + offset) / (1 + offset) * math.pi / 2) ** 2
    return np.minimum(1.0 - abar[1:] / abar[:-1], max_beta)


def make_schedule(kind: str = "linear", timesteps: int = 1000, beta_start: float = 1e-4,
                  beta_end: float = 0.02) -> NoiseSchedule:
    """A :class:`NoiseSchedule` of ``kind`` "linear" or "cosine": ``abar_t = cumprod(1 - beta)``."""
    if int(timesteps) < 2:
        raise InvalidControl("timesteps", f"a schedule needs at least 2 timesteps, got {timesteps}")
    if kind == "linear":
        if not 0 < beta_start < beta_end < 1:
            raise InvalidControl("beta_end", f"need 0 < beta_start < beta_end < 1, got {beta_start}, {beta_end}")
        betas = linear_betas(timesteps, beta_start, beta_end)
    elif kind == "cosine":
        betas = cosine_betas(timesteps)
    else:
        raise InvalidControl("schedule", f"must be linear or cosine, got {kind!r}")
    return NoiseSchedule(betas, np.cumprod(1.0 - betas), kind)


def signal_to_noise(alphas_cumprod: np.ndarray) -> np.ndarray:
    """``SNR(t) = abar_t / (1 - abar_t)``: signal power over noise power of ``q(x_t | x_0)`` (Kingma et al. 2021)."""
    abar = np.asarray(alphas_cumprod, dtype=np.float64)
    return abar / (1.0 - abar)


@step_result
class ScheduleResult:
    """Result of :func:`noise_schedule`."""

    schedule: NoiseSchedule
    schedule_plot: Curve
    snr_plot: Curve
    final_abar: float = metric("abar at the last timestep (signal left in x_T)")
    final_snr_db: float = metric("SNR at the last timestep", unit="dB")


def noise_schedule(*, schedule: Literal["linear", "cosine"] = "linear",
                   timesteps: Annotated[int, Range(2, 4000)] = 1000,
                   beta_start: Annotated[float, Range(1e-6, 0.1)] = 1e-4,
                   beta_end: Annotated[float, Range(1e-5, 0.5)] = 0.02) -> ScheduleResult:
    """The forward process's betas, ``abar_t`` and signal-to-noise ratio ``SNR = abar / (1 - abar)``.

    ``q(x_t | x_0) = N(sqrt(abar_t) x_0, (1 - abar_t) I)`` with ``abar_t = prod_{s <= t} (1 - beta_s)``
    (Ho et al. 2020, eq. 4). Linear: betas from ``beta_start`` to ``beta_end`` (Ho et al.; for T = 1000,
    scaled by 1000 / T otherwise); cosine:
    Nichol & Dhariwal 2021 eq. 17 (``diffusers`` "linear" / "squaredcos_cap_v2").

    Args:
        schedule: linear or cosine betas.
        timesteps: T, the number of noise levels.
        beta_start: the first beta at T = 1000 (linear only).
        beta_end: the last beta at T = 1000 (linear only).
    """
    sched = make_schedule(schedule, timesteps, beta_start, beta_end)
    t = np.arange(sched.timesteps, dtype=np.float64)
    abar = sched.alphas_cumprod
    plot = Curve(t, np.stack([sched.betas, abar, np.sqrt(abar), np.sqrt(1 - abar)]), title=f"{schedule} schedule",
                 xlabel="t", ylabel="value", labels=("beta_t", "abar_t", "sqrt(abar_t)", "sqrt(1 - abar_t)"))
    snr = signal_to_noise(abar)
    snr_plot = Curve(t, np.log10(snr), title="signal-to-noise ratio", xlabel="t", ylabel="log10 SNR",
                     labels=("log10 abar/(1 - abar)",))
    return ScheduleResult(sched, plot, snr_plot, float(abar[-1]), float(10 * np.log10(snr[-1])))


def q_sample(x0: np.ndarray, alpha_bar: float, noise: np.ndarray) -> np.ndarray:
    """A draw of ``q(x_t | x_0)``: ``sqrt(abar) x_0 + sqrt(1 - abar) eps``.

    Ho et al. 2020, eq. 4; diffusers' ``add_noise``.
    """
    return alpha_bar ** 0.5 * x0 + (1.0 - alpha_bar) ** 0.5 * noise


@step_result
class ForwardResult:
    """Result of :func:`forward_noising`."""

    noised: PointCloud | Image
    snr_db: float = metric("signal-to-noise ratio at t", unit="dB")
    signal_fraction: float = metric("sqrt(abar_t): how much of x_0 is left")


def forward_noising(training_data: TrainingData, schedule: NoiseSchedule, *,
                    t: Annotated[int, Range(0, 3999)] = 250, rng: np.random.Generator) -> ForwardResult:
    """The training data noised to step ``t`` by ``q(x_t | x_0)`` (eq. 4 of Ho et al. 2020), in normalized units.

    Data are normalized as the network sees them (:func:`normalization`), noised, and mapped back,
    so the cloud spreads out as t grows. Digits are shown as a grid of the first 100.

    Args:
        t: the timestep (0 .. T - 1).
    """
    data = _training_data(training_data)
    sched = _schedule(schedule)
    if not 0 <= t < sched.timesteps:
        raise InvalidControl("t", f"must be in [0, {sched.timesteps - 1}] for this schedule, got {t}")
    mean, scale = normalization(data)
    x = data.x[:TRACE_DIGITS] if data.kind == "digits" else data.x
    x0 = (x - mean) / scale
    xt = q_sample(x0, sched.abar(t), rng.standard_normal(x0.shape)) * scale + mean
    snr = signal_to_noise(sched.alphas_cumprod[t:t + 1])[0]
    return ForwardResult(_display(xt, data.kind), float(10 * np.log10(snr)), float(math.sqrt(sched.abar(t))))


def normalization(data: TrainingData) -> tuple[np.ndarray, float]:
    """``(mean (D,), scale)`` with ``x_norm = (x - mean) / scale``: digits to [-1, 1], points to unit spread."""
    if data.kind == "digits":
        return np.full(data.dim, 0.5), 0.5
    mean = data.x.mean(axis=0)
    return mean, float(np.sqrt(((data.x - mean) ** 2).mean()))


# ----------------------------------------------------------------------------------------------------
# The denoiser network
# ----------------------------------------------------------------------------------------------------
def timestep_embedding(t: torch.Tensor, dim: int, *, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding ``(B, dim)`` of (fractional) timesteps ``(B,)``: ``[cos(t f_i), sin(t f_i)]``,
    ``f_i = max_period^(-i / (dim/2))`` (Vaswani et al. 2017, as in Ho et al. 2020's U-Net)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    angles = t.float()[:, None] * freqs[None]
    return torch.cat([torch.cos(angles), torch.sin(angles)], dim=1)


class DenoiserMLP(torch.nn.Module):
    """An MLP ``f(x_t, t, c) -> (B, D)``: ``layers`` hidden layers of width ``hidden`` with SiLU, the
    time embedding (and the label's, for ``classes`` > 0; label ``classes`` is "no label") added to every layer."""

    def __init__(self, dim: int, hidden: int = 128, layers: int = 3, classes: int = 0, embed: int = 64) -> None:
        super().__init__()
        self.embed = embed
        self.time = torch.nn.Sequential(torch.nn.Linear(embed, hidden), torch.nn.SiLU(),
                                        torch.nn.Linear(hidden, hidden))
        self.label = torch.nn.Embedding(classes + 1, hidden) if classes > 0 else None
        self.inp = torch.nn.Linear(dim, hidden)
        self.hidden = torch.nn.ModuleList([torch.nn.Linear(hidden, hidden) for _ in range(layers)])
        self.out = torch.nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor, t: torch.Tensor, labels: torch.Tensor | None = None) -> torch.Tensor:
        c = self.time(timestep_embedding(t, self.embed))
        if self.label is not None:
            c = c + self.label(labels)
        h = torch.nn.functional.silu(self.inp(x) + c)
        for layer in self.hidden:
            h = torch.nn.functional.silu(layer(h) + c)
        return self.out(h)


def network_from(checkpoint: DenoiserCheckpoint, device: str = "cpu") -> DenoiserMLP:
    """The :class:`DenoiserMLP` of a checkpoint, weights loaded, in eval mode on ``device``."""
    net = DenoiserMLP(checkpoint.dim, checkpoint.hidden, checkpoint.layers, checkpoint.classes)
    try:
        net.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in checkpoint.weights.items()})
    except RuntimeError as exc:
        raise InvalidValue("model.weights", f"do not fit the network of this configuration: {exc}") from None
    return net.to(device).eval()


def _torch_generator(rng: np.random.Generator) -> torch.Generator:
    return torch.Generator().manual_seed(int(rng.integers(0, 2**62)))


def _randn(shape: tuple[int, ...], generator: torch.Generator, device: str) -> torch.Tensor:
    """Standard normal noise drawn on the CPU (reproducible across devices) and moved to ``device``."""
    return torch.randn(shape, generator=generator, dtype=torch.float32).to(device)


# ----------------------------------------------------------------------------------------------------
# Training: denoising (epsilon / x0 / v) and flow matching
# ----------------------------------------------------------------------------------------------------
def training_target(objective: str, x0: torch.Tensor, noise: torch.Tensor, alpha_bar: torch.Tensor) -> torch.Tensor:
    """What the network learns to predict from ``x_t = sqrt(abar) x0 + sqrt(1 - abar) eps``:
    eps (Ho et al. eq. 14), x0, or ``v = sqrt(abar) eps - sqrt(1 - abar) x0`` (Salimans & Ho 2022)."""
    if objective == "epsilon":
        return noise
    if objective == "x0":
        return x0
    return alpha_bar.sqrt() * noise - (1 - alpha_bar).sqrt() * x0


def flow_matching_pair(x_data: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Lipman et al. 2023's linear path with sigma_min = 0: ``x_t = (1 - t) x_noise + t x_data``
    (eq. 22) and its velocity target ``u_t = x_data - x_noise`` (eq. 23). ``t`` ``(B, 1)``."""
    return (1 - t) * noise + t * x_data, x_data - noise


@step_result
class TrainResult:
    """Result of :func:`train_denoiser`."""

    model: DenoiserCheckpoint
    loss_curve: Curve
    final_loss: float = metric("mean training loss over the last 10 % of iterations")
    train_seconds: float = metric("wall-clock training time", unit="s")


def train_denoiser(training_data: TrainingData, schedule: NoiseSchedule, *, objective: Objective = "epsilon",
                   conditional: bool = False, label_dropout: Annotated[float, Range(0.0, 1.0)] = 0.15,
                   iterations: Annotated[int, Range(1, 200000)] = 4000,
                   batch_size: Annotated[int, Range(1, 65536)] = 512,
                   hidden: Annotated[int, Range(4, 2048)] = 128, layers: Annotated[int, Range(1, 12)] = 3,
                   learning_rate: Annotated[float, Range(1e-6, 1.0)] = 3e-3,
                   rng: np.random.Generator, device: str = "cpu") -> Generator[Progress, None, TrainResult]:
    """Train the MLP denoiser by regression: a diffusion objective or flow matching, optionally class-conditional.

    Diffusion (Ho et al. 2020, Algorithm 1): draw ``x_0``, ``t ~ U{0..T-1}``, ``eps ~ N(0, I)``,
    ``x_t = sqrt(abar_t) x_0 + sqrt(1 - abar_t) eps`` and regress the network's output at
    ``(x_t, t)`` on eps, x0 or v (:func:`training_target`). Flow matching (Lipman et al. 2023,
    eq. 23): ``t ~ U[0, 1]``, ``x_t = (1 - t) eps + t x_0``, target ``x_0 - eps``
    (:func:`flow_matching_pair`); the network sees ``1000 t``. Conditional (Ho & Salimans 2022,
    Algorithm 1): the label joins the input and is replaced by the null label with probability
    ``label_dropout``. Adam with a cosine-decayed learning rate; the returned weights are an
    exponential moving average of the iterates (window about a tenth of the run). Yields the loss
    every 50 iterations.

    Args:
        objective: what the network predicts: epsilon, x0, v (diffusion) or flow (the velocity).
        conditional: learn p(x | label) too (needs a dataset with labels: digits).
        label_dropout: probability of dropping the label during training (classifier-free guidance).
        iterations: optimizer steps.
        batch_size: samples per step.
        hidden: width of the MLP.
        layers: hidden layers.
        learning_rate: Adam's initial learning rate.
    """
    data = _training_data(training_data)
    sched = _schedule(schedule)
    if conditional and (data.labels is None or data.classes < 1):
        raise InvalidControl("conditional", f"dataset {data.name!r} has no labels: train an unconditional model "
                                            "(conditional = false) or use the digits")
    classes = data.classes if conditional else 0
    mean, scale = normalization(data)
    x_all = torch.as_tensor((data.x - mean) / scale, dtype=torch.float32, device=device)
    labels_all = torch.as_tensor(data.labels if classes else np.zeros(len(data.x), np.int64), device=device)
    abar = torch.as_tensor(sched.alphas_cumprod, dtype=torch.float32, device=device)
    generator = _torch_generator(rng)
    with torch.random.fork_rng(devices=[]):  # the network's initial weights, from rng; torch's global state untouched
        torch.manual_seed(int(rng.integers(0, 2**62)))
        net = DenoiserMLP(data.dim, hidden, layers, classes).to(device)
    ema = [p.detach().clone() for p in net.parameters()]
    ema_decay = 1.0 - 1.0 / max(10.0, iterations / 10.0)
    optimizer = torch.optim.Adam(net.parameters(), lr=learning_rate)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda i: 0.5 * (1 + math.cos(math.pi * min(i, iterations) / iterations)) * 0.98 + 0.02)
    losses = np.zeros(iterations)
    started = time.perf_counter()
    n = len(x_all)
    for it in range(iterations):
        idx = torch.randint(n, (batch_size,), generator=generator).to(device)
        x0 = x_all[idx]
        noise = _randn(tuple(x0.shape), generator, device)
        if objective == "flow":
            t = torch.rand((batch_size, 1), generator=generator).to(device)
            xt, target = flow_matching_pair(x0, noise, t)
            tau = t[:, 0] * TIME_SCALE
        else:
            steps = torch.randint(sched.timesteps, (batch_size,), generator=generator).to(device)
            a = abar[steps][:, None]
            xt = a.sqrt() * x0 + (1 - a).sqrt() * noise
            target = training_target(objective, x0, noise, a)
            tau = steps.float()
        labels = None
        if classes:
            drop = torch.rand(batch_size, generator=generator).to(device) < label_dropout
            labels = torch.where(drop, torch.full_like(labels_all[idx], classes), labels_all[idx])
        loss = torch.nn.functional.mse_loss(net(xt, tau, labels), target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        with torch.no_grad():
            torch._foreach_lerp_(ema, [p.detach() for p in net.parameters()], 1.0 - ema_decay)
        losses[it] = float(loss.detach())
        if (it + 1) % 50 == 0 or it + 1 == iterations:
            yield Progress(iteration=it + 1, total=iterations, loss=float(losses[max(0, it - 49):it + 1].mean()),
                           message=f"{objective} loss")
    seconds = time.perf_counter() - started
    with torch.no_grad():
        for p, e in zip(net.parameters(), ema):
            p.copy_(e)
    weights = {k: v.detach().cpu().numpy().copy() for k, v in net.state_dict().items()}
    checkpoint = DenoiserCheckpoint(weights, data.name, data.dim, objective, hidden, layers, classes, sched.timesteps,
                                    mean, scale, 1.0 if data.kind == "digits" else 0.0,
                                    label_dropout if classes else 0.0)
    window = max(1, iterations // 20)
    smooth = np.convolve(losses, np.ones(window) / window, mode="valid")
    curve = Curve(np.arange(len(smooth), dtype=np.float64) + window, smooth, title="training loss", xlabel="iteration",
                  ylabel="MSE", labels=(f"{objective} loss (mean of {window})",))
    return TrainResult(checkpoint, curve, float(losses[-max(1, iterations // 10):].mean()), seconds)


# ----------------------------------------------------------------------------------------------------
# The updates (the lesson's math; array-agnostic: numpy arrays or torch tensors, float abar)
# ----------------------------------------------------------------------------------------------------
def combine_guidance(eps_conditional: np.ndarray, eps_unconditional: np.ndarray, *,
                     guidance_scale: Annotated[float, Range(0.0, 20.0)] = 2.0) -> Annotated[np.ndarray, "eps_guided"]:
    """Classifier-free guidance: ``eps~ = (1 + w) eps(x, c) - w eps(x, null)`` (Ho & Salimans 2022, eq. 6).

    ``w = 0`` is the conditional model; larger ``w`` pushes samples towards what distinguishes the
    class. (diffusers writes the same with ``s = 1 + w``: ``eps_u + s (eps_c - eps_u)``.) Works on
    numpy arrays and torch tensors of any equal shapes, e.g. ``(N, D)``.

    Args:
        guidance_scale: w >= 0.
    """
    return (1.0 + guidance_scale) * eps_conditional - guidance_scale * eps_unconditional


def _coefficient(value: Any, like: Any) -> Any:
    """A schedule number in the arithmetic of ``like``: a 0-d tensor of its dtype (float32 samples round as
    diffusers' schedulers do) or a float64 number for numpy arrays."""
    if isinstance(like, torch.Tensor):
        return torch.as_tensor(value, dtype=like.dtype, device=like.device)
    return np.float64(value)


def _at_least(value: Any, floor: float) -> Any:
    return value.clamp(min=floor) if isinstance(value, torch.Tensor) else np.maximum(value, floor)


def predicted_x0_from_eps(x_t: Any, eps: Any, alpha_bar: float) -> Any:
    """``x0_hat = (x_t - sqrt(1 - abar) eps) / sqrt(abar)`` (Ho et al. 2020, eq. 15; DDIM eq. 12's "predicted x0")."""
    abar = _coefficient(alpha_bar, x_t)
    return (x_t - (1 - abar) ** 0.5 * eps) / abar ** 0.5


def ddim_step(x_t: Any, eps: Any, alpha_bar: float, alpha_bar_prev: float, *, eta: float = 0.0,
              noise: Any = None, x0: Any = None) -> Any:
    """One DDIM update ``x_t -> x_{t_prev}`` (Song et al. 2021, eq. 12 with sigma of eq. 16):

        x0_hat  = (x_t - sqrt(1 - abar_t) eps) / sqrt(abar_t)
        sigma   = eta sqrt((1 - abar_prev) / (1 - abar_t)) sqrt(1 - abar_t / abar_prev)
        x_prev  = sqrt(abar_prev) x0_hat + sqrt(1 - abar_prev - sigma^2) eps + sigma z

    ``x0`` replaces ``x0_hat`` (e.g. clipped) while ``eps`` stays the model's, as diffusers'
    ``DDIMScheduler.step`` (``use_clipped_model_output=False``). ``noise`` z is needed when eta > 0.
    Works on numpy arrays (float64 arithmetic) and torch tensors (the coefficients in the tensor's
    dtype, so float32 samples round as diffusers does: no Python work per element either way).
    """
    if x0 is None and eta == 0 and isinstance(x_t, torch.Tensor):
        # deterministic: x_prev = c1 x_t + c2 eps with the coefficients in float64, two kernels
        a, ap = float(alpha_bar), float(alpha_bar_prev)
        c1 = math.sqrt(ap / a)
        c2 = math.sqrt(max(1.0 - ap, 0.0)) - math.sqrt(ap) * math.sqrt(1.0 - a) / math.sqrt(a)
        return torch.add(x_t * c1, eps, alpha=c2)
    abar, abar_prev = _coefficient(alpha_bar, x_t), _coefficient(alpha_bar_prev, x_t)
    if x0 is None:
        x0 = (x_t - (1 - abar) ** 0.5 * eps) / abar ** 0.5
    variance = _at_least((1 - abar_prev) / (1 - abar) * (1 - abar / abar_prev), 0.0)
    sigma = eta * variance ** 0.5
    x_prev = abar_prev ** 0.5 * x0 + _at_least(1 - abar_prev - sigma ** 2, 0.0) ** 0.5 * eps
    if eta > 0:
        x_prev = x_prev + sigma * noise
    return x_prev


def ddpm_step(x_t: Any, x0: Any, alpha_bar: float, alpha_bar_prev: float, *, noise: Any = None) -> Any:
    """One ancestral DDPM update: a draw of the posterior ``q(x_prev | x_t, x0_hat)`` (Ho et al. 2020, eqs. 6-7).

        alpha   = abar_t / abar_prev,  beta = 1 - alpha
        mu      = sqrt(abar_prev) beta / (1 - abar_t) x0_hat + sqrt(alpha) (1 - abar_prev) / (1 - abar_t) x_t
        x_prev  = mu + sqrt(beta~) z,   beta~ = (1 - abar_prev) / (1 - abar_t) beta   (no noise when ``noise`` is None)

    With strided timesteps (fewer steps than T) ``alpha`` spans the stride, as diffusers' ``DDPMScheduler``
    ("fixed_small" variance). Arithmetic as in :func:`ddim_step`.
    """
    abar, abar_prev = _coefficient(alpha_bar, x_t), _coefficient(alpha_bar_prev, x_t)
    alpha = abar / abar_prev
    beta = 1 - alpha
    mean = (abar_prev ** 0.5 * beta / (1 - abar)) * x0 + (alpha ** 0.5 * (1 - abar_prev) / (1 - abar)) * x_t
    if noise is None:
        return mean
    variance = _at_least((1 - abar_prev) / (1 - abar) * beta, 1e-20)
    return mean + variance ** 0.5 * noise


def ancestral_step(x0: Any, eps: Any, a_next: float, b_next: float, sigma: float, *, eta: float, noise: Any) -> Any:
    """One step of the reverse SDE's ancestral discretization on the path ``x = a x0 + b eps`` (``sigma = b / a``).

    In Karras et al.'s variable ``x~ = x / a`` the step from ``sigma`` to ``sigma'`` splits the
    target noise into a deterministic and a fresh part (k-diffusion's ``get_ancestral_step``):
    ``sigma_up = min(sigma', eta sigma' sqrt(1 - sigma'^2 / sigma^2))``, ``sigma_down^2 = sigma'^2 - sigma_up^2``,
    ``x~' = x0_hat + sigma_down eps_hat + sigma_up z``. In ``x``: ``x' = a' x0_hat + b' (r_down eps_hat + r_up z)``
    with ``r = sigma_. / sigma'``. For a diffusion model and eta = 1 its variance is DDPM's posterior
    variance; it also runs on a flow-matching model (``a = t``, ``b = 1 - t``).
    """
    if b_next <= 0:
        return x0
    sigma_next = b_next / a_next
    ratio = 0.0 if not math.isfinite(sigma) else sigma_next / sigma
    r_up = min(1.0, eta * max(0.0, 1.0 - ratio ** 2) ** 0.5)
    r_down = (1.0 - r_up ** 2) ** 0.5
    return a_next * x0 + b_next * (r_down * eps + r_up * noise)


def leading_timesteps(timesteps: int, steps: int) -> list[tuple[int, int]]:
    """``(t, t_prev)`` pairs of a sampler with ``steps`` steps: diffusers' "leading" spacing.

    ``t = (steps - 1 - i) * (T // steps)``, ``t_prev = t - T // steps`` (negative: the clean sample, abar = 1).
    """
    _check_steps(steps, timesteps)
    ratio = timesteps // steps
    return [((steps - 1 - i) * ratio, (steps - 2 - i) * ratio) for i in range(steps)]


def _check_steps(steps: int, timesteps: int | None = None) -> None:
    if int(steps) < 1:
        raise InvalidControl("steps", f"a sampler needs at least one step, got {steps}")
    if timesteps is not None and int(steps) > int(timesteps):
        raise InvalidControl("steps", f"at most {timesteps} steps on a schedule of {timesteps} timesteps, got {steps}")


# ----------------------------------------------------------------------------------------------------
# Samplers: generators yielding (x_t, x0_hat) after every step
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SamplerState:
    """One snapshot of a sampler: after ``step`` of ``steps`` (0: the initial noise), ``x_t`` and ``x0``
    ``(N, D)`` float32 tensors in the normalized space, and the noise level ``sigma = b/a`` reached."""

    step: int
    steps: int
    x_t: torch.Tensor
    x0: torch.Tensor
    noise_level: float
    evaluations: int


class Denoiser:
    """A checkpoint made callable: ``predict(x, time) -> (x0_hat, eps_hat)`` in normalized units, with guidance.

    ``time`` is the discrete timestep of a diffusion model or the flow time t in [0, 1].
    ``labels`` ``(N,)`` are the classes asked for (conditional models); ``guidance_scale`` w
    combines conditional and unconditional outputs by :func:`combine_guidance` (output-space
    guidance: every objective's target is affine in the output, so guiding the output guides eps).
    """

    def __init__(self, checkpoint: DenoiserCheckpoint, schedule: NoiseSchedule | None, *, device: str = "cpu",
                 labels: torch.Tensor | None = None, guidance_scale: float = 0.0) -> None:
        self.checkpoint = checkpoint
        self.schedule = schedule
        self.device = device
        self.net = network_from(checkpoint, device)
        self.labels = labels
        self.guidance_scale = float(guidance_scale)
        self.evaluations = 0
        if guidance_scale != 0 and not checkpoint.conditional:
            raise InvalidControl("guidance_scale", "this model was trained without labels (conditional = false): "
                                                   "classifier-free guidance needs a conditional model; use 0")
        if checkpoint.conditional and labels is None:
            raise InvalidValue("labels", "a conditional model needs the class of every sample")

    @torch.no_grad()
    def output(self, x: torch.Tensor, time_value: float) -> torch.Tensor:
        """The network's (guided) output at ``x`` ``(N, D)`` and one time."""
        tau = torch.full((len(x),), float(time_value) * (TIME_SCALE if self.checkpoint.is_flow else 1.0),
                         device=x.device)
        self.evaluations += 1
        if not self.checkpoint.conditional:
            return self.net(x, tau)
        if self.guidance_scale == 0:
            return self.net(x, tau, self.labels)
        null = torch.full_like(self.labels, self.checkpoint.classes)
        both = self.net(torch.cat([x, x]), torch.cat([tau, tau]), torch.cat([self.labels, null]))
        return combine_guidance(both[:len(x)], both[len(x):], guidance_scale=self.guidance_scale)

    def coefficients(self, time_value: float) -> tuple[float, float]:
        """``(a, b)`` of the path at a time: ``x_t = a x0 + b eps``."""
        if self.checkpoint.is_flow:
            return float(time_value), 1.0 - float(time_value)
        abar = self.schedule.abar(int(time_value))
        return abar ** 0.5, (1.0 - abar) ** 0.5

    def predict(self, x: torch.Tensor, time_value: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(x0_hat, eps_hat, output)``; x0_hat clamped to ``[-clip, clip]`` when the checkpoint says so, and
        then eps_hat recomputed from it (``x_t = a x0_hat + b eps_hat`` holds; unclipped eps with a clipped
        x0 drives deterministic DDIM off the data)."""
        out = self.output(x, time_value)
        a, b = self.coefficients(time_value)
        objective = self.checkpoint.objective
        if objective == "flow":  # x_t = (1 - t) eps + t x1, v = x1 - eps
            x0, eps = x + b * out, x - a * out
        elif objective == "epsilon":
            x0, eps = (x - b * out) / a, out
        elif objective == "x0":
            x0, eps = out, (x - a * out) / max(b, 1e-12)
        else:  # v
            x0, eps = a * x - b * out, a * out + b * x
        if self.checkpoint.clip > 0 and b > 0:  # eps from the clamped x0 (diffusers' use_clipped_model_output)
            x0 = x0.clamp(-self.checkpoint.clip, self.checkpoint.clip)
            eps = (x - a * x0) / b
        return x0, eps, out


def _noise_level(a: float, b: float) -> float:
    return math.inf if a <= 0 else b / a


def sample_ddpm(denoiser: Denoiser, x_T: torch.Tensor, *, steps: int,
                generator: torch.Generator) -> Generator[SamplerState, None, torch.Tensor]:
    """Ancestral sampling (Ho et al. 2020, Algorithm 2) over ``steps`` strided timesteps (:func:`ddpm_step`)."""
    _require_diffusion(denoiser.checkpoint, "ddpm")
    schedule = denoiser.schedule
    x = x_T
    yield SamplerState(0, steps, x, torch.zeros_like(x), math.inf, 0)
    for i, (t, t_prev) in enumerate(leading_timesteps(schedule.timesteps, steps)):
        x0, _, _ = denoiser.predict(x, t)
        noise = _randn(tuple(x.shape), generator, str(x.device)) if t > 0 else None
        x = ddpm_step(x, x0, schedule.abar(t), schedule.abar(t_prev), noise=noise)
        yield SamplerState(i + 1, steps, x, x0, _sigma_of(schedule.abar(t_prev)), denoiser.evaluations)
    return x


def sample_ddim(denoiser: Denoiser, x_T: torch.Tensor, *, steps: int, eta: float = 0.0,
                generator: torch.Generator) -> Generator[SamplerState, None, torch.Tensor]:
    """DDIM (Song et al. 2021, eq. 12) over ``steps`` strided timesteps (:func:`ddim_step`); eta in [0, 1]."""
    _require_diffusion(denoiser.checkpoint, "ddim")
    _check_eta(eta)
    schedule = denoiser.schedule
    x = x_T
    yield SamplerState(0, steps, x, torch.zeros_like(x), math.inf, 0)
    for i, (t, t_prev) in enumerate(leading_timesteps(schedule.timesteps, steps)):
        x0, eps, _ = denoiser.predict(x, t)
        noise = _randn(tuple(x.shape), generator, str(x.device)) if eta > 0 else None
        x = ddim_step(x, eps, schedule.abar(t), schedule.abar(t_prev), eta=eta, noise=noise,
                      x0=x0 if denoiser.checkpoint.clip > 0 else None)
        yield SamplerState(i + 1, steps, x, x0, _sigma_of(schedule.abar(t_prev)), denoiser.evaluations)
    return x


def _sigma_of(abar: float) -> float:
    return ((1.0 - abar) / abar) ** 0.5


def _ode_grid(denoiser: Denoiser, steps: int) -> list[tuple[float, float]]:
    """``(time, time_next)`` pairs from noise to data: flow t = i/n; diffusion the leading timesteps."""
    if denoiser.checkpoint.is_flow:
        _check_steps(steps)
        return [(i / steps, (i + 1) / steps) for i in range(steps)]
    return [(float(t), float(p)) for t, p in leading_timesteps(denoiser.schedule.timesteps, steps)]


def _abar_at(denoiser: Denoiser, time_value: float) -> float:
    return denoiser.schedule.abar(int(time_value))


def sample_ode(denoiser: Denoiser, x_T: torch.Tensor, *, steps: int, method: Literal["euler", "heun"] = "euler",
               ) -> Generator[SamplerState, None, torch.Tensor]:
    """Euler or Heun (Karras et al. 2022, Algorithm 1) on the sampling ODE.

    Flow matching: ``dx/dt = v(x, t)`` from t = 0 (noise) to 1 (data) with ``h = 1 / steps``;
    Heun averages the slopes at both ends (``x' = x + h (v(x, t) + v(x_e, t + h)) / 2``, ``x_e``
    the Euler guess). Diffusion: the probability-flow ODE in ``x~ = x / sqrt(abar)``,
    ``sigma = sqrt((1 - abar) / abar)``: ``dx~/dsigma = eps_hat`` over the leading timesteps; its
    Euler step is exactly DDIM with eta = 0, and Heun's correction is skipped at sigma = 0 (Karras).
    """
    x = x_T
    yield SamplerState(0, steps, x, torch.zeros_like(x), math.inf, 0)
    flow = denoiser.checkpoint.is_flow
    for i, (tc, tn) in enumerate(_ode_grid(denoiser, steps)):
        if flow:
            h = tn - tc
            x0, _, v = denoiser.predict(x, tc)
            x_next = x + h * v
            if method == "heun":
                _, _, v2 = denoiser.predict(x_next, tn)
                x_next = x + h * 0.5 * (v + v2)
            x = x_next
            level = _noise_level(tn, 1 - tn)
        else:
            a_c, a_n = _abar_at(denoiser, tc), (1.0 if tn < 0 else _abar_at(denoiser, tn))
            s_c, s_n = _sigma_of(a_c), _sigma_of(a_n)
            x0, eps, _ = denoiser.predict(x, tc)
            xt = x / a_c ** 0.5 + (s_n - s_c) * eps  # Euler in x~
            if method == "heun" and s_n > 0:
                _, eps2, _ = denoiser.predict(xt * a_n ** 0.5, tn)
                xt = x / a_c ** 0.5 + (s_n - s_c) * 0.5 * (eps + eps2)
            x = xt * a_n ** 0.5
            level = s_n
        yield SamplerState(i + 1, steps, x, x0, level, denoiser.evaluations)
    return x


def sample_sde(denoiser: Denoiser, x_T: torch.Tensor, *, steps: int, eta: float = 1.0,
               generator: torch.Generator) -> Generator[SamplerState, None, torch.Tensor]:
    """A stochastic sampler of the reverse SDE (Song et al. 2021) by ancestral steps (:func:`ancestral_step`).

    Runs on diffusion and flow-matching models alike; ``eta`` scales the fresh noise (0: the
    deterministic DDIM / Euler path, 1: the full reverse-SDE noise, the sample step's choice). On
    a diffusion model with eta = 1 each step draws DDPM's posterior over the stride.
    """
    _check_eta(eta)
    x = x_T
    yield SamplerState(0, steps, x, torch.zeros_like(x), math.inf, 0)
    for i, (tc, tn) in enumerate(_ode_grid(denoiser, steps)):
        a_c, b_c = denoiser.coefficients(tc)
        if denoiser.checkpoint.is_flow:
            a_n, b_n = tn, 1.0 - tn
        else:
            abar_n = 1.0 if tn < 0 else _abar_at(denoiser, tn)
            a_n, b_n = abar_n ** 0.5, (1.0 - abar_n) ** 0.5
        x0, eps, _ = denoiser.predict(x, tc)
        noise = _randn(tuple(x.shape), generator, str(x.device))
        x = ancestral_step(x0, eps, a_n, b_n, _noise_level(a_c, b_c), eta=eta, noise=noise)
        yield SamplerState(i + 1, steps, x, x0, _noise_level(a_n, b_n), denoiser.evaluations)
    return x


def _require_diffusion(checkpoint: DenoiserCheckpoint, sampler: str) -> None:
    if checkpoint.is_flow:
        raise InvalidControl("sampler", f"{sampler} needs a diffusion model (objective epsilon, x0 or v); this model "
                                        "was trained by flow matching: use euler, heun or sde")


def _check_eta(eta: float) -> None:
    if not 0.0 <= float(eta) <= 1.0:
        raise InvalidControl("eta", f"must be in [0, 1] (0: deterministic DDIM, 1: DDPM's variance), got {eta}")


def run_sampler(sampler: str, denoiser: Denoiser, x_T: torch.Tensor, *, steps: int, eta: float,
                generator: torch.Generator) -> Iterator[SamplerState]:
    """The generator of sampler ``sampler`` ("ddpm", "ddim", "euler", "heun", "sde"); ``eta`` is DDIM's (the
    SDE sampler always adds the full reverse-SDE noise: call :func:`sample_sde` for another eta)."""
    _check_steps(steps, None if denoiser.checkpoint.is_flow else denoiser.schedule.timesteps)
    if sampler == "ddpm":
        return sample_ddpm(denoiser, x_T, steps=steps, generator=generator)
    if sampler == "ddim":
        return sample_ddim(denoiser, x_T, steps=steps, eta=eta, generator=generator)
    if sampler in ("euler", "heun"):
        return sample_ode(denoiser, x_T, steps=steps, method=sampler)
    if sampler == "sde":
        return sample_sde(denoiser, x_T, steps=steps, eta=1.0, generator=generator)
    raise InvalidControl("sampler", f"must be one of ddpm, ddim, euler, heun, sde; got {sampler!r}")


# ----------------------------------------------------------------------------------------------------
# The sample step
# ----------------------------------------------------------------------------------------------------
@step_result
class SampleResult:
    """Result of :func:`sample`."""

    samples: PointCloud | Image
    predicted_x0: PointCloud | Image
    generated: np.ndarray
    generated_labels: np.ndarray
    trace: SamplingTrace
    sampling_seconds: float = metric("wall-clock sampling time", unit="s")
    evaluations: int = metric("network evaluations per sample")


def sample(model: DenoiserCheckpoint, schedule: NoiseSchedule, training_data: TrainingData, *,
           sampler: SamplerName = "ddim", steps: Annotated[int, Range(1, 4000)] = 50,
           eta: Annotated[float, Range(0.0, 1.0)] = 0.0,
           guidance_scale: Annotated[float, Range(0.0, 20.0)] = 0.0,
           label: Annotated[int, Range(-1, 1000)] = -1,
           count: Annotated[int, Range(1, 20000)] = 1000,
           rng: np.random.Generator, device: str = "cpu") -> Generator[Progress, None, SampleResult]:
    """Draw ``count`` samples from the trained model, one sampler step at a time.

    Starts from ``x_T ~ N(0, I)`` (flow: ``x_0`` at t = 0) and runs DDPM ancestral sampling, DDIM
    with ``eta``, Euler or Heun on the ODE, or the stochastic SDE sampler (see the ``sample_*``
    generators). A conditional model samples class ``label`` (-1: classes 0, 1, 2 ... in turn)
    with classifier-free guidance of scale ``guidance_scale`` (w in ``(1 + w) eps_c - w eps_u``).
    Yields after every step; the progress carries the current ``x_t`` and the predicted ``x0`` as
    previews (``samples``, ``predicted_x0``) at every step up to 100 steps, every ``steps // 100``-th beyond.

    Args:
        sampler: ddpm, ddim, euler, heun or sde.
        steps: sampler steps (ddpm and ddim: at most T; 1000 ddpm steps is Ho et al.'s sampler).
        eta: stochasticity of ddim (0 deterministic, 1 DDPM's variance); sde always adds the full noise.
        guidance_scale: classifier-free guidance w (conditional models only).
        label: the class to draw (-1: all classes in turn; conditional models only).
        count: number of samples.
    """
    data = _training_data(training_data)
    checkpoint = check_checkpoint(model, data)
    sched = _schedule(schedule)
    _check_eta(eta)
    if not checkpoint.is_flow and checkpoint.timesteps != sched.timesteps:
        raise InvalidValue("schedule", f"the model was trained on a schedule of {checkpoint.timesteps} timesteps, "
                                       f"this one has {sched.timesteps}: rerun train_denoiser")
    if label >= 0 and not checkpoint.conditional:
        raise InvalidControl("label", "this model was trained without labels: use -1")
    if label >= checkpoint.classes > 0:
        raise InvalidControl("label", f"must be -1 or in [0, {checkpoint.classes - 1}], got {label}")
    labels = None
    requested = np.full(count, -1, dtype=np.int64)
    if checkpoint.conditional:
        requested = np.full(count, label) if label >= 0 else np.arange(count) % checkpoint.classes
        labels = torch.as_tensor(requested, device=device)
    denoiser = Denoiser(checkpoint, sched, device=device, labels=labels, guidance_scale=guidance_scale)
    generator = _torch_generator(rng)
    x_T = _randn((count, checkpoint.dim), generator, device)
    started = time.perf_counter()
    traced = min(count, TRACE_DIGITS if data.kind == "digits" else TRACE_POINTS)
    keep = set(np.unique(np.round(np.linspace(0, steps, min(MAX_TRACE_FRAMES, steps + 1))).astype(int)).tolist())
    preview_every = max(1, steps // 100)
    frames: list[tuple[int, float, np.ndarray, np.ndarray]] = []
    generator_of_states = run_sampler(sampler, denoiser, x_T, steps=steps, eta=eta, generator=generator)
    state = None
    for state in generator_of_states:
        if state.step in keep:
            frames.append((state.step, state.noise_level, _to_data(state.x_t[:traced], checkpoint),
                           _to_data(state.x0[:traced], checkpoint)))
        if state.step > 0:
            values = {}
            if state.step % preview_every == 0 or state.step == steps:  # at most about 100 previews drawn
                values = {"samples": _display(_to_data(state.x_t[:traced], checkpoint), data.kind),
                          "predicted_x0": _display(_to_data(state.x0[:traced], checkpoint), data.kind)}
            yield Progress(iteration=state.step, total=steps, message=f"{sampler} step", values=values)
    seconds = time.perf_counter() - started
    final = _to_data(state.x_t, checkpoint)
    if data.kind == "digits":
        final = np.clip(final, 0.0, 1.0)
    trace = SamplingTrace(np.stack([f[2] for f in frames]), np.stack([f[3] for f in frames]),
                          np.array([f[0] for f in frames]), np.array([f[1] for f in frames]),
                          requested[:traced], data.kind, sampler, steps)
    return SampleResult(_display(final, data.kind), _display(_to_data(state.x0, checkpoint), data.kind), final,
                        requested, trace, seconds, denoiser.evaluations)


def check_checkpoint(model: Any, data: TrainingData) -> DenoiserCheckpoint:
    """``model`` if it is a checkpoint trained on ``data``'s dataset, else a clear :class:`InvalidValue`."""
    if not isinstance(model, DenoiserCheckpoint):
        raise InvalidValue("model", f"expected a DenoiserCheckpoint, got {type(model).__name__}")
    if model.dataset != data.name or model.dim != data.dim:
        raise InvalidValue("model", f"this checkpoint was trained on dataset {model.dataset!r} ({model.dim}-D) but "
                                    f"the session's data are {data.name!r} ({data.dim}-D): run train_denoiser on "
                                    "these data or open a session on that dataset")
    return model


def _to_data(x: torch.Tensor, checkpoint: DenoiserCheckpoint) -> np.ndarray:
    return x.detach().cpu().numpy().astype(np.float64) * checkpoint.scale + checkpoint.mean


def _as_3d(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return x if x.shape[1] == 3 else np.concatenate([x, np.zeros((len(x), 3 - x.shape[1]))], axis=1)


def digit_grid(x: np.ndarray, *, columns: int = 10, gap: int = 1) -> Image:
    """Flattened 8 x 8 digits ``(N, 64)`` in [0, 1] as one grid image (``columns`` per row, ``gap`` px apart)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0, 1).reshape(-1, *DIGIT_SHAPE)
    rows = max(1, math.ceil(len(x) / columns))
    h, w = DIGIT_SHAPE
    grid = np.zeros((rows * (h + gap) + gap, columns * (w + gap) + gap), dtype=np.float32)
    for i, digit in enumerate(x):
        r, c = divmod(i, columns)
        grid[gap + r * (h + gap):gap + r * (h + gap) + h, gap + c * (w + gap):gap + c * (w + gap) + w] = digit
    return Image(grid, name="digits")


def _display(x: np.ndarray, kind: str) -> PointCloud | Image:
    if kind == "digits":
        return digit_grid(x[:TRACE_DIGITS])
    return PointCloud(_as_3d(x))


def _training_data(value: Any) -> TrainingData:
    if not isinstance(value, TrainingData):
        raise InvalidValue("training_data", f"expected TrainingData, got {type(value).__name__}")
    return value


def _schedule(value: Any) -> NoiseSchedule:
    if not isinstance(value, NoiseSchedule):
        raise InvalidValue("schedule", f"expected a NoiseSchedule, got {type(value).__name__}")
    return value


# ----------------------------------------------------------------------------------------------------
# Lesson steps: one DDIM update on guided noise predictions
# ----------------------------------------------------------------------------------------------------
@step_result
class UpdateInputs:
    """Result of :func:`prepare_update`: what one guided DDIM step reads."""

    x_t: np.ndarray
    eps_conditional: np.ndarray
    eps_unconditional: np.ndarray
    step_alphas: np.ndarray
    update_noise: np.ndarray


def prepare_update(model: DenoiserCheckpoint, schedule: NoiseSchedule, training_data: TrainingData, *,
                   timestep: Annotated[int, Range(0, 3999)] = 600, stride: Annotated[int, Range(1, 4000)] = 20,
                   label: Annotated[int, Range(0, 1000)] = 3, count: Annotated[int, Range(1, 4096)] = 64,
                   rng: np.random.Generator, device: str = "cpu") -> UpdateInputs:
    """Noised training samples at ``timestep`` and the model's noise predictions, for one guided DDIM step.

    ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps`` for ``count`` training samples (normalized
    units); ``eps_conditional`` is the model's eps for class ``label``, ``eps_unconditional`` for
    the null label (for an unconditional model both are its eps). ``step_alphas`` is
    ``[abar_t, abar_prev]`` with ``t_prev = timestep - stride`` (abar_prev = 1 when negative);
    ``update_noise`` the z a stochastic (eta > 0) update adds. Output arrays are float64 ``(count, D)``.

    Args:
        timestep: t of x_t.
        stride: how far the update jumps: t_prev = t - stride.
        label: the class of the conditional prediction.
        count: samples.
    """
    data = _training_data(training_data)
    checkpoint = check_checkpoint(model, data)
    sched = _schedule(schedule)
    _require_diffusion(checkpoint, "a DDIM update")
    if not 0 <= timestep < sched.timesteps:
        raise InvalidControl("timestep", f"must be in [0, {sched.timesteps - 1}], got {timestep}")
    if checkpoint.conditional and label >= checkpoint.classes:
        raise InvalidControl("label", f"must be in [0, {checkpoint.classes - 1}], got {label}")
    mean, scale = checkpoint.mean, checkpoint.scale
    pick = rng.choice(len(data.x), size=count, replace=count > len(data.x))
    x0 = (data.x[pick] - mean) / scale
    abar_t, abar_prev = sched.abar(timestep), sched.abar(timestep - stride)
    x_t = q_sample(x0, abar_t, rng.standard_normal(x0.shape))
    denoiser = Denoiser(checkpoint, sched, device=device, labels=torch.zeros(count, dtype=torch.long, device=device))
    xt = torch.as_tensor(x_t, dtype=torch.float32, device=device)
    tau = torch.full((count,), float(timestep), device=device)
    with torch.no_grad():
        def eps_for(labels: torch.Tensor | None) -> np.ndarray:
            out = denoiser.net(xt, tau, labels)
            a, b = denoiser.coefficients(timestep)
            eps = {"epsilon": lambda: out, "x0": lambda: (xt - a * out) / max(b, 1e-12),
                   "v": lambda: a * out + b * xt}[checkpoint.objective]()
            return eps.cpu().numpy().astype(np.float64)

        if checkpoint.conditional:
            eps_c = eps_for(torch.full((count,), label, device=device))
            eps_u = eps_for(torch.full((count,), checkpoint.classes, device=device))
        else:
            eps_c = eps_u = eps_for(None)
    return UpdateInputs(x_t, eps_c, eps_u.copy(), np.array([abar_t, abar_prev]), rng.standard_normal(x0.shape))


def ddim_update(x_t: np.ndarray, eps_guided: np.ndarray, step_alphas: np.ndarray, update_noise: np.ndarray, *,
                eta: Annotated[float, Range(0.0, 1.0)] = 0.0) -> Annotated[np.ndarray, "x_prev"]:
    """One DDIM step from ``x_t`` to ``x_prev`` given the noise prediction (Song et al. 2021, eqs. 12 and 16).

    ``step_alphas = [abar_t, abar_prev]``; ``x_t``, ``eps_guided``, ``update_noise`` ``(N, D)``.
    See :func:`ddim_step` for the equations; diffusers' ``DDIMScheduler.step`` computes the same.

    Args:
        eta: 0 deterministic DDIM, 1 DDPM's variance.
    """
    _check_eta(eta)
    abar_t, abar_prev = (float(a) for a in np.asarray(step_alphas, dtype=np.float64).reshape(2))
    return np.asarray(ddim_step(np.asarray(x_t, np.float64), np.asarray(eps_guided, np.float64), abar_t, abar_prev,
                                eta=eta, noise=np.asarray(update_noise, np.float64)), dtype=np.float64)


# ----------------------------------------------------------------------------------------------------
# Metrics
# ----------------------------------------------------------------------------------------------------
def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance of point sets ``(N, D)`` and ``(M, D)``: mean nearest-neighbour
    distance from a to b plus from b to a (``scipy.spatial.cKDTree`` queries)."""
    from scipy.spatial import cKDTree

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def mmd_rbf(a: np.ndarray, b: np.ndarray, *, bandwidth: float | None = None, max_points: int = 1000,
            seed: int = 0) -> float:
    """Maximum mean discrepancy with a Gaussian kernel (Gretton et al. 2012, biased estimate, square root).

    ``k(x, y) = exp(-|x - y|^2 / (2 h^2))``, ``h`` the median pairwise distance of ``b`` unless
    given; at most ``max_points`` of each set (a fixed random subset).
    """
    rng = np.random.default_rng(seed)
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a = a[rng.permutation(len(a))[:max_points]]
    b = b[rng.permutation(len(b))[:max_points]]

    def sq(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        return np.maximum((p ** 2).sum(1)[:, None] + (q ** 2).sum(1)[None] - 2 * p @ q.T, 0.0)

    bb = sq(b, b)
    h = bandwidth if bandwidth is not None else float(np.sqrt(np.median(bb[np.triu_indices(len(b), 1)])))
    k = lambda d: np.exp(-d / (2 * h * h))  # noqa: E731
    value = k(sq(a, a)).mean() + k(bb).mean() - 2 * k(sq(a, b)).mean()
    return float(np.sqrt(max(value, 0.0)))


def train_digit_classifier(x: np.ndarray, labels: np.ndarray) -> Any:
    """A small classifier of 8 x 8 digits ``(N, 64)`` in [0, 1]: multinomial logistic regression
    (``sklearn.linear_model.LogisticRegression``), about 96 % accurate on held-out digits."""
    from sklearn.linear_model import LogisticRegression

    return LogisticRegression(max_iter=2000, C=1.0).fit(np.asarray(x), np.asarray(labels))


@functools.lru_cache(maxsize=8)
def _cached_digit_classifier(seed: int, held_out_fraction: float) -> Any:
    """The classifier of :func:`digits` with this split (trained once per split: sessions share it)."""
    loaded_x, loaded_labels = _digits_split(seed, held_out_fraction)
    return train_digit_classifier(loaded_x, loaded_labels)


def _digits_split(seed: int, held_out_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    from sklearn.datasets import load_digits

    bunch = load_digits()
    order = np.random.default_rng(seed).permutation(len(bunch.data))
    held = int(round(len(order) * held_out_fraction))
    return np.asarray(bunch.data, dtype=np.float64)[order[held:]] / 16.0, np.asarray(bunch.target)[order[held:]]


def diversity_score(x: np.ndarray, reference: np.ndarray, *, max_points: int = 500) -> float:
    """Mean pairwise distance of samples ``(N, D)`` over that of reference data.

    1: as diverse as the data; 0: every sample the same.
    """
    def mean_pairwise(p: np.ndarray) -> float:
        p = np.asarray(p, dtype=np.float64)[:max_points]
        d = np.sqrt(np.maximum((p ** 2).sum(1)[:, None] + (p ** 2).sum(1)[None] - 2 * p @ p.T, 0))
        return float(d[np.triu_indices(len(p), 1)].mean()) if len(p) > 1 else 0.0

    return mean_pairwise(x) / max(mean_pairwise(reference), 1e-12)


def digit_metrics(generated: np.ndarray, labels: np.ndarray, truth: dict[str, Any]) -> dict[str, float]:
    """``digit_accuracy``: how often the module's classifier agrees with the requested class (-1 labels
    skipped); ``diversity``: :func:`diversity_score` within each requested class against the held-out
    digits of that class, averaged (without labels: over all samples). Guidance trades one for the other."""
    generated = np.asarray(generated, dtype=np.float64)
    labels = np.asarray(labels)
    held = np.asarray(truth["held_out"])
    held_labels = truth.get("held_out_labels")
    asked = labels >= 0
    metrics: dict[str, float] = {}
    if asked.any() and held_labels is not None:
        scores = [diversity_score(generated[labels == c], held[np.asarray(held_labels) == c])
                  for c in np.unique(labels[asked]) if np.sum(labels == c) > 1 and np.sum(held_labels == c) > 1]
        metrics["diversity"] = float(np.mean(scores)) if scores else 0.0
    else:
        metrics["diversity"] = diversity_score(generated, held)
    if asked.any() and "classifier" in truth:
        predicted = truth["classifier"].predict(generated[asked])
        metrics["digit_accuracy"] = float(np.mean(predicted == labels[asked]))
    return metrics


def evaluate_sample(state: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Points: Chamfer distance and MMD of the samples to held-out points; digits: classifier accuracy, diversity."""
    if "held_out" not in truth:
        return {}
    data = state["training_data"]
    generated = np.asarray(state["generated"])
    if data.kind == "digits":
        return digit_metrics(generated, state["generated_labels"], truth)
    held = np.asarray(truth["held_out"])
    return {"chamfer": chamfer_distance(generated, held), "mmd": mmd_rbf(generated, held)}


PIPELINE = Pipeline.build(
    name="diffusion",
    title="Diffusion sampling",
    summary="Generative models made watchable: noise data with the forward process (linear or cosine schedule), "
            "train a small denoiser (epsilon, x0, v or flow matching, optionally class-conditional), then watch "
            "DDPM, DDIM, Euler/Heun ODE and SDE samplers turn noise into a 3D shape or into digits, with "
            "classifier-free guidance.",
    steps=[noise_schedule, forward_noising, train_denoiser, sample, prepare_update, combine_guidance, ddim_update],
    datasets=[shape_3d, two_moons, swiss_roll, digits],
    evaluations={"sample": evaluate_sample},
)

__all__ = ["PIPELINE", "TrainingData", "NoiseSchedule", "DenoiserCheckpoint", "SamplingTrace", "SamplerState",
           "Denoiser", "DenoiserMLP", "shape_3d", "two_moons", "swiss_roll", "digits", "make_schedule",
           "linear_betas", "cosine_betas", "signal_to_noise", "noise_schedule", "forward_noising", "q_sample",
           "train_denoiser", "training_target", "flow_matching_pair", "combine_guidance", "ddim_step", "ddpm_step",
           "ancestral_step", "predicted_x0_from_eps", "leading_timesteps", "sample_ddpm", "sample_ddim", "sample_ode",
           "sample_sde", "run_sampler", "sample", "check_checkpoint", "prepare_update", "ddim_update",
           "chamfer_distance", "mmd_rbf", "train_digit_classifier", "diversity_score", "digit_metrics",
           "evaluate_sample", "digit_grid", "network_from", "timestep_embedding", "normalization"]
