"""lab.data.scenes: the named scenes (determinism, texture rich enough for SIFT, consistent across views)."""

import cv2
import numpy as np
import pytest

from lab.core import InvalidValue, UnknownName
from lab.data.scenes import (SCENE_NAMES, Box, MeshObject, Plane, Scene, Sphere, named_scene, orbit_cameras,
                             pixel_rays, render)
from lab.data.scenes.named import _build
from lab.geometry.camera import project_points


def gray8(view) -> np.ndarray:
    return np.clip(view.image.gray() * 255.0 + 0.5, 0, 255).astype(np.uint8)


def test_scene_names_and_contents():
    assert SCENE_NAMES == ("room", "table", "facade")
    kinds = {name: {type(item) for item in named_scene(name).objects} for name in SCENE_NAMES}
    assert {Plane, Box, Sphere} <= kinds["room"]
    assert {Plane, Box, Sphere, MeshObject} <= kinds["table"]
    assert Plane in kinds["facade"]
    for name in SCENE_NAMES:
        scene = named_scene(name)
        assert isinstance(scene, Scene) and scene.name == name and scene.home is not None
        lower, upper = scene.bounds()
        assert np.all(lower <= scene.center) and np.all(scene.center <= upper)


def test_named_scenes_are_cached_and_deterministic_per_seed():
    assert named_scene("room", seed=3) is named_scene("room", seed=3)
    first, again = _build.__wrapped__("facade", 3), _build.__wrapped__("facade", 3)
    other = _build.__wrapped__("facade", 4)
    assert len(first.objects) == len(again.objects) == len(other.objects)
    for a, b in zip(first.objects, again.objects):
        np.testing.assert_array_equal(a.hull()[0], b.hull()[0])
        assert (a.texture is None) == (b.texture is None)
        if a.texture is not None:
            np.testing.assert_array_equal(a.texture.image, b.texture.image)
    assert not np.array_equal(first.objects[0].texture.image, other.objects[0].texture.image)
    # placements change with the seed too (room: crates and balls move)
    room_a, room_b = named_scene("room", seed=0), named_scene("room", seed=1)
    moved = [not np.allclose(a.hull()[0], b.hull()[0]) for a, b in zip(room_a.objects, room_b.objects)]
    assert sum(moved) >= 5


def test_unknown_scene_name_and_bad_seed_are_refused_clearly():
    with pytest.raises(UnknownName, match="unknown scene 'kitchen'") as info:
        named_scene("kitchen")
    assert info.value.field == "scene" and "room" in info.value.reason
    for seed in (-1, 1.5, True):
        with pytest.raises(InvalidValue, match="seed"):
            named_scene("room", seed=seed)


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_sift_finds_over_a_thousand_features_on_a_640x480_view(name):
    scene = named_scene(name)
    cameras = orbit_cameras(scene, num_views=1)  # from the scene's home viewpoint
    view = render(scene, cameras, 0)
    assert view.image.pixels.shape == (480, 640, 3)
    assert view.mask.mean() > 0.5
    keypoints = cv2.SIFT_create().detect(gray8(view), None)
    assert len(keypoints) > 1000


def test_sift_matches_between_nearby_room_views_are_plentiful_and_agree_with_the_true_depth():
    scene = named_scene("room")
    cameras = orbit_cameras(scene, num_views=2, arc_deg=8.0, width=640, height=480)
    first, second = render(scene, cameras, 0), render(scene, cameras, 1)
    sift = cv2.SIFT_create()
    k1, d1 = sift.detectAndCompute(gray8(first), None)
    k2, d2 = sift.detectAndCompute(gray8(second), None)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m for m, n in pairs if m.distance < 0.75 * n.distance]
    assert len(good) > 500
    x1 = np.array([k1[m.queryIdx].pt for m in good])
    x2 = np.array([k2[m.trainIdx].pt for m in good])
    # transfer x1 into view 2 through the true depth at the nearest pixel centre
    origin, directions = pixel_rays(cameras, 0)
    u, v = np.round(x1).astype(int).T
    X = origin + first.depth[v, u, None] * directions[v, u]
    transferred = project_points(X, cameras.K[1], None, cameras.R[1], cameras.t[1])
    error = np.linalg.norm(transferred - x2, axis=1)
    assert np.mean(error < 3.0) > 0.9


def test_every_pixel_of_a_room_view_sees_a_surface():
    view = render(named_scene("room"), orbit_cameras(named_scene("room"), num_views=3, width=64, height=48), 2)
    assert view.mask.all() and np.isfinite(view.depth).all()
    assert 0.3 < view.depth.min() and view.depth.max() < 12.0
