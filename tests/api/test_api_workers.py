"""Several API workers on one database, in process: sticky session ids, the 421 answer, and grading in one
worker only (the real processes behind a proxy: test_api_worker_processes.py)."""

from __future__ import annotations

import os
import socket
import sys
import threading
import time
from pathlib import Path

import pytest
from api_helpers import make_client, new_session

from lab.api.workers import WorkerIdentity, owner_of, parse_peers
from lab.core import SessionStore
from lab.lessons.format import LessonCatalog
from lab.lessons.service import LessonService
from lab.lessons.store import SubmissionQueue
from lab.server import MAX_RESTARTS, WorkerPlan, serve_workers

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "lessons"))
from lesson_helpers import FIXTURES, submission

PEERS = {"w0": "http://127.0.0.1:8000", "w1": "http://127.0.0.1:8001"}


def worker_client(name: str, **kwargs):
    store = SessionStore(max_sessions=8, idle_seconds=3600.0, max_bytes=64 * 2**20)
    return make_client(store, worker=WorkerIdentity(name, PEERS), **kwargs)


def test_a_session_lives_on_its_worker_and_another_worker_answers_421_naming_it():
    with worker_client("w0") as w0, worker_client("w1") as w1:
        session = new_session(w0)
        assert owner_of(session) == "w0" and len(session) == len("w0-") + 12
        read = w0.get(f"/api/sessions/{session}")
        assert read.status_code == 200 and read.headers["x-vision-lab-worker"] == "w0"
        assert read.json()["links"]["self"] == f"/api/sessions/{session}"
        misdirected = [w1.get(f"/api/sessions/{session}"), w1.delete(f"/api/sessions/{session}"),
                       w1.post(f"/api/sessions/{session}/steps/add_noise", json={}),
                       w1.post(f"/api/sessions/{session}/run-until/mean_intensity", json={}),
                       w1.post(f"/api/sessions/{session}/reset"), w1.post(f"/api/sessions/{session}/cancel"),
                       w1.get(f"/api/sessions/{session}/events"),
                       w1.get(f"/api/sessions/{session}/values/images"),
                       w1.put(f"/api/sessions/{session}/values/images", content=b"{}",
                              headers={"Content-Type": "application/json"})]
        for response in misdirected:
            assert response.status_code == 421, response.text
            assert response.headers["x-vision-lab-worker"] == "w1"
            assert response.json() == {
                "error": "misdirected", "field": "session", "worker": "w0", "url": PEERS["w0"],
                "reason": f"session {session!r} lives on worker w0 ({PEERS['w0']}), not on this worker (w1): "
                          "live sessions stay in the process that made them; route /api/sessions/w0-* to "
                          "worker w0"}
        assert w0.get(f"/api/sessions/{session}").status_code == 200  # nothing happened to it
        assert w0.post(f"/api/sessions/{session}/steps/add_noise", json={}).status_code == 200
        unknown = w1.get("/api/sessions/w7-0123456789ab")
        assert unknown.status_code == 421 and "url" not in unknown.json()
        assert "its address is not known here" in unknown.json()["reason"]
        assert w1.get("/api/sessions/w1-0123456789ab").status_code == 404  # its own id: the store answers
        health = w1.get("/api/health").json()
        assert (health["worker"], health["grading"]) == ("w1", True)
        responses = w1.app.openapi()["paths"]["/api/sessions/{session_id}"]["get"]["responses"]
        assert "421" in responses


def test_a_lone_server_keeps_plain_ids_and_never_answers_421(client):
    session = new_session(client)
    assert owner_of(session) is None and "-" not in session
    assert "x-vision-lab-worker" not in client.get(f"/api/sessions/{session}").headers
    assert client.get("/api/sessions/w0-0123456789ab").status_code == 404
    assert client.get("/api/health").json()["worker"] is None


