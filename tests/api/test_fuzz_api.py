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
cases in four, so the fuzzer gets past the 404s; the fourth keeps what was generated. The real
modules are fuzzed too, on their read-only routes (``test_real_module_descriptions``): a session
on one loads for up to seconds.

Two allowances, each for what a static schema cannot say: a schema-valid request may be a 422 on
the routes whose input is checked against the session at run time (:data:`RUNTIME_CHECKED_INPUTS`),
and a form text field generated as ``null`` or a number is not sent as invalid data
(:func:`typed_form_text`).

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
from hypothesis import HealthCheck, assume, settings
from hypothesis import strategies as st
from schemathesis.core.parameters import ParameterLocation
from toy_pipeline import TOY

from lab.api import create_app
from lab.core import Pipeline, SessionStore
from lab.core.errors import LabError
from lab.lessons.service import LessonService
from lab.lessons.store import Submission, SubmissionQueue

EXAMPLES = int(os.environ.get("VISION_LAB_FUZZ_EXAMPLES", "20"))
#: A hung request (a run that never ends) fails the test instead of holding CI.
pytestmark = pytest.mark.timeout(240)
#: Sessions the fuzzer may leave live at once; older ones are deleted before the next request.
MAX_LIVE_SESSIONS = 12
UPLOAD_LIMIT = 200_000
#: Text fields of the submission form (POST /api/lessons/{id}/submissions), besides the file.
FORM_TEXT_FIELDS = ("student",)

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

    def live_sessions(self) -> list[str]:
        """The newest live session (a new toy one when the fuzzer deleted the last); older ones beyond
        :data:`MAX_LIVE_SESSIONS` are deleted. Empty when the server refuses a new one."""
        store: SessionStore = self.app.state.store
        ids = store.ids()
        for session_id in ids[:-MAX_LIVE_SESSIONS]:
            store.delete(session_id)
        if ids:
            return ids[-1:]
        response = self.client.post("/api/sessions", json={"module": "toy"})
        return [response.json()["id"]] if response.status_code == 201 else []

    def __call__(self, case: schemathesis.Case) -> None:
        """Replace generated path parameters (never negative ones: those must stay invalid)."""
        components = case.meta.components if case.meta is not None else {}
        path = components.get(ParameterLocation.PATH)
        params = dict(case.path_parameters or {})
        if not params or (path is not None and path.mode.is_negative):
            return
        store: SessionStore = self.app.state.store
        if "session_id" in params and params["session_id"] not in store.ids():
            params["session_id"] = _pick(params["session_id"], self.live_sessions())
        pipeline = self.pipeline_of(params.get("session_id"))
        if pipeline is not None:
            if "step" in params:
                params["step"] = _pick(params["step"], [s.name for s in pipeline.steps])
            if "name" in params:
                names = sorted({n for s in pipeline.steps for n in (*s.reads, *s.writes)})
                params["name"] = _pick(params["name"], names)
        if "lesson_id" in params:
            params["lesson_id"] = _pick(params["lesson_id"], self.lessons)
        if "submission_id" in params:
            params["submission_id"] = _pick(params["submission_id"], self.submissions)
        case.path_parameters = params

    def pipeline_of(self, session_id: Any) -> Pipeline | None:
        """The pipeline of live session ``session_id``; None when there is no such session (or it just went)."""
        try:
            return self.app.state.store.get(session_id).pipeline if isinstance(session_id, str) else None
        except LabError:
            return None

    def reset(self) -> None:
        """Forget every session (a stateful scenario starts from an empty store, so replays are the same)."""
        store: SessionStore = self.app.state.store
        for session_id in store.ids():
            store.delete(session_id)


def typed_form_text(case: schemathesis.Case) -> bool:
    """Whether a submission form's text field was generated as another JSON type (``null``, a number, a list).

    A form carries text only: such a "negative" value arrives as valid text (``"null"``, a student
    so named), so the case is not invalid data and is left out (``assume``).
    """
    body = case.body
    return (case.media_type == "multipart/form-data" and isinstance(body, dict)
            and any(name in body and not isinstance(body[name], str) for name in FORM_TEXT_FIELDS))


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
    assume(not typed_form_text(case))
    aim(case)
    response = case.call_and_validate()  # every check; a failure raises
    assert response.status_code < 500, response.text


def test_stateful(api_schema: schemathesis.BaseSchema, aim: Aim) -> None:
    """Stateful phase: scenarios along the OpenAPI links (sessions, steps, values, submissions)."""
    base = api_schema.as_state_machine()
    answered: list[tuple[str, int]] = []  # (path template, status) of every call the scenarios made

    class Machine(base):  # type: ignore[misc, valid-type]
        def setup(self) -> None:
            aim.reset()

        def before_call(self, case: schemathesis.Case) -> None:
            assume(not typed_form_text(case))
            aim(case)

        def after_call(self, response: Any, case: schemathesis.Case) -> None:
            answered.append((case.operation.path, response.status_code))

    Machine.run(settings=settings(max_examples=EXAMPLES, stateful_step_count=8, deadline=None,
                                  database=None, derandomize=True,
                                  suppress_health_check=list(HealthCheck)))
    assert all(status < 500 for _, status in answered)
    # the links reach live sessions: some call on a session route succeeded
    assert any(path.startswith("/api/sessions/{session_id}") and status < 300 for path, status in answered), answered



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
    response = case.call_and_validate()
    assert response.status_code < 500, response.text
