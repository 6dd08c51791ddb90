"""``/api/sessions``: create a session on a dataset, run steps, stream progress, cancel, reset, delete.

Sessions live in the shared :class:`~lab.core.store.SessionStore`, so a session made here can be
opened in the viewer and vice versa. Runs and dataset loads go through the app's bounded
:class:`~lab.api.runs.RunPools` (never the event loop; loads and quick steps have pools of their
own): when a pool's workers are busy they wait in its queue, and when that is full they are
refused with 429 and ``Retry-After``. New sessions are admitted within the store's caps (429 per
client, 503 for the server) and never evict one in use.
``?wait=false`` returns 202 at once and the run's progress and outcome arrive on
``GET /api/sessions/{id}/events``.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import AsyncIterable, AsyncIterator
from functools import partial
from typing import Annotated, Any
from urllib.parse import urlencode

import anyio
from fastapi import APIRouter, Body, Depends, Path, Query, Request, Response
from fastapi.sse import EventSourceResponse, ServerSentEvent
from pydantic import BaseModel, ConfigDict, Field

from lab.api.deps import (CatalogDep, ClientDep, PoolsDep, SessionDep, StoreDep, check_session_owner,
                          get_worker)
from lab.api.errors import LabJSONResponse, NothingRunning, error_responses, jsonable
from lab.api.runs import RunJob, RunMonitor, RunPool, check_idle, plan_step, plan_until, record_outcome
from lab.api.workers import MISDIRECTED
from lab.core.errors import InvalidValue, LabError
from lab.core.pipeline import DatasetSpec, Pipeline, Session

router = APIRouter(prefix="/api/sessions", tags=["sessions"], responses=error_responses(MISDIRECTED))
logger = logging.getLogger(__name__)

#: How often an event stream looks for new progress (seconds).
POLL_SECONDS = 0.05

_RETRY_AFTER_HEADER = {"Retry-After": {"description": "Seconds after which to try again.",
                                       "schema": {"type": "integer", "minimum": 1}}}


def retry_later_responses(texts: dict[int, str]) -> dict[int | str, dict[str, Any]]:
    """:func:`error_responses` for ``texts``, with the ``Retry-After`` header on 429 and 503."""
    responses = error_responses(texts)
    for code in (429, 503):
        if code in texts:
            responses[code] = {**responses[code], "headers": _RETRY_AFTER_HEADER}
    return responses


StepName = Annotated[str, Path(description="Step name, as listed by GET /api/modules/{module}.")]
Wait = Annotated[bool, Query(description="`true`: answer when the run is over (200 with its record). "
                                         "`false`: answer 202 at once; follow "
                                         "GET /api/sessions/{id}/events.")]


class SessionCreate(BaseModel):
    """Which module and dataset a new session starts from."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"module": "calibration", "dataset": "synthetic", "options": {"num_views": 12}, "seed": 0},
        {"module": "calibration", "dataset": "folder",
         "options": {"path": "/data/my_photos", "columns": 9, "rows": 6}},
    ]})

    module: str = Field(description="Module name (GET /api/modules).")
    dataset: str | None = Field(None, description="Dataset name; default: the module's first dataset.")
    options: dict[str, Any] = Field(default_factory=dict,
                                    description="Dataset options (their JSON Schema is in "
                                                "GET /api/modules/{module}); folder datasets take `path`.")
    seed: int = Field(0, ge=0, le=2**32 - 1, strict=True,  # a JSON integer: not false, "3" or 1.5
                      description="Seeds every step's random generator (recorded, replayable).")


def viewer_link(viewer_url: str | None, **query: str) -> str | None:
    """The viewer's address opening a session (``?session=ID``) or a module; None without a viewer.

    ``viewer_url`` may be ``:PORT`` (same host as the page), which stays relative.
    """
    if not viewer_url:
        return None
    base = viewer_url.split("?", 1)[0]
    base = base if base.endswith("/") else base + "/"
    return base + "?" + urlencode(query)


