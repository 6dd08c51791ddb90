"""``/api/lessons`` and ``/api/submissions``: lesson texts and starters, uploads graded in the
background.

    GET  /api/lessons                     the lessons (id, title, module, points, tasks)
    GET  /api/lessons/{id}                one lesson: its text, tasks (signatures, checks) and starter file
    GET  /api/lessons/{id}/starter.py     the starter file itself
    POST /api/lessons/{id}/submissions    upload a .py (multipart field ``file``) -> 202 {id, status, url}
    GET  /api/submissions/{id}            status (queued, running, done, error) and results.json (no seeds;
                                          ?view=instructor adds them, with the instructor's token)
    GET  /api/lessons/{id}/submissions    every submission of a lesson, for an instructor
    GET  /api/lessons/{id}/assignment     the lesson's assignment seed (instructor)
    PUT  /api/lessons/{id}/assignment     set it: {"seed": 0 .. 2**31 - 1} (instructor)
    POST /api/lessons/{id}/regrade        requeue every graded submission of the lesson (instructor)
    GET  /api/lessons/{id}/stats          the class's results per check and its scores (instructor)

Grading never runs in a request: an upload is committed to the database and a worker of the
:class:`~lab.lessons.service.LessonService` grades it. The service comes from
``app.state.lesson_service``; when the app has none, the router's lifespan builds one from the
environment (:meth:`LessonService.from_env`) and starts it (requeueing what a killed server left
running). Tests build an app with just this router: :func:`build_app`. Of several API processes sharing
the database (``vision-lab serve --workers N``), one grades (:func:`grades_here`); every one accepts
submissions and answers every read from the database, never from its own memory.

Every submission is graded with the lesson's secret assignment seed (drawn on first use, stored
with the submissions), so a regrade gives the same score; the seed and the check data's seeds
appear only on the instructor's routes.
"""

from __future__ import annotations

import contextlib
import hmac
import os
from collections.abc import AsyncIterator
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, FastAPI, File, Form, Path, Query, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import PlainTextResponse
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, StrictInt

from lab.api.errors import LabJSONResponse, error_responses, register_error_handlers
from lab.core.errors import LabError, UnknownName
from lab.lessons.service import LessonService
from lab.lessons.submission import check_upload
from lab.lessons.store import MAX_SEED, default_database_url


class Forbidden(LabError):
    """An instructor-only route without the instructor's token."""

    status = 403
    kind = "forbidden"


def _database_exists() -> bool:
    """A database is configured, or the default SQLite file exists (so there may be gradings to
    requeue)."""
    url = default_database_url()
    if os.environ.get("VISION_LAB_DATABASE_URL") or not url.startswith("sqlite:///"):
        return True
    return os.path.exists(url[len("sqlite:///"):])


@contextlib.asynccontextmanager
async def lessons_lifespan(app: FastAPI) -> AsyncIterator[None]:
    """Start the lesson service with the app (requeue interrupted gradings, start the workers), stop it
    after.

    Without ``app.state.lesson_service`` the service is built from the environment; when no database
    is configured and the default SQLite file does not exist yet, nothing can have been interrupted,
    so the service is only built on the first lesson request (no file is created by merely starting).
    """
    service = getattr(app.state, "lesson_service", None)
    if service is None and _database_exists():
        service = LessonService.from_env()
        app.state.lesson_service = service
    if service is not None:
        service.start(dispatch=grades_here(app))
    try:
        yield
    finally:
        service = getattr(app.state, "lesson_service", None)
        if service is not None:
            service.stop()


router = APIRouter(prefix="/api", tags=["lessons"], lifespan=lessons_lifespan,
                   responses=error_responses({404: "Unknown lesson or submission."}))

LessonId = Annotated[str, Path(description="Lesson id (`01-calibration`) or name (`calibration`).",
                               pattern=r"^[a-z0-9][a-z0-9-]{0,99}$")]
SubmissionId = Annotated[str, Path(description="The id returned by POST /api/lessons/{id}/submissions.",
                                   pattern=r"^[0-9a-f]{32}$")]


def get_lesson_service(request: Request) -> LessonService:
    """The app's lesson service (built from the environment and started on first use if the lifespan
    did not run; started only where :func:`grades_here`)."""
    service = getattr(request.app.state, "lesson_service", None)
    if service is None:
        service = LessonService.from_env()
        request.app.state.lesson_service = service
    if not service.started:
        service.start(dispatch=grades_here(request.app))
    return service


