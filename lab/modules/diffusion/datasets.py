"""The datasets of diffusion: points on 3D shapes and 2D curves, and scikit-learn's 8 x 8 digits (offline).

Each gives the state ``training_data`` (:class:`~lab.modules.diffusion.values.TrainingData`) and a
value to draw (``points`` or ``digits``); its truth holds held-out samples to measure the model's
samples against (and, for digits, a classifier that scores them).
"""

from __future__ import annotations

import functools
from typing import Annotated, Any, Literal

import numpy as np

from lab.core import Loaded, Mesh, PointCloud, Range
from lab.modules.diffusion.display import as_3d, digit_grid
from lab.modules.diffusion.evaluate import train_digit_classifier
from lab.modules.diffusion.values import TrainingData


def _points_loaded(x: np.ndarray, held: np.ndarray, name: str, description: str,
                   mesh: Mesh | None = None) -> Loaded:
    state: dict[str, Any] = {"training_data": TrainingData(x, "points", name), "points": PointCloud(as_3d(x))}
    if mesh is not None:
        state["mesh"] = mesh
    return Loaded(state=state, truth={"held_out": held}, description=description)


def shape_3d(*, shape: Literal["torus", "capsule", "box", "icosphere"] = "torus",
             count: Annotated[int, Range(100, 20000)] = 2000,
             held_out: Annotated[int, Range(100, 20000)] = 2000, seed: int = 0) -> Loaded:
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


def two_moons(*, count: Annotated[int, Range(100, 20000)] = 2000,
              held_out: Annotated[int, Range(100, 20000)] = 2000,
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


def swiss_roll(*, count: Annotated[int, Range(100, 20000)] = 2000,
               held_out: Annotated[int, Range(100, 20000)] = 2000,
               noise: Annotated[float, Range(0.0, 2.0)] = 0.2, dimensions: Literal[2, 3] = 3,
               seed: int = 0) -> Loaded:
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
    """scikit-learn's 1797 handwritten 8 x 8 digits, labels 0-9 (``sklearn.datasets.load_digits``, offline).

    Pixels are scaled to [0, 1]. A held-out part trains the small digit classifier that scores
    samples (:func:`~lab.modules.diffusion.evaluate.train_digit_classifier`) and measures their diversity.

    Args:
        held_out_fraction: the fraction of the digits kept apart.
        seed: seed of the split.
    """
    from sklearn.datasets import load_digits

    bunch = load_digits()
    x = np.asarray(bunch.data, dtype=np.float64) / 16.0
    labels = np.asarray(bunch.target, dtype=np.int64)
    order = np.random.default_rng(seed).permutation(len(x))
    held = round(len(x) * float(held_out_fraction))
    train, test = order[held:], order[:held]
    data = TrainingData(x[train], "digits", "digits", labels[train], 10)
    truth = {"held_out": x[test], "held_out_labels": labels[test],
             "classifier": _cached_digit_classifier(int(seed), float(held_out_fraction))}
    return Loaded(state={"training_data": data, "digits": digit_grid(x[train][:100])}, truth=truth,
                  description=f"{len(train)} 8x8 digits with labels ({held} held out)")


@functools.lru_cache(maxsize=8)
def _cached_digit_classifier(seed: int, held_out_fraction: float) -> Any:
    """The classifier of :func:`digits` with this split (trained once per split: sessions share it)."""
    loaded_x, loaded_labels = _digits_split(seed, held_out_fraction)
    return train_digit_classifier(loaded_x, loaded_labels)


def _digits_split(seed: int, held_out_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    from sklearn.datasets import load_digits

    bunch = load_digits()
    order = np.random.default_rng(seed).permutation(len(bunch.data))
    held = round(len(order) * held_out_fraction)
    train = order[held:]
    return np.asarray(bunch.data, dtype=np.float64)[train] / 16.0, np.asarray(bunch.target)[train]


__all__ = ["digits", "shape_3d", "swiss_roll", "two_moons"]
