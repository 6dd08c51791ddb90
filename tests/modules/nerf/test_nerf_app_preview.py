"""The training preview follows a camera (issue 17, viewer): lab.modules.nerf.preview's FollowedPreview and
the NeRF interaction that hands it the browser's camera (lab/viewer/interactions/nerf.py).

Known answers for the camera conversion (a point straight ahead lands on the principal point, one to the
right and below lands right and below), the follower's rays against the rays of the camera it follows (and
of training view 0 before and after), coarse while moving and sharp once still (a fake clock), and a tiny
training run whose previews change shape and content once the camera moves while the result's preview stays
training view 0. The browser test is tests/e2e/test_e2e_nerf_preview.py."""

from __future__ import annotations


import numpy as np
import pytest
import torch
import viser.transforms as vtf

from modules.texture_helpers import drive

from lab.core import Cameras, Cancelled, InvalidValue, Progress, SessionStore, open_session
from lab.modules import nerf as N
from lab.modules.nerf import PIPELINE
from lab.modules.nerf.preview import (FOLLOWER, MOVING_SIDE, STILL_SECONDS, FollowedPreview, depth_shift,
                                      offering_preview)
from lab.modules.nerf.rays import cameras_rays, scaled_cameras
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.interactions import interactions_for
from lab.viewer.interactions.nerf import RayOfPixel, TrainingCamera, browser_cameras

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def session():
    session = open_session(PIPELINE, "synthetic_object", {"train_views": 3, "test_views": 1}, seed=2)
    session.run("generate_rays")
    session.run("encode_positions")
    return session


def _project(cameras: Cameras, point: np.ndarray) -> np.ndarray:
    x = cameras.K[0] @ (cameras.R[0] @ point + cameras.t[0])
    return x[:2] / x[2]


def test_browser_camera_as_an_opencv_camera():
    R_wc = vtf.SO3.from_rpy_radians(0.3, -0.7, 1.1).as_matrix()
    position = np.array([1.0, -2.0, 0.5])
    cameras = browser_cameras(position, vtf.SO3.from_matrix(R_wc).wxyz, np.radians(60.0), 1.5, side=300)
    assert (cameras.width, cameras.height) == (300, 200)
    np.testing.assert_allclose(cameras.K[0, 1, 1], 100.0 / np.tan(np.radians(30.0)))
    ahead = position + R_wc @ np.array([0.0, 0.0, 3.0])
    np.testing.assert_allclose(_project(cameras, ahead), [149.5, 99.5], atol=1e-9)
    right_below = position + R_wc @ np.array([0.2, 0.1, 3.0])
    u, v = _project(cameras, right_below)
    assert u > 149.5 and v > 99.5
    tall = browser_cameras(position, vtf.SO3.from_matrix(R_wc).wxyz, np.radians(60.0), 0.5, side=300)
    assert (tall.width, tall.height) == (150, 300)
    with pytest.raises(InvalidValue, match="fov"):
        browser_cameras(position, vtf.SO3.from_matrix(R_wc).wxyz, 0.0, 1.5)


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _rays(cameras: Cameras, side: int, bounds=None):
    """The rays of ``cameras`` at longest side ``side``, origins moved by depth_shift when ``bounds``."""
    small = scaled_cameras(cameras, min(1.0, side / max(cameras.width, cameras.height)))
    origins, directions = cameras_rays(small)
    shift = 0.0 if bounds is None else depth_shift(small, bounds)
    return origins[0] + shift * directions[0], directions[0], (small.height, small.width)


def test_follower_renders_the_camera_it_follows(session):
    cameras, bounds, clock = session.state["cameras"], session.state["bounds"], Clock()
    follower = FollowedPreview(cameras, bounds, clock=clock)
    start = _rays(cameras, 64)
    torch.testing.assert_close(follower.origins, start[0])
    torch.testing.assert_close(follower.directions, start[1])
    assert follower.shape == start[2] == (64, 64)
    other = browser_cameras(np.array([0.0, 0.0, -8.0]), np.array([1.0, 0.0, 0.0, 0.0]), 1.0, 2.0)
    follower.follow(other)
    moving = _rays(other, MOVING_SIDE, bounds)
    torch.testing.assert_close(follower.origins, moving[0])
    torch.testing.assert_close(follower.directions, moving[1])
    assert follower.shape == moving[2] == (16, 32)
    clock.now += STILL_SECONDS + 0.01
    still = _rays(other, 64, bounds)
    torch.testing.assert_close(follower.origins, still[0])
    torch.testing.assert_close(follower.directions, still[1])
    assert follower.shape == (32, 64) and follower.follows == 1
    follower.reset()
    torch.testing.assert_close(follower.origins, start[0])  # origins first: it makes the rays, as the loops read
    torch.testing.assert_close(follower.directions, start[1])
    assert follower.shape == (64, 64)