def grades_here(app: FastAPI) -> bool:
    """Whether this process grades (claims queued submissions, requeues interrupted ones at start).

    False for the other workers of ``vision-lab serve --workers N`` and for ``--no-grading``: they store
    submissions and read them, results and the instructor's views back from the shared database, and
    one process (worker ``w0``) grades, so its start-up requeue cannot take a live grader's claims.
    """
    return bool(getattr(app.state, "grading", True))


def _summary_text(text: str) -> str:
    """The first paragraph after the title of lesson.md."""
    paragraphs = [p.strip() for p in text.split("\n\n") if p.strip()]
    body = [p for p in paragraphs if not p.startswith("#")]
    return " ".join(body[0].split()) if body else ""


@router.get("/lessons", summary="List the lessons",
            description="Every lesson: id, title, module, points, a summary and its tasks (step names and "
                        "points).")
def list_lessons(request: Request) -> LabJSONResponse:
    service = get_lesson_service(request)
    listed = []
    for lesson_id in service.catalog.ids():
        try:
            lesson = service.catalog.get(lesson_id)
        except LabError as exc:  # a broken lesson is listed with the reason, never takes the list down
            listed.append({"id": lesson_id, "title": lesson_id, "available": False, "reason": str(exc),
                           "tasks": []})
            continue
        listed.append({**lesson.summary(), "summary": _summary_text(lesson.text), "available": True,
                       "url": f"/api/lessons/{lesson.id}",
                       "starter_url": f"/api/lessons/{lesson.id}/starter.py"})
    return LabJSONResponse(listed)


@router.get("/lessons/{lesson_id}", summary="Describe one lesson",
            description="The lesson text (Markdown), its tasks (the step, its signature, points, the checks) "
                        "and the starter file a student fills in. Check data and seeds stay hidden.")
def describe_lesson(request: Request, lesson_id: LessonId) -> LabJSONResponse:
    lesson = get_lesson_service(request).catalog.get(lesson_id)
    return LabJSONResponse({**lesson.describe(), "summary": _summary_text(lesson.text),
                            "starter_url": f"/api/lessons/{lesson.id}/starter.py",
                            "submissions_url": f"/api/lessons/{lesson.id}/submissions"})


class PythonSourceResponse(PlainTextResponse):
    """A Python file as UTF-8 text: ``text/x-python``, as the OpenAPI document says."""

    media_type = "text/x-python"


@router.get("/lessons/{lesson_id}/starter.py", summary="Download the starter file",
            response_class=PythonSourceResponse)
def starter_file(request: Request, lesson_id: LessonId) -> PythonSourceResponse:
    lesson = get_lesson_service(request).catalog.get(lesson_id)
    disposition = f'attachment; filename="{lesson.id}-starter.py"'
    return PythonSourceResponse(lesson.starter, headers={"Content-Disposition": disposition})


@router.post("/lessons/{lesson_id}/submissions", status_code=202, summary="Submit a file for grading",
             description="Upload the student's Python file (multipart field `file`, optional form field "
                         "`student`). Answers 202 with the submission's id at once; grading runs in the "
                         "background. Poll GET /api/submissions/{id} for the result (Gradescope's "
                         "results.json).",
             responses=error_responses({413: "The file is too large.",
                                        415: "The file is not Python source text.",
                                        422: "The file does not parse as Python."}),
             openapi_extra={"requestBody": {"content": {"multipart/form-data": {"encoding": {"file": {
                 "contentType": "text/x-python",
                 "headers": {"Content-Disposition": {
                     "description": "The file part's name ends in `.py` (415 otherwise).",
                     "schema": {"type": "string",
                                "example": 'form-data; name="file"; filename="solution.py"'}}}}}}}}})
async def submit(request: Request, lesson_id: LessonId,
                 file: Annotated[UploadFile, File(description="The student's .py file.")],
                 student: Annotated[str, Form(max_length=200,
                                              description="Who submits (shown to the instructor).")] = ""
                 ) -> LabJSONResponse:
    service = get_lesson_service(request)
    lesson = service.catalog.get(lesson_id)
    payload = await file.read(service.max_submission_bytes + 1)
    text = await run_in_threadpool(check_upload, payload, file.filename or "",
                                   limit=service.max_submission_bytes)
    submission_id = service.submit(lesson.id, file.filename or "submission.py", text, student=student)
    return LabJSONResponse({"id": submission_id, "lesson": lesson.id, "status": "queued",
                            "url": f"/api/submissions/{submission_id}"}, status_code=202)


