"""Fuzz the REST API from the OpenAPI document it serves, with schemathesis, in-process (ASGI).

Every phase runs: examples, coverage and fuzzing (one test per operation, ``test_operation``) and
stateful (``test_stateful``: scenarios that follow the document's OpenAPI links, e.g. a new
session's id into every session route, a submission's id into its status). Every built-in check
runs on every response: no 5xx, documented status codes, content types and headers, bodies that
match their schema, negative data rejected, positive data accepted, ``Allow`` on 405, deleted
sessions gone (use_after_free) and new ones there (ensure_resource_availability).

The app is the real one (:func:`lab.api.create_app`, every route, the real lessons) around the
toy pipeline, so that runs take milliseconds; grading is a stub (no sandbox, no child process), as
the fuzzer tests the routes, not the grader. :class:`Aim` points generated path parameters at
things that exist (a live toy session, its steps and values, a lesson, a submission) for three
cases in four, so the fuzzer gets past the 404s; the fourth keeps what was generated.

Bounded: ``VISION_LAB_FUZZ_EXAMPLES`` (default 20) examples per operation in the fuzzing phase and
as many stateful scenarios; the whole file takes about a minute on two cores.
"""

from __future__ import annotations

import os
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from fastapi import FastAPI
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from schemathesis.core.parameters import ParameterLocation
from toy_pipeline import TOY

from lab.api import create_app
from lab.core import SessionStore
from lab.lessons.service import LessonService
from lab.lessons.store import Submission, SubmissionQueue

EXAMPLES = int(os.environ.get("VISION_LAB_FUZZ_EXAMPLES", "20"))
#: Sessions the fuzzer may leave live at once; older ones are deleted before the next request.
MAX_LIVE_SESSIONS = 12
UPLOAD_LIMIT = 200_000

#: Routes whose input is checked against what exists at run time, beyond what a static schema can say:
#: a dataset's options, a step's controls, an upload's bytes (an image, JSON of the value's type), the
#: formats a value has. A schema-valid request there may still be a 422.
RUNTIME_CHECKED_INPUTS = r"^/api/sessions(/\{session_id\}/(steps|run-until|values)/.*)?$"

CONFIG = {
    "generation": {"max-examples": EXAMPLES, "database": "none", "deterministic": True},
    "phases": {"stateful": {"max-steps": 8}},
    "max-stream-events": 20,
    "operations": [{
        "include-path-regex": RUNTIME_CHECKED_INPUTS,
        "checks": {"positive_data_acceptance": {
            "expected-statuses": ["2xx", "3xx", "401", "403", "404", "409", "422", "429"]}},
    }],
}


#: The file part of a submission (``encoding.file.contentType`` in the document): small valid Python sources.
schemathesis.openapi.media_type("text/x-python", st.builds(
    lambda name, value: f"v_{name} = {value!r}\n".encode(), st.from_regex(r"\A[a-z0-9_]{0,8}\Z"),
    st.integers() | st.text(max_size=20)))


def stub_grade(submission: Submission) -> dict[str, Any]:
    """A results.json without running anything (the grader has tests of its own)."""
    return {"score": 0.0, "execution_time": 0.0, "output": f"not graded: {submission.filename}", "tests": []}


def build_fuzz_app(database: Path) -> FastAPI:
    """The real app around the toy module, with the real lessons and stub grading."""
    app = create_app(SessionStore(max_sessions=64, idle_seconds=3600.0, max_bytes=256 * 2**20),
                     modules={"toy": TOY}.__getitem__, module_names=["toy"], max_upload_bytes=UPLOAD_LIMIT)
    app.state.lesson_service = LessonService(queue=SubmissionQueue(f"sqlite:///{database}"), grade=stub_grade,
                                             poll_s=0.1)
    return app


