"""The run planner: Pipeline.plan from data flow, Session.run_plan / stale / fork.

One branching pipeline stands for the real shapes: a dataset value read by two independent branches
(texture's ``quilt`` beside its lesson micro-steps), a value written by two steps (epipolar's ``F``
by the 8-point and the RANSAC step), a dataset that already holds a downstream value (epipolar's
``correspondences`` holds x1, x2 without features).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pytest
from toy_pipeline import TOY

from lab.core import Cancelled, InvalidControl, Loaded, Pipeline, Range, UnknownName, open_session, step_result


def detect(images: np.ndarray, *, count: Annotated[int, Range(1, 9)] = 3) -> Annotated[np.ndarray, "features"]:
    """Features of the images."""
    return images[:count] * 1.0


@step_result
class Matched:
    x1: np.ndarray
    x2: np.ndarray


def match(features: np.ndarray, *, shift: float = 1.0) -> Matched:
    """Correspondences."""
    return Matched(features, features + shift)


def fit_linear(x1: np.ndarray, x2: np.ndarray) -> Annotated[np.ndarray, "F"]:
    """A first F."""
    return np.array([float((x2 - x1).mean())])


@step_result
class Robust:
    F: np.ndarray
    inliers: np.ndarray


def fit_robust(x1: np.ndarray, x2: np.ndarray, *, threshold: float = 2.0) -> Robust:
    """A better F, and inliers."""
    return Robust(np.array([float((x2 - x1).mean()) + threshold]), np.ones(len(x1), dtype=bool))


def draw_lines(F: np.ndarray, inliers: np.ndarray) -> Annotated[np.ndarray, "lines"]:
    """Reads the robust F (the last writer ahead of it)."""
    return F * inliers.sum()


def side_branch(images: np.ndarray, *, gain: float = 1.0) -> Annotated[np.ndarray, "side"]:
    """Reads only the dataset value, like texture's quilt."""
    return images * gain


def photos(*, size: Annotated[int, Range(1, 9)] = 4) -> Loaded:
    return Loaded({"images": np.arange(float(size))})


def correspondences() -> Loaded:
    return Loaded({"x1": np.zeros(3), "x2": np.ones(3)})


BRANCHY = Pipeline.build(name="branchy", title="Branchy", summary="", datasets=[photos, correspondences],
                         steps=[detect, match, fit_linear, fit_robust, draw_lines, side_branch])


def names(plan) -> list[str]:
    return list(plan.steps)


def test_a_step_that_reads_only_the_dataset_plans_only_itself():
    assert names(BRANCHY.plan("side_branch", {"images"})) == ["side_branch"]


def test_the_plan_follows_data_flow_not_list_order():
    plan = BRANCHY.plan("draw_lines", {"images"})
    # fit_linear also writes F but draw_lines reads the F of fit_robust, the last writer ahead of it
    assert names(plan) == ["detect", "match", "fit_robust", "draw_lines"]
    assert plan.reasons == {"detect": "missing", "match": "missing", "fit_robust": "missing", "draw_lines": "target"}
    assert plan.target == ("draw_lines",)


def test_present_values_are_not_recomputed_and_a_dataset_may_hold_downstream_values():
    assert names(BRANCHY.plan("fit_robust", {"x1", "x2"})) == ["fit_robust"]
    assert names(BRANCHY.plan("fit_robust", {"images", "features", "x1", "x2"})) == ["fit_robust"]


def test_stale_steps_and_what_reads_their_outputs_are_planned():
    available = {"images", "features", "x1", "x2", "F", "inliers"}
    plan = BRANCHY.plan("draw_lines", available, stale={"detect"})
    assert names(plan) == ["detect", "match", "fit_robust", "draw_lines"]
    assert plan.reasons == {"detect": "stale", "match": "stale", "fit_robust": "stale", "draw_lines": "target"}


def test_run_all_plans_missing_stale_and_dependants():
    assert names(BRANCHY.plan(None, {"images"})) == [s.name for s in BRANCHY.steps]
    done = {"images", "features", "x1", "x2", "F", "inliers", "lines", "side"}
    assert names(BRANCHY.plan(None, done)) == []
    assert names(BRANCHY.plan(None, done, stale={"match"})) == ["match", "fit_linear", "fit_robust", "draw_lines"]


