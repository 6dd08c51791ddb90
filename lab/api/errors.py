"""Every failure the API returns is JSON ``{"error": kind, "field": ..., "reason": ...}``.

Errors from :mod:`lab.core.errors` carry their HTTP status; FastAPI's request validation errors
(a malformed JSON body, a wrongly typed query parameter) and Starlette's HTTP errors (an unknown
route) are reshaped into the same body; anything else is a bug in the lab and becomes a 500 whose
body still has that shape. A request body over the size limit is refused by
:class:`BodyLimitMiddleware` before it is read into memory.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from typing import Any, cast

import numpy as np
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, ExceptionHandler, Message, Receive, Scope, Send

from lab.core.errors import CapacityExceeded, LabError

log = logging.getLogger("lab.api")


class NothingRunning(LabError):
    """``cancel`` was asked for while no step runs in the session."""

    status = 409
    kind = "not_running"


class ModuleUnavailable(LabError):
    """A registered module failed to load (a bug in that module, reported without a traceback)."""

    status = 503
    kind = "unavailable"


def error_body(kind: str, field: str, reason: str) -> dict[str, str]:
    return {"error": kind, "field": field, "reason": reason}


class ErrorBody(BaseModel):
    """The body of every error response."""

    error: str = Field(description="The kind: not_found, invalid_request, invalid_control, invalid_value, "
                                   "missing_input, busy, step_failed, cancelled, not_running, capacity, "
                                   "too_many_requests, overloaded, unavailable, misdirected, internal.",
                       examples=["invalid_control"])
    field: str = Field(description="What is at fault: a control, an option (`options.path`), a value, "
                                   "`session`, `module`, `step`, `body`...", examples=["sigma"])
    reason: str = Field(description="Why, in words.", examples=["must be at most 1.0, got 3.0"])


_DEFAULT_ERROR_TEXT = {
    400: "The body cannot be parsed (JSON that is not UTF-8, a broken form) or Content-Length is not a "
         "number.",
    404: "Unknown module, dataset, session, step or value.",
    409: "A step is running, or a value the step reads does not exist yet.",
    413: "The body is too large, or the server has no room for another session.",
    422: "A malformed body, or a bad control, option or value.",
}


def error_responses(texts: dict[int, str] | None = None) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` documenting error statuses with the :class:`ErrorBody` schema."""
    merged = {**_DEFAULT_ERROR_TEXT, **(texts or {})}
    return {code: {"model": ErrorBody, "description": text} for code, text in merged.items()}


