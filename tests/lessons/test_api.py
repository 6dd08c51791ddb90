"""The lesson routes of the REST API: an app with just lab.api.lessons.router and the shared error handlers."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient

from lab.api.lessons import build_app
from lab.lessons.format import LessonCatalog
from lab.lessons.service import LessonService
from lab.lessons.store import SubmissionQueue

from lesson_helpers import FIXTURES, submission, wait_done


def make_service(tmp_path, **kwargs) -> LessonService:
    return LessonService(catalog=LessonCatalog(FIXTURES / "lessons"),
                         queue=SubmissionQueue(f"sqlite:///{tmp_path / 'db.sqlite'}"), poll_s=0.1, **kwargs)


@pytest.fixture()
def client(tmp_path):
    with TestClient(build_app(make_service(tmp_path))) as test_client:
        yield test_client


def upload(client, text: bytes | str, filename="mine.py", lesson="00-toy", **data):
    payload = text.encode() if isinstance(text, str) else text
    return client.post(f"/api/lessons/{lesson}/submissions", files={"file": (filename, payload, "text/x-python")},
                       data=data)


def test_list_and_describe_lessons(client):
    listed = client.get("/api/lessons").json()
    assert [entry["id"] for entry in listed] == ["00-toy"]
    assert listed[0]["title"] == "Toy lesson: noise and means" and listed[0]["points"] == 6.0
    assert [t["step"] for t in listed[0]["tasks"]] == ["make_noisy", "mean_intensity"]
    described = client.get("/api/lessons/toy").json()
    assert described["id"] == "00-toy" and described["text"].startswith("# Toy lesson")
    assert "raise NotImplementedError" in described["starter"]
    assert described["tasks"][1]["signature"] == "mean_intensity(noisy: ImageSet, *, scale: int = 1) -> np.ndarray"
    assert "1234" not in str(described)  # the instructor's seed stays hidden
    starter = client.get("/api/lessons/00-toy/starter.py")
    assert starter.status_code == 200 and starter.text == described["starter"]
    assert starter.headers["content-type"].startswith("text/x-python")


def test_unknown_lessons_and_submissions_are_404_json(client):
    for path in ("/api/lessons/stereo", "/api/lessons/stereo/starter.py", "/api/submissions/" + "0" * 32):
        response = client.get(path)
        assert response.status_code == 404 and response.json()["error"] == "not_found"
    assert client.get("/api/submissions/not-an-id").status_code == 422
    response = upload(client, "x = 1", lesson="stereo")
    assert response.status_code == 404 and response.json()["field"] == "lesson"


def test_a_submission_is_graded_in_the_background(client):
    response = upload(client, submission("toy", "solution.py"), student="ana")
    assert response.status_code == 202
    body = response.json()
    assert body["status"] == "queued" and body["url"] == f"/api/submissions/{body['id']}"
    done = wait_done(client, body["id"])
    assert done["status"] == "done" and done["score"] == 6.0 and done["max_score"] == 6.0
    assert done["results"]["score"] == 6.0 and len(done["results"]["tests"]) == 6
    assert done["student"] == "ana" and done["filename"] == "mine.py"


def test_grading_never_runs_in_the_request(client):
    slow = submission("toy", "solution.py").replace("def mean_intensity(noisy, *, scale=1):\n",
                                                    "def mean_intensity(noisy, *, scale=1):\n    import time\n"
                                                    "    time.sleep(0.5)\n")
    started = time.monotonic()
    response = upload(client, slow)
    answered = time.monotonic() - started
    assert response.status_code == 202
    assert client.get(response.json()["url"]).json()["status"] in ("queued", "running")
    done = wait_done(client, response.json()["id"])
    assert done["score"] == 6.0
    assert answered < done["finished"] - done["created"]  # the answer came before the grading ended


@pytest.mark.parametrize("payload,filename,status,kind,words", [
    (b"\x00\x01binary", "a.py", 415, "unsupported_media_type", "NUL bytes"),
    ("x = 'caf\xe9'\n".encode("latin-1"), "a.py", 415, "unsupported_media_type", "not UTF-8"),
    (b"x = 1\n", "a.txt", 415, "unsupported_media_type", "ending in .py"),
    (b"def f(:\n", "a.py", 422, "invalid_value", "line 1: SyntaxError"),
    (b"   \n", "a.py", 422, "invalid_value", "empty"),
    (b"x = 1  # " + b"y" * 300_000, "a.py", 413, "capacity", "larger than"),
])
def test_uploads_that_are_not_python_text_are_refused(client, payload, filename, status, kind, words):
    response = upload(client, payload, filename=filename)
    assert response.status_code == status
    body = response.json()
    assert body["error"] == kind and body["field"] == "file" and words in body["reason"]


def test_an_upload_without_a_file_is_422(client):
    response = client.post("/api/lessons/00-toy/submissions", data={"student": "ana"})
    assert response.status_code == 422 and response.json()["error"] == "invalid_request"


def test_instructor_listing_with_and_without_a_token(tmp_path):
    with TestClient(build_app(make_service(tmp_path, instructor_token="s3cret"))) as client:
        submission_id = upload(client, submission("toy", "solution.py"), student="bo").json()["id"]
        wait_done(client, submission_id)
        assert client.get("/api/lessons/00-toy/submissions").status_code == 403
        assert client.get("/api/lessons/00-toy/submissions",
                          headers={"Authorization": "Bearer wrong"}).json()["error"] == "forbidden"
        listed = client.get("/api/lessons/00-toy/submissions", headers={"Authorization": "Bearer s3cret"}).json()
    assert listed["lesson"] == "00-toy" and listed["counts"]["done"] == 1
    (row,) = listed["submissions"]
    assert row["id"] == submission_id and row["student"] == "bo" and row["score"] == 6.0 and "results" not in row


def test_open_listing_when_no_token_is_configured(client):
    assert client.get("/api/lessons/00-toy/submissions").json()["submissions"] == []


def test_the_lifespan_starts_and_stops_the_workers(tmp_path):
    service = make_service(tmp_path)
    with TestClient(build_app(service)):
        assert service.started and service.pool._threads
    assert not service.started and not service.pool._threads


def test_without_a_configured_service_the_database_is_made_on_first_use(tmp_path, monkeypatch):
    monkeypatch.delenv("VISION_LAB_DATABASE_URL", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    monkeypatch.setenv("VISION_LAB_LESSONS_DIR", str(FIXTURES / "lessons"))
    database = tmp_path / "data" / "vision-lab" / "submissions.sqlite"
    app = build_app()
    with TestClient(app) as client:
        assert getattr(app.state, "lesson_service", None) is None and not database.exists()
        assert client.get("/api/lessons").json()[0]["id"] == "00-toy"
        assert database.exists() and app.state.lesson_service.started
    assert not app.state.lesson_service.started
    second = build_app()
    with TestClient(second):
        assert second.state.lesson_service.started  # the file exists: started (and requeued) at start-up
