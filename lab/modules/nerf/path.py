"""A camera path for novel views: an orbit about the scene centre at the training cameras' mean height
(the "spiral" / "360" render paths of Mildenhall et al. 2020's code and nerfstudio's orbit).

"Up" is not known from the poses' frame alone (a ``transforms.json`` may have any world frame), so it is
taken from the cameras as nerfstudio's ``auto_orient`` does: the mean of their up vectors (the world
direction of each camera's ``-y`` axis, OpenCV's image up). The orbit lies in the plane perpendicular to
it, at the cameras' mean height above the centre and their mean horizontal distance from it, and every
camera of the path looks at the centre with that up (so image rows run down the world's vertical); the
first frame is at the azimuth of training camera 0.
"""

from __future__ import annotations

import numpy as np

from lab.core import Cameras, InvalidValue
from lab.data.scenes import orbit_cameras


def mean_up(cameras: Cameras) -> np.ndarray:
    """The unit mean of the cameras' up vectors ``-R[1]`` (world coordinates of the image's up), ``(3,)``."""
    up = -np.asarray(cameras.R)[:, 1, :].mean(axis=0)
    norm = float(np.linalg.norm(up))
    if not norm > 1e-6:
        raise InvalidValue("cameras", "the cameras' up vectors cancel out: no common up for an orbit")
    return up / norm


def orbit_path(cameras: Cameras, center: np.ndarray, frames: int, *, scale: float = 1.0) -> Cameras:
    """``frames`` cameras on a full circle about ``center`` (see the module docstring), with camera 0's
    intrinsics at ``scale`` times its resolution (pixel centres kept: ``cx' = (cx + 0.5) scale - 0.5``)."""
    up = mean_up(cameras)
    offsets = cameras.centers - np.asarray(center, dtype=np.float64)
    heights = offsets @ up
    horizontal = offsets - heights[:, None] * up
    radius = float(np.linalg.norm(horizontal, axis=1).mean())
    if not radius > 1e-9:
        raise InvalidValue("cameras", "the cameras stand on the axis through the centre: no orbit about it")
    K = np.array(cameras.K[0], dtype=np.float64)
    K[:2, :] *= scale
    K[:2, 2] += 0.5 * scale - 0.5
    width, height = max(1, round(cameras.width * scale)), max(1, round(cameras.height * scale))
    path = orbit_cameras(np.asarray(center, dtype=np.float64), num_views=frames, radius=radius,
                         elevation=float(heights.mean()), start_deg=0.0, up=up, K=K, width=width,
                         height=height)
    # turn the orbit so that frame 0 stands where training camera 0 does
    first = path.centers[0] - center
    first = first - (first @ up) * up
    angle = float(np.arctan2(np.cross(first, horizontal[0]) @ up, first @ horizontal[0]))
    return orbit_cameras(np.asarray(center, dtype=np.float64), num_views=frames, radius=radius,
                         elevation=float(heights.mean()), start_deg=float(np.degrees(angle)), up=up, K=K,
                         width=width, height=height)


__all__ = ["mean_up", "orbit_path"]
