"""The epipolar module's viewer interactions: click a pixel -> its epipolar line and ray; drag a 3D point ->
its projections, epipolar plane and lines; the four pose candidates with the cheirality test; inliers
and outliers coloured. Pure math against ground truth, then the interactions in a ClientView."""

from __future__ import annotations

import numpy as np
import pytest

from lab.core import InvalidValue, MissingInput, open_session
from lab.data.two_view import correspondences
from lab.modules.epipolar import PIPELINE, epipolar_lines, essential_candidates, recover_pose
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.interactions import EXPLORE_ROOT, interactions_for
from lab.geometry.camera_views import (camera_centre, click_to_pixel, epipolar_plane_corners, image_placement,
                                       lift_pixels, pixel_ray, project_point)
from lab.geometry.two_view import fundamental_from_pose
from lab.viewer.drawing import draw_overlays, match_pair_image
from lab.viewer.interactions.epipolar import (INTERACTIONS, EpipolarExplorer, MatchColours, PoseCandidates,
                                              analyse_candidates, candidate_layout,
                                              candidate_points, check_pixel,
                                              explorer_overlays, move, pick, scene_depths, two_view_geometry)

#: A small synthetic pair: 120 points, 0.5 px noise, 30 % outliers, 320 x 240 images.
SMALL = {"num_points": 120, "width": 320, "height": 240, "cx": 159.5, "cy": 119.5, "fx": 300.0, "fy": 300.0,
         "seed": 2}
NOISE_PX = 0.5


def line_distance(line, xy):
    line = np.asarray(line, dtype=np.float64)
    return float(abs(line[:2] @ np.asarray(xy) + line[2]) / np.hypot(line[0], line[1]))


def ray_distance(origin, direction, point):
    """Distance from ``point`` to the line ``origin + s direction``."""
    d = np.asarray(direction) / np.linalg.norm(direction)
    v = np.asarray(point) - np.asarray(origin)
    return float(np.linalg.norm(v - (v @ d) * d))


@pytest.fixture(scope="module")
def loaded():
    return correspondences(**SMALL)


@pytest.fixture
def view(server, store):
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    view.open_session(store.create(PIPELINE, "correspondences", SMALL))
    return view


def parts(view):
    explorer = next(i for i in view.interactions if isinstance(i, EpipolarExplorer))
    candidates = next(i for i in view.interactions if isinstance(i, PoseCandidates))
    matches = next(i for i in view.interactions if isinstance(i, MatchColours))
    return explorer, candidates, matches


# --- pure math ------------------------------------------------------------------------------------------
def test_interactions_are_found_by_the_pipeline_name():
    assert interactions_for("epipolar") == INTERACTIONS == [EpipolarExplorer, PoseCandidates, MatchColours]


def test_pixel_ray_passes_through_the_3d_point_that_projects_there(loaded):
    truth = loaded.truth
    for K, R, t, pixels in ((truth["K1"], np.eye(3), np.zeros(3), truth["x1_exact"]),
                            (truth["K2"], truth["R"], truth["t"], truth["x2_exact"])):
        for pixel, point in zip(pixels[:20], truth["points3d"][:20], strict=True):
            origin, direction = pixel_ray(K, R, t, pixel)
            assert np.allclose(origin, camera_centre(R, t))
            assert np.isclose(np.linalg.norm(direction), 1.0)
            assert ray_distance(origin, direction, point) < 1e-9 * np.linalg.norm(point)
            assert (point - origin) @ direction > 0  # in front: along the ray, not behind


def test_lift_pixels_then_a_click_ray_gives_the_pixel_back(loaded):
    truth = loaded.truth
    rng = np.random.default_rng(0)
    pixels = rng.uniform([0, 0], [319, 239], (10, 2))
    viewer = np.array([2.0, -3.0, -4.0])
    for K, R, t in ((truth["K1"], np.eye(3), np.zeros(3)), (truth["K2"], truth["R"], truth["t"])):
        lifted = lift_pixels(K, R, t, pixels, 0.35)
        depth = (lifted @ R.T + t)[:, 2]
        assert np.allclose(depth, 0.35)
        assert np.allclose(np.array([project_point(K, R, t, X)[0] for X in lifted]), pixels)
        for pixel, X in zip(pixels, lifted, strict=True):
            assert np.allclose(click_to_pixel(viewer, X - viewer, K, R, t, 0.35), pixel, atol=1e-8)