def session_json(request: Request, session: Session) -> dict[str, Any]:
    """A session's summary: values and their types, step status, history, metrics, warnings."""
    monitor = request.app.state.runs.monitor(session)
    out = session.summary()
    out.update({
        "title": session.pipeline.title,
        "description": session.description,
        "warnings": current_warnings(session),
        "progress": monitor.last_progress if session.running is not None else None,
        "viewer_url": request.app.state.viewer_url,
        "links": {"self": f"/api/sessions/{session.id}", "events": f"/api/sessions/{session.id}/events",
                  "values": f"/api/sessions/{session.id}/values/{{name}}",
                  "module": f"/api/modules/{session.pipeline.name}",
                  "viewer": viewer_link(request.app.state.viewer_url, session=session.id)},
    })
    return out


def current_warnings(session: Session) -> list[dict[str, str]]:
    """Warnings of the runs whose results are in the state now, in pipeline order."""
    latest: dict[str, tuple[str, ...]] = {}
    for record in session.history:
        if record.status == "ok":
            latest[record.step] = record.warnings
    return [{"step": spec.name, "message": message} for spec in session.pipeline.steps
            if spec.name in session.metrics for message in latest.get(spec.name, ())]


def _load_session(pipeline: Pipeline, spec: DatasetSpec, options: dict[str, Any], seed: int,
                  session_id: str | None = None) -> Session:
    """Load a dataset (on a worker), naming the option at fault in every error; ``session_id``: the new
    session's id (None: the core's default)."""
    option_names = {o.name for o in spec.options}
    try:
        loaded = spec.load(options)
    except LabError as exc:
        if exc.field in option_names:
            raise type(exc)(f"options.{exc.field}", exc.reason) from None
        raise
    except (OSError, ValueError) as exc:  # e.g. a folder that does not exist or holds no images
        field = "options.path" if spec.takes_path else "dataset"
        raise InvalidValue(field, f"dataset {spec.name!r} could not be loaded: {exc}") from None
    return Session(pipeline, loaded, dataset=spec.name, options=options, seed=seed, session_id=session_id)


_CREATE_RESPONSES = retry_later_responses({
    413: "The dataset alone needs more memory than the server allows for all sessions.",
    429: "This client address already holds its share of live sessions, or the worker pool and its queue "
         "are full; see Retry-After.",
    503: "The server holds its most live sessions, or their memory is at the cap (none in use is evicted); "
         "see Retry-After."})


@router.post("", status_code=201, summary="Create a session", responses=_CREATE_RESPONSES,
             description="Load a dataset of a module into a new session and return its summary (201; the "
                         "id is `id`). 404 for an unknown module or dataset, 422 for a bad option, 413 when "
                         "the dataset is too large; when there is no room, 429 (this client holds its share "
                         "of sessions, or the workers are saturated) or 503 (the server is full), with "
                         "Retry-After. No session in use is ever evicted to make room.")
async def create_session(request: Request, body: SessionCreate, catalog: CatalogDep, store: StoreDep,
                         pools: PoolsDep, client: ClientDep) -> LabJSONResponse:
    pipeline = catalog.get(body.module)
    spec = pipeline.dataset(body.dataset)
    try:
        store.check_path(spec, body.options)
    except LabError as exc:
        raise type(exc)(f"options.{exc.field}", exc.reason) from None
    store.check_room(client=client)  # refuse at once rather than after waiting for a worker
    options = dict(body.options)
    worker = get_worker(request)  # several processes: the id names this one, which a proxy routes on
    load = partial(_load_session, pipeline, spec, options, body.seed,
                   worker.new_session_id() if worker is not None else None)
    session = await pools.loads.call(partial(store.admit, load, client=client))
    return LabJSONResponse(session_json(request, session), status_code=201,
                           headers={"Location": f"/api/sessions/{session.id}"})


@router.get("/{session_id}", summary="Read a session",
            description="State value names and types, the status of every step (`done`, `ready`, "
                        "`blocked`), the history (step, params, seed, seconds, metrics, status), current "
                        "metrics and warnings, and the running step's latest progress.")
def read_session(request: Request, session: SessionDep) -> LabJSONResponse:
    return LabJSONResponse(session_json(request, session))


