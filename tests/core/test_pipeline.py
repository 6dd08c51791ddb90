"""The runner: inputs, controls, history, metrics, downstream invalidation, generators, overrides."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from lab.core import (Cancelled, InvalidControl, InvalidValue, MissingInput, Progress, SessionBusy, StepFailed,
                      UnknownName, open_session)
from toy_pipeline import TOY


@pytest.fixture
def session():
    return open_session(TOY, options={"count": 3, "size": 8}, seed=7)


def test_dataset_options_are_checked(session):
    assert TOY.dataset(None).name == "gradients"
    with pytest.raises(InvalidControl) as info:  # options are checked as step controls are: one class
        open_session(TOY, options={"colour": 1})
    assert info.value.field == "options.colour" and "options are ['count', 'size']" in info.value.reason
    with pytest.raises(InvalidControl) as info:
        open_session(TOY, options={"count": 99})
    assert info.value.field == "options.count"
    with pytest.raises(UnknownName):
        open_session(TOY, "nope")


def test_steps_run_in_order_and_record_history_and_metrics(session):
    assert session.step_status() == {"add_noise": "ready", "mean_intensity": "blocked", "lift": "blocked"}
    record = session.run("add_noise", {"sigma": 0.05})
    assert record.status == "ok" and record.params == {"sigma": 0.05, "mode": "gaussian"}
    assert 0 < record.metrics["mean_abs_change"] < 0.05
    record = session.run("mean_intensity")
    assert set(record.metrics) == {"means_abs_error"}  # evaluation against the truth joins the metrics
    assert session.get("means").shape == (3,)
    assert [r.step for r in session.history] == ["add_noise", "mean_intensity"]
    assert session.summary()["steps"]["lift"] == "ready"


def test_a_step_before_its_inputs_exist_is_refused_and_changes_nothing(session):
    before = dict(session.state)
    with pytest.raises(MissingInput) as info:
        session.run("mean_intensity")
    assert info.value.field == "noisy" and "add_noise" in info.value.reason
    assert session.state == before and session.history == []


def test_bad_controls_are_refused_before_anything_runs(session):
    with pytest.raises(InvalidControl):
        session.run("add_noise", {"sigma": -1})
    assert session.history == [] and "noisy" not in session.state


def test_rerunning_a_step_invalidates_exactly_what_lies_downstream(session):
    session.run_until("lift")
    assert {"noisy", "means", "cloud"} <= set(session.state)
    means = session.get("means")
    session.run("mean_intensity", {"scale": 2})
    assert "cloud" not in session.state and "noisy" in session.state  # lift is downstream, add_noise is not
    np.testing.assert_allclose(session.get("means"), 2 * means)
    session.run("add_noise")
    assert "means" not in session.state and "cloud" not in session.state
    assert session.step_status() == {"add_noise": "done", "mean_intensity": "ready", "lift": "blocked"}


def test_put_replaces_an_input_and_drops_downstream_values(session):
    session.run_until("mean_intensity")
    downstream = session.put("noisy", session.get("images"))
    assert downstream == ["mean_intensity", "lift"]
    assert "means" not in session.state


def test_randomness_comes_from_a_recorded_per_step_seed(session):
    first = session.run("add_noise").seed
    a = session.get("noisy")[0].pixels.copy()
    second = session.run("add_noise").seed
    assert first == second
    np.testing.assert_array_equal(a, session.get("noisy")[0].pixels)
    other = open_session(TOY, options={"count": 3, "size": 8}, seed=8)
    other.run("add_noise")
    assert not np.array_equal(a, other.get("noisy")[0].pixels)


def test_generator_steps_stream_progress_and_return_their_result(session):
    session.run_until("mean_intensity")
    seen: list[Progress] = []
    record = session.run("lift", {"iterations": 4}, on_progress=lambda step, p: seen.append(p))
    assert [p.iteration for p in seen] == [1, 2, 3, 4]
    assert record.metrics["final_loss"] == pytest.approx(0.5**4)
    assert session.get("cloud").xyz.shape == (3, 3)


def test_cancelling_a_generator_step_leaves_the_state_as_it_was(session):
    session.run_until("mean_intensity")

    def cancel_at_two(step, progress):
        if progress.iteration == 2:
            session.cancel()

    with pytest.raises(Cancelled):
        session.run("lift", {"iterations": 100}, on_progress=cancel_at_two)
    assert "cloud" not in session.state
    assert session.history[-1].status == "cancelled"
    assert session.running is None
    session.run("lift", {"iterations": 2})  # the session still works


def test_a_step_that_raises_is_recorded_and_leaves_the_state(session):
    def broken(images, *, sigma=0.1, mode="gaussian", rng):
        raise ZeroDivisionError("boom")

    with pytest.raises(StepFailed) as info:
        session.run("add_noise", override=broken)
    assert "ZeroDivisionError: boom" in info.value.reason
    assert session.history[-1].status == "failed" and session.history[-1].replaced
    assert "noisy" not in session.state


def test_an_override_replaces_the_step_and_the_rest_runs_on_its_output(session):
    session.run("add_noise")

    def doubled(noisy, *, scale=1):
        return np.full(len(noisy), 2.0)

    session.run("mean_intensity", override=doubled)
    np.testing.assert_array_equal(session.get("means"), [2.0, 2.0, 2.0])
    session.run("lift", {"iterations": 1})
    np.testing.assert_array_equal(session.get("cloud").xyz[:, 0], [2.0, 2.0, 2.0])


@pytest.mark.parametrize("bad, words", [
    ("not an array", "must return ndarray"),
    (np.array([np.nan, 1.0, 2.0]), "NaN"),
])
def test_an_override_returning_the_wrong_type_or_nan_is_refused(session, bad, words):
    session.run("add_noise")
    with pytest.raises(InvalidValue) as info:
        session.run("mean_intensity", override=lambda noisy, *, scale=1: bad)
    assert words in info.value.reason
    assert "means" not in session.state


def test_one_step_at_a_time(session):
    session.run_until("mean_intensity")
    started, release = threading.Event(), threading.Event()

    def slow(step, progress):
        started.set()
        release.wait(5)

    worker = threading.Thread(target=lambda: session.run("lift", {"iterations": 1}, on_progress=slow))
    worker.start()
    assert started.wait(5)
    with pytest.raises(SessionBusy):
        session.run("add_noise")
    with pytest.raises(SessionBusy):
        session.put("noisy", session.get("images"))
    release.set()
    worker.join(5)
    assert session.get("cloud") is not None


def test_reset_forgets_a_step_and_everything_after_it(session):
    session.run_until("lift")
    session.reset("mean_intensity")
    assert set(session.state) == {"images", "noisy"}
    session.reset()
    assert set(session.state) == {"images"}


def test_unknown_names_list_what_exists(session):
    with pytest.raises(UnknownName) as info:
        session.run("nope")
    assert "add_noise" in info.value.reason
    with pytest.raises(UnknownName) as info:
        session.get("means")
    assert "mean_intensity" in info.value.reason


def test_replacing_dataset_values_drops_the_truth_but_computed_ones_keep_it(session):
    session.run("add_noise")
    session.put("noisy", session.get("images"))  # produced by a step: the truth still holds
    assert session.truth
    session.put("images", session.get("noisy"))  # the data itself changed
    assert session.truth == {}


def test_a_failing_evaluation_keeps_the_result_and_warns(session, monkeypatch):
    def broken(state, truth):
        raise IndexError("4 views against 3 poses")

    monkeypatch.setitem(session.pipeline.evaluations, "mean_intensity", broken)
    session.run("add_noise")
    record = session.run("mean_intensity")
    assert record.status == "ok" and "means" in session.state
    assert any("IndexError" in w for w in record.warnings)
