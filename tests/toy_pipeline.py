"""A tiny pipeline for testing the core and the front ends without a real module's cost."""

from __future__ import annotations

from typing import Annotated, Generator, Literal

import numpy as np

from lab.core.step import step_result
from lab.core import Image, ImageSet, Loaded, Pipeline, PointCloud, Progress, Range, metric


@step_result
class Noisy:
    """Result of :func:`add_noise`."""

    noisy: ImageSet
    mean_abs_change: float = metric("mean absolute change", unit="intensity")


def add_noise(images: ImageSet, *, sigma: Annotated[float, Range(0.0, 1.0)] = 0.1,
              mode: Literal["gaussian", "uniform"] = "gaussian", rng: np.random.Generator) -> Noisy:
    """Add noise to every image.

    Args:
        sigma: standard deviation of the noise.
        mode: noise distribution.
    """
    out = []
    change = []
    for image in images.images:
        if mode == "gaussian":
            noise = rng.normal(0.0, sigma, image.pixels.shape)
        else:
            noise = rng.uniform(-sigma, sigma, image.pixels.shape)
        pixels = np.clip(image.pixels + noise, 0, 1).astype(np.float32)
        change.append(np.abs(pixels - image.pixels).mean())
        out.append(Image(pixels, image.name))
    return Noisy(ImageSet(tuple(out)), float(np.mean(change)))


def mean_intensity(noisy: ImageSet, *, scale: Annotated[int, Range(1, 10)] = 1) -> Annotated[np.ndarray, "means"]:
    """Mean intensity per image, times ``scale``."""
    return np.array([im.pixels.mean() * scale for im in noisy.images])


@step_result
class Lifted:
    cloud: PointCloud
    final_loss: float = metric("loss at the last iteration")


def lift(means: np.ndarray, *, iterations: Annotated[int, Range(1, 1000)] = 5) -> Generator[Progress, None, Lifted]:
    """A long step: yields progress every iteration."""
    loss = 1.0
    for i in range(iterations):
        loss *= 0.5
        yield Progress(iteration=i + 1, total=iterations, loss=loss)
    xyz = np.stack([means, means, np.arange(len(means), dtype=float)], axis=1)
    return Lifted(PointCloud(xyz), loss)


def gradients(*, count: Annotated[int, Range(1, 8)] = 3, size: Annotated[int, Range(2, 256)] = 16) -> Loaded:
    """Horizontal gradient images; truth is each image's mean."""
    images = tuple(Image(np.tile(np.linspace(0, (i + 1) / count, size, dtype=np.float32), (size, 1)), f"g{i}")
                   for i in range(count))
    return Loaded({"images": ImageSet(images)}, {"means": np.array([im.pixels.mean() for im in images])})


def evaluate_means(state, truth):
    if "means" not in truth:
        return {}
    return {"means_abs_error": float(np.abs(state["means"] - truth["means"]).max())}


TOY = Pipeline.build(name="toy", title="Toy", summary="A pipeline for tests.",
                     steps=[add_noise, mean_intensity, lift], datasets=[gradients],
                     evaluations={"mean_intensity": evaluate_means})