@router.delete("/{session_id}", status_code=204, summary="Delete a session",
               description="Forget the session (a running step is cancelled).")
def delete_session(request: Request, store: StoreDep,
                   session_id: Annotated[str, Path(description="The session's id.")]) -> Response:
    check_session_owner(request, session_id)
    store.delete(session_id)
    return Response(status_code=204)


@router.post("/{session_id}/reset", summary="Reset a session",
             description="Forget the outputs of every step, or of `step` and everything downstream of it. "
                         "The dataset's values stay. 409 while a step runs.")
def reset_session(request: Request, session: SessionDep,
                  step: Annotated[str | None,
                                  Query(description="Reset only this step and what follows from it.")] = None
                  ) -> LabJSONResponse:
    if step is not None:
        session.pipeline.step(step)
    check_idle(session, request.app.state.runs.monitor(session))
    session.reset(step)
    return LabJSONResponse(session_json(request, session))


async def _launch(job: RunJob, wait: bool, pool: RunPool) -> LabJSONResponse:
    """Run ``job`` on the pool: 429 when its workers and queue are full, 409 when the session is busy."""
    at_once = pool.reserve()  # 429 before the session is marked busy
    try:
        job.monitor.begin(job)  # atomically refuses a second run (409)
    except BaseException:
        pool.release()
        raise
    if not wait:
        pool.start(job.execute)
        sid = job.session.id
        return LabJSONResponse({"session": sid, "step": job.step,
                                "status": "running" if at_once else "queued", "until": job.until,
                                "events": f"/api/sessions/{sid}/events",
                                "cancel": f"/api/sessions/{sid}/cancel"}, status_code=202)
    loop = asyncio.get_running_loop()
    finished = asyncio.Event()
    job.add_done_callback(lambda: loop.call_soon_threadsafe(finished.set))
    pool.start(job.execute)
    await finished.wait()
    if job.error is not None:
        raise job.error
    return LabJSONResponse(job.result)


_RUN_RESPONSES: dict[int | str, dict[str, Any]] = {
    202: {"description": "Started in the background, or queued for a worker (`?wait=false`; `status` says "
                 "which); follow the `events` link."},
    **retry_later_responses({
        404: "Unknown session or step.",
        409: "A value the step reads does not exist yet, another step is running, or the run was cancelled.",
        422: "A control is unknown, out of range or wrongly typed, or the step failed on its input.",
        429: "The worker pool runs its most steps and its queue is full; see Retry-After."}),
}


@router.post("/{session_id}/steps/{step}", summary="Run a step", responses=_RUN_RESPONSES,
             description="Run one step with the controls given in the JSON body (omitted ones take their "
                         "defaults; their schema is in GET /api/modules/{module}). Its outputs replace the "
                         "old ones and invalidate the steps downstream. Answers the run record: params, "
                         "seed, seconds, metrics (with evaluations against the truth when the dataset has "
                         "one), warnings.")
async def run_step(request: Request, session: SessionDep, store: StoreDep, pools: PoolsDep, step: StepName,
                   controls: Annotated[dict[str, Any] | None,
                                       Body(description="Controls of the step by name.",
                                            examples=[{"sigma": 0.2}])] = None,
                   wait: Wait = True) -> LabJSONResponse:
    spec = session.pipeline.step(step)
    monitor: RunMonitor = request.app.state.runs.monitor(session)
    check_idle(session, monitor)
    plan_step(session, spec, controls)
    return await _launch(RunJob(session, store, monitor, step=spec.name, params=controls), wait,
                         pools.for_step(session, spec.name))


@router.post("/{session_id}/run-until/{step}", summary="Run every step up to one",
             responses=_RUN_RESPONSES,
             description="Run the plan of `step`: the steps it needs by data flow whose outputs are missing "
                         "or stale, in pipeline order, then `step` itself (a step that reads only the "
                         "dataset runs alone). The JSON body maps step names to their controls "
                         "(`{\"detect_corners\": {\"window\": 7}}`); all of them are checked before "
                         "anything runs, and a done step given other controls than it ran with is stale and "
                         "runs again with what reads its outputs. Answers the plan (`plan`: steps and why "
                         "each runs), the steps that `ran`, and their run records.")
