"""The first camera of every module: everything drawn in 3D inside the canvas, centred, and not tiny.

The fit's pinhole math first (:func:`lab.viewer.camera.fit_camera` on hand-made points), then each module's
default dataset after Run all (diffusion's denoiser trained briefly), framed as a browser tab frames it: the
content's points (the state's 3D values and the boxes of what the interactions draw) are projected through
the framed camera with viser's default fov and the canvas the viewer leaves between its docked panels in a
1400 x 900 window, and must lie inside it with a margin and fill a fair share of it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lab.core.values import Cameras, PointCloud
from lab.modules import get_pipeline
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.camera import (DEFAULT_ASPECT, FILL, CameraFramer, CameraPose, Viewport, aim, fit_camera,
                               fits, frame_pose, project)
from lab.viewer.interactions import Interaction

#: The canvas of a 1400 x 900 window between the image panel (left) and the control panel (right).
CANVAS = Viewport(math.radians(75.0), DEFAULT_ASPECT)
#: Lighter controls and dataset options where a module's defaults take long on a shared CPU (the drawing
#: does not change kind).
LIGHT = {"diffusion": {"train_denoiser": {"iterations": 150, "hidden": 32, "layers": 2, "batch_size": 128}},
         "nerf": {"fit_image_2d": {"side": 24, "iterations": 20},
                  "train_nerf": {"method": "grid", "grid_resolution": 32, "iterations": 120,
                                 "budget_seconds": 0.0},
                  "render_path": {"frames": 4, "scale": 0.3},
                  "extract_mesh": {"resolution": 32, "level": 2.0}},
         "splatting": {"initialize_gaussians": {"points": 300},
                       "train_splats": {"iterations": 30, "budget_seconds": 0.0, "densify_from": 10,
                                        "densify_every": 10},
                       "render_path": {"frames": 4, "scale": 0.3}}}
OPTIONS = {"sfm": {"num_views": 8}, "nerf": {"train_views": 6, "test_views": 2},
           "splatting": {"train_views": 6, "test_views": 2}}
MODULES = ("calibration", "epipolar", "stereo", "sfm", "texture", "diffusion", "nerf", "splatting")


def extent_on_canvas(points: np.ndarray, pose: CameraPose,
                     viewport: Viewport) -> tuple[np.ndarray, np.ndarray]:
    """The min and max canvas coordinates ``(2,)`` (fractions, x right, y down) of ``points``."""
    xy = project(points, pose, viewport)
    assert np.all(np.isfinite(xy)), "a content point is behind the camera"
    return xy.min(axis=0), xy.max(axis=0)


# --- the fit's math -------------------------------------------------------------------------------------
@pytest.mark.parametrize("aspect", [0.6, 1.0, 1.8])
@pytest.mark.parametrize("forward", [(0.0, 0.0, 1.0), (-0.35, 0.6, 1.1), (1.0, 0.2, 0.0)])
def test_fit_puts_the_outermost_points_at_the_margin_centred(aspect, forward):
    rng = np.random.default_rng(3)
    points = rng.normal(size=(300, 3)) * np.array([3.0, 1.0, 0.5]) + np.array([5.0, -2.0, 7.0])
    viewport = Viewport(math.radians(60.0), aspect)
    pose = fit_camera(points, np.array(forward), viewport)
    lo, hi = extent_on_canvas(points, pose, viewport)
    margin = (1.0 - FILL) / 2
    assert np.all(lo >= margin - 1e-5) and np.all(hi <= 1 - margin + 1e-5)
    # as close as it can be: along the tighter direction the content touches both margins ...
    touches = np.isclose(lo, margin, atol=1e-5) & np.isclose(hi, 1 - margin, atol=1e-5)
    assert touches.any()
    # ... and along the other it is centred
    np.testing.assert_allclose((lo + hi) / 2, [0.5, 0.5], atol=1e-5)
    # the camera looks along forward, with world up (-y) at the top of the picture
    direction = (pose.look_at - pose.position) / np.linalg.norm(pose.look_at - pose.position)
    np.testing.assert_allclose(direction, np.array(forward) / np.linalg.norm(forward), atol=1e-9)
    above = project(pose.look_at[None] + np.array([[0.0, -1e-3, 0.0]]), pose, viewport)[0]
    if abs(direction[1]) < 0.99:
        assert above[1] < 0.5


def test_a_wider_canvas_frames_a_wide_scene_closer():
    points = np.array([[-4.0, -0.5, 0.0], [4.0, 0.5, 0.0], [0.0, 0.0, 0.5]])
    narrow = fit_camera(points, np.array([0.0, 0.0, 1.0]), Viewport(math.radians(75), 0.6))
    wide = fit_camera(points, np.array([0.0, 0.0, 1.0]), Viewport(math.radians(75), 1.6))
    assert np.linalg.norm(wide.position - wide.look_at) < np.linalg.norm(narrow.position - narrow.look_at)


def test_bad_viewports_and_empty_content_are_refused():
    from lab.core.errors import InvalidValue

    with pytest.raises(InvalidValue, match="fov"):
        Viewport(0.0, 1.0)
    with pytest.raises(InvalidValue, match="finite point"):
        fit_camera(np.full((2, 3), np.nan), np.array([0.0, 0.0, 1.0]), CANVAS)


class _Boxed(Interaction):
    def __init__(self, box: np.ndarray) -> None:  # no context: only bounds() is asked for
        self.box = box

    def bounds(self) -> np.ndarray:
        return self.box


def test_the_content_is_the_state_and_what_interactions_draw_without_far_outliers():
    rng = np.random.default_rng(0)
    cloud = rng.uniform(-1, 1, (500, 3))
    cloud[0] = (1e6, 0, 0)  # a point triangulated at infinity must not shrink the picture
    box = np.array([[5.0, 0.0, 0.0], [6.0, 1.0, 1.0]])
    points, _forward = aim({"cloud": PointCloud(cloud)}, [_Boxed(box)])
    assert points[:, 0].max() == pytest.approx(6.0)
    assert points[:, 0].min() == pytest.approx(cloud[1:, 0].min())
    assert aim({}, []) is None


class _Camera:
    """A viser camera handle as the browser reports it, for the framer."""

    def __init__(self, aspect: float) -> None:
        self.fov, self.image_width, self.image_height = math.radians(75), round(900 * aspect), 900
        self.position = self.look_at = self.up_direction = np.zeros(3)
        self.callbacks: list = []

    def on_update(self, callback):
        self.callbacks.append(callback)
        return callback


class _Client:
    def __init__(self, aspect: float) -> None:
        self.camera = _Camera(aspect)


def test_the_framer_fits_the_reported_canvas_and_refits_when_it_changes_shape_until_the_camera_moves():
    client = _Client(1.4)
    framer = CameraFramer(client, is_client=True)
    cloud = {"cloud": PointCloud(np.array([[-3.0, -0.5, 0.0], [3.0, 0.5, 0.0], [0.0, 0.0, 1.0]]))}
    framer.frame(cloud, [])
    wide = np.array(client.camera.position)
    np.testing.assert_allclose(wide, frame_pose(cloud, [], Viewport(math.radians(75), 1260 / 900)).position)
    # the image panel appears: the canvas narrows; the camera has not been moved, so the fit follows
    client.camera.image_width = 552
    client.camera.callbacks[0](client.camera)
    narrow = np.array(client.camera.position)
    np.testing.assert_allclose(narrow, frame_pose(cloud, [], Viewport(math.radians(75), 552 / 900)).position)
    assert not np.allclose(narrow, wide)
    # the student orbits; a later resize leaves the camera alone
    client.camera.position = narrow + 1.0
    client.camera.image_width = 1000
    client.camera.callbacks[0](client.camera)
    np.testing.assert_allclose(client.camera.position, narrow + 1.0)
    framer.frame(cloud, [])  # framed once per session
    np.testing.assert_allclose(client.camera.position, narrow + 1.0)


# --- every module's first camera ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ran():
    """``ran(module)``: the module's default dataset after Run all (made once for the file, on first use)."""
    torch.set_num_threads(1)
    from lab.core import SessionStore

    store = SessionStore(max_sessions=8)
    sessions = {}

    def session_of(module: str):
        if module not in sessions:
            pipeline = get_pipeline(module)
            session = store.create(pipeline, pipeline.datasets[0].name, OPTIONS.get(module, {}))
            session.run_until(None, LIGHT.get(module, {}))
            sessions[module] = session
        return store, sessions[module]

    return session_of