def test_dependants_adds_only_downstream_steps_that_have_outputs():
    available = {"images", "features", "x1", "x2", "F", "inliers"}  # draw_lines and side_branch never ran
    plan = BRANCHY.plan("match", available, stale={"match"}, dependants=True)
    assert names(plan) == ["match", "fit_linear", "fit_robust"]
    assert names(BRANCHY.plan("match", available | {"lines"}, dependants=True)) == \
        ["match", "fit_linear", "fit_robust", "draw_lines"]


def test_several_targets_and_unknown_names():
    assert names(BRANCHY.plan(["side_branch", "match"], {"images"})) == ["detect", "match", "side_branch"]
    with pytest.raises(UnknownName):
        BRANCHY.plan("nope", set())
    with pytest.raises(UnknownName):
        BRANCHY.plan("match", set(), stale={"nope"})


def test_producer_before_a_reader_is_the_last_writer_ahead_of_it():
    assert BRANCHY.producer("F").name == "fit_linear"
    assert BRANCHY.producer("F", before="draw_lines").name == "fit_robust"
    assert BRANCHY.producer("F", before="fit_robust").name == "fit_linear"
    assert BRANCHY.producer("images", before="detect") is None


def test_session_marks_changed_controls_stale_with_their_downstream():
    session = open_session(BRANCHY)
    session.run_until("draw_lines")
    assert session.step_status()["draw_lines"] == "done"
    assert session.stale({"match": {"shift": 1.0}}) == set()  # the controls it ran with
    assert session.stale({"match": {"shift": 2.0}}) == {"match", "fit_robust", "draw_lines"}  # fit_linear never ran
    status = session.step_status({"match": {"shift": 2.0}})
    assert status["detect"] == "done" and status["match"] == "stale" and status["draw_lines"] == "stale"
    assert status["side_branch"] == "ready"
    with pytest.raises(InvalidControl):
        session.stale({"match": {"shift": "far"}})


def test_run_plan_reruns_a_changed_step_and_its_dependants():
    session = open_session(BRANCHY)
    session.run_until("draw_lines")
    before = session.state["lines"].copy()
    params = {"match": {"shift": 3.0}}
    seen = []
    records = session.run_plan(session.plan("match", params, dependants=True), params, on_step=seen.append)
    assert [r.step for r in records] == ["match", "fit_robust", "draw_lines"] == [r.step for r in seen]
    assert session.ran_with["match"] == {"shift": 3.0}
    assert not np.array_equal(session.state["lines"], before)
    assert session.stale(params) == set()


def test_run_plan_checks_every_control_first_and_stops_when_asked():
    session = open_session(BRANCHY)
    plan = session.plan("draw_lines")
    with pytest.raises(InvalidControl):
        session.run_plan(plan, {"fit_robust": {"threshold": "x"}})
    assert session.history == []  # nothing ran
    calls = iter([False, True])
    with pytest.raises(Cancelled):
        session.run_plan(plan, should_stop=lambda: next(calls))
    assert [r.step for r in session.history] == ["detect"]


def test_run_plan_overrides_replace_a_step():
    session = open_session(BRANCHY)
    session.run_plan(session.plan("match"), overrides={"detect": lambda images, count: images * 0.0})
    assert np.all(session.state["x1"] == 0.0) and session.history[0].replaced


def test_fork_copies_state_and_history_and_leaves_the_original_alone():
    session = open_session(TOY, seed=3)
    session.run_until("mean_intensity", {"add_noise": {"sigma": 0.2}})
    twin = session.fork()
    assert twin.id != session.id and twin.seed == 3 and twin.dataset == session.dataset
    assert twin.ran_with == session.ran_with and len(twin.history) == len(session.history)
    twin.run("add_noise", {"sigma": 0.0})
    assert "means" not in twin.state and "means" in session.state  # the original keeps its result
    assert session.ran_with["add_noise"] == {"sigma": 0.2, "mode": "gaussian"}


def test_reset_and_rerun_forget_what_outputs_were_made_with():
    session = open_session(TOY)
    session.run_until("lift")
    session.reset("mean_intensity")
    assert set(session.ran_with) == {"add_noise"}
    session.run_until("lift")
    session.run("add_noise", {"sigma": 0.3})  # drops what was computed from the old noise
    assert set(session.ran_with) == {"add_noise"}
