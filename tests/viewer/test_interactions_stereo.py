"""The stereo module's viewer interactions: disparity and error maps against the truth; click a pixel -> every
matching cost over disparity with its minimum and the true disparity; the rectified rig in 3D; a baseline
slider that restarts the synthetic rig and shows the depth uncertainty u_z = z^2 u_d / (f B).

Pure math first (known answers from the synthetic pair's exact disparity), then the interactions in a
ClientView on a quiet viser server. The synthetic pair is small (112 x 84) so that each session loads
and runs in about a second.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from lab.core import Image, InvalidControl, InvalidValue, open_session
from lab.geometry.camera_views import lift_pixels
from lab.modules.stereo import COSTS, PIPELINE, box_mean, colorize_disparity, depth_from_disparity, error_map
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.interactions import EXPLORE_ROOT, interactions_for
from lab.viewer.interactions.stereo import (INTERACTIONS, BaselineExplorer, BaselineRecord, CostCurveExplorer,
                                            DisparityMaps, check_pick, click_to_left_pixel, cost_plot,
                                            depth_range, depth_uncertainty_curve, disparity_stage,
                                            gather_cost_curves, matching_settings,
                                            normalize_curves, rig_segments,
                                            searchable_disparity, stereo_maps, uncertainty_plot)

SMALL = {"width": 112, "height": 84, "baseline": 0.3}
MAX_DISPARITY = 24


@pytest.fixture(scope="module")
def session():
    """The small synthetic pair run to winner-take-all with the raw SAD costs (no aggregation)."""
    s = open_session(PIPELINE, "synthetic", SMALL)
    s.run("rectify_pair")
    s.run("cost_volume", {"cost": "sad", "window": 5, "max_disparity": MAX_DISPARITY})
    s.run("aggregate_costs", {"method": "none"})
    s.run("winner_take_all")
    return s


def textured_pixels(session, count: int = 6) -> list[tuple[int, int]]:
    """Pixels with the most texture (gray variance over 7 x 7) where the truth is smooth, away from the
    borders."""
    from scipy.ndimage import maximum_filter, minimum_filter

    left, truth = session.state["left"], session.truth["disparity"]
    gray = left.gray().astype(np.float64)
    variance = box_mean(gray * gray, 7) - box_mean(gray, 7) ** 2
    usable = (truth >= 0) & (maximum_filter(truth, 7) - minimum_filter(truth, 7) < 0.5)
    usable[:6], usable[-6:], usable[:, :MAX_DISPARITY + 4], usable[:, -6:] = False, False, False, False
    picked: list[tuple[int, int]] = []
    for index in np.argsort(np.where(usable, variance, -1.0).ravel())[::-1]:
        y, x = divmod(int(index), left.width)
        if all(abs(x - a) + abs(y - b) > 8 for a, b in picked):  # spread out
            picked.append((x, y))
        if len(picked) == count:
            break
    return picked


@pytest.fixture
def view(server, store):
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    view.open_session(store.create(PIPELINE, "synthetic", SMALL))
    return view


def parts(view) -> tuple[DisparityMaps, CostCurveExplorer, BaselineExplorer]:
    kinds = (DisparityMaps, CostCurveExplorer, BaselineExplorer)
    return tuple(next(i for i in view.interactions if isinstance(i, kind)) for kind in kinds)  # type: ignore


def run_to(view, step: str, **controls) -> None:
    """Run every step up to ``step`` with the test's cost volume settings (and ``controls`` per step)."""
    names = [s.name for s in PIPELINE.steps]
    for name in names[:names.index(step) + 1]:
        params = {"cost_volume": {"cost": "census", "max_disparity": MAX_DISPARITY}}.get(name, {})
        view.run_with(name, {**params, **controls.get(name, {})})
    assert view.session.step_status()[step] == "done", view.errors


# --- pure math ------------------------------------------------------------------------------------------
def test_interactions_are_found_by_the_pipeline_name():
    assert interactions_for("stereo") == INTERACTIONS == [DisparityMaps, CostCurveExplorer, BaselineExplorer]


