"""Sessions and runs are admitted within caps, never evicted: 429/503 with Retry-After, truthful 404s.

A flood of session creations is refused past the caps (total: 503; per client address: 429)
while a session in use stays reachable and runs steps; runs go through the app's bounded worker
pools, whose queues hold what they can and refuse the rest with 429, while /api/health answers.
No timing is asserted: only what is answered.
"""

from __future__ import annotations

import os
import threading
from collections import Counter

import pytest
from api_helpers import assert_error, make_client, new_session, running_step, wait_until
from fastapi.testclient import TestClient

import lab.api.runs
from lab.api.runs import WORKER_NICENESS, RunPool
from lab.core import SessionStore


def _store(**options) -> SessionStore:
    return SessionStore(**{"max_sessions": 8, "max_sessions_per_client": 1000, "idle_seconds": 3600.0,
                           "max_bytes": 2**26, **options})


def _as(client: TestClient, address: str) -> TestClient:
    """Another client of the same app, connecting from ``address``."""
    return TestClient(client.app, client=(address, 40000))


def test_300_creations_are_refused_past_the_cap_while_a_session_in_use_runs_steps():
    with make_client(_store()) as client:
        mine = new_session(client)
        statuses: Counter[int] = Counter()
        for i in range(300):
            response = client.post("/api/sessions", json={"module": "toy"})
            statuses[response.status_code] += 1
            if response.status_code != 201:
                body = assert_error(response, 503, "sessions", "overloaded")
                assert "limit 8" in body["reason"] and int(response.headers["Retry-After"]) >= 1
            if i % 50 == 0:  # the session in use is never evicted: it answers and runs steps throughout
                run = client.post(f"/api/sessions/{mine}/steps/add_noise", json={"sigma": 0.01 * (i % 7 + 1)})
                assert run.status_code == 200, run.text
        assert statuses == {201: 7, 503: 293}
        assert client.get(f"/api/sessions/{mine}").json()["history"][-1]["status"] == "ok"
        assert client.get("/api/health").json()["sessions"] == 8


def test_one_client_address_gets_429_past_its_share_and_others_still_get_in():
    with make_client(_store(max_sessions_per_client=2)) as client:
        first = _as(client, "10.0.0.1")
        ids = [new_session(first) for _ in range(2)]
        response = first.post("/api/sessions", json={"module": "toy"})
        body = assert_error(response, 429, "sessions", "too_many_requests")
        assert "10.0.0.1 holds 2 live sessions" in body["reason"] and int(response.headers["Retry-After"]) >= 1
        new_session(_as(client, "10.0.0.2"))  # another address has its own share
        assert first.delete(f"/api/sessions/{ids[0]}").status_code == 204
        new_session(first)  # a deleted session gives its place back
        assert client.get("/api/health").json()["max_sessions_per_client"] == 2


def test_x_forwarded_for_counts_only_when_the_app_is_told_to_trust_it():
    with make_client(_store(max_sessions_per_client=1)) as client:
        new_session(client)
        spoofed = client.post("/api/sessions", json={"module": "toy"}, headers={"X-Forwarded-For": "10.9.9.9"})
        assert_error(spoofed, 429, "sessions", "too_many_requests")  # default: the socket's peer address
    with make_client(_store(max_sessions_per_client=1), trust_forwarded_for=True) as client:
        for address in ("10.0.0.1", "10.0.0.2"):
            response = client.post("/api/sessions", json={"module": "toy"},
                                   headers={"X-Forwarded-For": f"1.2.3.4, {address}"})  # the proxy's entry is last
            assert response.status_code == 201, response.text
        again = client.post("/api/sessions", json={"module": "toy"}, headers={"X-Forwarded-For": "10.0.0.1"})
        body = assert_error(again, 429, "sessions")
        assert body["reason"].startswith("10.0.0.1 holds 1 live sessions")


def test_the_404_of_a_missing_session_says_truthfully_why():
    with make_client(_store(idle_seconds=60.0)) as client:
        expired, deleted = new_session(client), new_session(client)
        client.app.state.store.get(expired).last_used -= 120.0
        assert client.delete(f"/api/sessions/{deleted}").status_code == 204
        texts = {expired: f"session {expired!r} expired after 60 s idle and was dropped",
                 deleted: f"session {deleted!r} was deleted",
                 "0123456789ab": "no such session '0123456789ab'"}
        for sid, text in texts.items():
            assert assert_error(client.get(f"/api/sessions/{sid}"), 404, "session", "not_found")["reason"] == text
            assert assert_error(client.post(f"/api/sessions/{sid}/steps/add_noise"), 404, "session")["reason"] == text
        assert assert_error(client.delete(f"/api/sessions/{deleted}"), 404, "session")["reason"] == texts[deleted]


def _gated_ready(client: TestClient) -> str:
    """A gated session whose inputs of crawl are made, once the heavy pool is idle again: the run's answer
    comes when its job ends, the worker gives its place back just after (a test that then expects a free
    worker must not see that place still held)."""
    sid = new_session(client, "gated")
    assert client.post(f"/api/sessions/{sid}/run-until/mean_intensity").status_code == 200
    wait_until(lambda: _heavy_idle(client), "the worker to give its place back")
    return sid


def _heavy_idle(client: TestClient) -> bool:
    runs = client.get("/api/health").json()["runs"]["heavy"]
    return runs["running"] == runs["queued"] == 0


