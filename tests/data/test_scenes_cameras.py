"""lab.data.scenes: camera paths (orbit, forward motion, stereo rig) as lab.core.Cameras."""

import numpy as np
import pytest

from lab.core import Cameras, InvalidValue
from lab.data.scenes import (DEFAULT_FOV_DEG, forward_cameras, intrinsics, named_scene, orbit_cameras,
                             stereo_rig)
from lab.geometry.camera import project_points
from lab.geometry.rotations import rotation_angle_deg


def test_intrinsics_default_to_a_60_degree_view_centred_on_the_image():
    K = intrinsics(width=640, height=480)
    np.testing.assert_allclose(K, [[320 / np.tan(np.radians(DEFAULT_FOV_DEG / 2)), 0, 319.5],
                                   [0, 320 / np.tan(np.radians(DEFAULT_FOV_DEG / 2)), 239.5], [0, 0, 1]])
    np.testing.assert_allclose(intrinsics(width=100, height=80, fx=50.0, fy=60.0, cx=10.0, cy=20.0),
                               [[50, 0, 10], [0, 60, 20], [0, 0, 1]])


def test_orbit_cameras_circle_the_centre_and_look_at_it():
    centre = np.array([1.0, -2.0, 0.5])
    cams = orbit_cameras(centre, num_views=6, radius=2.5, elevation=0.8, width=320, height=240)
    assert isinstance(cams, Cameras) and len(cams) == 6
    assert cams.K.shape == (6, 3, 3) and cams.width == 320 and cams.height == 240 and cams.dist is None
    offsets = cams.centers - centre
    np.testing.assert_allclose(offsets[:, 2], 0.8)
    np.testing.assert_allclose(np.linalg.norm(offsets[:, :2], axis=1), 2.5)
    azimuth = np.degrees(np.arctan2(offsets[:, 1], offsets[:, 0]))
    np.testing.assert_allclose(np.diff(np.unwrap(np.radians(azimuth))), np.radians(60.0))
    for k in range(6):
        np.testing.assert_allclose(project_points(centre[None], cams.K[k], None, cams.R[k], cams.t[k])[0],
                                   cams.K[k][:2, 2], atol=1e-9)  # the centre is on the optical axis
        assert np.allclose(np.linalg.det(cams.R[k]), 1.0)
        up_in_image = cams.R[k] @ np.array([0.0, 0.0, 1.0])
        assert up_in_image[1] < 0  # world up points up in the image (-y)


def test_orbit_of_a_scene_starts_at_its_home_and_partial_arcs_include_both_ends():
    scene = named_scene("room")
    cams = orbit_cameras(scene, num_views=3, arc_deg=20.0, width=64, height=48)
    np.testing.assert_allclose(cams.centers[0], scene.home, atol=1e-12)
    np.testing.assert_allclose(rotation_angle_deg(cams.R[0], cams.R[2]), 20.0, atol=1e-6)
    np.testing.assert_allclose(rotation_angle_deg(cams.R[0], cams.R[1]), 10.0, atol=1e-6)


def test_orbit_jitter_is_reproducible_per_seed():
    a = orbit_cameras(np.zeros(3), num_views=4, jitter=0.05, seed=1)
    b = orbit_cameras(np.zeros(3), num_views=4, jitter=0.05, seed=1)
    c = orbit_cameras(np.zeros(3), num_views=4, jitter=0.05, seed=2)
    exact = orbit_cameras(np.zeros(3), num_views=4)
    np.testing.assert_array_equal(a.t, b.t)
    assert not np.allclose(a.t, c.t)
    moved = np.linalg.norm(a.centers - exact.centers, axis=1)
    assert np.all(moved > 0) and np.all(moved < 0.5)


def test_orbit_takes_an_explicit_K_and_distortion():
    K = np.array([[300.0, 0, 160], [0, 310.0, 120], [0, 0, 1]])
    cams = orbit_cameras(np.zeros(3), num_views=2, K=K, width=320, height=240, dist=[-0.1, 0.01, 0, 0, 0])
    np.testing.assert_array_equal(cams.K, np.stack([K, K]))
    np.testing.assert_allclose(cams.dist, [[-0.1, 0.01, 0, 0, 0]] * 2)


