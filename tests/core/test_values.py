"""Typed values check their shapes and dtypes on construction."""

from __future__ import annotations

import numpy as np
import pytest

from lab.core import Cameras, Curve, Image, ImageSet, InvalidValue, Mesh, PointCloud, Points2D


def test_image_converts_uint8_and_checks_shape():
    image = Image(np.full((2, 3, 3), 255, np.uint8))
    assert image.pixels.dtype == np.float32 and image.pixels.max() == 1.0
    assert (image.height, image.width) == (2, 3)
    np.testing.assert_allclose(image.gray(), 1.0, rtol=1e-6)
    for bad in (np.zeros((2, 3, 4)), np.zeros(5), np.zeros((0, 3))):
        with pytest.raises(InvalidValue):
            Image(bad)


def test_points_select_a_view():
    points = Points2D(np.arange(8.0).reshape(4, 2), view=[0, 1, 0, 1], ids=[0, 0, 1, 1])
    one = points.in_view(1)
    np.testing.assert_array_equal(one.xy, [[2, 3], [6, 7]])
    np.testing.assert_array_equal(one.ids, [0, 1])
    with pytest.raises(InvalidValue) as info:
        Points2D(np.zeros((3, 2)), view=[0, 1])
    assert info.value.field == "view"


def test_cameras_broadcast_a_single_camera_and_give_centres():
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    cams = Cameras(np.eye(3), R, [1.0, 2.0, 3.0], 10, 10, dist=np.zeros(5))
    assert cams.K.shape == (1, 3, 3) and cams.dist.shape == (1, 5)
    np.testing.assert_allclose(cams.centers[0], -R.T @ [1.0, 2.0, 3.0])


def test_bad_shapes_are_refused():
    with pytest.raises(InvalidValue):
        PointCloud(np.zeros((3, 2)))
    with pytest.raises(InvalidValue):
        Mesh(np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(InvalidValue):
        Curve([0, 1], [[1, 2, 3]])
    with pytest.raises(InvalidValue):
        ImageSet((np.zeros((2, 2)),))
    with pytest.raises(InvalidValue):
        PointCloud([[0.0, np.inf, 0.0]])