def test_runs_beyond_the_pool_wait_in_its_queue_then_get_429_and_health_answers(gate):
    with make_client(_store(), workers=1, queued_runs=1) as client:
        first, second = _gated_ready(client), _gated_ready(client)
        third = new_session(client, "gated")  # nothing run yet: its steps go to the heavy pool
        started = client.post(f"/api/sessions/{first}/steps/crawl", params={"wait": "false"})
        assert started.status_code == 202 and started.json()["status"] == "running"
        wait_until(lambda: running_step(client, first) == "crawl", "crawl to start")
        queued = client.post(f"/api/sessions/{second}/steps/crawl", params={"wait": "false"})
        assert queued.status_code == 202 and queued.json()["status"] == "queued"
        assert_error(client.post(f"/api/sessions/{second}/steps/add_noise"), 409, "session", "busy")

        refused = client.post(f"/api/sessions/{third}/steps/add_noise")  # the worker and the queue are taken
        body = assert_error(refused, 429, "server", "too_many_requests")
        assert "1 more waiting" in body["reason"] and int(refused.headers["Retry-After"]) >= 1
        assert client.post("/api/sessions", json={"module": "toy"}).status_code == 201  # loads: a pool of their own
        assert running_step(client, third) is None  # a refused run leaves its session idle

        health = client.get("/api/health")  # the event loop is free while the worker is held
        assert health.status_code == 200
        assert health.json()["runs"]["heavy"] == {"workers": 1, "running": 1, "queued": 1, "max_queued": 1}
        assert running_step(client, second) is None  # still waiting its turn, not running

        gate.release(100)
        wait_until(lambda: client.get(f"/api/sessions/{second}").json()["steps"]["crawl"] == "done", "the queued run")
        wait_until(lambda: _heavy_idle(client), "the worker to give its place back")
        assert client.post(f"/api/sessions/{third}/steps/add_noise").status_code == 200


def test_a_step_known_to_be_quick_skips_the_heavy_queue(gate, monkeypatch):
    monkeypatch.setattr(lab.api.runs, "LIGHT_SECONDS", 3600.0)  # any recorded run counts as quick: no timing
    with make_client(_store(), workers=1, queued_runs=0) as client:
        heavy, quick, fresh = _gated_ready(client), _gated_ready(client), new_session(client, "gated")
        client.post(f"/api/sessions/{heavy}/steps/crawl", params={"wait": "false"})
        wait_until(lambda: running_step(client, heavy) == "crawl", "crawl to start")
        assert_error(client.post(f"/api/sessions/{fresh}/steps/add_noise"), 429, "server")  # not known quick yet
        again = client.post(f"/api/sessions/{quick}/steps/add_noise", json={"sigma": 0.3})  # quick last time
        assert again.status_code == 200 and again.json()["params"]["sigma"] == 0.3
        assert client.get("/api/health").json()["runs"]["heavy"]["running"] == 1
        gate.release(100)


def test_a_queued_run_can_be_cancelled_before_it_starts(gate):
    with make_client(_store(), workers=1, queued_runs=4) as client:
        first, second = _gated_ready(client), _gated_ready(client)
        client.post(f"/api/sessions/{first}/steps/crawl", params={"wait": "false"})
        wait_until(lambda: running_step(client, first) == "crawl", "crawl to start")
        assert client.post(f"/api/sessions/{second}/steps/crawl", params={"wait": "false"}).json()["status"] == "queued"
        assert client.post(f"/api/sessions/{second}/cancel").status_code == 202
        gate.release(100)
        with client.stream("GET", f"/api/sessions/{second}/events") as stream:
            lines = list(stream.iter_lines())
        assert "event: error" in lines and any('"cancelled"' in line for line in lines)
        assert client.get(f"/api/sessions/{second}").json()["steps"]["crawl"] != "done"


def test_the_schema_declares_429_and_503_with_retry_after():
    with make_client(_store()) as client:
        paths = client.get("/openapi.json").json()["paths"]
    create = paths["/api/sessions"]["post"]["responses"]
    step = paths["/api/sessions/{session_id}/steps/{step}"]["post"]["responses"]
    for responses, codes in ((create, ("429", "503")), (step, ("429",))):
        for code in codes:
            assert "Retry-After" in responses[code]["headers"]
            assert responses[code]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody")


def test_workers_run_at_a_lower_cpu_priority_than_the_threads_answering_requests():
    pool = RunPool(workers=1, queue=0)
    seen: list[int] = []
    done = threading.Event()
    pool.submit(lambda: (seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id())), done.set()))
    assert done.wait(20)
    here = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    assert seen[0] == min(19, here + WORKER_NICENESS)


def test_idle_workers_leave_and_the_pool_starts_new_ones_for_new_work(monkeypatch):
    monkeypatch.setattr(lab.api.runs, "WORKER_IDLE_SECONDS", 0.05)
    pool = RunPool(workers=2, queue=2)
    done: list[int] = []
    for i in range(4):
        pool.submit(lambda i=i: done.append(i))
    wait_until(lambda: len(done) == 4 and not pool._threads, "the idle workers to leave")
    pool.submit(lambda: done.append(4))
    wait_until(lambda: len(done) == 5, "a new worker to run the next job")
    wait_until(lambda: pool.stats() == {"workers": 2, "running": 0, "queued": 0, "max_queued": 2},
               "every place to be given back")