def test_click_rays_that_miss_the_image_plane_are_refused(loaded):
    K = loaded.truth["K1"]
    with pytest.raises(InvalidValue, match="edge-on"):
        click_to_pixel((0, 0, -1), (1, 0, 0), K, np.eye(3), np.zeros(3), 0.5)
    with pytest.raises(InvalidValue, match="behind the viewer"):
        click_to_pixel((0, 0, 1), (0, 0, 1), K, np.eye(3), np.zeros(3), 0.5)


def test_project_point_known_answer_and_depth(loaded):
    truth = loaded.truth
    for X, x1, x2 in zip(truth["points3d"][:20], truth["x1_exact"], truth["x2_exact"], strict=False):
        pixel1, depth1 = project_point(truth["K1"], np.eye(3), np.zeros(3), X)
        pixel2, depth2 = project_point(truth["K2"], truth["R"], truth["t"], X)
        assert np.allclose(pixel1, x1) and np.allclose(pixel2, x2)
        assert np.isclose(depth1, X[2]) and depth2 > 0
    _, behind = project_point(truth["K1"], np.eye(3), np.zeros(3), (0.1, 0.2, -3.0))
    assert behind == pytest.approx(-3.0)
    with pytest.raises(InvalidValue, match="depth 0"):
        project_point(truth["K1"], np.eye(3), np.zeros(3), (1.0, 1.0, 0.0))


def test_epipolar_plane_holds_both_centres_and_cuts_the_images_along_the_epipolar_lines(loaded):
    truth = loaded.truth
    K, R, t = truth["K1"], truth["R"], truth["t"]
    c1, c2 = np.zeros(3), camera_centre(R, t)
    F = fundamental_from_pose(K, K, R, t)
    assert np.allclose(F / np.sign(F[2, 2]), truth["F"] / np.sign(truth["F"][2, 2]), atol=1e-9)
    for X, x1, x2 in zip(truth["points3d"][:10], truth["x1_exact"], truth["x2_exact"], strict=False):
        quad = epipolar_plane_corners(c1, c2, X, extend=1.5)
        assert quad.shape == (4, 3) and np.allclose(quad[:2], [c1, c2])
        normal = np.cross(c2 - c1, X - c1)
        assert np.allclose((quad - c1) @ normal, 0.0, atol=1e-9 * np.linalg.norm(normal) * np.linalg.norm(X))
        # every point of the plane projects onto the epipolar lines: F x1 in image 2, F^T x2 in image 1
        on_plane = quad[2:] * 0.3 + 0.35 * X
        for P in on_plane:
            assert line_distance(epipolar_lines(F, x1, image=1)[0], project_point(K, R, t, P)[0]) < 1e-6
            assert line_distance(epipolar_lines(F, x2, image=2)[0],
                                 project_point(K, np.eye(3), np.zeros(3), P)[0]) < 1e-6
    with pytest.raises(InvalidValue, match="baseline"):
        epipolar_plane_corners(c1, c2, 2.5 * c2)


def test_image_placement_covers_each_pixel_ray(loaded):
    truth = loaded.truth
    K, R, t = truth["K2"], truth["R"], truth["t"]
    placement = image_placement(K, R, t, 320, 240, 0.5)
    assert placement.render_width == pytest.approx(0.5 * 320 / 300)
    assert placement.render_height == pytest.approx(0.4)
    assert np.allclose(placement.rotation, R.T)
    assert np.allclose(project_point(K, R, t, placement.position)[0], (159.5, 119.5))
    corners = np.array([project_point(K, R, t, c)[0] for c in placement.corners])
    assert np.allclose(corners, [[-0.5, -0.5], [319.5, -0.5], [319.5, 239.5], [-0.5, 239.5]])
    # the plane's x and y axes (viser draws u along +x, v along +y) are the image's u and v directions
    assert np.allclose(placement.corners[1] - placement.corners[0], placement.render_width * R.T[:, 0])
    assert np.allclose(placement.corners[3] - placement.corners[0], placement.render_height * R.T[:, 1])