def jsonable(value: Any) -> Any:
    """``value`` with NumPy scalars made plain and NaN / infinity made ``null`` (strict JSON)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    return value


class LabJSONResponse(JSONResponse):
    """A JSON response that never fails on NaN, infinity or NumPy scalars (they become plain JSON)."""

    def render(self, content: Any) -> bytes:
        return json.dumps(jsonable(content), ensure_ascii=False, allow_nan=False,
                          separators=(",", ":")).encode("utf-8")


# --- exception handlers -------------------------------------------------------------------------
async def lab_error_handler(request: Request, exc: LabError) -> JSONResponse:
    return LabJSONResponse(exc.to_dict(), status_code=exc.status, headers=exc.headers())


def _field_of(loc: Sequence[Any]) -> str:
    """``("body", "options", "columns")`` -> ``options.columns``; ``("query", "format")`` -> ``format``."""
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header", "cookie"):
        where, parts = parts[0], parts[1:]
        if where == "body" and parts and parts[0].isdigit():  # a JSON decode error's character position
            parts = []
        if not parts:
            return where
    return ".".join(parts) or "request"


def _reason_of(error: dict[str, Any]) -> str:
    if error.get("type") == "json_invalid":
        ctx = error.get("ctx") or {}
        position = error.get("loc", ("body", "?"))[-1]
        return f"malformed JSON: {ctx.get('error', 'cannot be parsed')} at character {position}"
    reason = str(error.get("msg", "is invalid"))
    value = error.get("input")
    if isinstance(value, (bytes, bytearray)):  # a body that was not sent as JSON
        try:
            json.loads(value)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            return (f"malformed JSON: {exc}; the body must be a JSON object sent with "
                    "Content-Type: application/json")
        return f"{reason}; send the body as JSON with Content-Type: application/json"
    if error.get("type") not in ("missing", "extra_forbidden") and isinstance(value, (str, int, float, bool)):
        text = repr(value)
        reason += f", got {text if len(text) <= 60 else text[:57] + '...'}"
    return reason


async def validation_error_handler(request: Request, exc: RequestValidationError) -> JSONResponse:
    errors = list(exc.errors())
    first = errors[0] if errors else {"loc": ("request",), "msg": "is invalid"}
    body: dict[str, Any] = error_body("invalid_request", _field_of(first.get("loc", ())), _reason_of(first))
    if len(errors) > 1:
        body["details"] = [{"field": _field_of(e.get("loc", ())), "reason": _reason_of(e)} for e in errors]
    return LabJSONResponse(body, status_code=422)


_HTTP_KINDS = {400: "bad_request", 404: "not_found", 405: "method_not_allowed", 413: "capacity",
               415: "unsupported_media_type"}


async def http_error_handler(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    kind = _HTTP_KINDS.get(exc.status_code, "http_error")
    field = "path" if exc.status_code in (404, 405) else "request"
    detail = exc.detail if isinstance(exc.detail, str) else json.dumps(jsonable(exc.detail))
    if exc.status_code == 404 and detail == "Not Found":
        detail = f"no route {request.url.path!r}; the API is described at /docs"
    if exc.status_code == 400 and isinstance(exc.__cause__, RecursionError):  # FastAPI's json.loads
        field, detail = "body", ("the JSON body nests arrays and objects too deeply to be read; the lab's "
                                 "bodies nest a few levels")
    headers = dict(getattr(exc, "headers", None) or {})
    if exc.status_code == 405:
        detail = f"{request.method} is not allowed on {request.url.path!r}; see /docs"
        headers["Allow"] = ", ".join(allowed_methods(request))
    return LabJSONResponse(error_body(kind, field, detail), status_code=exc.status_code,
                           headers=headers or None)


_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")


def allowed_methods(request: Request) -> list[str]:
    """Every method some route answers on the request's path: a 405's ``Allow`` (Starlette names one
    route's)."""
    routes = request.app.router.routes
    return [method for method in _METHODS
            if any(route.matches({**request.scope, "method": method})[0] is Match.FULL for route in routes)]


async def unexpected_error_handler(request: Request, exc: Exception) -> JSONResponse:
    """A bug in the lab: log the traceback, answer JSON (the only path to a 500)."""
    log.exception("unexpected error on %s %s", request.method, request.url.path)
    return LabJSONResponse(error_body("internal", "server", f"internal error ({type(exc).__name__}: {exc}); "
                                                           "this is a bug in the lab, please report it"),
                           status_code=500)


def register_error_handlers(app: FastAPI) -> None:
    # Starlette types a handler as taking any Exception, though it passes each handler the class it is
    # registered for (Callable parameters are contravariant: Kludex/starlette#2417); the casts say so.
    app.add_exception_handler(LabError, cast(ExceptionHandler, lab_error_handler))
    app.add_exception_handler(RequestValidationError, cast(ExceptionHandler, validation_error_handler))
    app.add_exception_handler(StarletteHTTPException, cast(ExceptionHandler, http_error_handler))
    app.add_exception_handler(Exception, unexpected_error_handler)


# --- request size -------------------------------------------------------------------------------
class BodyLimitMiddleware:
    """Refuse request bodies over ``max_bytes`` with a JSON 413, never holding more than that in memory.

    A declared ``Content-Length`` over the limit is refused before any byte is read. A chunked
    body (no length) is read up to the limit and then either refused or replayed to the app.
    """

    def __init__(self, app: ASGIApp, *, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = int(max_bytes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = Headers(scope=scope).get("content-length")
        if declared is not None:
            try:
                size = int(declared)
            except ValueError:
                await self._refuse(scope, receive, send, 400, error_body(
                    "bad_request", "content-length", f"not a number: {declared!r}"))
                return
            if size > self.max_bytes:
                await self._too_large(scope, receive, send, f"{size} bytes")
                return
            await self.app(scope, receive, send)  # the server never delivers more than it declared
            return
        if scope.get("method") in ("GET", "HEAD", "DELETE", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        chunks: list[bytes] = []
        total = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away
                return
            chunk = message.get("body", b"")
            total += len(chunk)
            if total > self.max_bytes:
                await self._too_large(scope, receive, send, f"more than {self.max_bytes} bytes")
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": b"".join(chunks), "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _too_large(self, scope: Scope, receive: Receive, send: Send, size: str) -> None:
        error = CapacityExceeded("body", f"the request body is {size}; the limit is {self.max_bytes} bytes "
                                         f"({self.max_bytes / 2**20:.1f} MiB)")
        await self._refuse(scope, receive, send, 413, error.to_dict())

    @staticmethod
    async def _refuse(scope: Scope, receive: Receive, send: Send, status: int, body: dict[str, str]) -> None:
        response = LabJSONResponse(body, status_code=status, headers={"Connection": "close"})
        await response(scope, receive, send)
