"""The FastAPI app: modules, sessions, values, the landing page, and JSON errors everywhere.

``create_app`` builds one app around a :class:`~lab.core.store.SessionStore`; the viewer, in the
same process, is given the same store, so a session made over REST opens in the viewer and the
other way round. All live state is in the store (``app.state.store``); ``app.state`` also holds
the module catalog, the run monitors and ``viewer_url`` (which the CLI may set after creating the
app).

    app = create_app(SessionStore(max_sessions=16), viewer_url="http://127.0.0.1:8080")
    uvicorn.run(app, host="127.0.0.1", port=8000)
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import FileResponse, HTMLResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline

import lab
from lab.api import modules as modules_router
from lab.api import sessions as sessions_router
from lab.api import values as values_router
from lab.api.deps import ModuleCatalog
from lab.api.errors import BodyLimitMiddleware, LabJSONResponse, register_error_handlers
from lab.api.openapi import install_openapi
from lab.api.runs import DEFAULT_QUEUE, DEFAULT_WORKERS, LIGHT_WORKERS, RunPool, RunPools, RunRegistry
from lab.api.workers import WorkerHeaderMiddleware, WorkerIdentity
from lab.core.pipeline import Pipeline
from lab.core.store import SessionStore

#: The landing page and its assets (repository root ``static/``).
STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
DEFAULT_MAX_UPLOAD_BYTES = 32 * 2**20
#: The lab's icon (an eye on the accent blue), served at /favicon.ico; the landing page inlines the same.
FAVICON_SVG = ("<svg xmlns='http://www.w3.org/2000/svg' viewBox='0 0 32 32'>"
               "<rect width='32' height='32' rx='7' fill='#2f6fde'/>"
               "<path d='M5 16c3-6 7-9 11-9s8 3 11 9c-3 6-7 9-11 9s-8-3-11-9z' fill='none' stroke='white' "
               "stroke-width='2.5'/><circle cx='16' cy='16' r='4' fill='white'/></svg>")

_DESCRIPTION = """\
Drive Vision Lab's teaching modules from scripts: list the modules and the JSON Schema of every
step's controls, create a session on a dataset (or on uploaded images), run steps one at a time or
up to a step, stream the progress of long steps as server-sent events, and read any intermediate
value as JSON, NPY, PNG or PLY. Sessions are shared with the 3D viewer.

