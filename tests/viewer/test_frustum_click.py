"""A click on the picture a camera frustum carries lands on the pixel it shows (issue 16, item 5): the
renderer turns the click's ray into that pixel (viser's frustum geometry), and an interaction may take it
(epipolar's explorer picks it, as on its own image planes); else the click selects the view."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lab.core.values import Cameras
from lab.viewer.renderers import frustum_click_pixel, frustum_plane_depth

WIDTH, HEIGHT, F = 640, 480, 500.0


def rig() -> Cameras:
    K = np.array([[[F, 0, WIDTH / 2], [0, F, HEIGHT / 2], [0, 0, 1.0]]] * 2)
    R = Rotation.from_rotvec([[0.0, 0.0, 0.0], [0.1, -0.3, 0.05]]).as_matrix()
    t = np.array([[0.0, 0.0, 0.0], [-1.0, 0.1, 0.2]])
    return Cameras(K=K, R=R, t=t, width=WIDTH, height=HEIGHT, image="images")


FOV = 2.0 * math.atan2(HEIGHT / 2.0, F)


def on_picture(cameras: Cameras, index: int, u: float, v: float, scale: float) -> np.ndarray:
    """The world point of the frustum's picture that shows pixel (u, v)."""
    depth = frustum_plane_depth(FOV, WIDTH / HEIGHT, scale)
    half = math.tan(FOV / 2.0)
    x = (u / WIDTH - 0.5) * 2.0 * half * (WIDTH / HEIGHT) * depth
    y = (v / HEIGHT - 0.5) * 2.0 * half * depth
    camera_point = np.array([x, y, depth])
    return cameras.R[index].T @ (camera_point - cameras.t[index])


@pytest.mark.parametrize("index", [0, 1])
@pytest.mark.parametrize("u,v", [(100.0, 50.0), (320.0, 240.0), (633.0, 470.0)])
def test_a_ray_through_the_picture_gives_back_the_pixel(index, u, v):
    cameras = rig()
    target = on_picture(cameras, index, u, v, scale=0.2)
    origin = target + np.array([0.7, -1.5, -3.0])  # a viewer's eye somewhere in front and above
    pixel = frustum_click_pixel(cameras, index, fov=FOV, scale=0.2, ray_origin=origin,
                                ray_direction=(target - origin) / np.linalg.norm(target - origin))
    np.testing.assert_allclose(pixel, (u, v), atol=1e-6)


def test_the_picture_lies_where_viser_draws_it():
    """viser scales a frustum to a fixed volume: depth z with half-height tan(fov/2) z and volume
    x y z / 3 = scale^3 (CameraFrustumVariants.tsx)."""
    depth = frustum_plane_depth(FOV, WIDTH / HEIGHT, 0.3)
    half = math.tan(FOV / 2.0)
    assert (half * depth) * (half * WIDTH / HEIGHT * depth) * depth / 3.0 == pytest.approx(0.3 ** 3)


def test_a_ray_that_misses_the_picture_or_looks_away_gives_no_pixel():
    cameras = rig()
    target = on_picture(cameras, 0, 320.0, 240.0, scale=0.2)
    assert frustum_click_pixel(cameras, 0, fov=FOV, scale=0.2, ray_origin=target + [0, 0, -1.0],
                               ray_direction=[0, 0, -1.0]) is None  # away from the picture
    outside = on_picture(cameras, 0, 900.0, 240.0, scale=0.2)
    origin = outside + np.array([0.0, 0.0, -2.0])
    assert frustum_click_pixel(cameras, 0, fov=FOV, scale=0.2, ray_origin=origin,
                               ray_direction=outside - origin) is None
    assert frustum_click_pixel(cameras, 0, fov=FOV, scale=0.2, ray_origin=None, ray_direction=None) is None


def test_the_epipolar_explorer_takes_a_click_on_a_frustum_of_the_session(server, store):
    from lab.modules.epipolar import PIPELINE
    from lab.viewer.app import ClientView, ModuleCatalog
    from lab.viewer.interactions.epipolar import EpipolarExplorer

    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    view.open_session(store.create(PIPELINE, "correspondences",
                                   {"num_points": 60, "noise_px": 0.5, "outlier_rate": 0.2, "seed": 3}))
    explorer = next(i for i in view.interactions if isinstance(i, EpipolarExplorer))
    assert view._pixel_clicked("images", 1, np.array([200.0, 150.0]))
    assert explorer.last_pick is not None and explorer.last_pick.image == 2
    np.testing.assert_allclose(explorer.last_pick.pixel, (200.0, 150.0))
    assert not view._pixel_clicked("other_images", 0, np.array([1.0, 1.0]))  # not the pair: selects the view
