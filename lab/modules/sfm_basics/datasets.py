"""The dataset of the SfM lesson pipeline: random points seen by cameras on an orbit, projected exactly."""

from __future__ import annotations

from typing import Annotated

import numpy as np

from lab.core import Loaded, Points2D, Range
from lab.data.scenes.cameras import intrinsics, orbit_cameras


def synthetic(*, num_points: Annotated[int, Range(6, 2000)] = 60, num_views: Annotated[int, Range(2, 30)] = 6,
              noise_px: Annotated[float, Range(0.0, 20.0)] = 1.0,
              map_noise: Annotated[float, Range(0.0, 1.0)] = 0.05,
              visibility: Annotated[float, Range(0.3, 1.0)] = 0.8,
              outlier_rate: Annotated[float, Range(0.0, 0.5)] = 0.0,
              seed: int = 0) -> Loaded:
    """Random 3D points in a box seen by cameras on an orbit, projected exactly, plus pixel noise.

    The points are uniform in a 2 m cube centred at ``(8, 5, 1)`` (the world origin is a corner
    of the site, about 9 m away, behind some of the cameras); ``num_views`` cameras (640 x 480, 60 degree
    field of view)
    sit on a circle of radius 4.5 m, 1.5 m up, around the cube's centre and look at it, each eye
    and look-at point jittered by 0.1 m. Each camera sees each point with probability
    ``visibility`` (every point is seen by at least two cameras and every camera sees at least 12
    points). Pixels are the exact projections plus Gaussian noise of ``noise_px``; a share
    ``outlier_rate`` of the observations is replaced by uniform random pixels.

    Args:
        num_points: 3D points N.
        num_views: cameras V.
        noise_px: standard deviation of the pixel noise.
        map_noise: standard deviation (metres) of the noise on the known 3D points ``points3d``
            given to the PnP step (the "map" an incremental reconstruction has so far).
        visibility: probability that a camera sees a point.
        outlier_rate: share of observations replaced by random pixels.
        seed: the random seed.

    Truth: ``R`` (V, 3, 3), ``t`` (V, 3), ``X`` (N, 3) (the exact points), ``pixels`` (M, 2) (the
    exact projections of the observations).
    """
    rng = np.random.default_rng(seed)
    center = np.array([8.0, 5.0, 1.0])
    X = center + rng.uniform(-1.0, 1.0, size=(num_points, 3))
    width, height = 640, 480
    K = intrinsics(width=width, height=height)
    cameras = orbit_cameras(center, num_views=num_views, radius=4.5, elevation=1.5,
                            start_deg=float(rng.uniform(0.0, 360.0)), K=K, width=width, height=height,
                            jitter=0.1, seed=int(rng.integers(2**31)))
    R, t = cameras.R, cameras.t
    seen = rng.random((num_views, num_points)) < visibility
    for n in np.flatnonzero(seen.sum(axis=0) < 2):  # every point in at least two views
        seen[rng.choice(num_views, size=2, replace=False), n] = True
    for v in np.flatnonzero(seen.sum(axis=1) < 12):  # every camera sees enough points for PnP
        seen[v, rng.choice(num_points, size=min(12, num_points), replace=False)] = True
    view, ids = np.nonzero(seen)  # ordered by camera, then point
    Xc = np.einsum("mij,mj->mi", R[view], X[ids]) + t[view]
    exact = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2]
    pixels = exact + rng.normal(0.0, noise_px, size=exact.shape)
    outliers = rng.random(len(pixels)) < outlier_rate
    pixels[outliers] = rng.uniform((0.0, 0.0), (width - 1.0, height - 1.0), size=(int(outliers.sum()), 2))
    observations = Points2D(pixels, view=view, ids=ids, image="")
    state = {
        "K": K, "image_size": np.array([width, height]),
        "points3d": X + rng.normal(0.0, map_noise, size=X.shape),
        "observations": observations, "camera_indices": view.astype(np.int64),
        "point_indices": ids.astype(np.int64), "num_cameras": int(num_views), "num_points": int(num_points),
    }
    truth = {"R": R, "t": t, "X": X, "pixels": exact}
    return Loaded(state, truth, description=f"{num_points} points, {num_views} cameras on an orbit, "
                                            f"{len(view)} observations, {noise_px:g} px noise")