def test_candidate_layout():
    offsets = candidate_layout(4, 2.0)  # two by two, centred in x, rows below the rig (+y is down)
    assert offsets.shape == (4, 3)
    assert np.allclose(offsets[:, 0], [-1.0, 1.0, -1.0, 1.0])
    assert np.allclose(offsets[:, 1], [2.0, 2.0, 4.0, 4.0]) and not offsets[:, 2].any()
    row = candidate_layout(3, 1.0, columns=3, first=0.0)
    assert np.allclose(row[:, 0], [-1.0, 0.0, 1.0]) and not row[:, 1].any()
    with pytest.raises(InvalidValue, match="spacing"):
        candidate_layout(4, 0.0)


def test_exactly_one_candidate_passes_cheirality_and_it_is_the_recovered_pose(loaded):
    truth, state = loaded.truth, loaded.state
    inliers = ~truth["outliers"]
    candidates = essential_candidates(truth["E"])
    x1, x2 = truth["x1_exact"], truth["x2_exact"]
    analysis = analyse_candidates(candidates, truth["K1"], truth["K2"], x1, x2, source="truth")
    assert analysis.total == len(x1)
    assert analysis.counts[analysis.chosen] == len(x1)  # every exact pair in front of both cameras
    assert np.sum(analysis.counts == len(x1)) == 1 and np.all(np.delete(analysis.counts,
                                                                        analysis.chosen) < len(x1))
    chosen = analysis.candidates[analysis.chosen]
    assert np.allclose(chosen[:, :3], truth["R"], atol=1e-9)
    assert np.allclose(chosen[:, 3], truth["t"] / np.linalg.norm(truth["t"]), atol=1e-9)
    pose = recover_pose(truth["E"], state["x1"], state["x2"], truth["K1"], truth["K2"], inliers)
    assert np.allclose(pose, chosen)
    # the points drawn: the chosen candidate's are the true points up to the baseline's length
    points, in_front = candidate_points(candidates, truth["K1"], truth["K2"], x1[:10], x2[:10])
    assert points.shape == (4, 10, 3) and in_front.shape == (4, 10)
    assert np.allclose(points[analysis.chosen] * np.linalg.norm(truth["t"]),
                       truth["points3d"][:10], rtol=1e-6)
    assert in_front[analysis.chosen].all() and not in_front[(analysis.chosen + 2) % 4].any()  # -t: all behind
    spacing = 1.6 * analysis.far * analysis.scale  # two by two below the rig, apart from each other
    np.testing.assert_allclose(analysis.offsets, candidate_layout(4, spacing, first=0.9))
    with pytest.raises(InvalidValue, match="candidates"):
        analyse_candidates(candidates[:, :, :3], truth["K1"], truth["K2"], x1, x2)
    with pytest.raises(MissingInput):
        analyse_candidates(candidates, truth["K1"], truth["K2"], x1[:0], x2[:0])


def test_check_pixel():
    assert np.allclose(check_pixel((3, 4.5), 10, 8, 1), (3, 4.5))
    assert np.allclose(check_pixel([-0.5, 7.5], 10, 8, 1), (-0.5, 7.5))
    with pytest.raises(InvalidValue, match="outside image 2"):
        check_pixel((10, 1), 10, 8, 2)
    with pytest.raises(InvalidValue, match="finite"):
        check_pixel((np.nan, 1), 10, 8, 1)
    with pytest.raises(InvalidValue, match="two numbers"):
        check_pixel((1, 2, 3), 10, 8, 1)


def test_geometry_comes_from_the_session_else_the_truth(loaded):
    state, truth = dict(loaded.state), loaded.truth
    geometry = two_view_geometry(state, truth)
    assert geometry.f_source == geometry.pose_source == "the ground truth"
    assert np.allclose(geometry.R, truth["R"]) and np.allclose(geometry.F, truth["F"]) and geometry.has_pose
    session = open_session(PIPELINE, "correspondences", SMALL)
    session.run_until("recover_pose")
    geometry = two_view_geometry(session.state, session.truth)
    assert geometry.f_source.startswith("the session")
    assert geometry.pose_source == "the session (recover_pose)"
    assert geometry.F is session.state["F"] or np.allclose(geometry.F, session.state["F"])
    assert np.allclose(geometry.t, session.state["pose"][:,
                                                         3]) and np.isclose(np.linalg.norm(geometry.t), 1.0)
    session.run("refine_pose")
    assert two_view_geometry(session.state, session.truth).pose_source == "the session (refine_pose)"
    # no truth, nothing computed: F and the pose are unknown (K from the dataset stays)
    bare = two_view_geometry(state, {})
    assert bare.F is None and not bare.has_pose and bare.K1 is not None
    assert bare.camera(2) is None and bare.camera(1) is not None
    assert two_view_geometry({"images": None}, truth) is None
    # with only a pose (no F anywhere), F is the pose's
    only_pose = two_view_geometry({**state}, {k: v for k, v in truth.items() if k != "F"})
    assert only_pose.f_source.startswith("the pose")


