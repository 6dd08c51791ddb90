"""The assignment seed stored with a lesson run: drawn once, kept, used by every grading, never shown to a
student; set by the instructor (REST, CLI), and a regrade of a lesson's submissions."""

from __future__ import annotations

import json
import threading

import pytest
import typer
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from lab.api.lessons import build_app
from lab.core.errors import InvalidValue
from lab.lessons.cli import PRACTICE_NOTE, register
from lab.lessons.format import LessonCatalog
from lab.lessons.service import LessonService
from lab.lessons.store import MAX_SEED, SubmissionQueue

from lesson_helpers import FIXTURES, submission, wait_done

TOY = str(FIXTURES / "lessons" / "00-toy")
TOKEN = "s3cret"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def make_service(url: str, **kwargs) -> LessonService:
    return LessonService(catalog=LessonCatalog(FIXTURES / "lessons"), queue=SubmissionQueue(url), poll_s=0.05,
                         instructor_token=TOKEN, **kwargs)


def upload(client, source: str, student: str = "ana") -> str:
    response = client.post("/api/lessons/00-toy/submissions", data={"student": student},
                           files={"file": ("mine.py", source.encode(), "text/x-python")})
    assert response.status_code == 202, response.text
    return response.json()["id"]


# --- the store -----------------------------------------------------------------------------------------
def test_the_seed_is_drawn_once_and_kept_across_service_instances(tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    first, second = make_service(url), make_service(url)
    seed = first.queue.assignment_seed("00-toy")
    assert 0 <= seed <= MAX_SEED
    assert second.queue.assignment_seed("00-toy") == seed == first.queue.assignment_seed("00-toy")
    other = second.queue.assignment_seed("01-calibration")  # one per lesson
    assert first.queue.set_assignment_seed("00-toy", 42) == 42
    assert second.queue.assignment_seed("00-toy") == 42
    assert make_service(url).queue.assignment_seed("00-toy") == 42
    assert first.queue.assignment_seed("01-calibration") == other
    assert second.queue.set_assignment_seed("02-epipolar", MAX_SEED) == MAX_SEED  # set before first use


def test_concurrent_first_use_agrees_on_one_seed(tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    queues = [SubmissionQueue(url) for _ in range(4)]
    seen: list[int] = []
    threads = [threading.Thread(target=lambda q=q: seen.append(q.assignment_seed("00-toy"))) for q in queues]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(seen) == 4 and len(set(seen)) == 1


@pytest.mark.parametrize("bad", [-1, MAX_SEED + 1, 2**40, True, "5", 1.5, None])
def test_the_store_refuses_bad_seeds(tmp_path, bad):
    queue = SubmissionQueue(f"sqlite:///{tmp_path / 'db.sqlite'}")
    with pytest.raises(InvalidValue) as caught:
        queue.set_assignment_seed("00-toy", bad)
    assert caught.value.field == "seed"


# --- grading with it -------------------------------------------------------------------------------------
def test_the_service_grades_with_the_stored_seed(tmp_path, monkeypatch):
    from lab.lessons import grader

    seen: list[int | None] = []

    class Report:
        def results_json(self) -> dict:
            return {"score": 1.0, "tests": [{"name": "t", "score": 1.0, "max_score": 1.0, "status": "passed",
                                             "output": "Passed"}]}

    def fake_grade(lesson, source, *, seed=None, **_):
        seen.append(seed)
        return Report()

    monkeypatch.setattr(grader, "grade", fake_grade)
    service = make_service(f"sqlite:///{tmp_path / 'db.sqlite'}")
    service.queue.set_assignment_seed("00-toy", 777)
    with TestClient(build_app(service)) as client:
        assert wait_done(client, upload(client, "x = 1"))["status"] == "done"
    assert seen == [777]


def comparable(body: dict) -> dict:
    """A submission's results without the time grading took (``execution_time``, the summary line's)."""
    return {k: v for k, v in body["results"].items() if k not in ("execution_time", "output")}


def test_a_regrade_with_the_same_seed_gives_the_same_results_and_no_seed_reaches_the_student(tmp_path):
    service = make_service(f"sqlite:///{tmp_path / 'db.sqlite'}")
    seed = 987654321
    with TestClient(build_app(service)) as client:
        put = client.put("/api/lessons/toy/assignment", json={"seed": seed}, headers=AUTH)
        assert put.json()["seed"] == seed
        submission_id = upload(client, submission("toy", "wrong_ignores_scale.py"))
        first = wait_done(client, submission_id)
        assert first["status"] == "done" and 0 < first["score"] < first["max_score"]
        regraded = client.post("/api/lessons/00-toy/regrade", headers=AUTH)
        assert regraded.status_code == 202 and regraded.json()["requeued"] == 1
        again = wait_done(client, submission_id)
        assert again["status"] == "done" and comparable(again) == comparable(first)
        instructor = client.get(f"/api/submissions/{submission_id}?view=instructor", headers=AUTH).json()
        student_paths = (f"/api/submissions/{submission_id}", "/api/lessons", "/api/lessons/00-toy",
                         "/api/lessons/00-toy/starter.py")
        student_texts = [client.get(path).text for path in student_paths]
    derived = ints(instructor["results"]["extra_data"]["seeds"])
    assert derived  # the instructor sees the check data's seeds
    for text in student_texts:
        for secret in [seed, *(s for s in derived if s >= 10_000)]:  # (a lesson's pinned seed may be short)
            assert str(secret) not in text


def ints(value) -> list[int]:
    """Every integer in a JSON value."""
    if isinstance(value, dict):
        return [i for v in value.values() for i in ints(v)]
    if isinstance(value, list):
        return [i for v in value for i in ints(v)]
    return [value] if isinstance(value, int) and not isinstance(value, bool) else []


def test_the_student_view_drops_an_assignment_seed_the_grader_would_write(tmp_path):
    results = {"score": 1.0, "tests": [], "extra_data": {"seeds": {"small": [5]}, "assignment_seed": 123456,
                                                        "max_score": 1.0}}
    service = make_service(f"sqlite:///{tmp_path / 'db.sqlite'}", grade=lambda job: results)
    with TestClient(build_app(service)) as client:
        submission_id = upload(client, "x = 1")
        student = wait_done(client, submission_id)
    assert student["results"]["extra_data"] == {"max_score": 1.0}


# --- the instructor's routes ----------------------------------------------------------------------------
INSTRUCTOR_ROUTES = [("get", "/api/lessons/00-toy/assignment", None),
                     ("put", "/api/lessons/00-toy/assignment", {"seed": 5}),
                     ("put", "/api/lessons/00-toy/assignment", {"seed": -1}),  # 403 before the body is read
                     ("post", "/api/lessons/00-toy/regrade", None),
                     ("get", "/api/lessons/00-toy/stats", None)]


@pytest.fixture()
def client(tmp_path):
    service = make_service(f"sqlite:///{tmp_path / 'db.sqlite'}",
                           grade=lambda job: {"score": 0.0, "tests": []})
    with TestClient(build_app(service)) as test_client:
        yield test_client


@pytest.mark.parametrize("method,path,body", INSTRUCTOR_ROUTES)
def test_instructor_routes_need_the_token(client, method, path, body):
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": TOKEN}):
        response = client.request(method, path, json=body, headers=headers)
        assert response.status_code == 403 and response.json()["error"] == "forbidden"
    if body is None or body["seed"] >= 0:
        assert client.request(method, path, json=body, headers=AUTH).status_code in (200, 202)


def test_get_and_put_the_assignment_seed(client):
    drawn = client.get("/api/lessons/toy/assignment", headers=AUTH).json()
    assert drawn["lesson"] == "00-toy" and 0 <= drawn["seed"] <= MAX_SEED
    assert client.get("/api/lessons/00-toy/assignment", headers=AUTH).json() == drawn
    put = client.put("/api/lessons/00-toy/assignment", json={"seed": 0}, headers=AUTH).json()
    assert put["seed"] == 0 and put["regrade_url"] == "/api/lessons/00-toy/regrade"
    assert client.get("/api/lessons/00-toy/assignment", headers=AUTH).json()["seed"] == 0
    assert client.put("/api/lessons/00-toy/assignment", json={"seed": 12.0}, headers=AUTH).json()["seed"] == 12
    assert client.get("/api/lessons/stereo/assignment", headers=AUTH).status_code == 404


@pytest.mark.parametrize("body", [{"seed": -1}, {"seed": MAX_SEED + 1}, {"seed": "5"}, {"seed": 1.5},
                                  {"seed": 1e300}, {"seed": True}, {"seed": None}, {}, {"seed": 1, "extra": 2}, [5]])
def test_bad_seeds_are_422_json(client, body):
    before = client.get("/api/lessons/00-toy/assignment", headers=AUTH).json()["seed"]
    response = client.put("/api/lessons/00-toy/assignment", json=body, headers=AUTH)
    assert response.status_code == 422
    error = response.json()
    assert error["error"] == "invalid_request" and error["field"] in ("seed", "extra", "body")
    assert client.get("/api/lessons/00-toy/assignment", headers=AUTH).json()["seed"] == before


def test_a_malformed_body_is_422_json(client):
    response = client.put("/api/lessons/00-toy/assignment", content=b"{seed: 5", headers={
        **AUTH, "Content-Type": "application/json"})
    assert response.status_code == 422 and response.json()["field"] == "body"


def test_a_regrade_requeues_done_and_error_submissions_and_keeps_their_results(tmp_path):
    queue = SubmissionQueue(f"sqlite:///{tmp_path / 'db.sqlite'}")
    ids = [queue.submit("00-toy", "a.py", f"x = {k}") for k in range(4)]
    other = queue.submit("01-calibration", "a.py", "x = 9")
    for _ in range(5):
        queue.claim()
    queue.finish(ids[0], {"score": 2.0, "tests": []})
    queue.fail(ids[1], "boom")
    queue.finish(other, {"score": 1.0, "tests": []})  # another lesson: untouched
    # ids[2] stays running, ids[3] too: neither is requeued
    service = LessonService(catalog=LessonCatalog(FIXTURES / "lessons"), queue=queue,
                            grade=lambda job: {"score": 5.0, "tests": []})
    assert service.regrade("00-toy") == 2
    kept = queue.get(ids[0])
    assert kept.status == "queued" and kept.results == {"score": 2.0, "tests": []} and kept.attempts == 0
    assert queue.get(ids[1]).status == "queued" and queue.get(ids[2]).status == "running"
    assert queue.get(other).status == "done" and queue.counts("00-toy")["running"] == 2
    assert service.regrade("00-toy") == 0  # nothing graded left to requeue


# --- the CLI ----------------------------------------------------------------------------------------------
@pytest.fixture()
def cli():
    application = typer.Typer()

    @application.callback()
    def main() -> None:
        """vision-lab (test)"""

    register(application)
    return lambda *args, env=None: CliRunner().invoke(application, [str(a) for a in args], env=env)


def test_cli_prints_and_sets_the_stored_seed(cli, tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    env = {"VISION_LAB_DATABASE_URL": url}
    first = cli("lesson", "seed", TOY, env=env)
    assert first.exit_code == 0, first.output
    assert cli("lesson", "seed", TOY, env=env).stdout == first.stdout  # drawn once
    assert int(first.stdout) == SubmissionQueue(url).assignment_seed("00-toy")
    assert cli("lesson", "seed", TOY, "--set", 31337, env=env).stdout.strip() == "31337"
    assert SubmissionQueue(url).assignment_seed("00-toy") == 31337


@pytest.mark.parametrize("args,field", [(["no-such-lesson"], "lesson"), ([TOY, "--set", -1], "--set"),
                                        ([TOY, "--set", 2**31], "--set")])
def test_cli_seed_errors_are_one_line_and_exit_2(cli, tmp_path, args, field):
    env = {"VISION_LAB_DATABASE_URL": f"sqlite:///{tmp_path / 'db.sqlite'}"}
    result = cli("lesson", "seed", *args, env=env)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {field}: ")


def graded(result) -> dict:
    assert result.exit_code == 0, result.output
    body = json.loads(result.stdout)
    return {k: v for k, v in body.items() if k not in ("execution_time", "output")}  # (times)


def test_cli_grade_seed_from_the_option_or_the_environment_else_a_practice_run(cli):
    with_option = cli("grade", TOY, "--reference", "--json", "--seed", 7,
                      env={"VISION_LAB_ASSIGNMENT_SEED": ""})
    from_env = cli("grade", TOY, "--reference", "--json", env={"VISION_LAB_ASSIGNMENT_SEED": "7"})
    assert graded(with_option) == graded(from_env)
    assert PRACTICE_NOTE not in with_option.stderr and PRACTICE_NOTE not in from_env.stderr
    practice = cli("grade", TOY, "--reference", "--json", env={"VISION_LAB_ASSIGNMENT_SEED": ""})
    assert graded(practice)["score"] == 6.0 and practice.stderr.strip() == PRACTICE_NOTE
    bad = cli("grade", TOY, "--reference", env={"VISION_LAB_ASSIGNMENT_SEED": "seven"})
    assert bad.exit_code == 2 and bad.stderr.strip().startswith("error: VISION_LAB_ASSIGNMENT_SEED: ")


def test_a_server_without_an_instructor_token_never_serves_the_seed(tmp_path):
    """Without a token every instructor route is open (a laptop), but the seed is a secret: 403."""
    from fastapi.testclient import TestClient

    from lab.api.lessons import build_app
    from lab.lessons.format import LessonCatalog
    from lab.lessons.service import LessonService
    from lab.lessons.store import SubmissionQueue

    service = LessonService(catalog=LessonCatalog(FIXTURES / "lessons"),
                            queue=SubmissionQueue(f"sqlite:///{tmp_path / 'open.sqlite'}"),
                            grade=lambda submission: {})
    with TestClient(build_app(service)) as client:
        for method, body in (("get", None), ("put", {"seed": 5})):
            response = client.request(method, "/api/lessons/00-toy/assignment", json=body)
            assert response.status_code == 403 and "VISION_LAB_INSTRUCTOR_TOKEN" in response.text
