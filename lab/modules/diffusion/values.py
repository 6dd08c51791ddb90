"""The typed values of diffusion that are not drawn: the data to learn, the schedule, the model, a trace.

Steps pass these between them by state name (``training_data``, ``schedule``, ``model``, ``trace``)
instead of loose arrays, and each checks what it reads with the ``as_*`` functions below.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from lab.core import InvalidValue

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
    """The forward process: ``betas`` float64 ``(T,)`` and ``alphas_cumprod``
    ``abar_t = prod_{s<=t} (1 - beta_s)``."""

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
    """A trained denoiser: ``weights`` (the network's state_dict as float32 numpy arrays), its configuration.

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
    """What a sampler did, for scrubbing: ``x_t`` and ``x0`` float32 ``(F, M, D)``, data units, ``F`` frames.

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
        object.__setattr__(self, "noise_level",
                           np.asarray(self.noise_level, dtype=np.float64).reshape(len(x_t)))
        object.__setattr__(self, "labels", np.asarray(self.labels, dtype=np.int64).reshape(x_t.shape[1]))

    @property
    def frames(self) -> int:
        return len(self.x_t)


def as_training_data(value: Any) -> TrainingData:
    """``value`` if it is :class:`TrainingData`, else a clear :class:`InvalidValue`."""
    if not isinstance(value, TrainingData):
        raise InvalidValue("training_data", f"expected TrainingData, got {type(value).__name__}")
    return value


def as_schedule(value: Any) -> NoiseSchedule:
    """``value`` if it is a :class:`NoiseSchedule`, else a clear :class:`InvalidValue`."""
    if not isinstance(value, NoiseSchedule):
        raise InvalidValue("schedule", f"expected a NoiseSchedule, got {type(value).__name__}")
    return value


def check_checkpoint(model: Any, data: TrainingData) -> DenoiserCheckpoint:
    """``model`` if it is a checkpoint trained on ``data``'s dataset, else a clear :class:`InvalidValue`."""
    if not isinstance(model, DenoiserCheckpoint):
        raise InvalidValue("model", f"expected a DenoiserCheckpoint, got {type(model).__name__}")
    if model.dataset != data.name or model.dim != data.dim:
        raise InvalidValue("model", f"this checkpoint was trained on dataset {model.dataset!r} "
                                    f"({model.dim}-D) but the session's data are {data.name!r} "
                                    f"({data.dim}-D): run train_denoiser on these data or open a session on "
                                    "that dataset")
    return model


def normalization(data: TrainingData) -> tuple[np.ndarray, float]:
    """``(mean (D,), scale)``, ``x_norm = (x - mean) / scale``: digits to [-1, 1], points to unit spread."""
    if data.kind == "digits":
        return np.full(data.dim, 0.5), 0.5
    mean = data.x.mean(axis=0)
    return mean, float(np.sqrt(((data.x - mean) ** 2).mean()))


__all__ = ["DIFFUSION_OBJECTIVES", "DIGIT_SHAPE", "MAX_TRACE_FRAMES", "TIME_SCALE", "TRACE_DIGITS",
           "TRACE_POINTS", "DenoiserCheckpoint", "NoiseSchedule", "Objective", "SamplerName", "SamplingTrace",
           "TrainingData", "as_schedule", "as_training_data", "check_checkpoint", "normalization"]
