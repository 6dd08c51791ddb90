"""Several API processes behind one proxy: which process a live session lives on, and the answer when a
request for it reaches another one (issue 20, item 3; docs/design.md section 2).

What must survive a process (submissions, their results, the instructor's views, assignment seeds) is
in the submissions database, which every process shares. A live session is not: its state (images,
point clouds, a NeRF being trained) is in the memory of the process that made it, and only there. So
sessions are *sticky*, and the id says where: a process started as worker ``w1``
(``vision-lab serve --workers N`` names them ``w0`` .. ``wN-1``) gives its sessions ids
``w1-<12 hex digits>``, and a proxy routes ``/api/sessions/w1-...`` to worker ``w1`` by the path alone
(no cookie, so a script with no cookie jar is routed right too; README, "Behind a proxy").

A request for a session of another worker is answered **421 Misdirected Request** (RFC 9110 section
15.5.20: this server is not the one that can answer for this URI) with the JSON error body plus
``worker`` (the owner) and ``url`` (its own address, when known), never a misleading 404. Re-creating the
session from its recorded history was considered and not chosen: replaying every step can mean minutes of
training, an upload's values are not recorded, and two processes would each hold a copy that diverge.

Every response carries :data:`WORKER_HEADER` naming the worker that answered, so a proxy's routing can
be checked from outside.
"""

from __future__ import annotations

import re
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from lab.core.errors import LabError

#: A worker's id: short, lower-case letters and digits (it becomes part of session ids and URLs).
WORKER_ID = re.compile(r"[a-z0-9]{1,16}")
#: The response header naming the worker that answered.
WORKER_HEADER = "X-Vision-Lab-Worker"
#: A session id that carries its worker: ``<worker>-<hex>`` (ids without a worker have no ``-``).
_OWNED_ID = re.compile(r"([a-z0-9]{1,16})-[0-9a-f]+")
#: The OpenAPI text of the 421 answer, on every route of a session.
MISDIRECTED = {421: "The session lives in another worker process of this server (several behind a proxy): "
                    "`worker` names it and `url` is its address; route `/api/sessions/<worker>-*` there."}


class Misdirected(LabError):
    """A request for a live session that lives in another worker process (HTTP 421)."""

    status = 421
    kind = "misdirected"

    def __init__(self, field: str, reason: str, *, worker: str, url: str | None) -> None:
        super().__init__(field, reason)
        self.worker = worker
        self.url = url

    def to_dict(self) -> dict[str, str]:
        body = super().to_dict()
        body["worker"] = self.worker
        if self.url is not None:
            body["url"] = self.url
        return body


def check_worker_id(value: str) -> str:
    """``value`` if it is a valid worker id, else ValueError saying what one looks like."""
    if not WORKER_ID.fullmatch(value):
        raise ValueError(f"a worker id is 1 to 16 lower-case letters and digits (like w0), got {value!r}")
    return value


def parse_peers(text: str) -> dict[str, str]:
    """``"w0=http://127.0.0.1:8000,w1=http://127.0.0.1:8001"`` -> {worker id: its API's base URL}."""
    peers: dict[str, str] = {}
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        name, sep, url = item.partition("=")
        if not sep or not url.strip():
            raise ValueError(f"peers are WORKER=URL separated by commas, got {item!r}")
        peers[check_worker_id(name.strip())] = url.strip().rstrip("/")
    return peers


def owner_of(session_id: str) -> str | None:
    """The worker a session id names (None for an id made by a process with no worker id)."""
    match = _OWNED_ID.fullmatch(session_id)
    return match.group(1) if match else None


@dataclass(frozen=True)
class WorkerIdentity:
    """This process among several sharing one database: its id and where the others' APIs are.

    ``peers`` maps worker ids to their API's base URL (this worker's own entry may be there too); it is
    used only to name where a misdirected session lives.
    """

    id: str
    peers: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_worker_id(self.id)
        for name in self.peers:
            check_worker_id(name)

    def new_session_id(self) -> str:
        """A fresh session id owned by this worker: ``<id>-<12 hex digits>``."""
        return f"{self.id}-{uuid.uuid4().hex[:12]}"

    def check_owner(self, session_id: str) -> None:
        """Raise :class:`Misdirected` when ``session_id`` names another worker; return when it names this
        one or none (then the store answers, 404 if it does not hold it)."""
        owner = owner_of(session_id)
        if owner is None or owner == self.id:
            return
        url = self.peers.get(owner)
        where = f" ({url})" if url else " (its address is not known here)"
        raise Misdirected("session", f"session {session_id!r} lives on worker {owner}{where}, not on this "
                                     f"worker ({self.id}): live sessions stay in the process that made them; "
                                     f"route /api/sessions/{owner}-* to worker {owner}",
                          worker=owner, url=url)


class WorkerHeaderMiddleware:
    """Adds ``X-Vision-Lab-Worker: <id>`` to every HTTP response (streams included, untouched)."""

    def __init__(self, app: ASGIApp, *, worker: str) -> None:
        self.app = app
        self.header = (WORKER_HEADER.lower().encode("latin-1"), worker.encode("latin-1"))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_header(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", []), self.header]}
            await send(message)

        await self.app(scope, receive, send_with_header)


__all__ = ["MISDIRECTED", "WORKER_HEADER", "Misdirected", "WorkerHeaderMiddleware", "WorkerIdentity",
           "check_worker_id", "owner_of", "parse_peers"]