def test_worker_ids_and_peers_are_checked():
    assert parse_peers(" w0=http://a:1/ , w1=http://b:2,") == {"w0": "http://a:1", "w1": "http://b:2"}
    for bad in ("w0", "w0=", "W0=http://a", "w 0=http://a"):
        with pytest.raises(ValueError):
            parse_peers(bad)
    with pytest.raises(ValueError, match="lower-case letters and digits"):
        WorkerIdentity("w-1")
    assert owner_of("w12-00ff") == "w12" and owner_of("00ff00ff00ff") is None and owner_of("w1-xyz") is None


def _graded(submission_row) -> dict:
    return {"score": 1.0, "tests": [{"name": "t", "score": 1.0, "max_score": 1.0, "status": "passed"}]}


def test_a_worker_that_does_not_grade_stores_submissions_and_reads_back_what_another_graded(tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"

    def service() -> LessonService:
        return LessonService(catalog=LessonCatalog(FIXTURES / "lessons"), queue=SubmissionQueue(url),
                             poll_s=0.05, grade=_graded)

    front, grader = worker_client("w1", grading=False), worker_client("w0")
    front.app.state.lesson_service, grader.app.state.lesson_service = service(), service()
    with front:
        answer = front.post("/api/lessons/00-toy/submissions",
                            files={"file": ("s.py", submission("toy", "solution.py"), "text/x-python")})
        assert answer.status_code == 202, answer.text
        submission_id = answer.json()["id"]
        time.sleep(0.3)  # several poll periods of a dispatcher, were one running here
        assert not front.app.state.lesson_service.pool.running  # no dispatcher claims here
        assert front.get(f"/api/submissions/{submission_id}").json()["status"] == "queued"
        with grader:  # the grading worker starts, claims it from the shared database and grades it
            deadline = time.monotonic() + 30
            while front.get(f"/api/submissions/{submission_id}").json()["status"] != "done":
                assert time.monotonic() < deadline, "the grading worker never graded it"
                time.sleep(0.05)
        body = front.get(f"/api/submissions/{submission_id}").json()
        assert (body["score"], body["gradings"]) == (1.0, 1)
        assert body["results"]["tests"][0]["status"] == "passed"
        listed = front.get("/api/lessons/00-toy/submissions").json()
        assert [s["id"] for s in listed["submissions"]] == [submission_id] and listed["counts"]["done"] == 1
        assert front.get("/api/lessons/00-toy/stats").json()["lesson"] == "00-toy"


def _plan(name: str, code: str, port: int) -> WorkerPlan:
    return WorkerPlan(name, port, port + 100, (sys.executable, "-c", code, "--host", "127.0.0.1"))


def test_the_supervisor_restarts_a_worker_that_exits_and_gives_up_on_one_that_keeps_dying(tmp_path):
    starts = tmp_path / "starts"
    crashing = _plan("w0", f"open({str(starts)!r}, 'a').write('x'); raise SystemExit(3)", free_port())
    assert serve_workers([crashing], poll_s=0.02) == 1
    assert starts.read_text() == "x" * (MAX_RESTARTS + 1)  # the first start and MAX_RESTARTS more

    stop = threading.Event()
    started = tmp_path / "pid"
    code = f"import os, time; open({str(started)!r}, 'w').write(str(os.getpid())); time.sleep(60)"
    sleeper = _plan("w0", code, free_port())
    runner = threading.Thread(target=lambda: codes.append(serve_workers([sleeper], stop=stop, poll_s=0.02)))
    codes: list[int] = []
    runner.start()
    deadline = time.monotonic() + 30
    while not (started.exists() and started.read_text()):
        assert time.monotonic() < deadline, "the worker never started"
        time.sleep(0.02)
    stop.set()
    runner.join(timeout=30)
    assert codes == [0]
    with pytest.raises(ProcessLookupError):  # stopped and reaped
        os.kill(int(started.read_text()), 0)


def test_the_supervisor_refuses_a_taken_port_before_starting_anything(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        marker = tmp_path / "started"
        with pytest.raises(OSError, match=f"worker w1's port {port}"):
            serve_workers([_plan("w0", f"open({str(marker)!r}, 'w')", free_port()),
                           _plan("w1", f"open({str(marker)!r}, 'w')", port)])
    assert not marker.exists()


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]