def test_check_pick_rounds_to_pixel_centres_and_refuses_the_outside():
    assert check_pick(3.4, 6.6, 10, 8) == (3, 7)
    assert check_pick(-0.5, -0.49, 10, 8) == (0, 0)
    assert check_pick(9.49, 7.2, 10, 8) == (9, 7)
    for x, y in ((10, 0), (-0.6, 0), (0, 7.5), (np.nan, 1), (1, np.inf)):
        with pytest.raises(InvalidValue, match=r"outside the left image|finite"):
            check_pick(x, y, 10, 8)
    with pytest.raises(InvalidValue, match="two numbers"):
        check_pick("a", 1, 10, 8)


def test_a_click_ray_through_the_left_image_plane_gives_that_pixel(session):
    K = session.state["K"]
    left = session.state["left"]
    viewer = np.array([0.4, -1.5, -2.0])
    for pixel in ((0, 0), (57, 33), (111, 83)):
        on_plane = lift_pixels(K, np.eye(3), np.zeros(3), np.array([pixel], np.float64), 0.7)[0]
        assert click_to_left_pixel(viewer, on_plane - viewer, K, left.width, left.height, 0.7) == pixel
    with pytest.raises(InvalidValue, match="edge-on"):
        click_to_left_pixel(viewer, (1.0, 0.0, 0.0), K, left.width, left.height, 0.7)
    outside = lift_pixels(K, np.eye(3), np.zeros(3), np.array([[200.0, 10.0]]), 0.7)[0]
    with pytest.raises(InvalidValue, match="outside the left image"):
        click_to_left_pixel(viewer, outside - viewer, K, left.width, left.height, 0.7)


def test_normalize_curves_maps_each_row_to_0_1_and_keeps_its_minimum():
    rng = np.random.default_rng(0)
    costs = np.stack([rng.uniform(3, 9, 20), 1000 * rng.uniform(0, 1, 20), np.full(20, 4.0)])
    out = normalize_curves(costs)
    assert out.shape == costs.shape
    assert np.allclose(out[:2].min(axis=1), 0) and np.allclose(out[:2].max(axis=1), 1)
    assert np.array_equal(out[:2].argmin(axis=1), costs[:2].argmin(axis=1))
    assert np.all(out[2] == 0)  # a flat curve: no minimum to favour
    # invariant to each cost's unit and offset
    assert np.allclose(normalize_curves(5 * costs[:2] + 2), out[:2])


def test_cost_curve_minima_are_the_winner_take_all_disparity_of_the_session_cost(session):
    """With the raw costs (no aggregation) the session's cost curve is lowest exactly where winner-take-all
    chose, at every pixel tried, and so is the session's own volume's column."""
    left, right = session.state["left"], session.state["right"]
    wta = session.state["disparity_wta"]
    rng = np.random.default_rng(3)
    pixels = [(0, 0), (left.width - 1, left.height - 1), (5, 40)] + [
        (int(x), int(y)) for x, y in zip(rng.integers(0, left.width, 12),
                                         rng.integers(0, left.height, 12), strict=True)]
    for x, y in pixels:
        curves = gather_cost_curves(left, right, x, y, window=5, max_disparity=MAX_DISPARITY,
                                    aggregated_cost=session.state["aggregated_cost"])
        assert curves.labels == (*COSTS, "aggregated")
        assert curves.costs.shape == curves.normalized.shape == (len(COSTS) + 1, MAX_DISPARITY + 1)
        assert curves.minimum("sad") == wta[y, x], (x, y)
        assert curves.minimum("aggregated") == wta[y, x]
        assert np.allclose(curves.costs[COSTS.index("sad")], session.state["cost_volume"][y, x], atol=1e-6)
        assert np.array_equal(curves.minima, np.argmin(curves.costs, axis=1))
    with pytest.raises(InvalidValue, match="no curve"):
        curves.minimum("sgm")