def test_pick_and_move_known_answers(loaded):
    truth = loaded.truth
    geometry = two_view_geometry(loaded.state, truth)
    depth, far = scene_depths(geometry, (truth["x1_exact"], truth["x2_exact"]))
    assert 0 < depth < far and np.isclose(depth, np.median(truth["points3d"][:, 2]), rtol=1e-6)
    for i in range(5):
        result = pick(geometry, truth["x1_exact"][i], image=1, far=far)
        assert line_distance(result.line, truth["x2_exact"][i]) < 1e-6
        assert ray_distance(result.ray[0], result.ray[1] - result.ray[0], truth["points3d"][i]) < 1e-9
        assert result.segment.shape == (2, 2) and result.plane.shape == (3, 3)
        back = pick(geometry, truth["x2_exact"][i], image=2, far=far)
        assert line_distance(back.line, truth["x1_exact"][i]) < 1e-6
        assert ray_distance(back.ray[0], back.ray[1] - back.ray[0], truth["points3d"][i]) < 1e-9
        moved = move(geometry, truth["points3d"][i])
        assert np.allclose(moved.pixels, [truth["x1_exact"][i], truth["x2_exact"][i]])
        assert np.all(moved.depths > 0)
        assert line_distance(moved.lines[0], moved.pixels[0]) < 1e-6
        assert line_distance(moved.lines[1], moved.pixels[1]) < 1e-6
    overlays = explorer_overlays(geometry, result, moved)
    assert len(overlays[0]) >= 3 and len(overlays[1]) >= 3  # pixel / line, projection, line (+ epipole)
    with pytest.raises(InvalidValue, match="image"):
        pick(geometry, (1, 1), image=3)
    with pytest.raises(MissingInput, match="fundamental"):
        pick(two_view_geometry(loaded.state, {}), (1, 1))
    with pytest.raises(MissingInput, match="pose"):
        move(two_view_geometry(loaded.state, {}), (0, 0, 5))


def test_match_pair_image_colours_inliers_green_and_outliers_red(loaded):
    images, x1, x2 = loaded.state["images"], loaded.state["x1"], loaded.state["x2"]
    inliers = ~loaded.truth["outliers"]
    picture = match_pair_image(images[0], images[1], x1, x2, inliers, height=240)
    assert picture.shape == (240, 640, 3) and picture.dtype == np.uint8

    def count(rgb, color):
        return int(np.sum(np.all(rgb == np.array(color, np.uint8), axis=2)))

    assert count(picture, (30, 200, 60)) > 100 and count(picture, (235, 40, 40)) > 100
    assert count(picture, (255, 210, 0)) == 0
    everything_in = match_pair_image(images[0], images[1], x1, x2, np.ones(len(x1), bool), height=240)
    assert count(everything_in, (235, 40, 40)) == 0
    unclassified = match_pair_image(images[0], images[1], x1, x2, None, height=120)
    assert unclassified.shape == (120, 320, 3) and count(unclassified, (255, 210, 0)) > 0


# --- in the viewer --------------------------------------------------------------------------------------
def test_the_interactions_are_built_with_the_truth_before_any_step(view):
    explorer, candidates, matches = parts(view)
    assert view.errors == []
    assert explorer.geometry.f_source == "the ground truth"
    assert "ground truth" in explorer.source_md.content
    names = explorer.scene_nodes()
    for part in ("rig/camera1/image", "rig/camera2/image", "rig/camera1/frustum",
                 "point/handle", "point/plane"):
        assert part in names
    assert explorer.nodes.handles["rig/camera1/image"].name == f"{EXPLORE_ROOT}/epipolar/rig/camera1/image"
    bounds = explorer.bounds()  # for framing the tab's camera: holds both centres and the point
    c2 = camera_centre(explorer.geometry.R, explorer.geometry.t)
    for point in (np.zeros(3), c2, explorer.last_point.point):
        assert np.all(bounds[0] <= point + 1e-9) and np.all(point <= bounds[1] + 1e-9)
    # before RANSAC: the candidates of the true E, and the matches not classified yet
    assert candidates.analysis is not None and candidates.analysis.source == "the ground truth E"
    assert len([n for n in candidates.scene_nodes() if n.endswith("/rig")]) == 4
    assert matches.counts is None and "run estimate_fundamental_ransac" in matches.summary_md.content