@pytest.mark.parametrize("module", MODULES)
def test_every_module_opens_with_its_3d_content_inside_the_canvas_and_not_tiny(server, ran, module):
    store, session = ran(module)
    view = ClientView(server, store, ModuleCatalog([session.pipeline]), is_client=False, background=False)
    view.open_session(session)
    state = dict(session.state)
    pose = frame_pose(state, view.interactions, CANVAS)
    assert pose is not None, f"{module}: nothing to frame after Run all"
    points, _ = aim(state, view.interactions)
    lo, hi = extent_on_canvas(points, pose, CANVAS)
    assert np.all(lo >= 0.04) and np.all(hi <= 0.96), f"{module}: content outside the canvas: {lo}, {hi}"
    span = hi - lo
    assert span.max() >= 0.8, f"{module}: the content takes only {span} of the canvas"
    # every camera of the state is in view, and the interactions' drawings too
    for value in state.values():
        if isinstance(value, Cameras):
            xy = project(value.centers, pose, CANVAS)
            assert np.all((xy > 0.03) & (xy < 0.97)), f"{module}: a camera is out of view"
    for interaction in view.interactions:
        box = interaction.bounds()
        if box is not None:
            xy = project(box, pose, CANVAS)
            assert np.all((xy > 0.03) & (xy < 0.97)), f"{module}: {type(interaction).__name__} out of view"
    view.close()