def test_the_true_disparity_is_at_the_minimum_on_textured_pixels(session):
    left, right, truth = session.state["left"], session.state["right"], session.truth["disparity"]
    for x, y in textured_pixels(session):
        curves = gather_cost_curves(left, right, x, y, window=5, max_disparity=MAX_DISPARITY,
                                    truth_disparity=truth)
        assert curves.truth == pytest.approx(truth[y, x])
        for label in COSTS:
            assert abs(curves.minimum(label) - curves.truth) <= 1.0, (label, x, y,
                                                                      curves.minima, curves.truth)


def test_a_pixel_without_truth_has_none_and_bad_pixels_are_refused(session):
    left, right = session.state["left"], session.state["right"]
    unknown = np.full((left.height, left.width), -1.0)
    assert gather_cost_curves(left, right, 50, 40, window=5, max_disparity=8,
                              truth_disparity=unknown).truth is None
    with pytest.raises(InvalidValue, match="outside the left image"):
        gather_cost_curves(left, right, left.width, 0, window=5, max_disparity=8)


def test_cost_plot_marks_each_minimum_and_the_truth_on_one_shared_axis(session):
    left, right, truth = session.state["left"], session.state["right"], session.truth["disparity"]
    x, y = textured_pixels(session, 1)[0]
    curves = gather_cost_curves(left, right, x, y, window=5, max_disparity=MAX_DISPARITY,
                                truth_disparity=truth)
    config = cost_plot(curves, session_cost="census")
    data, series = config["data"], config["series"]
    n = len(COSTS)
    assert len(data) == len(series) == 1 + 2 * n + 1  # x, the curves, their minimum markers, the truth
    assert all(len(column) == MAX_DISPARITY + 3 for column in data)  # the truth inserted twice
    xs = data[0]
    assert np.all(np.diff(xs) >= 0)
    for s, label in enumerate(COSTS):
        curve, marker = data[1 + s], data[1 + n + s]
        assert np.nanmin(curve) == pytest.approx(0.0) and np.nanmax(curve) == pytest.approx(1.0)
        [at] = np.flatnonzero(np.isfinite(marker))
        assert xs[at] == curves.minimum(label) and marker[at] == pytest.approx(0.0)
        assert series[1 + n + s]["points"]["show"] and series[1 + s]["label"].startswith(label)
    assert "session's cost" in series[1 + COSTS.index("census")]["label"]
    assert series[1 + COSTS.index("census")]["width"] > series[1]["width"]
    line = data[-1]
    assert np.allclose(xs[np.isfinite(line)], curves.truth)
    assert np.nanmax(line) > 1.0
    assert np.nanmin(line) == 0.0
    no_truth = cost_plot(gather_cost_curves(left, right, x, y, window=5, max_disparity=MAX_DISPARITY))
    assert len(no_truth["data"]) == 1 + 2 * n and len(no_truth["data"][0]) == MAX_DISPARITY + 1


def test_depth_uncertainty_curve_is_the_formula():
    z = np.linspace(0.5, 12.0, 40)
    for f, B, u_d in ((500.0, 0.12, 0.5), (83.1, 0.3, 1.0), (1200.0, 2.0, 0.25)):
        u = depth_uncertainty_curve(z, focal_px=f, baseline=B, disparity_std=u_d)
        assert np.allclose(u, z ** 2 * u_d / (f * B), rtol=1e-12)
    # doubling the baseline halves the uncertainty; it grows with the square of depth
    u1 = depth_uncertainty_curve(z, focal_px=500.0, baseline=0.1, disparity_std=0.5)
    assert np.allclose(depth_uncertainty_curve(z, focal_px=500.0, baseline=0.2, disparity_std=0.5), u1 / 2)
    assert np.allclose(depth_uncertainty_curve(2 * z, focal_px=500.0, baseline=0.1,
                                               disparity_std=0.5), 4 * u1)
    # and it is the module's: depth_from_disparity at d = f B / z
    depth, module = depth_from_disparity(np.array([[10.0, 25.0]]), np.diag([500.0, 500.0, 1.0]), 0.1,
                                         disparity_std=0.5)
    assert np.allclose(depth_uncertainty_curve(depth[0], focal_px=500.0, baseline=0.1,
                                               disparity_std=0.5), module[0])
    for bad in (np.array([0.0, 1.0]), np.array([np.nan]), np.ones((2, 2))):
        with pytest.raises(InvalidValue, match="depths"):
            depth_uncertainty_curve(bad, focal_px=500.0, baseline=0.1, disparity_std=0.5)
    with pytest.raises(InvalidValue, match="baseline"):
        depth_uncertainty_curve(z, focal_px=500.0, baseline=0.0, disparity_std=0.5)


