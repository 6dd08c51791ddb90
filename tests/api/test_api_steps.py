"""Running steps: records and metrics, run-until, bad controls, missing inputs, failures, and a step
run in the background with its progress streamed, a second run refused, and cancel."""

from __future__ import annotations

import threading
from typing import Generator

import numpy as np
import pytest
from api_helpers import assert_error, make_client, new_session, parse_events, running_step, snapshot, wait_until
from toy_pipeline import gradients

from lab.core.step import step_result
from lab.core import ImageSet, Pipeline, Progress, metric


@step_result
class Odd:
    odd: np.ndarray
    ratio: float = metric("not a number here")


def odd_step(images: ImageSet) -> Generator[Progress, None, Odd]:
    """Yields NumPy integers and a NaN loss; returns a NaN metric."""
    yield Progress(iteration=np.int64(1), total=np.int64(1), loss=float("nan"))
    return Odd(np.array([np.int64(3), 1.0]), float("nan"))


ODD = Pipeline.build(name="odd", title="Odd", summary="", steps=[odd_step], datasets=[gradients],
                     evaluations={"odd_step": lambda state, truth: {"inf": np.float64(np.inf), "n": np.int64(2)}})


def test_run_step_returns_the_record_with_params_seed_and_metrics(client):
    sid = new_session(client)
    response = client.post(f"/api/sessions/{sid}/steps/add_noise", json={"sigma": 0.05, "mode": "uniform"})
    assert response.status_code == 200
    record = response.json()
    assert record["step"] == "add_noise" and record["status"] == "ok" and record["session"] == sid
    assert record["params"] == {"sigma": 0.05, "mode": "uniform"}
    assert record["outputs"] == ["noisy"]
    assert 0 < record["metrics"]["mean_abs_change"] <= 0.05
    assert record["steps"]["mean_intensity"] == "ready"


def test_controls_are_optional_and_default(client):
    sid = new_session(client)
    record = client.post(f"/api/sessions/{sid}/steps/add_noise").json()
    assert record["params"] == {"sigma": 0.1, "mode": "gaussian"}


def test_same_seed_same_result(client, store):
    first, second = new_session(client, seed=3), new_session(client, seed=3)
    for sid in (first, second):
        client.post(f"/api/sessions/{sid}/steps/add_noise", json={"sigma": 0.3})
    a = store.get(first).get("noisy")[0].pixels
    b = store.get(second).get("noisy")[0].pixels
    np.testing.assert_array_equal(a, b)


def test_evaluation_against_the_truth_joins_the_metrics(client, store):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/steps/add_noise", json={"sigma": 0.0})
    record = client.post(f"/api/sessions/{sid}/steps/mean_intensity").json()
    assert record["metrics"]["means_abs_error"] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(store.get(sid).get("means"), store.get(sid).truth["means"], atol=1e-6)


def test_rerunning_a_step_invalidates_what_follows(client):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/run-until/lift")
    record = client.post(f"/api/sessions/{sid}/steps/add_noise", json={"sigma": 0.5}).json()
    assert record["steps"] == {"add_noise": "done", "mean_intensity": "ready", "lift": "blocked"}


def test_run_until_runs_what_is_not_done_with_per_step_controls(client):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/steps/add_noise")
    body = client.post(f"/api/sessions/{sid}/run-until/lift", json={"lift": {"iterations": 4}}).json()
    assert [r["step"] for r in body["records"]] == ["mean_intensity", "lift"]
    assert body["records"][1]["params"] == {"iterations": 4}
    assert body["records"][1]["metrics"]["final_loss"] == 0.5**4
    assert body["steps"] == {"add_noise": "done", "mean_intensity": "done", "lift": "done"}