async def run_until(request: Request, session: SessionDep, store: StoreDep, pools: PoolsDep, step: StepName,
                    params: Annotated[dict[str, dict[str, Any] | None] | None,
                                      Body(description="Controls per step name.")] = None,
                    wait: Wait = True) -> LabJSONResponse:
    spec = session.pipeline.step(step)
    monitor: RunMonitor = request.app.state.runs.monitor(session)
    check_idle(session, monitor)
    plan_until(session, spec, params)
    return await _launch(RunJob(session, store, monitor, step=spec.name, params=params, until=True),
                         wait, pools.heavy)


@router.post("/{session_id}/cancel", status_code=202, summary="Cancel the running step",
             description="Ask the running step to stop: a long (generator) step stops at its next "
                         "progress snapshot and its run ends with an `error` event of kind `cancelled`; a "
                         "run-until stops before its next step. The state stays as it was before the "
                         "cancelled step. 409 when nothing runs.")
def cancel_run(request: Request, session: SessionDep) -> LabJSONResponse:
    monitor: RunMonitor = request.app.state.runs.monitor(session)
    job = monitor.job
    if job is not None:
        job.cancel_requested.set()
    running = session.running
    if running is None and job is None:
        raise NothingRunning("session", "no step is running in this session")
    session.cancel()
    step = running or (job.current if job else None)
    return LabJSONResponse({"session": session.id, "cancelling": step,
                            "long": bool(step and session.pipeline.step(step).is_generator)},
                           status_code=202)


def _event(name: str, data: dict[str, Any], event_id: str | None = None) -> ServerSentEvent:
    return ServerSentEvent(event=name, raw_data=json.dumps(jsonable(data), allow_nan=False), id=event_id)


async def quiet_hang_up() -> AsyncIterator[None]:
    """A request-scoped dependency that ends an event stream quietly when its client hangs up.

    FastAPI's ``EventSourceResponse`` forwards the route's events through a keep-alive task and a
    one-event buffer to the response. When a client stops reading (a full socket) and then hangs up, the
    response stops with an event in that buffer and the task's next write raises
    ``anyio.BrokenResourceError`` out of the request's exit stack, which uvicorn logged as ~130 lines of
    traceback (fastapi discussion #15725). The stream's teardown unwinds through this dependency (entered
    before the stream), which drops only those stream errors; any other error still propagates.
    """
    try:
        yield
    except* (anyio.BrokenResourceError, anyio.ClosedResourceError):
        logger.debug("an event-stream client hung up mid-stream")


@router.get("/{session_id}/events", response_class=EventSourceResponse, summary="Stream a run's progress",
            description="Server-sent events of the latest run in the session: `progress` events "
                        "(`{step, iteration, total, loss, message}`) while it runs, then one `done` event "
                        "(the same JSON as the synchronous answer) or `error` event (`{error, field, reason, "
                        "step}`), and the stream ends. A client that connects after the run is over gets its "
                        "retained events again; when nothing has run, one `idle` event (or the outcome of "
                        "the last recorded run).", dependencies=[Depends(quiet_hang_up)])
async def stream_events(request: Request, session: SessionDep) -> AsyncIterable[ServerSentEvent]:
    monitor: RunMonitor = request.app.state.runs.monitor(session)
    after = 0
    run_id, events, active = monitor.poll(after)
    if not active and (run_id == 0 or len(session.history) > monitor.history_at_finish):
        # No run of the API's (or a newer one elsewhere): report the last recorded run, or idle.
        if session.history:
            yield _event(*record_outcome(session, session.history[-1]))
        else:
            yield _event("idle", {"session": session.id, "running": session.running})
        return
    while True:
        for seq, name, data in events:
            after = seq
            yield _event(name, data, f"{run_id}:{seq}")
            if name in ("done", "error"):
                return
        if not active:
            return
        await asyncio.sleep(POLL_SECONDS)
        current, events, active = monitor.poll(after)
        if current != run_id:  # a new run began before this one's end was seen (events dropped)
            return