def test_uncertainty_plot_has_one_curve_per_baseline_on_one_grid():
    now, before = BaselineRecord(0.3, 100.0, 0.5), [BaselineRecord(0.12, 100.0, 0.5),
                                                    BaselineRecord(1.0, 100.0, 0.5)]
    config = uncertainty_plot(now, before, 1.0, 5.0, samples=11)
    z, *curves = config["data"]
    assert np.allclose(z, np.linspace(1.0, 5.0, 11)) and len(curves) == 3
    for curve, record in zip(curves, [now, *before], strict=True):
        assert np.allclose(curve, z ** 2 * 0.5 / (100.0 * record.baseline))
    labels = [s["label"] for s in config["series"][1:]]
    assert labels == ["B = 0.3 m (now)", "B = 0.12 m", "B = 1 m"]
    previewed = uncertainty_plot(now, before, 1.0, 5.0, samples=11, preview=BaselineRecord(0.5, 100.0, 0.5))
    assert previewed["series"][-1]["label"] == "B = 0.5 m (slider, not applied)"
    assert np.allclose(previewed["data"][-1], z ** 2 * 0.5 / (100.0 * 0.5))


def test_depth_range_and_settings_known_answers(session):
    truth_depth = session.truth["depth"]
    near, far = depth_range(truth_depth, None)
    assert near == pytest.approx(truth_depth[truth_depth > 0].min())
    assert far == pytest.approx(truth_depth.max())
    assert depth_range(None, None) == (0.5, 10.0)
    assert depth_range(np.zeros((4, 4)), np.linspace(1, 3, 101)) == pytest.approx((1.02, 2.98))
    defaults = {c.name: c.default for c in PIPELINE.step("cost_volume").controls}
    ran = matching_settings(session.state, session.history, defaults, 112)
    assert (ran.cost, ran.window, ran.max_disparity) == ("sad", 5, MAX_DISPARITY)
    assert ran.source.startswith("the session")
    fresh = matching_settings({}, [], defaults, 40, np.array([[3.0, 50.0]]))
    assert (fresh.cost, fresh.window, fresh.max_disparity) == ("census", 5, 39)  # capped by the width
    assert searchable_disparity(np.array([[-1.0, 30.2]]), 640, 480, 64) == 64
    assert searchable_disparity(np.array([[-1.0, 100.2]]), 640, 480, 64) == 103
    assert searchable_disparity(np.array([[500.0]]), 640, 480, 64) == 2 ** 26 // (640 * 480) - 1  # volume cap
    assert searchable_disparity(None, 32, 24, 64) == 31