def test_depth_shift_centres_near_far_on_the_scene(session):
    bounds = session.state["bounds"]
    for distance in (8.0, 3.0, 0.5):  # far away, about the training cameras' distance, inside the box
        camera = browser_cameras(bounds.center - [0.0, 0.0, distance], np.array([1.0, 0.0, 0.0, 0.0]), 1.0, 1.0)
        shift = depth_shift(camera, bounds)
        middle = (bounds.near + bounds.far) / 2.0
        if distance - middle >= -bounds.near:
            assert shift == pytest.approx(distance - middle)  # the centre at depth (near + far) / 2 from o + s d
        else:
            assert shift == -bounds.near  # never a sample behind the camera


def test_training_previews_follow_the_camera_the_result_stays_view_0(session):
    state = session.state
    steps = N.train_nerf(state["rays"], state["encoding"], state["cameras"], method="grid", grid_resolution=16,
                         batch_rays=256, iterations=60, preview_every=10, budget_seconds=0,
                         rng=np.random.default_rng(0))
    first = next(steps)
    follower = first.values[FOLLOWER]
    assert isinstance(follower, FollowedPreview)
    before = first.values["preview"].pixels
    assert before.shape == (64, 64, 3)
    # a camera 1.4 times as far from the object as training view 0, looking at it: the object looks smaller
    cam = state["cameras"]
    centre = -cam.R[0].T @ cam.t[0]
    target = np.asarray(state["bounds"].center, dtype=np.float64)
    eye = target + 1.4 * (centre - target)
    far_away = Cameras(cam.K[:1], cam.R[:1], (-cam.R[0] @ eye)[None], cam.width, cam.height)
    follower.follow(far_away)
    snapshots, result = drive(steps)
    after = [s.values["preview"].pixels for s in snapshots if "preview" in s.values]
    # coarse while the camera counts as moving, sharp once it stands still (STILL_SECONDS: no timing here)
    assert after and all(a.shape in ((MOVING_SIDE, MOVING_SIDE, 3), (64, 64, 3)) for a in after)
    assert all(s.values[FOLLOWER] is follower for s in snapshots)
    assert result.preview.pixels.shape == (64, 64, 3)  # the result: training view 0, as before

    def footprint(image: np.ndarray) -> float:  # share of pixels that are not the white background
        return float(np.mean(np.abs(image - 1.0).max(axis=-1) > 0.1))

    seen, trained = footprint(after[-1]), footprint(result.preview.pixels)
    assert 0.2 * trained < seen < 0.75 * trained, (seen, trained)


def test_cancel_goes_through_to_the_training_loop():
    seen = []

    def loop():
        for k in range(5):
            try:
                yield Progress(iteration=k, values={"preview": k})
            except Cancelled:
                seen.append(k)
                break
        return "trained so far"

    follower = FollowedPreview(Cameras(np.eye(3), np.eye(3), np.zeros(3), 4, 4),
                               N.SceneBounds(1.0, 2.0, np.zeros(3), 1.0))
    wrapped = offering_preview(loop(), follower)
    first = next(wrapped)
    assert first.values == {"preview": 0, FOLLOWER: follower}
    with pytest.raises(StopIteration) as stop:
        wrapped.throw(Cancelled("train_nerf", "cancelled"))
    assert stop.value.value == "trained so far" and seen == [0]
    assert drive(offering_preview(loop(), follower))[1] == "trained so far"


class FakeCamera:
    """What viser's CameraHandle gives: pose, field of view, aspect, and a timestamp once reported."""

    def __init__(self) -> None:
        self.position = np.array([0.0, -1.0, -5.0])
        self.wxyz = np.array([1.0, 0.0, 0.0, 0.0])
        self.fov, self.aspect, self.update_timestamp = 1.0, 1.25, 1.0


def test_the_interaction_hands_the_camera_to_a_running_training(server):
    store = SessionStore(max_sessions=2)
    assert interactions_for("nerf") == [TrainingCamera, RayOfPixel]
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    session = store.create(PIPELINE, "synthetic_object", {"train_views": 2, "test_views": 1})
    view.open_session(session)
    interaction = next(i for i in view.interactions if isinstance(i, TrainingCamera))
    assert interaction.on_progress in session.listeners
    assert not interaction.send()  # no training yet
    follower = FollowedPreview(session.state["cameras"], session.state["bounds"])
    interaction.on_progress("train_nerf", Progress(iteration=10, values={FOLLOWER: follower}))
    assert follower.follows == 0  # no camera reported (the server-wide scene)
    interaction.camera = FakeCamera()
    assert interaction.send() and follower.follows == 1
    expected = browser_cameras(interaction.camera.position, interaction.camera.wxyz, 1.0, 1.25)
    torch.testing.assert_close(follower.origins, _rays(expected, MOVING_SIDE, session.state["bounds"])[0])
    assert follower.shape == (26, 32)
    interaction.follow.value = False
    assert interaction.send()  # training view 0 again
    assert follower.origins.shape == (64 * 64, 3) and follower.shape == (64, 64)
    view.close()
    assert interaction.on_progress not in session.listeners