#: Keys of results.json's ``extra_data`` only the instructor's view shows (the check data's seeds; the
#: assignment seed, should the grader ever write it there).
INSTRUCTOR_ONLY_EXTRA = ("seeds", "seed", "assignment_seed")


def student_view(submission: dict[str, Any]) -> dict[str, Any]:
    """A submission's JSON without what stays hidden from students: ``results.extra_data.seeds`` (and
    any other key of :data:`INSTRUCTOR_ONLY_EXTRA`)."""
    results = submission.get("results")
    if not isinstance(results, dict) or not isinstance(results.get("extra_data"), dict):
        return submission
    extra = {k: v for k, v in results["extra_data"].items() if k not in INSTRUCTOR_ONLY_EXTRA}
    return {**submission, "results": {**results, "extra_data": extra}}


@router.get("/submissions/{submission_id}", summary="A submission's status and results",
            description="`status` is `queued`, `running`, `done` (with `results`: Gradescope's results.json) "
                        "or `error` (grading itself failed; `error` says why). The default student view "
                        "leaves out the check data's seeds (`results.extra_data.seeds`); `?view=instructor` "
                        "includes them and needs `Authorization: Bearer <VISION_LAB_INSTRUCTOR_TOKEN>` when "
                        "that is set.",
            responses=error_responses({403: "view=instructor without the instructor token."}))
def get_submission(request: Request, submission_id: SubmissionId,
                   view: Annotated[Literal["student", "instructor"],
                                   Query(description="`instructor` adds the seeds of the check data.")
                                   ] = "student") -> LabJSONResponse:
    service = get_lesson_service(request)
    if view == "instructor":
        _check_instructor(request, service)
    found = service.queue.get(submission_id)
    if found is None:
        raise UnknownName("submission", f"no submission {submission_id!r}")
    body = found.to_json()
    return LabJSONResponse(body if view == "instructor" else student_view(body))


@router.get("/lessons/{lesson_id}/submissions", summary="A lesson's submissions (instructor)",
            description="Every submission of the lesson, newest first, with status and score (no results "
                        "or source). Needs `Authorization: Bearer <VISION_LAB_INSTRUCTOR_TOKEN>` when that "
                        "is set.",
            responses=error_responses({403: "Instructor token missing or wrong."}))
def list_submissions(request: Request, lesson_id: LessonId) -> LabJSONResponse:
    service = get_lesson_service(request)
    _check_instructor(request, service)
    lesson = service.catalog.get(lesson_id)
    rows: list[dict[str, Any]] = [s.to_json(with_results=False) for s in service.queue.list(lesson.id)]
    return LabJSONResponse({"lesson": lesson.id, "submissions": rows, "counts": service.queue.counts()})


def require_instructor(request: Request) -> LessonService:
    """A dependency of the instructor's routes: the service, after the token is checked (before the body
    is read, so a request without the token is 403 whatever it sends)."""
    service = get_lesson_service(request)
    _check_instructor(request, service)
    return service


def require_configured_instructor(request: Request) -> LessonService:
    """Like :func:`require_instructor`, for a secret (the assignment seed): a server without an instructor
    token refuses, since anyone could otherwise read the seed and rebuild the hidden data."""
    service = get_lesson_service(request)
    if not service.instructor_token:
        raise Forbidden("authorization", "the assignment seed is served only when the server has an "
                                         "instructor token: set VISION_LAB_INSTRUCTOR_TOKEN")
    _check_instructor(request, service)
    return service


Instructor = Annotated[LessonService, Depends(require_instructor)]
SecretKeeper = Annotated[LessonService, Depends(require_configured_instructor)]
INSTRUCTOR_ERRORS = error_responses({403: "Instructor token missing or wrong."})


def _json_integer(value: object) -> object:
    """A JSON integer as JSON Schema reads it: ``5`` or ``5.0``, never ``"5"`` or ``true`` (then strict)."""
    if isinstance(value, (bool, str)):
        raise ValueError("an assignment seed is a JSON integer")
    return int(value) if isinstance(value, float) and value.is_integer() else value