def test_stereo_maps_against_the_truth(session):
    truth = session.truth["disparity"]
    perfect = stereo_maps("final", truth, truth, threshold=2.0)
    assert perfect.scores["bad2_all"] == 0.0 and perfect.scores["coverage"] == 1.0
    assert np.array_equal(perfect.disparity.pixels, perfect.truth.pixels)
    assert np.array_equal(perfect.errors.pixels, error_map(truth, truth, threshold=2.0).pixels)
    wrong = truth + 3.0
    wrong[:10] = -1.0  # holes
    maps = stereo_maps("winner-take-all", wrong, truth, threshold=2.0, scale=30.0)
    assert maps.scale == 30.0 and maps.scores["bad2_all"] == 1.0 and maps.scores["bad2_pred"] == 1.0
    assert np.array_equal(maps.disparity.pixels, colorize_disparity(wrong, max_disparity=30.0).pixels)
    assert np.all(maps.errors.pixels[:10, :, 2] > 0.9)  # blue
    assert np.all(maps.errors.pixels[10:, :, 0] >= 0.5)  # red
    alone = stereo_maps("final", truth, None, threshold=1.0)
    assert alone.truth is None and alone.errors is None and alone.scores == {}
    with pytest.raises(InvalidControl, match="threshold"):
        stereo_maps("final", truth, truth, threshold=0.0)
    assert disparity_stage({"disparity_wta": truth, "disparity_subpixel": truth + 1},
                           "latest")[0] == "sub-pixel"
    assert disparity_stage({}, "latest") is None
    assert disparity_stage({"disparity": truth}, "final")[0] == "final"
    with pytest.raises(InvalidValue, match="stage"):
        disparity_stage({}, "sgm")


def test_rig_segments_place_both_cameras_a_baseline_apart():
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]])
    rig = rig_segments(K, 0.3, 100, 80, 2.0)
    assert rig.shape == (2, 8, 2, 3)
    assert np.allclose(rig[0, :4, 0], 0.0) and np.allclose(rig[1, :4, 0], [0.3, 0, 0])  # spokes: centres
    assert np.allclose(rig[:, :, 1, 2], 2.0) and np.allclose(rig[1, 4:] - rig[0, 4:], [0.3, 0, 0], atol=1e-6)
    assert np.allclose(rig[0, 4, 0], [-50 * 2 / 100, -40 * 2 / 100, 2.0])  # the outline's top-left corner


# --- the interactions in a viewer ---------------------------------------------------------------------
def test_before_rectification_there_is_nothing_to_pick_but_the_uncertainty_is_shown(view):
    maps, costs, baseline = parts(view)
    assert "rectify_pair" in costs.source_md.content and costs.curves is None and costs.scene_nodes() == []
    assert maps.maps is None and not maps.disparity_panel.visible
    assert costs.pick_pixel(3, 3) is None and "no rectified pair yet" in view.errors[-1]
    config = baseline.plot_config()  # from the dataset's calibration already
    assert [s["label"] for s in config["series"][1:]] == ["B = 0.3 m (now)"]
    assert baseline.slider is not None and baseline.slider.value == pytest.approx(0.3)
    baseline.slider.value = 0.9  # moving the slider previews its curve, dotted, without a restart
    session = view.session
    labels = [s["label"] for s in baseline.plot_config()["series"][1:]]
    assert labels == ["B = 0.3 m (now)", "B = 0.9 m (slider, not applied)"]
    assert len(baseline._plot.series) == 3 and "would give" in baseline.summary_md.content
    assert view.session is session


def test_click_a_pixel_shows_every_cost_with_its_minimum_and_the_truth(view):
    _, costs, _ = parts(view)
    run_to(view, "winner_take_all", aggregate_costs={"method": "none"})
    state, truth = view.session.state, view.session.truth["disparity"]
    assert costs.settings.cost == "census" and costs.settings.max_disparity == MAX_DISPARITY
    for x, y in ((60, 40), (30, 20)):
        curves = costs.pick_pixel(x, y)
        assert curves.pixel == (x, y) and (costs.x_input.value, costs.y_input.value) == (x, y)
        assert curves.minimum("census") == state["disparity_wta"][y, x] == curves.minimum("aggregated")
        assert curves.truth == pytest.approx(truth[y, x])
        assert f"winner-take-all: **{state['disparity_wta'][y, x]}**" in costs.pick_md.content
    # the Plots tab has the curves (a uPlot), the session's cost marked
    config = costs.plot_config()
    assert costs._plot is not None and len(costs._plot.series) == len(config["series"])
    assert any("census (session's cost)" in s["label"] for s in config["series"])
    assert {"rig/left/image", "rig/left/frustum", "rig/right/frustum", "rig/baseline", "pick/ray",
            "pick/pixel"} <= set(costs.scene_nodes())
    assert costs.ctx.node("rig") == f"{EXPLORE_ROOT}/stereo/rig"
    # the number inputs do the same as a click
    costs.x_input.value = 70
    assert costs.curves.pixel == (70, 20)
    assert costs.bounds() is not None and costs.bounds()[1, 0] >= 0.3  # both cameras framed
    # the legend says what the rig and the pick are
    assert [e.name for e in costs.legend()] == ["stereo rig", "picked pixel"]


