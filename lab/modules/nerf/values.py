"""The typed values of NeRF that flow between steps (not drawn directly): bounds, rays, encoding, model.

Steps pass these by state name (``bounds``, ``rays``, ``encoding``, ``model``) instead of loose
arrays, and check what they read with the ``as_*`` functions below.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from lab.core import InvalidValue

_T = TypeVar("_T")


def check_near_far(near: float, far: float, field: str = "bounds") -> tuple[float, float]:
    """``(near, far)`` as floats if ``0 <= near < far`` and both are finite, else :class:`InvalidValue`."""
    near, far = float(near), float(far)
    if not (np.isfinite(near) and np.isfinite(far)):
        raise InvalidValue(field, f"near and far must be finite, got near={near}, far={far}")
    if near < 0:
        raise InvalidValue(field, f"near must be >= 0 (in front of the camera), got {near}")
    if near >= far:
        raise InvalidValue(field, f"near ({near:g}) must be less than far ({far:g}): every ray is sampled "
                                  "between them")
    return near, far


@dataclass(frozen=True, eq=False)
class SceneBounds:
    """Where the scene is: rays are sampled at depths ``near .. far`` (camera Z, scene units), and points
    are normalized to ``(X - center) / radius`` before the encoding (the object inside the unit ball,
    so that ``sin(2^0 pi p)`` spans at most one period over it)."""

    near: float
    far: float
    center: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        near, far = check_near_far(self.near, self.far)
        object.__setattr__(self, "near", near)
        object.__setattr__(self, "far", far)
        center = np.asarray(self.center, dtype=np.float64).reshape(-1)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise InvalidValue("bounds.center", f"expected 3 finite numbers, got {self.center!r}")
        object.__setattr__(self, "center", center)
        radius = float(self.radius)
        if not (np.isfinite(radius) and radius > 0):
            raise InvalidValue("bounds.radius", f"must be a positive number, got {self.radius!r}")
        object.__setattr__(self, "radius", radius)


@dataclass(frozen=True, eq=False)
class RayBundle:
    """Every training pixel's ray: ``origins`` and ``directions`` float32 ``(N, 3)`` (world; a direction's
    camera-frame z is 1, so the ray parameter ``t`` is the depth Z), the pixel's ``colors`` float32
    ``(N, 3)`` in [0, 1], the ``views`` ``(N,)`` it came from, and the scene's ``bounds``."""

    origins: np.ndarray
    directions: np.ndarray
    colors: np.ndarray
    views: np.ndarray
    bounds: SceneBounds

    def __post_init__(self) -> None:
        n = len(np.asarray(self.origins))
        for name in ("origins", "directions", "colors"):
            array = np.asarray(getattr(self, name), dtype=np.float32)
            if array.shape != (n, 3) or not np.all(np.isfinite(array)):
                raise InvalidValue(f"rays.{name}", f"expected finite ({n}, 3), got {array.shape}")
            object.__setattr__(self, name, array)
        object.__setattr__(self, "views", np.asarray(self.views, dtype=np.int64).reshape(n))
        if not isinstance(self.bounds, SceneBounds):
            raise InvalidValue("rays.bounds", f"expected SceneBounds, got {type(self.bounds).__name__}")

    def __len__(self) -> int:
        return len(self.origins)


@dataclass(frozen=True)
class EncodingConfig:
    """The positional encoding of Mildenhall et al. 2020, section 5.1: ``frequencies`` L for positions
    (their 10; 6 in the classic course project), ``direction_frequencies`` for view directions (their 4),
    and whether ``p`` itself joins ``gamma(p)`` (``include_input``, as their code does)."""

    frequencies: int = 6
    direction_frequencies: int = 4
    include_input: bool = True


@dataclass(frozen=True)
class FieldConfig:
    """The network and the sampling a checkpoint was trained with (see :class:`~.model.NerfMLP`)."""

    encoding: EncodingConfig
    hidden: int
    layers: int
    samples: int
    fine_samples: int


@dataclass(frozen=True, eq=False)
class NerfCheckpoint:
    """A trained radiance field: the network's ``weights`` (its state_dict as float32 numpy arrays), its
    ``config``, the scene ``bounds`` it was trained in and the ``background`` colour ``(3,)`` composited
    behind what the rays leave unabsorbed (white for object scenes)."""

    weights: dict[str, np.ndarray]
    config: FieldConfig
    bounds: SceneBounds
    background: np.ndarray

    def __post_init__(self) -> None:
        if not isinstance(self.weights, dict) or not self.weights:
            raise InvalidValue("model.weights", "a checkpoint needs the network's weights (a dict of arrays)")
        object.__setattr__(self, "weights", {str(k): np.asarray(v, dtype=np.float32)
                                             for k, v in self.weights.items()})
        background = np.asarray(self.background, dtype=np.float32).reshape(-1)
        if background.shape != (3,):
            raise InvalidValue("model.background", f"expected an RGB colour, got {self.background!r}")
        object.__setattr__(self, "background", background)


def _expect(value: Any, kind: type[_T], field: str, noun: str) -> _T:
    if not isinstance(value, kind):
        raise InvalidValue(field, f"expected {noun}, got {type(value).__name__}")
    return value


def as_bounds(value: Any) -> SceneBounds:
    """``value`` if it is :class:`SceneBounds`, else a clear :class:`InvalidValue`."""
    return _expect(value, SceneBounds, "bounds", "SceneBounds")


def as_rays(value: Any) -> RayBundle:
    """``value`` if it is a :class:`RayBundle`, else a clear :class:`InvalidValue`."""
    return _expect(value, RayBundle, "rays", "a RayBundle")


def as_encoding(value: Any) -> EncodingConfig:
    """``value`` if it is an :class:`EncodingConfig`, else a clear :class:`InvalidValue`."""
    return _expect(value, EncodingConfig, "encoding", "an EncodingConfig")


def as_checkpoint(value: Any) -> NerfCheckpoint:
    """``value`` if it is a :class:`NerfCheckpoint`, else a clear :class:`InvalidValue`."""
    return _expect(value, NerfCheckpoint, "model", "a NerfCheckpoint")


__all__ = ["EncodingConfig", "FieldConfig", "NerfCheckpoint", "RayBundle", "SceneBounds", "as_bounds",
           "as_checkpoint", "as_encoding", "as_rays", "check_near_far"]