class AssignmentSeed(BaseModel):
    """A lesson's assignment seed: every hidden dataset of a grading run is derived from it."""

    model_config = ConfigDict(extra="forbid")

    seed: Annotated[StrictInt, BeforeValidator(_json_integer)] = Field(
        ge=0, le=MAX_SEED, description="An integer in 0 .. 2**31 - 1; keep it secret.", examples=[123456789])


@router.get("/lessons/{lesson_id}/assignment", summary="The lesson's assignment seed (instructor)",
            description="The secret seed every grading of this lesson derives its hidden data from (drawn on "
                        "first use). Grade a file locally with the same data: `vision-lab grade LESSON "
                        "file.py --seed SEED`. Needs the instructor token; a server without one refuses "
                        "(403).",
            responses=INSTRUCTOR_ERRORS)
def get_assignment(service: SecretKeeper, lesson_id: LessonId) -> LabJSONResponse:
    lesson = service.catalog.get(lesson_id)
    return LabJSONResponse({"lesson": lesson.id, "seed": service.queue.assignment_seed(lesson.id)})


@router.put("/lessons/{lesson_id}/assignment", summary="Set the lesson's assignment seed (instructor)",
            description="Submissions graded from now on use the new seed; POST /api/lessons/{id}/regrade "
                        "grades the others again with it. Needs the instructor token (a server without one "
                        "refuses, 403).",
            responses=INSTRUCTOR_ERRORS)
def put_assignment(service: SecretKeeper, lesson_id: LessonId, body: AssignmentSeed) -> LabJSONResponse:
    lesson = service.catalog.get(lesson_id)
    seed = service.queue.set_assignment_seed(lesson.id, body.seed)
    return LabJSONResponse({"lesson": lesson.id, "seed": seed,
                            "regrade_url": f"/api/lessons/{lesson.id}/regrade"})


@router.post("/lessons/{lesson_id}/regrade", status_code=202, summary="Regrade a lesson (instructor)",
             description="Every graded submission of the lesson (`done`, and `error`: a failure of the lab) "
                         "goes back to `queued` and is graded again with the current assignment seed and "
                         "lesson. Each keeps its previous results until the new ones replace them. A "
                         "submission `running` now is not requeued (`running` counts them): regrade again "
                         "once they are done if the seed changed meanwhile. Needs the instructor token when "
                         "one is set.", responses=INSTRUCTOR_ERRORS)
def regrade(service: Instructor, lesson_id: LessonId) -> LabJSONResponse:
    lesson = service.catalog.get(lesson_id)
    requeued = service.regrade(lesson.id)
    return LabJSONResponse({"lesson": lesson.id, "requeued": requeued,
                            "running": service.queue.counts(lesson.id)["running"],
                            "submissions_url": f"/api/lessons/{lesson.id}/submissions"}, status_code=202)


@router.get("/lessons/{lesson_id}/stats", summary="The class's results (instructor)",
            description="Over the latest graded submission of each student: per check, how many failed it, "
                        "their share and the hints given; the score distribution; the checks that never fail "
                        "or fail everyone (flagged from `min_submissions` submissions). Needs the instructor "
                        "token when one is set.", responses=INSTRUCTOR_ERRORS)
def lesson_stats(service: Instructor, lesson_id: LessonId) -> LabJSONResponse:
    lesson = service.catalog.get(lesson_id)
    return LabJSONResponse(service.stats(lesson.id).to_json())


def _check_instructor(request: Request, service: LessonService) -> None:
    token = service.instructor_token
    if not token:
        return
    given = request.headers.get("authorization", "")
    scheme, _, value = given.partition(" ")
    if scheme.lower() != "bearer" or not hmac.compare_digest(value.strip().encode(), token.encode()):
        raise Forbidden("authorization", "this is for instructors: send 'Authorization: Bearer <token>'")


def build_app(service: LessonService | None = None) -> FastAPI:
    """An app with just the lesson routes and the shared JSON errors (tests; a grading-only server)."""
    app = FastAPI(title="Vision Lab lessons", default_response_class=LabJSONResponse)
    if service is not None:
        app.state.lesson_service = service
    register_error_handlers(app)
    app.include_router(router)
    return app


def standalone_app() -> FastAPI:
    """``uvicorn --factory lab.api.lessons:standalone_app``: the lesson routes configured from the
    environment."""
    return build_app(LessonService.from_env())


__all__ = ["build_app", "check_upload", "get_lesson_service", "grades_here", "lessons_lifespan", "router",
           "standalone_app"]