def test_a_click_on_the_left_image_plane_in_the_scene_picks_that_pixel(view):
    _, costs, _ = parts(view)
    run_to(view, "rectify_pair")
    K = view.session.state["K"]
    target = (80, 22)
    on_plane = lift_pixels(K, np.eye(3), np.zeros(3), np.array([target], np.float64), costs.depth)[0]
    viewer = np.array([0.2, -0.8, -1.5])
    assert costs.click_image(viewer, on_plane - viewer).pixel == target
    # as viser calls the plane's click callback; a miss is shown, not raised into viser
    plane = costs.nodes.handles["rig/left/image"]
    [entry] = plane._impl.click_cb
    other = lift_pixels(K, np.eye(3), np.zeros(3), np.array([[10.0, 70.0]]), costs.depth)[0]
    entry.callback(SimpleNamespace(target=plane, ray_origin=tuple(viewer),
                                   ray_direction=tuple(other - viewer)))
    assert costs.curves.pixel == (10, 70)
    entry.callback(SimpleNamespace(target=plane, ray_origin=(0.0, 0.0, -1.0), ray_direction=(1.0, 0.0, 0.0)))
    assert "edge-on" in view.errors[-1]


def test_a_pick_outside_the_image_is_a_clear_error_in_the_tab(view):
    _, costs, _ = parts(view)
    run_to(view, "rectify_pair")
    before = costs.curves
    assert costs.pick_pixel(500, 3) is None
    assert "outside the left image (112 x 84" in view.errors[-1]
    assert costs.pick_pixel(-4, 10) is None and "outside" in view.errors[-1]
    assert costs.curves is before  # the last good pick stays


def test_maps_and_the_point_cloud_with_both_cameras(view):
    maps, costs, _baseline = parts(view)
    run_to(view, "winner_take_all")
    assert maps.maps.stage == "winner-take-all" and maps.disparity_panel.visible and maps.error_panel.visible
    # the truth's colours in full
    assert maps.maps.scale == pytest.approx(view.session.truth["disparity"].max())
    assert "bad-2" in maps.summary_md.content
    run_to(view, "reconstruct_points")
    state = view.session.state
    assert maps.maps.stage == "final"
    assert maps.maps.scores["bad2_all"] == pytest.approx(view.session.metrics["filter_disparity"]["bad2_all"])
    shown = maps.show("winner-take-all", threshold=1.0)
    assert shown.stage == "winner-take-all" and "bad1_pred" in shown.scores
    assert maps.show("sgm") is None and "stage" in view.errors[-1]
    # reconstruct_points draws the cloud and both cameras (generic Cameras): the explorer's own frustums go
    assert {"points3d", "cameras"} <= set(view.drawer.drawn)
    assert np.allclose(state["cameras"].centers, [[0, 0, 0], [0.3, 0, 0]])
    assert "rig/left/frustum" not in costs.scene_nodes() and "rig/left/image" in costs.scene_nodes()
    assert "pick/point" in costs.scene_nodes()  # the picked pixel's ray ends at its depth