def test_forward_cameras_step_along_the_direction():
    cams = forward_cameras(num_views=4, step=0.25, start=(1.0, 2.0, 1.5), direction=(0.0, 2.0, 0.0))
    np.testing.assert_allclose(np.diff(cams.centers, axis=0), [[0.0, 0.25, 0.0]] * 3, atol=1e-12)
    np.testing.assert_allclose(cams.centers[0], [1.0, 2.0, 1.5], atol=1e-12)
    for k in range(4):
        np.testing.assert_allclose(cams.R[k], cams.R[0])
        np.testing.assert_allclose(cams.R[k][2], [0.0, 1.0, 0.0], atol=1e-12)  # looking along the motion
    turning = forward_cameras(num_views=3, step=0.1, start=(0.0, 0.0, 1.0), direction=(1.0, 0.0, 0.0), turn_deg=5.0)
    np.testing.assert_allclose(rotation_angle_deg(turning.R[0], turning.R[2]), 10.0, atol=1e-9)
    assert turning.R[1][2][1] > 0  # a positive turn goes left: towards up x direction = +y


def test_forward_cameras_of_a_scene_start_at_home_and_head_for_the_centre():
    scene = named_scene("room")
    cams = forward_cameras(scene=scene, num_views=2, step=0.2, width=64, height=48)
    np.testing.assert_allclose(cams.centers[0], scene.home, atol=1e-12)
    heading = np.asarray(scene.center) - np.asarray(scene.home)
    heading[2] = 0.0
    np.testing.assert_allclose(cams.centers[1] - cams.centers[0], 0.2 * heading / np.linalg.norm(heading),
                               atol=1e-12)


def test_stereo_rig_is_rectified_with_disparity_f_b_over_z():
    cams = stereo_rig(baseline=0.12, eye=(0.0, -3.0, 1.0), target=(0.0, 0.0, 1.0), width=320, height=240)
    assert len(cams) == 2
    np.testing.assert_allclose(cams.R[0], cams.R[1])
    np.testing.assert_allclose(cams.centers[1] - cams.centers[0], 0.12 * cams.R[0][0], atol=1e-12)
    X = np.random.default_rng(0).uniform([-1, -1, 0], [1, 1, 2], (20, 3))
    left = project_points(X, cams.K[0], None, cams.R[0], cams.t[0])
    right = project_points(X, cams.K[1], None, cams.R[1], cams.t[1])
    Z = (X @ cams.R[0].T + cams.t[0])[:, 2]
    np.testing.assert_allclose(left[:, 0] - right[:, 0], cams.K[0][0, 0] * 0.12 / Z, rtol=1e-12)
    np.testing.assert_allclose(left[:, 1], right[:, 1], atol=1e-9)


def test_stereo_rig_verges_and_takes_other_intrinsics():
    K_right = np.array([[400.0, 0, 150], [0, 400.0, 110], [0, 0, 1]])
    cams = stereo_rig(baseline=0.2, verge_deg=6.0, K_right=K_right, dist_right=[0.05, 0, 0, 0, 0])
    np.testing.assert_allclose(rotation_angle_deg(cams.R[0], cams.R[1]), 6.0, atol=1e-9)
    z_left, z_right = cams.R[0][2], cams.R[1][2]
    x_left = cams.R[0][0]
    assert z_left @ x_left == pytest.approx(0.0) and cams.R[0][2] @ (cams.R[1][2] - cams.R[0][2]) < 0
    assert (z_right - z_left) @ x_left < 0  # toed in: the optical axes converge
    np.testing.assert_allclose(cams.K[1], K_right)
    np.testing.assert_allclose(cams.dist, [[0, 0, 0, 0, 0], [0.05, 0, 0, 0, 0]])


def test_camera_path_errors_are_clear():
    with pytest.raises(InvalidValue, match="elevation") as info:
        orbit_cameras(np.zeros(3), radius=2.0, height=1.5)  # height is the image height in pixels
    assert info.value.field == "height"
    with pytest.raises(InvalidValue, match="num_views"):
        orbit_cameras(np.zeros(3), num_views=0)
    with pytest.raises(InvalidValue, match="radius"):
        orbit_cameras(np.zeros(3), radius=-1.0)
    with pytest.raises(InvalidValue, match="scene_or_center"):
        orbit_cameras("room")
    with pytest.raises(InvalidValue, match="parallel"):
        forward_cameras(direction=(0.0, 0.0, 1.0))
    with pytest.raises(InvalidValue, match="baseline"):
        stereo_rig(baseline=0.0)
    with pytest.raises(InvalidValue, match="jitter"):
        orbit_cameras(np.zeros(3), jitter=-0.1)