def test_run_until_says_what_ran_and_reruns_a_step_given_other_controls(client):
    sid = new_session(client)
    first = client.post(f"/api/sessions/{sid}/run-until/lift").json()
    assert first["ran"] == ["add_noise", "mean_intensity", "lift"]
    assert first["plan"]["reasons"] == {"add_noise": "missing", "mean_intensity": "missing", "lift": "target"}
    again = client.post(f"/api/sessions/{sid}/run-until/lift", json={"add_noise": {"sigma": 0.1}}).json()
    assert again["ran"] == ["lift"]  # add_noise ran with these controls (the defaults): nothing is stale
    changed = client.post(f"/api/sessions/{sid}/run-until/lift", json={"add_noise": {"sigma": 0.3}}).json()
    assert changed["ran"] == ["add_noise", "mean_intensity", "lift"]
    assert changed["plan"]["reasons"]["add_noise"] == "stale"
    assert changed["records"][0]["params"]["sigma"] == 0.3


# --- bad input --------------------------------------------------------------------------------------
@pytest.mark.parametrize("controls, field, fragment", [
    ({"sigma": 3.0}, "sigma", "at most 1.0"),
    ({"sigma": -0.1}, "sigma", "at least 0.0"),
    ({"sigma": "loud"}, "sigma", "number"),
    ({"sigma": True}, "sigma", "number"),
    ({"sigma": None}, "sigma", "number"),
    ({"mode": "pink"}, "mode", "one of"),
    ({"volume": 11}, "volume", "controls are ['sigma', 'mode']"),
])
def test_bad_control_is_422_naming_it_and_changes_nothing(client, controls, field, fragment):
    sid = new_session(client)
    before = snapshot(client, sid)
    body = assert_error(client.post(f"/api/sessions/{sid}/steps/add_noise", json=controls), 422, field,
                        "invalid_control")
    assert fragment in body["reason"]
    assert snapshot(client, sid) == before


def test_integer_control_refuses_a_fraction(client):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/steps/add_noise")
    before = snapshot(client, sid)
    assert_error(client.post(f"/api/sessions/{sid}/steps/mean_intensity", json={"scale": 1.5}), 422, "scale")
    assert snapshot(client, sid) == before


@pytest.mark.parametrize("content, fragment", [
    (b'{"sigma": 0.2', "malformed JSON"),
    (b"[0.2]", "dictionary"),
    (b'"loud"', "dictionary"),
])
def test_body_that_is_not_a_json_object_is_422(client, content, fragment):
    sid = new_session(client)
    before = snapshot(client, sid)
    response = client.post(f"/api/sessions/{sid}/steps/add_noise", content=content,
                           headers={"content-type": "application/json"})
    body = assert_error(response, 422, "body", "invalid_request")
    assert fragment in body["reason"]
    assert snapshot(client, sid) == before


def test_unknown_step_is_404(client):
    sid = new_session(client)
    before = snapshot(client, sid)
    body = assert_error(client.post(f"/api/sessions/{sid}/steps/fly"), 404, "step", "not_found")
    assert "add_noise" in body["reason"]
    assert_error(client.post(f"/api/sessions/{sid}/run-until/fly"), 404, "step", "not_found")
    assert snapshot(client, sid) == before


def test_step_before_its_inputs_exist_is_409_naming_the_input(client):
    sid = new_session(client)
    before = snapshot(client, sid)
    body = assert_error(client.post(f"/api/sessions/{sid}/steps/lift"), 409, "means", "missing_input")
    assert "mean_intensity" in body["reason"]
    assert snapshot(client, sid) == before


def test_step_that_fails_on_its_input_is_422_with_the_reason(client):
    sid = new_session(client)
    client.put(f"/api/sessions/{sid}/values/means", json=[[1.0, 2.0], [3.0, 4.0]])
    before = snapshot(client, sid)
    body = assert_error(client.post(f"/api/sessions/{sid}/steps/lift"), 422, "lift", "step_failed")
    assert "ValueError" in body["reason"]
    after = snapshot(client, sid)
    assert after["history"][-1]["status"] == "failed"  # the failure is recorded (and bumps the version) ...
    unchanged = lambda s: {k: v for k, v in s.items() if k not in ("history", "version")}  # noqa: E731
    assert unchanged(after) == unchanged(before)  # ... and nothing else changed