def test_the_baseline_slider_restarts_the_rig_and_runs_to_the_point_cloud(view):
    _, _, old = parts(view)
    run_to(view, "cost_volume")
    first = view.session
    assert old.set_baseline(0.6)
    view.wait()
    new_maps, new_costs, new = parts(view)
    session = view.session
    assert session is not first and session.options["baseline"] == pytest.approx(0.6)
    assert session.dataset == "synthetic" and session.options["width"] == 112
    assert session.state["baseline"] == pytest.approx(0.6)
    assert session.step_status()["reconstruct_points"] == "done"
    assert np.allclose(session.state["cameras"].centers[1], [0.6, 0, 0])
    # the old session's controls, the range widened to the larger true disparities (d = f B / Z doubles)
    [record] = [r for r in session.history if r.step == "cost_volume"]
    assert record.params["cost"] == "census"
    assert record.params["max_disparity"] >= np.ceil(session.truth["disparity"].max())
    # the uncertainty plot shows the new baseline and the previous one, each the formula
    config = new.plot_config()
    labels = [s["label"] for s in config["series"][1:]]
    assert labels == ["B = 0.6 m (now)", "B = 0.3 m"]
    z = config["data"][0]
    f = session.state["K"][0, 0]
    assert np.allclose(config["data"][1], z ** 2 * 0.5 / (f * 0.6))
    assert np.allclose(config["data"][2], 2 * config["data"][1])
    assert new._plot is not None and "B = 0.6 m" in new.summary_md.content
    assert new_maps.maps.stage == "final" and new_costs.curves is not None
    assert not old.handles and not view.errors
    # a baseline out of the rig's range: a clear error, the session stays
    assert not new.set_baseline(5.0)
    assert "baseline" in view.errors[-1] and view.session is session


def test_reset_clears_the_drawing_and_picks_say_why(view):
    maps, costs, _ = parts(view)
    run_to(view, "winner_take_all")
    costs.pick_pixel(40, 40)
    view.reset("rectify_pair")
    assert costs.curves is None and costs.scene_nodes() == [] and costs._plot is None
    assert maps.maps is None and not maps.error_panel.visible
    assert costs.pick_pixel(40, 40) is None and "run rectify_pair" in view.errors[-1]
    run_to(view, "rectify_pair")  # and it comes back
    assert costs.pick_pixel(40, 40).pixel == (40, 40) and "rig/left/image" in costs.scene_nodes()


def test_datasets_without_a_baseline_option_have_no_slider(server, store):
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    view.open_session(store.create(PIPELINE, "motorcycle", {"downsample": 8}))
    _, costs, baseline = parts(view)
    assert baseline.slider is None and "fixed" in baseline.summary_md.content
    assert not baseline.set_baseline(0.3) and "synthetic" in view.errors[-1]
    view.run_with("rectify_pair", {})
    curves = costs.pick_pixel(60, 30)
    assert curves is not None and curves.truth is not None  # Middlebury's true disparity


def test_closing_removes_every_node_and_plot(view, store):
    _, costs, baseline = parts(view)
    run_to(view, "rectify_pair")
    assert costs.scene_nodes() and costs._plot is not None and baseline._plot is not None
    view.open_session(store.create(PIPELINE, "synthetic", SMALL))
    assert costs.scene_nodes() == [] and not costs.handles and not baseline.handles


def test_image_values_are_left_to_the_generic_drawing(view):
    """The interactions add what the generic drawing lacks: it draws the pair and the final disparity
    image."""
    run_to(view, "filter_disparity")
    assert {"left", "right", "disparity_image"} <= set(view.drawer.drawn)
    assert isinstance(view.session.state["disparity_image"], Image)


def test_the_baseline_button_restarts_the_rig_with_the_sliders_baseline(view):
    """The button's own callback (it once passed an argument _apply does not take, so a click only showed a
    TypeError)."""
    _, _, baseline = parts(view)
    first = view.session
    baseline.slider.value = 0.45
    baseline.apply_button.value = True  # a button's value setter runs its click callbacks
    view.wait()
    assert not view.errors and view.session is not first
    assert view.session.options["baseline"] == pytest.approx(0.45)
    assert view.session.step_status()["reconstruct_points"] == "done"
