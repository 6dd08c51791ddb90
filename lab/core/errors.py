"""Errors that every front end turns into a clear message.

Each error names the thing at fault (``field``) and why (``reason``). The REST API maps
``status`` onto the HTTP status code and returns ``{"error": kind, "field": ..., "reason": ...}``;
the CLI prints one line and exits 2; the grader writes the reason into the failed test.
"""

from __future__ import annotations

import math


class LabError(Exception):
    """Base class: a problem with what the user asked for, never a bug in the lab."""

    status: int = 400
    kind: str = "bad_request"

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason

    def to_dict(self) -> dict[str, str]:
        return {"error": self.kind, "field": self.field, "reason": self.reason}

    def headers(self) -> dict[str, str]:
        """HTTP headers the REST API sends with this error (none; ``Retry-After`` for :class:`RetryLater`)."""
        return {}


class UnknownName(LabError):
    """An unknown module, step, dataset, value or session."""

    status = 404
    kind = "not_found"


class InvalidControl(LabError):
    """A control (keyword parameter) is missing its type, out of range or not one of its choices."""

    status = 422
    kind = "invalid_control"


class InvalidValue(LabError):
    """A state value or upload has the wrong type, shape, dtype or contents."""

    status = 422
    kind = "invalid_value"


class MissingInput(LabError):
    """A step was run before the values it reads exist."""

    status = 409
    kind = "missing_input"


class SessionBusy(LabError):
    """Another step is running in this session."""

    status = 409
    kind = "busy"


class Forbidden(LabError):
    """The request is understood but not allowed here (a folder outside the server's data root)."""

    status = 403
    kind = "forbidden"


class CapacityExceeded(LabError):
    """Too many live sessions, too much memory, or an upload that is too large."""

    status = 413
    kind = "capacity"


class RetryLater(LabError):
    """No room now for a session or a run (the server is full); room comes back, so try again later.

    ``retry_after`` is a whole number of seconds, at least 1, sent as ``Retry-After``.
    """

    status = 503
    kind = "overloaded"

    def __init__(self, field: str, reason: str, *, retry_after: float) -> None:
        super().__init__(field, reason)
        self.retry_after = max(1, math.ceil(retry_after))

    def headers(self) -> dict[str, str]:
        return {"Retry-After": str(self.retry_after)}


class TooManyRequests(RetryLater):
    """This client holds its share of sessions, or the worker pool and its queue are full."""

    status = 429
    kind = "too_many_requests"


class StepFailed(LabError):
    """The step raised on this input (e.g. too few views with a detected board)."""

    status = 422
    kind = "step_failed"


class Cancelled(LabError):
    """A long step was cancelled before it finished."""

    status = 409
    kind = "cancelled"