Every error is JSON `{"error": kind, "field": what is at fault, "reason": why}` with a 4xx status;
a 500 means a bug in the lab.
"""

_TAGS = [
    {"name": "modules", "description": "Teaching modules, their steps, controls and datasets."},
    {"name": "sessions",
     "description": "Live sessions: create, run steps, stream progress, cancel, reset."},
    {"name": "values", "description": "Read and upload state values."},
    {"name": "service", "description": "Health and the landing page."},
]


def _lessons_router() -> APIRouter | None:
    """``lab.api.lessons.router`` when that module exists (it is written separately)."""
    try:
        module = importlib.import_module("lab.api.lessons")
    except ModuleNotFoundError as exc:
        if exc.name == "lab.api.lessons":
            return None
        raise
    return getattr(module, "router", None)


def create_app(store: SessionStore | None = None, *, modules: Callable[[str], Pipeline] | None = None,
               module_names: Sequence[str] | None = None, viewer_url: str | None = None,
               max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES, extra_routers: Iterable[APIRouter] = (),
               workers: int = DEFAULT_WORKERS, queued_runs: int = DEFAULT_QUEUE,
               trust_forwarded_for: bool = False, worker: WorkerIdentity | None = None,
               grading: bool = True) -> FastAPI:
    """Build the REST API and landing page.

    Args:
        store: the live sessions, shared with the viewer (a new default store when None).
        modules: module name -> pipeline (default :func:`lab.modules.get_pipeline`; tests inject a toy one).
        module_names: the modules to serve, in listing order (default :data:`lab.modules.MODULES`).
        viewer_url: where the viewer runs; linked from the landing page and ``/api/health``.
        max_upload_bytes: largest request body accepted (413 above it, refused before it is read).
        extra_routers: more routers to include (``lab.api.lessons.router`` is included when it exists).
        workers: threads of the heavy pool, which runs the steps not known to be quick (LIGHT_WORKERS
            more run the quick ones, and as many load datasets).
        queued_runs: runs and loads that may wait for a worker in each pool; more are refused with 429 and
            Retry-After.
        trust_forwarded_for: count sessions per client by the last ``X-Forwarded-For`` entry (set it only
            behind one trusted proxy); default: by the socket's peer address.
        worker: this process's id among several sharing the database (:mod:`lab.api.workers`): its
            sessions' ids carry it, a request for another worker's session is answered 421, and every
            response names it in ``X-Vision-Lab-Worker``. None: a lone server (ids as before).
        grading: this process grades submissions (claims them from the database); False: it only stores
            them and reads them back, another process on the same database grades (``--no-grading``).
    """
    if max_upload_bytes < 1:
        raise ValueError("max_upload_bytes must be positive")
    # fastapi-offline serves Swagger UI (v5: renders OpenAPI 3.1) and ReDoc from the package, not a CDN:
    # /docs works on a machine with no internet, as in a classroom lab.
    app = FastAPIOffline(title="Vision Lab", version=lab.__version__, description=_DESCRIPTION,
                         openapi_tags=_TAGS, default_response_class=LabJSONResponse)
    app.state.store = store if store is not None else SessionStore()
    app.state.catalog = ModuleCatalog.of(modules, module_names)
    app.state.runs = RunRegistry()
    app.state.pools = RunPools(heavy=RunPool(workers=workers, queue=queued_runs),
                               light=RunPool(workers=LIGHT_WORKERS, queue=queued_runs),
                               loads=RunPool(workers=LIGHT_WORKERS, queue=queued_runs))
    app.state.trust_forwarded_for = bool(trust_forwarded_for)
    app.state.viewer_url = viewer_url
    app.state.max_upload_bytes = int(max_upload_bytes)
    app.state.worker = worker
    app.state.grading = bool(grading)
    register_error_handlers(app)
    app.add_middleware(BodyLimitMiddleware, max_bytes=int(max_upload_bytes))
    if worker is not None:
        app.add_middleware(WorkerHeaderMiddleware, worker=worker.id)

    routers = [modules_router.router, sessions_router.router, values_router.router, *extra_routers]
    lessons = _lessons_router()
    if lessons is not None and all(r is not lessons for r in routers):
        routers.append(lessons)
    for router in routers:
        app.include_router(router)

    @app.get("/api/health", tags=["service"], summary="Health and server facts",
             description="`status` is `ok` when the API answers; also the version, live sessions and their "
                         "caps, the worker pools (`runs`: `heavy`, `light` and `loads`, each with workers, "
                         "running, queued, max_queued), the served modules, `viewer_url` (null when no "
                         "viewer runs), `worker` (this process's id among several behind a proxy, null for a "
                         "lone server) and `grading` (whether this process grades submissions). Answered "
                         "in the event loop, never waiting for a worker, so it stays fast while steps run.")
    async def health(request: Request) -> LabJSONResponse:
        state = request.app.state
        return LabJSONResponse({"status": "ok", "version": lab.__version__, "sessions": len(state.store),
                "max_sessions": state.store.max_sessions,
                "max_sessions_per_client": state.store.max_sessions_per_client, "runs": state.pools.stats(),
                "modules": list(state.catalog.names), "viewer_url": state.viewer_url,
                "max_upload_bytes": state.max_upload_bytes,
                "worker": state.worker.id if state.worker is not None else None, "grading": state.grading})

    @app.get("/", include_in_schema=False)
    def landing_page() -> Response:
        index = STATIC_DIR / "index.html"
        if not index.is_file():  # an install without the static folder still says where to go
            return HTMLResponse("<!doctype html><title>Vision Lab</title>"
                                '<link rel="icon" href="/favicon.ico"><h1>Vision Lab</h1>'
                                '<p><a href="/docs">API documentation</a></p>')
        return FileResponse(index, media_type="text/html")

    @app.get("/favicon.ico", include_in_schema=False)
    def favicon() -> Response:
        return Response(FAVICON_SVG, media_type="image/svg+xml", headers={"Cache-Control": "max-age=86400"})

    if STATIC_DIR.is_dir():
        app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    install_openapi(app, module_names=app.state.catalog.names)
    return app