def test_click_a_pixel_shows_its_epipolar_line_and_ray(view):
    explorer, _, _ = parts(view)
    view.run("refine_points", until=True)
    assert [e.name for e in explorer.legend()] == ["explorer cameras", "3D point"]  # a point, no pick yet
    assert view.errors == [] and explorer.geometry.f_source.startswith("the session")
    truth, state = view.session.truth, view.session.state
    inliers = np.flatnonzero(state["inliers"] & ~truth["outliers"])
    for i in inliers[:5]:
        result = explorer.pick_pixel(*truth["x1_exact"][i])
        # the session's F: the line passes through the true match within the noise
        assert line_distance(result.line, truth["x2_exact"][i]) < 4 * NOISE_PX
        # the session's pose (|t| = 1): the ray passes through the true point, scaled to the baseline
        point = truth["points3d"][i] / np.linalg.norm(truth["t"])
        assert ray_distance(result.ray[0], result.ray[1] - result.ray[0],
                            point) < 0.02 * np.linalg.norm(point)
    names = explorer.scene_nodes()
    assert {"pick/ray", "pick/plane", "pick/line", "pick/pixel"} <= set(names)
    ray = explorer.nodes.handles["pick/ray"].points
    assert np.allclose(ray.reshape(2, 3), result.ray, atol=1e-5)
    assert explorer.pixel_input.value == pytest.approx(tuple(truth["x1_exact"][inliers[4]]))
    assert "epipolar line" in explorer.pick_md.content
    # the epipolar line is drawn into image 2 (yellow) on its plane in 3D and in the Images panel
    assert np.any(np.all(explorer.textures[1] >= (200, 170, 0), axis=2) & (explorer.textures[1][..., 2] < 80))
    # a pixel of image 2 gives a line in image 1
    back = explorer.pick_pixel(*truth["x2_exact"][inliers[0]], image=2)
    assert line_distance(back.line, truth["x1_exact"][inliers[0]]) < 4 * NOISE_PX


def test_a_click_on_the_image_plane_in_the_scene_picks_that_pixel(view):
    explorer, _, _ = parts(view)
    geometry = explorer.geometry
    target = np.array([[200.0, 60.0]])
    for image in (1, 2):
        camera = geometry.camera(image)
        on_plane = lift_pixels(*camera, target, explorer.depth)[0]
        viewer = np.array([0.5, -2.0, -3.0])
        result = explorer.click_image(image, viewer, on_plane - viewer)
        assert result.image == image and np.allclose(result.pixel, target[0], atol=1e-6)
        assert np.allclose(result.line, pick(geometry, target[0], image=image, far=explorer.far).line)
    # the same through the GUI's number inputs
    explorer.image_choice.value = "image 1"
    explorer.pixel_input.value = (10.0, 20.0)
    assert np.allclose(explorer.last_pick.pixel, (10.0, 20.0)) and explorer.last_pick.image == 1


def test_drag_a_point_moves_its_projections_plane_and_lines(view):
    explorer, _, _ = parts(view)
    truth = view.session.truth
    for i in (0, 7):
        result = explorer.move_point(truth["points3d"][i])
        assert np.allclose(result.pixels, [truth["x1_exact"][i], truth["x2_exact"][i]])
        assert line_distance(result.lines[0], result.pixels[0]) < 1e-6
        assert line_distance(result.lines[1], result.pixels[1]) < 1e-6
    plane = explorer.nodes.handles["point/plane"]
    assert np.allclose(plane.vertices, result.plane.astype(np.float32))
    assert np.allclose(explorer.nodes.handles["point/handle"].position, truth["points3d"][7])
    assert explorer.point_input.value == pytest.approx(tuple(truth["points3d"][7]))
    assert {"point/rays", "point/line1", "point/line2", "point/marker"} <= set(explorer.scene_nodes())
    # the gizmo's drag calls the same code (as viser's on_update would)
    explorer._move(np.array([0.2, 0.1, 4.0]), from_handle=True)
    assert np.allclose(explorer.point_input.value, (0.2, 0.1, 4.0))
    # the number inputs too
    explorer.point_input.value = (0.0, 0.3, 6.0)
    assert np.allclose(explorer.last_point.point, (0.0, 0.3, 6.0))
    assert "behind" not in explorer.point_md.content
    explorer.move_point((0.0, 0.0, -2.0))
    assert "behind the camera" in explorer.point_md.content