def _pick(generated: Any, choices: Sequence[str]) -> Any:
    """One of ``choices`` for three generated values in four (the same one each time), else the value."""
    digest = zlib.crc32(repr(generated).encode())
    if digest % 4 == 0 or not choices:
        return generated
    return choices[(digest // 4) % len(choices)]


class Aim:
    """Points a case's path parameters at things that exist in the app, so requests get past 404."""

    def __init__(self, app: FastAPI) -> None:
        self.app = app
        self.client = TestClient(app)
        service: LessonService = app.state.lesson_service
        self.lessons = service.catalog.ids()
        self.submissions = [service.submit(self.lessons[0], "fuzz.py", "x = 1\n")] if self.lessons else []

    def session_id(self) -> str:
        """A live toy session (a new one when the fuzzer deleted the last)."""
        store: SessionStore = self.app.state.store
        ids = store.ids()
        for session_id in ids[:-MAX_LIVE_SESSIONS]:
            store.delete(session_id)
        live = ids[-MAX_LIVE_SESSIONS:]
        if live:
            return live[-1]
        response = self.client.post("/api/sessions", json={"module": "toy"})
        assert response.status_code == 201, response.text
        return response.json()["id"]

    def __call__(self, case: schemathesis.Case) -> None:
        """Replace generated path parameters (never negative ones: those must stay invalid)."""
        components = case.meta.components if case.meta is not None else {}
        path = components.get(ParameterLocation.PATH)
        params = dict(case.path_parameters or {})
        if not params or (path is not None and path.mode.is_negative):
            return
        store: SessionStore = self.app.state.store
        if "session_id" in params and params["session_id"] not in store.ids():
            params["session_id"] = _pick(params["session_id"], [self.session_id()])
        if "session_id" in params and params["session_id"] in store.ids():
            pipeline = store.get(params["session_id"]).pipeline
            if "step" in params:
                params["step"] = _pick(params["step"], [s.name for s in pipeline.steps])
            if "name" in params:
                params["name"] = _pick(params["name"], sorted({n for s in pipeline.steps for n in (*s.reads, *s.writes)}))
        if "lesson_id" in params:
            params["lesson_id"] = _pick(params["lesson_id"], self.lessons)
        if "submission_id" in params:
            params["submission_id"] = _pick(params["submission_id"], self.submissions)
        case.path_parameters = params


@pytest.fixture(scope="module")
def fuzz_app(tmp_path_factory: pytest.TempPathFactory) -> FastAPI:
    app = build_fuzz_app(tmp_path_factory.mktemp("fuzz") / "submissions.sqlite")
    yield app
    app.state.lesson_service.stop()


@pytest.fixture(scope="module")
def aim(fuzz_app: FastAPI) -> Aim:
    return Aim(fuzz_app)


@pytest.fixture(scope="module")
def api_schema(fuzz_app: FastAPI) -> schemathesis.BaseSchema:
    return schemathesis.openapi.from_asgi("/openapi.json", fuzz_app, config=schemathesis.Config.from_dict(CONFIG))


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
def test_operation(case: schemathesis.Case, aim: Aim) -> None:
    """Examples, coverage and fuzzing phases: every check on every response."""
    aim(case)
    case.call_and_validate()


def test_stateful(api_schema: schemathesis.BaseSchema, aim: Aim) -> None:
    """Stateful phase: scenarios along the OpenAPI links (sessions, steps, values, submissions)."""
    base = api_schema.as_state_machine()

    class Machine(base):  # type: ignore[misc, valid-type]
        def before_call(self, case: schemathesis.Case) -> None:
            aim(case)

    Machine.run(settings=settings(max_examples=EXAMPLES, stateful_step_count=8, deadline=None,
                                  database=None, derandomize=True,
                                  suppress_health_check=list(HealthCheck)))



@pytest.fixture(scope="module")
def real_modules_schema() -> schemathesis.BaseSchema:
    """The app as served, with the real modules (read-only routes: their sessions load for seconds)."""
    app = create_app(SessionStore(max_sessions=4))
    return schemathesis.openapi.from_asgi("/openapi.json", app, config=schemathesis.Config.from_dict(CONFIG))


real_modules = schemathesis.pytest.from_fixture("real_modules_schema").include(
    method="GET", path_regex=r"^/api/(modules|health)")


@real_modules.parametrize()
def test_real_module_descriptions(case: schemathesis.Case) -> None:
    """Every check on the real modules' listing and descriptions (controls' JSON Schema, datasets)."""
    case.call_and_validate()
