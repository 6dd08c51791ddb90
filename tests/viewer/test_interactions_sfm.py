"""The SfM module's viewer interaction: points coloured by reprojection error, a picked point's track.
Pure functions against known answers, then the interaction in a ClientView on a small reconstruction."""

from __future__ import annotations

import numpy as np
import pytest

from lab.core import InvalidValue, MissingInput, Points2D
from lab.data.reconstruction import SparseModel
from lab.modules.sfm import PIPELINE
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.interactions import EXPLORE_ROOT, interactions_for
from lab.viewer.interactions.sfm import (INTERACTIONS, MODEL_VIEWS, TrackExplorer, error_colors, latest_model,
                                         nearest_point_to_ray, track_observations)

OPTIONS = {"num_views": 4, "width": 240, "height": 180, "arc_deg": 45.0}


def two_camera_model():
    """Two cameras 1 m apart looking along +z, two points; the second point's view-1 pixel is 3 px off."""
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    poses = np.zeros((2, 3, 4))
    poses[:, :, :3] = np.eye(3)
    poses[1, :, 3] = [-1.0, 0, 0]  # camera 1 at x = 1
    points = np.array([[0.5, 0.0, 5.0], [0.0, 0.2, 4.0]])
    pixels = []
    for p in points:
        for v in range(2):
            x = K @ (p + poses[v, :, 3])
            pixels.append(x[:2] / x[2])
    pixels = np.array(pixels)
    pixels[3] += [3.0, 0.0]
    return SparseModel(K=np.stack([K, K]), poses=poses, registered=np.ones(2, dtype=bool),
                       names=("a.png", "b.png"),
                       sizes=np.array([[100, 80], [100, 80]]),
                       keypoints=Points2D(pixels, view=np.array([0, 1, 0, 1])),
                       track_of=np.array([0, 0, 1, 1]), observed=np.ones(4, dtype=bool), points=points,
                       point_tracks=np.array([0, 1]), colors=np.zeros((2, 3)), errors=np.array([0.0, 1.5]))


def test_interactions_are_found_by_the_pipeline_name():
    assert interactions_for("sfm") == INTERACTIONS == [TrackExplorer]


def test_track_observations_known_answer():
    model = two_camera_model()
    first = track_observations(model, 0)
    assert [o.name for o in first] == ["a.png", "b.png"]
    assert all(o.error_px < 1e-9 for o in first)
    np.testing.assert_allclose(first[1].center, [1.0, 0.0, 0.0])
    second = track_observations(model, 1)
    assert second[1].error_px == pytest.approx(3.0)
    means = [np.mean([o.error_px for o in track_observations(model, j)]) for j in (0, 1)]
    np.testing.assert_allclose(means, [0.0, 1.5], atol=1e-9)  # each point's mean error, as the model says
    np.testing.assert_allclose(means, model.errors, atol=1e-9)
    with pytest.raises(InvalidValue, match="no point 2"):
        track_observations(model, 2)


def test_nearest_point_to_ray_and_error_colours():
    points = np.array([[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [0.0, 0.0, -5.0]])
    assert nearest_point_to_ray(points, [0.9, 0.0, 0.0], [0.0, 0.0, 1.0]) == 1
    assert nearest_point_to_ray(points, [0.0, 0.0, 0.0], [0.0, 0.0, -1.0]) == 2  # only what lies ahead
    with pytest.raises(InvalidValue, match="no point lies in front"):
        nearest_point_to_ray(points[:2], [0.0, 0.0, 10.0], [0.0, 0.0, 1.0])
    colors = error_colors(np.array([0.0, 0.5, 5.0]), 1.0)
    np.testing.assert_allclose(colors[0], [0.1, 0.8, 0.2])
    np.testing.assert_allclose(colors[2], [0.9, 0.1, 0.1])
    assert latest_model({}) is None
    model = two_camera_model()
    assert latest_model({"model": model}) is model
    assert latest_model({"model": two_camera_model(), "filtered_model": model}) is model  # the most refined
    assert set(MODEL_VIEWS) <= PIPELINE.views


@pytest.fixture(scope="module")
def reconstructed():
    """A small reconstruction, made once: the state after every step."""
    from lab.core import open_session

    session = open_session(PIPELINE, "rendered", OPTIONS, seed=0)
    for spec in PIPELINE.steps:
        session.run(spec.name)
    return session.state


@pytest.fixture
def view(server, store, reconstructed):
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    session = store.create(PIPELINE, "rendered", {**OPTIONS, "num_views": 2, "width": 96, "height": 72,
                                                  "supersample": 1})
    view.open_session(session)
    return view, session


def explorer(view):
    return next(i for i in view.interactions if isinstance(i, TrackExplorer))


def test_pick_a_point_shows_its_track(view, reconstructed):
    view, session = view
    session.state = dict(reconstructed)
    session.version += 1
    view.refresh(force=True)
    part = explorer(view)
    model = latest_model(reconstructed)
    assert model is not None
    observations = part.pick_point(0)
    assert model is reconstructed["adjusted_model"]
    expected = np.flatnonzero(reconstructed["observations"].ids == 0)
    assert len(observations) == len(expected) >= 2
    assert all(o.error_px < 2.0 for o in observations)  # the filter kept only these
    assert {f"{EXPLORE_ROOT}/sfm/track",
            f"{EXPLORE_ROOT}/sfm/point"} <= {part.ctx.node(n) for n in part.scene_nodes()}
    assert "seen in" in part.table.content
    # a click ray through the point picks it
    center = observations[0].center
    X = model.points[5]
    again = part.click_ray(center, X - center)
    assert len(again) == int(np.sum(reconstructed["observations"].ids == 5))
    part.by_error.value = True
    colors = part.draw_errors()
    assert colors.shape == (len(model.points), 3)
    assert "errors" in part.scene_nodes()
    legend = {e.name: e for e in part.legend()}
    assert set(legend) == {"points by error", "picked track"}
    assert legend["points by error"].count == len(model.points)
    green, red = legend["picked track"].swatches
    assert green.color[1] > 150 and red.color[0] > 200 and green.marks == "0 px"


def test_survives_a_reset_and_reports_bad_picks(view, reconstructed):
    view, session = view
    session.state = dict(reconstructed)
    session.version += 1
    view.refresh(force=True)
    part = explorer(view)
    with pytest.raises(InvalidValue, match="no point"):
        part.pick_point(10 ** 7)
    session.state = {k: v for k, v in reconstructed.items() if k not in MODEL_VIEWS}
    session.version += 1
    view.refresh(force=True)
    assert part.model is None and part.scene_nodes() == []
    with pytest.raises(MissingInput, match="reconstruct_incrementally"):
        part.pick_point(0)
    part.show.value = None  # the GUI path shows the error in the tab instead of raising
    part.ctx.guarded(lambda: part.pick_point(0))()
    assert view.errors