@pytest.mark.parametrize("params, field", [
    ({"lift": {"iterations": 0}}, "lift.iterations"),
    ({"lift": {"speed": 2}}, "lift.speed"),
    ({"add_noise": {"sigma": "x"}}, "add_noise.sigma"),
    ({"fly": {}}, "fly"),
    ({"lift": 3}, "lift"),
])
def test_run_until_checks_every_control_before_running_anything(client, params, field):
    sid = new_session(client)
    before = snapshot(client, sid)
    assert_error(client.post(f"/api/sessions/{sid}/run-until/lift", json=params), 422, field)
    assert snapshot(client, sid) == before


def test_run_until_refuses_controls_of_a_later_step(client):
    sid = new_session(client)
    before = snapshot(client, sid)
    body = assert_error(client.post(f"/api/sessions/{sid}/run-until/add_noise", json={"lift": {}}), 422, "lift")
    assert "after" in body["reason"]
    assert snapshot(client, sid) == before


def test_run_until_with_a_missing_upload_is_409_before_running(client):
    sid = new_session(client)
    client.app.state.store.get(sid).state.pop("images")  # as if the dataset had no images
    before = snapshot(client, sid)
    assert_error(client.post(f"/api/sessions/{sid}/run-until/lift"), 409, "images", "missing_input")
    assert snapshot(client, sid) == before


# --- background runs, progress, busy, cancel ----------------------------------------------------------
def _gated_session_with_means(client) -> str:
    sid = new_session(client, "gated")
    client.post(f"/api/sessions/{sid}/run-until/mean_intensity")
    return sid


def test_wait_false_answers_202_and_the_events_end_with_done(client):
    sid = new_session(client)
    client.post(f"/api/sessions/{sid}/run-until/mean_intensity")
    response = client.post(f"/api/sessions/{sid}/steps/lift", params={"wait": "false"}, json={"iterations": 6})
    assert response.status_code == 202
    body = response.json()
    assert body["status"] == "running" and body["events"] == f"/api/sessions/{sid}/events"
    with client.stream("GET", body["events"]) as stream:
        assert stream.headers["content-type"].startswith("text/event-stream")
        events = list(parse_events(stream.iter_lines()))
    names = [name for name, _ in events]
    assert names == ["progress"] * 6 + ["done"]
    assert [data["iteration"] for _, data in events[:-1]] == [1, 2, 3, 4, 5, 6]
    assert events[0][1] == {"step": "lift", "iteration": 1, "total": 6, "loss": 0.5, "message": ""}
    done = events[-1][1]
    assert done["step"] == "lift" and done["status"] == "ok" and done["metrics"]["final_loss"] == 0.5**6
    assert client.get(f"/api/sessions/{sid}").json()["steps"]["lift"] == "done"


def test_events_stream_progress_live_while_the_step_runs(client, gate):
    sid = _gated_session_with_means(client)
    client.post(f"/api/sessions/{sid}/steps/crawl", params={"wait": "false"}, json={"iterations": 3})
    seen = []
    with client.stream("GET", f"/api/sessions/{sid}/events") as stream:
        for name, data in parse_events(stream.iter_lines()):
            seen.append((name, data))
            if name == "progress":
                # The step waits after each snapshot until released: this event arrived while it ran.
                assert running_step(client, sid) == "crawl"
                assert client.get(f"/api/sessions/{sid}").json()["progress"]["iteration"] == data["iteration"]
                gate.release()
    assert [n for n, _ in seen] == ["progress", "progress", "progress", "done"]
    assert [d.get("message") for _, d in seen[:3]] == ["step 1", "step 2", "step 3"]
    assert seen[-1][1]["outputs"] == ["crawled"]