def test_four_candidates_side_by_side_with_the_chosen_one_highlighted(view):
    _, candidates, _ = parts(view)
    view.run("recover_pose", until=True)
    a = candidates.analysis
    assert a.source == "the session (decompose_essential)"
    stored = view.session.state["candidates"]
    assert a.candidates is stored or np.allclose(a.candidates, stored)
    inliers = int(view.session.state["inliers"].sum())
    assert a.total == inliers and a.counts[a.chosen] >= 0.95 * inliers
    assert np.sum(a.counts >= 0.5 * inliers) == 1  # exactly one passes
    assert np.allclose(a.candidates[a.chosen], view.session.state["pose"])
    assert "✓ passes (chosen)" in candidates.table_md.content
    assert "is the pose recover_pose returned" in candidates.table_md.content
    names = candidates.scene_nodes()
    assert {f"candidates/{i}/{part}" for i in range(4) for part in ("rig", "label")} <= set(names)
    chosen_rig = candidates.nodes.handles[f"candidates/{a.chosen}/rig"]
    other_rig = candidates.nodes.handles[f"candidates/{(a.chosen + 1) % 4}/rig"]
    assert tuple(np.asarray(chosen_rig.colors).reshape(-1, 3)[0]) == (30, 190, 60)
    assert tuple(np.asarray(other_rig.colors).reshape(-1, 3)[0]) == (150, 150, 150)
    label = candidates.nodes.handles[f"candidates/{a.chosen}/label"]
    assert f"{int(a.counts[a.chosen])}/{a.total} in front" in label.text and "passes" in label.text
    # the copies sit two by two below the scene (+y is down), apart from each other
    rigs = [candidates.nodes.handles[f"candidates/{i}/rig"].points.reshape(-1, 3) for i in range(4)]
    centres = np.array([r.mean(axis=0) for r in rigs])
    assert centres[0, 0] < centres[1, 0] and centres[2, 0] < centres[3, 0]
    assert centres[2, 1] > centres[0, 1] > 0
    assert [e.name for e in candidates.legend()] == ["pose candidates"]
    candidates.show_box.value = False
    assert candidates.scene_nodes() == []
    candidates.show_box.value = True
    assert len(candidates.scene_nodes()) >= 8


def test_inliers_green_outliers_red_after_ransac(view):
    _, _, matches = parts(view)
    view.run("estimate_fundamental_ransac", until=True)
    inliers = view.session.state["inliers"]
    assert matches.counts == (int(inliers.sum()), int((~inliers).sum()))
    assert matches.panel.visible and matches.picture.shape[0] == 360
    assert "green" in matches.panel.label and "Against the ground truth" in matches.summary_md.content


def test_reset_falls_back_to_the_truth_and_survives(view):
    explorer, candidates, matches = parts(view)
    view.run("refine_points", until=True)
    explorer.pick_pixel(100.0, 100.0)
    explorer.move_point((0.1, 0.1, 5.0))
    view.reset("estimate_fundamental_8point")
    view.reset("estimate_fundamental_ransac")
    assert "F" not in view.session.state and "pose" not in view.session.state
    assert explorer.geometry.f_source == "the ground truth"
    assert explorer.geometry.pose_source == "the ground truth"
    assert explorer.last_pick is not None and explorer.last_point is not None  # redrawn with the truth
    assert "pick/ray" in explorer.scene_nodes()
    assert candidates.analysis.source == "the ground truth E"
    assert matches.counts is None
    assert explorer.pick_pixel(50.0, 60.0) is not None
    assert not any("Error" in e or "Traceback" in e for e in view.errors)