def test_epipolar_cameras_and_pose_candidates_are_in_view_and_not_tiny(server, ran):
    store, session = ran("epipolar")
    view = ClientView(server, store, ModuleCatalog([session.pipeline]), is_client=False, background=False)
    view.open_session(session)
    state = dict(session.state)
    pose = frame_pose(state, view.interactions, CANVAS)
    candidates = next(i for i in view.interactions if type(i).__name__ == "PoseCandidates")
    assert candidates.bounds() is not None, "the pose candidates say where they are drawn"
    corners = project(candidates.bounds(), pose, CANVAS)
    assert np.all((corners > 0.03) & (corners < 0.97))
    # the two cameras in view, inside the margin
    xy = project(state["cameras"].centers, pose, CANVAS)
    assert np.all((xy > 0.05) & (xy < 0.95))
    view.close()


def test_the_frustum_pictures_are_framed_not_only_the_camera_centres():
    from lab.viewer.renderers import FRUSTUM_SHARE, frustum_corners, frustum_plane_depth

    # one camera at the origin looking along +z, 90 degrees vertical fov, 4:3
    K = np.array([[[2.0, 0, 2.0], [0, 1.5, 1.5], [0, 0, 1]]])
    cameras = Cameras(K, np.eye(3)[None], np.zeros((1, 3)), width=4, height=3)
    corners = frustum_corners(cameras, 10.0)
    depth = frustum_plane_depth(math.pi / 2, 4 / 3, FRUSTUM_SHARE * 10.0)
    np.testing.assert_allclose(corners[:, 2], depth)
    np.testing.assert_allclose(np.abs(corners[:, 1]), depth)  # tan(45 degrees) = 1
    np.testing.assert_allclose(np.abs(corners[:, 0]), depth * 4 / 3)
    points, _ = aim({"cameras": cameras}, [])
    assert len(points) == 1 + 4 + 1  # the centre as a point, and the frustum whole: its picture and apex
    np.testing.assert_allclose(points[5], cameras.centers[0])


def test_content_that_outgrows_the_view_is_framed_again_while_the_camera_was_not_moved():
    client = _Client(552 / 900)
    framer = CameraFramer(client, is_client=True)
    small = {"rig": PointCloud(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.3, 0.2]]))}
    framer.frame(small, [])  # epipolar's rig, drawn from the truth before any step
    first = np.array(client.camera.position)
    framer.frame(small, [])  # the same content: nothing moves
    np.testing.assert_allclose(client.camera.position, first)
    rng = np.random.default_rng(1)
    grown = {**small, "cloud": PointCloud(rng.uniform([-7, -5, 4], [7, 2, 15], (400, 3)))}
    framer.frame(grown, [])  # Run all added a cloud many times the rig's size: framed again
    viewport = Viewport(math.radians(75), 552 / 900)
    np.testing.assert_allclose(client.camera.position, frame_pose(grown, [], viewport).position)
    # the student orbits; content that grows again leaves the camera alone
    client.camera.position = np.array(client.camera.position) + 3.0
    moved = np.array(client.camera.position)
    farther = {**grown, "far": PointCloud(rng.uniform([30, -5, 4], [60, 2, 15], (400, 3)))}
    assert not fits(aim(farther, [])[0], frame_pose(grown, [], viewport), viewport)  # it would be refitted
    framer.frame(farther, [])
    np.testing.assert_allclose(client.camera.position, moved)