def test_events_after_the_run_replay_it_and_idle_when_nothing_ran(client):
    sid = new_session(client)
    with client.stream("GET", f"/api/sessions/{sid}/events") as stream:
        assert list(parse_events(stream.iter_lines())) == [("idle", {"session": sid, "running": None})]
    client.post(f"/api/sessions/{sid}/run-until/lift", json={"lift": {"iterations": 2}})
    with client.stream("GET", f"/api/sessions/{sid}/events") as stream:
        events = list(parse_events(stream.iter_lines()))
    assert [n for n, _ in events] == ["progress", "progress", "done"]
    assert [r["step"] for r in events[-1][1]["records"]] == ["add_noise", "mean_intensity", "lift"]


def test_events_report_a_failed_run_as_an_error_event(client):
    sid = new_session(client)
    client.put(f"/api/sessions/{sid}/values/means", json=[[1.0, 2.0], [3.0, 4.0]])
    assert client.post(f"/api/sessions/{sid}/steps/lift", params={"wait": "false"}).status_code == 202
    with client.stream("GET", f"/api/sessions/{sid}/events") as stream:
        events = list(parse_events(stream.iter_lines()))
    name, data = events[-1]
    assert name == "error" and data["error"] == "step_failed" and data["field"] == "lift" and data["step"] == "lift"


def test_events_follow_a_step_the_viewer_runs(client, store, gate):
    sid = _gated_session_with_means(client)
    session = store.get(sid)
    client.get(f"/api/sessions/{sid}/events").close()  # the API now watches this session
    thread = threading.Thread(target=session.run, args=("crawl", {"iterations": 2}))  # as the viewer runs it
    thread.start()
    wait_until(lambda: session.running == "crawl", "the viewer's step to start")
    gate.release()
    with client.stream("GET", f"/api/sessions/{sid}/events") as stream:
        events = []
        for name, data in parse_events(stream.iter_lines()):
            events.append((name, data))
            if name == "progress" and data["iteration"] == 2:
                gate.release()
    thread.join(timeout=20)
    assert [n for n, _ in events] == ["progress", "progress", "done"]
    assert events[-1][1]["step"] == "crawl"


def test_a_viewer_run_nobody_watched_does_not_block_the_api(client, store):
    sid = new_session(client)
    client.get(f"/api/sessions/{sid}/events").close()  # the API watches this session's progress
    session = store.get(sid)
    session.run_until("lift")  # the viewer runs a long step; no event stream follows it to its end
    record = client.post(f"/api/sessions/{sid}/steps/lift", json={"iterations": 2})
    assert record.status_code == 200, record.text
    session.run("lift", {"iterations": 3})  # and again, then the API streams the latest run
    with client.stream("GET", f"/api/sessions/{sid}/events") as stream:
        events = list(parse_events(stream.iter_lines()))
    assert events[-1][0] == "done" and events[-1][1]["params"] == {"iterations": 3}


def test_a_second_run_while_one_runs_is_409_and_changes_nothing(client, gate):
    sid = _gated_session_with_means(client)
    assert client.post(f"/api/sessions/{sid}/steps/crawl", params={"wait": "false"}).status_code == 202
    wait_until(lambda: running_step(client, sid) == "crawl", "crawl to start")
    before = snapshot(client, sid)
    assert_error(client.post(f"/api/sessions/{sid}/steps/add_noise"), 409, "session", "busy")
    assert_error(client.post(f"/api/sessions/{sid}/steps/crawl", params={"wait": "false"}), 409, "session", "busy")
    assert_error(client.post(f"/api/sessions/{sid}/run-until/mean_intensity"), 409, "session", "busy")
    assert_error(client.post(f"/api/sessions/{sid}/reset"), 409, "session", "busy")
    assert_error(client.put(f"/api/sessions/{sid}/values/means", json=[0.5]), 409, "session", "busy")
    assert snapshot(client, sid) == before
    gate.release(3)
    wait_until(lambda: running_step(client, sid) is None, "crawl to finish")
    assert client.get(f"/api/sessions/{sid}").json()["steps"]["crawl"] == "done"