def test_without_truth_a_reset_clears_the_drawing_and_picks_say_why(server, store):
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    session = store.create(PIPELINE, "correspondences", SMALL)
    session.truth.clear()  # like a user's photos
    view.open_session(session)
    explorer, candidates, _matches = parts(view)
    assert explorer.geometry.F is None and "none yet" in explorer.source_md.content
    assert not any(n.startswith("point/") for n in explorer.scene_nodes())
    assert explorer.pick_pixel(10.0, 10.0) is None
    assert "no fundamental matrix yet" in view.errors[-1]
    assert candidates.analysis is None and "decompose_essential" in candidates.table_md.content
    view.run("refine_points", until=True)
    assert explorer.pick_pixel(10.0, 10.0) is not None and explorer.move_point((0, 0, 5)) is not None
    assert candidates.analysis is not None
    view.reset("estimate_fundamental_ransac")
    assert explorer.last_pick is None and explorer.last_point is None
    assert not any(n.startswith(("pick/", "point/")) for n in explorer.scene_nodes())
    assert candidates.analysis is None and candidates.scene_nodes() == []
    assert explorer.move_point((0, 0, 5)) is None and "no relative pose yet" in view.errors[-1]


def test_bad_picks_give_a_clear_error_not_an_exception(view):
    explorer, _, _ = parts(view)
    assert explorer.pick_pixel(400.0, 10.0) is None
    assert "outside image 1 (320x240" in view.errors[-1]
    assert explorer.pick_pixel(10.0, 500.0, image=2) is None
    assert "outside image 2" in view.errors[-1]
    assert explorer.pick_pixel(float("nan"), 1.0) is None and "finite" in view.errors[-1]
    assert explorer.click_image(1, (0, 0, -1), (1, 0, 0)) is None and "edge-on" in view.errors[-1]
    c2 = camera_centre(explorer.geometry.R, explorer.geometry.t)
    assert explorer.move_point(2 * c2) is None and "baseline" in view.errors[-1]
    assert explorer.move_point((1.0, "x", 2.0)) is None and "three numbers" in view.errors[-1]
    assert explorer.last_pick is None  # nothing drawn by the failures, the session untouched
    assert view.session.step_status()["estimate_fundamental_8point"] == "ready"


def test_rendered_scene_pick_passes_through_the_true_match(server, store):
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    view.open_session(store.create(PIPELINE, "rendered",
                                   {"width": 160, "height": 120, "supersample": 1, "seed": 1}))
    explorer, candidates, matches = parts(view)
    view.run("recover_pose", until=True)
    assert view.errors == []
    truth = view.session.truth
    distances = [line_distance(explorer.pick_pixel(*x1).line, x2)
                 for x1, x2 in zip(truth["x1_exact"][::40], truth["x2_exact"][::40], strict=True)]
    assert np.median(distances) < 1.0
    assert np.allclose(candidates.analysis.candidates[candidates.analysis.chosen], view.session.state["pose"])
    assert matches.counts is not None and matches.counts[0] > 0


def test_closing_removes_every_node(view, store):
    explorer, candidates, _matches = parts(view)
    handles = list(explorer.nodes.handles.values()) + list(candidates.nodes.handles.values())
    assert handles
    view.open_session(store.create(PIPELINE, "correspondences", SMALL))
    assert explorer.scene_nodes() == [] and candidates.scene_nodes() == []
    assert all(h._impl.removed for h in handles)
    assert view.interactions[0] is not explorer


def test_draw_overlays_draws_thick_lines_and_circles_at_the_right_pixels():
    from lab.core import Image, Points2D, Segments2D

    image = Image(np.full((100, 200), 0.5, np.float32))
    line = Segments2D(np.array([[10.0, 50.0]]), np.array([[190.0, 50.0]]), colors=np.array([[1.0, 1.0, 0.0]]))
    ring = Points2D(np.array([[100.0, 20.0]]), colors=np.array([[1.0, 0.0, 1.0]]))
    rgb = draw_overlays(image, [line, ring], min_side=400)
    assert rgb.shape == (200, 400, 3)  # enlarged twice, like the panel's images
    assert tuple(rgb[101, 200]) == (255, 255, 0) and tuple(rgb[60, 200]) == (128, 128, 128)
    # the ring around (100, 20) -> (201, 41)
    assert np.any(np.all(rgb[20:60, 180:220] == (255, 0, 255), axis=2))
    assert tuple(rgb[41, 201]) == (128, 128, 128)  # an outline: its centre is untouched


