"""Splatting's datasets beyond the NeRF module's (which it uses as they are): the synthetic object with
3D points to start the Gaussians from, as a reconstruction would bring them (Kerbl et al. 2023 start from
COLMAP's sparse points, section 5).

The points are the object's surface seen by the training views: pixels drawn at random where a view hits
the object, lifted to the world by their exact depth (``X = R^T (z K^-1 (u, v, 1) - t)``), in that pixel's
colour, optionally jittered by Gaussian noise standing in for a reconstruction's error.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np

from lab.core import Cameras, Loaded, PointCloud, Range
from lab.geometry.camera import pixels_to_normalized
from lab.modules.nerf import synthetic_object


def surface_points(cameras: Cameras, depths: np.ndarray, images: np.ndarray, count: int,
                   rng: np.random.Generator) -> PointCloud:
    """``count`` points drawn uniformly among the pixels of ``cameras`` whose camera depth ``depths``
    ``(V, H, W)`` is finite, lifted to the world, coloured by ``images`` ``(V, H, W, 3)`` at that pixel."""
    views, rows, cols = np.nonzero(np.isfinite(depths))
    pick = rng.choice(len(views), min(count, len(views)), replace=False)
    views, rows, cols = views[pick], rows[pick], cols[pick]
    xyz = np.empty((len(pick), 3))
    for view in np.unique(views):
        at = views == view
        pixels = np.stack([cols[at], rows[at]], axis=1).astype(np.float64)
        normalized = pixels_to_normalized(pixels, cameras.K[view])
        z = depths[view, rows[at], cols[at]]
        camera = np.concatenate([normalized * z[:, None], z[:, None]], axis=1)
        xyz[at] = (camera - cameras.t[view]) @ cameras.R[view]
    return PointCloud(xyz, np.clip(images[views, rows, cols], 0.0, 1.0))


def object_with_points(*, size: Literal[100, 200] = 100, train_views: Annotated[int, Range(2, 200)] = 40,
                       test_views: Annotated[int, Range(1, 50)] = 8, seed: int = 0,
                       points: Annotated[int, Range(4, 200000)] = 2000,
                       noise: Annotated[float, Range(0.0, 1.0)] = 0.0) -> Loaded:
    """The NeRF module's synthetic object (the same views, cameras and truth) with ``sfm_points``: points of
    its surface seen by the training views (the module docstring), to start the Gaussians from.

    Args:
        size: image width and height in pixels.
        train_views: views to train on.
        test_views: held-out views to evaluate on.
        seed: seed of the textures and of the points drawn.
        points: surface points drawn.
        noise: standard deviation of the Gaussian noise added to each point (scene units).
    """
    loaded = synthetic_object(size=size, train_views=train_views, test_views=test_views, seed=seed)
    rng = np.random.default_rng(seed)
    images = np.stack([image.pixels for image in loaded.state["images"].images])
    cloud = surface_points(loaded.state["cameras"], loaded.truth["train_depths"], images, points, rng)
    if noise > 0:
        cloud = PointCloud(cloud.xyz + rng.normal(0.0, noise, cloud.xyz.shape), cloud.colors)
    state = {**loaded.state, "sfm_points": cloud}
    return Loaded(state, loaded.truth, f"{loaded.description}; {len(cloud)} surface points to start from"
                                       + (f" (noise {noise:g})" if noise > 0 else ""))


__all__ = ["object_with_points", "surface_points"]
