"""The served OpenAPI document: FastAPI's, plus what FastAPI cannot say by itself.

* Error responses are JSON on every route. FastAPI files an error response's model under the
  route's own media type, so the event stream's and the starter file's errors read as
  ``text/event-stream`` and ``text/x-python``; they are moved under ``application/json``.
* ``module`` (of ``POST /api/sessions`` and ``GET /api/modules/{module}``) lists the served modules.
* OpenAPI links say which response field feeds which path parameter: a new session's ``id`` every
  ``/api/sessions/{session_id}/...`` route, a submission's ``id`` its status, a lesson's ``id`` its
  routes, a module's ``name`` its description. Clients (and the fuzzer's stateful phase) follow them.

    install_openapi(app, module_names=["calibration", ...])   # app.openapi() now returns the document
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from fastapi import FastAPI

JSON = "application/json"

#: (method, path, status) of a response -> [(method, path) of the target, {parameter: runtime expression}]:
#: the links every served document gets (targets missing from the document are left out).
LINKS: dict[tuple[str, str, str], list[tuple[tuple[str, str], dict[str, str]]]] = {
    ("get", "/api/modules", "200"): [
        (("get", "/api/modules/{module}"), {"module": "$response.body#/0/name"})],
    ("get", "/api/lessons", "200"): [
        (("get", "/api/lessons/{lesson_id}"), {"lesson_id": "$response.body#/0/id"}),
        (("get", "/api/lessons/{lesson_id}/starter.py"), {"lesson_id": "$response.body#/0/id"}),
        (("post", "/api/lessons/{lesson_id}/submissions"), {"lesson_id": "$response.body#/0/id"}),
        (("get", "/api/lessons/{lesson_id}/submissions"), {"lesson_id": "$response.body#/0/id"})],
    ("post", "/api/lessons/{lesson_id}/submissions", "202"): [
        (("get", "/api/submissions/{submission_id}"), {"submission_id": "$response.body#/id"}),
        (("get", "/api/lessons/{lesson_id}/submissions"), {"lesson_id": "$response.body#/lesson"})],
}
#: Every operation on a path with ``{session_id}`` is linked from a new session's id.
SESSION_SOURCE = ("post", "/api/sessions", "201")
SESSION_PARAMETER = "session_id"


def install_openapi(app: FastAPI, *, module_names: Sequence[str]) -> None:
    """Make ``app.openapi()`` serve FastAPI's document refined by :func:`refine` (built once, then cached)."""
    build = app.openapi  # FastAPI's own: builds the document once and keeps it in app.openapi_schema

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            document = build()  # also stored in app.openapi_schema, so refined once
            refine(document, module_names)
            return document
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def refine(document: dict[str, Any], module_names: Sequence[str]) -> None:
    """JSON error bodies, the module enum and the links, in place."""
    json_errors(document)
    module_enum(document, module_names)
    add_links(document)


def _operations(document: dict[str, Any]) -> dict[tuple[str, str], dict[str, Any]]:
    return {(method, path): operation for path, item in document.get("paths", {}).items()
            for method, operation in item.items() if isinstance(operation, dict) and "responses" in operation}


def json_errors(document: dict[str, Any]) -> None:
    """Move 4xx/5xx response bodies filed under a route's own media type to ``application/json``."""
    for operation in _operations(document).values():
        for status, response in operation["responses"].items():
            content = response.get("content")
            if status[:1] not in ("4", "5") or not content or JSON in content:
                continue
            response["content"] = {JSON: next(iter(content.values()))}


def module_enum(document: dict[str, Any], module_names: Sequence[str]) -> None:
    """``module`` of a new session and of ``GET /api/modules/{module}`` takes one of the served names."""
    names = list(module_names)
    if not names:
        return
    create = document.get("components", {}).get("schemas", {}).get("SessionCreate", {})
    if "module" in create.get("properties", {}):
        create["properties"]["module"]["enum"] = names
    describe = _operations(document).get(("get", "/api/modules/{module}"))
    for parameter in describe.get("parameters", []) if describe else []:
        if parameter.get("in") == "path" and parameter.get("name") == "module":
            parameter["schema"]["enum"] = names


def add_links(document: dict[str, Any]) -> None:
    """Add :data:`LINKS` and the session links to the responses they start from."""
    operations = _operations(document)
    links = dict(LINKS)
    links[SESSION_SOURCE] = [((method, path), {SESSION_PARAMETER: "$response.body#/id"})
                             for method, path in operations if "{" + SESSION_PARAMETER + "}" in path]
    for (method, path, status), targets in links.items():
        source = operations.get((method, path))
        if source is None or status not in source["responses"]:
            continue
        found = {}
        for target, parameters in targets:
            operation = operations.get(target)
            if operation is not None and operation.get("operationId"):
                found[operation["operationId"]] = {"operationId": operation["operationId"],
                                                   "parameters": parameters}
        if found:
            source["responses"][status].setdefault("links", {}).update(found)