def test_waiting_run_does_not_block_other_requests(client, gate):
    sid = _gated_session_with_means(client)
    answers = {}

    def run():
        answers["crawl"] = client.post(f"/api/sessions/{sid}/steps/crawl", json={"iterations": 1})

    thread = threading.Thread(target=run)
    thread.start()
    wait_until(lambda: running_step(client, sid) == "crawl", "crawl to start")
    assert client.get("/api/health").json()["status"] == "ok"  # the event loop still answers
    gate.release()
    thread.join(timeout=20)
    assert answers["crawl"].status_code == 200 and answers["crawl"].json()["status"] == "ok"


def test_cancel_stops_a_long_step_and_leaves_the_state(client, gate):
    sid = _gated_session_with_means(client)
    client.post(f"/api/sessions/{sid}/steps/crawl", params={"wait": "false"}, json={"iterations": 5})
    wait_until(lambda: running_step(client, sid) == "crawl", "crawl to start")
    before = snapshot(client, sid)
    response = client.post(f"/api/sessions/{sid}/cancel")
    assert response.status_code == 202
    assert response.json() == {"session": sid, "cancelling": "crawl", "long": True}
    gate.release()  # the step reaches its next snapshot, where the runner stops it
    with client.stream("GET", f"/api/sessions/{sid}/events") as stream:
        events = list(parse_events(stream.iter_lines()))
    name, data = events[-1]
    assert name == "error" and data["error"] == "cancelled" and data["field"] == "crawl"
    wait_until(lambda: running_step(client, sid) is None, "the cancelled step to end")
    after = snapshot(client, sid)
    assert after["history"][-1]["status"] == "cancelled"
    assert after["values"] == before["values"] and after["steps"]["crawl"] == "ready"


def test_cancel_a_waiting_run_answers_it_with_409_cancelled(client, gate):
    sid = _gated_session_with_means(client)
    answers = {}
    thread = threading.Thread(target=lambda: answers.setdefault(
        "crawl", client.post(f"/api/sessions/{sid}/steps/crawl", json={"iterations": 5})))
    thread.start()
    wait_until(lambda: running_step(client, sid) == "crawl", "crawl to start")
    client.post(f"/api/sessions/{sid}/cancel")
    gate.release()
    thread.join(timeout=20)
    assert_error(answers["crawl"], 409, "crawl", "cancelled")


def test_cancel_with_nothing_running_is_409(client):
    sid = new_session(client)
    before = snapshot(client, sid)
    assert_error(client.post(f"/api/sessions/{sid}/cancel"), 409, "session", "not_running")
    assert snapshot(client, sid) == before


def test_delete_cancels_a_running_step(client, store, gate):
    sid = _gated_session_with_means(client)
    session = store.get(sid)
    client.post(f"/api/sessions/{sid}/steps/crawl", params={"wait": "false"}, json={"iterations": 5})
    wait_until(lambda: session.running == "crawl", "crawl to start")
    assert client.delete(f"/api/sessions/{sid}").status_code == 204
    gate.release()
    wait_until(lambda: session.running is None, "the step to stop")
    assert session.history[-1].status == "cancelled"


def test_nan_and_numpy_numbers_become_plain_json(store):
    with make_client(store, modules={"odd": ODD}.__getitem__, module_names=["odd"]) as client:
        sid = new_session(client, "odd")
        record = client.post(f"/api/sessions/{sid}/steps/odd_step").json()
        assert record["metrics"] == {"ratio": None, "inf": None, "n": 2}
        assert client.get(f"/api/sessions/{sid}").json()["metrics"]["odd_step"] == record["metrics"]
        assert client.get(f"/api/sessions/{sid}/values/odd").json() == [3.0, 1.0]
        with client.stream("GET", f"/api/sessions/{sid}/events") as stream:
            events = list(parse_events(stream.iter_lines()))
        assert events[0] == ("progress", {"step": "odd_step", "iteration": 1, "total": 1, "loss": None, "message": ""})
        assert events[1][1]["metrics"]["ratio"] is None