def test_viser_callbacks_click_and_drag_reach_the_interaction(view):
    """The callbacks registered on the scene nodes, called as viser calls them (click on an image plane, a
    gizmo drag's update and end), do what pick_pixel / move_point do; their errors go to the tab."""
    from types import SimpleNamespace

    explorer, _, _ = parts(view)
    truth = view.session.truth
    plane = explorer.nodes.handles["rig/camera1/image"]
    target = lift_pixels(*explorer.geometry.camera(1), truth["x1_exact"][3:4], explorer.depth)[0]
    viewer = np.array([0.3, -1.0, -2.0])
    [entry] = plane._impl.click_cb
    entry.callback(SimpleNamespace(target=plane, ray_origin=tuple(viewer),
                                   ray_direction=tuple(target - viewer)))
    assert np.allclose(explorer.last_pick.pixel, truth["x1_exact"][3], atol=1e-6)
    assert line_distance(explorer.last_pick.line, truth["x2_exact"][3]) < 1e-6
    entry.callback(SimpleNamespace(target=plane, ray_origin=(0.0, 0.0, -1.0), ray_direction=(1.0, 0.0, 0.0)))
    assert "edge-on" in view.errors[-1]  # shown, not raised into viser

    gizmo = explorer.nodes.handles["point/handle"]
    panel_before = explorer.panel_images[1].image.copy()
    gizmo.position = tuple(truth["points3d"][9])
    for callback in gizmo._impl_aux.update_cb:
        callback(SimpleNamespace(target=gizmo, phase="update"))
    assert np.allclose(explorer.last_point.pixels, [truth["x1_exact"][9], truth["x2_exact"][9]])
    assert np.array_equal(explorer.panel_images[1].image, panel_before)  # panels wait for the drag's end
    for callback in gizmo._impl_aux.update_cb:
        callback(SimpleNamespace(target=gizmo, phase="end"))
    assert not np.array_equal(explorer.panel_images[1].image, panel_before)


def test_without_k_a_pick_gives_the_line_but_no_ray(server, store, loaded):
    state = {k: v for k, v in loaded.state.items() if k not in ("K1", "K2")}
    geometry = two_view_geometry({**state, "F": loaded.truth["F"]}, {})
    assert geometry.K1 is None and geometry.camera(1) is None and not geometry.has_pose
    result = pick(geometry, loaded.truth["x1_exact"][0])
    assert result.ray is None and result.plane is None
    assert line_distance(result.line, loaded.truth["x2_exact"][0]) < 1e-6
    # in the viewer: no rig in 3D, the line still drawn on image 2
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    session = store.create(PIPELINE, "correspondences", SMALL)
    session.truth.clear()
    for name in ("K1", "K2"):
        session.state.pop(name)
    view.open_session(session)
    explorer = parts(view)[0]
    assert explorer.scene_nodes() == [] and explorer.bounds() is None and "No K" in explorer.source_md.content
    view.run("estimate_fundamental_ransac", until=True)
    assert explorer.pick_pixel(*loaded.truth["x1_exact"][0]) is not None
    assert explorer.scene_nodes() == [] and explorer.last_pick.segment is not None


def test_camera_labels_stand_apart_beside_their_image_planes():
    from lab.viewer.interactions.epipolar.geometry import label_anchors

    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    R2, t2 = np.eye(3), np.array([-0.1, 0.0, 0.0])  # camera 2 a short baseline to the right of camera 1
    planes = [image_placement(K, R, t, 320, 240, 0.05).corners for R, t in ((np.eye(3), np.zeros(3)), (R2, t2))]
    centres = np.stack([np.zeros(3), camera_centre(R2, t2)])
    anchors = label_anchors(centres, planes, spread=0.2)
    assert anchors[0, 0] < planes[0][:, 0].min() - 0.19 and anchors[1, 0] > planes[1][:, 0].max() + 0.19
    assert anchors[1, 0] - anchors[0, 0] >= 2 * 0.2 + 0.1  # apart by both spreads and the baseline
    assert np.all(anchors[:, 1] < planes[0][:, 1].min())  # above the planes (y is down)
    seen = anchors[:, :2] / (anchors[:, 2:] + 3.0)  # seen from 3 behind the cameras, along their axis
    assert abs(seen[1, 0] - seen[0, 0]) > 0.1
    np.testing.assert_allclose(label_anchors(centres[:1], planes[:1], spread=0.2), centres[:1])  # one camera
