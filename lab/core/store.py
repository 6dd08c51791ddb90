"""The live-session store: sessions by id, admitted within caps on count and memory, never evicted.

A new session is admitted only while there is room: at most ``max_sessions`` live sessions, at
most ``max_sessions_per_client`` of them made by one client address, and the state of all of them
within ``max_bytes``. When there is no room the store refuses (:class:`TooManyRequests`, 429, for a
client over its share; :class:`RetryLater`, 503, when the server is full) with a ``retry_after``
hint; it never evicts a session someone may be using. Only sessions idle for ``idle_seconds``
are dropped, and a bounded record of dropped and deleted ids lets a lookup say truthfully why a
session is not there.
"""

from __future__ import annotations

import os
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from lab.core.errors import CapacityExceeded, Forbidden, RetryLater, TooManyRequests, UnknownName
from lab.core.pipeline import DatasetSpec, Pipeline, Session, open_session

#: How many dropped or deleted session ids the store remembers (the oldest are forgotten first).
GONE_MEMORY = 4096
#: The longest ``Retry-After`` the store advises (seconds): room may come sooner, when a session is deleted.
MAX_RETRY_AFTER = 60.0
#: ``Retry-After`` when no live session is idle (none will expire soon; deletions free room).
BUSY_RETRY_AFTER = 10.0

Gone = Literal["expired", "deleted"]


def _mib(nbytes: int) -> str:
    """``nbytes`` in MiB, to a tenth below 10 MiB."""
    mib = nbytes / 2**20
    return f"{mib:.1f} MiB" if mib < 10 else f"{mib:.0f} MiB"


def link_outside(path: str | os.PathLike, root: Path) -> str | None:
    """The first entry of folder ``path`` (or ``path`` itself) that is a symbolic link resolving
    outside ``root``.

    Loaders read a folder's own files, so its entries are what is checked, one by one; None when
    every entry stays inside ``root`` (a resolved folder).
    """
    target = Path(path).expanduser()
    try:
        entries = sorted(target.iterdir()) if target.is_dir() else [target]
    except OSError:  # unreadable: the loader reports it
        return None
    for entry in entries:
        if entry.is_symlink():
            try:
                resolved = entry.resolve()
            except (OSError, RuntimeError):  # a loop of links resolves nowhere: refused as well
                return entry.name
            if resolved != root and root not in resolved.parents:
                return entry.name
    return None


class SessionStore:
    """Holds live sessions for the API and the viewer (one process, shared by both).

    Sessions idle longer than ``idle_seconds`` expire (a running one never does). A new session
    is refused, never made room for by evicting another: 429 (:class:`TooManyRequests`) when its
    client already holds ``max_sessions_per_client``, 503 (:class:`RetryLater`) when the server
    holds ``max_sessions`` or the state of all sessions would exceed ``max_bytes``, 413
    (:class:`CapacityExceeded`) when the one session needs more than ``max_bytes``. ``client`` is
    the address a session was asked for from (None, e.g. the viewer: only the total caps apply).

    ``data_root`` (a folder; default None = anywhere) is where datasets that read the server's
    disk (option ``path``) may read: set it when serving beyond 127.0.0.1, so that a browser or a
    script cannot load ``/etc`` or another student's folder. :meth:`check_path` enforces it for
    the viewer and the REST API alike.
    """

    def __init__(self, *, max_sessions: int = 64, max_sessions_per_client: int = 16,
                 idle_seconds: float = 3600.0, max_bytes: int = 4 * 1024**3,
                 data_root: str | os.PathLike | None = None) -> None:
        if min(max_sessions, max_sessions_per_client, max_bytes) < 1 or idle_seconds <= 0:
            raise ValueError("the store's caps and idle time must be positive")
        self.max_sessions = max_sessions
        self.max_sessions_per_client = max_sessions_per_client
        self.idle_seconds = idle_seconds
        self.max_bytes = max_bytes
        self.data_root = Path(data_root).resolve() if data_root is not None else None
        self._sessions: dict[str, Session] = {}
        self._clients: dict[str, str | None] = {}  # session id -> the client that made it
        self._loading: Counter[str | None] = Counter()  # places held by sessions still loading, per client
        self._gone: OrderedDict[str, Gone] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._sessions)

    def __contains__(self, session_id: str) -> bool:
        return session_id in self._sessions

    def ids(self) -> list[str]:
        return list(self._sessions)

    def check_path(self, spec: DatasetSpec, options: dict[str, Any] | None) -> None:
        """Refuse (Forbidden, field ``path``) a ``path`` option outside :attr:`data_root`.

        The folder (or file) must resolve inside the root, and so must each of its files: a file
        that is a symbolic link to somewhere outside is refused by name
        (:func:`link_outside`).
        """
        if self.data_root is None or not spec.takes_path:
            return
        path = (options or {}).get("path")
        if path in (None, ""):
            return
        resolved = Path(str(path)).expanduser().resolve()
        if resolved != self.data_root and self.data_root not in resolved.parents:
            raise Forbidden("path", f"{str(path)!r} is outside the folder this server reads data from "
                                    f"({self.data_root}); put the data there or ask whoever runs the server")
        escaping = link_outside(resolved, self.data_root)
        if escaping is not None:
            raise Forbidden("path", f"{escaping!r} in {str(path)!r} is a symbolic link to outside the "
                                    f"folder this server reads data from ({self.data_root}); copy the file "
                                    "there instead")

    def create(self, pipeline: Pipeline, dataset: str | None = None, options: dict[str, Any] | None = None,
               *, seed: int = 0, client: str | None = None) -> Session:
        """Load a dataset into a new session and add it (refused, before loading, when there is no room)."""
        self.check_path(pipeline.dataset(dataset), options)
        return self.admit(lambda: open_session(pipeline, dataset, options, seed=seed), client=client)

    def add(self, session: Session, *, client: str | None = None) -> Session:
        """Add a session made elsewhere, within the caps."""
        return self.admit(lambda: session, client=client)

    def admit(self, load: Callable[[], Session], *, client: str | None = None) -> Session:
        """Hold a place for a new session of ``client`` within the caps, make it with ``load()``, add it.

        The place is held while ``load`` runs (outside the lock), so concurrent creations cannot
        overshoot ``max_sessions``; a ``load`` that raises leaves the store as it was. The memory
        cap is checked again once the session's size is known.
        """
        with self._lock:
            self._expire_locked()
            self._check_room_locked(client, 0)
            self._loading[client] += 1
        try:
            session = load()
        except BaseException:
            with self._lock:
                self._release_locked(client)
            raise
        with self._lock:
            self._release_locked(client)
            self._check_room_locked(client, session.nbytes())
            self._sessions[session.id] = session
            self._clients[session.id] = client
            self._gone.pop(session.id, None)
        return session

    def check_room(self, *, client: str | None = None) -> None:
        """Raise now what :meth:`admit` would raise for lack of room (before queueing work to load one)."""
        with self._lock:
            self._expire_locked()
            self._check_room_locked(client, 0)

    def get(self, session_id: str) -> Session:
        """The live session ``session_id`` (marked used now); UnknownName saying why when there is none."""
        with self._lock:
            self._expire_locked()
            session = self._sessions.get(session_id)
            if session is None:
                raise UnknownName("session", self._why_gone_locked(session_id))
            session.last_used = time.time()
        return session

    def why_gone(self, session_id: str) -> str:
        """Why there is no live session ``session_id``: it expired, was deleted, or never existed here."""
        with self._lock:
            return self._why_gone_locked(session_id)

    def delete(self, session_id: str) -> None:
        """Forget a session (a running step is asked to stop)."""
        with self._lock:
            session = self._sessions.pop(session_id, None)
            if session is None:
                raise UnknownName("session", self._why_gone_locked(session_id))
            self._drop_locked(session_id, "deleted")
        session.cancel()

    def check_memory(self) -> None:
        """Drop idle-expired sessions (called after a step or an upload grows a session's state).

        Nothing in use is evicted: while the total is over ``max_bytes``, new sessions are refused.
        """
        with self._lock:
            self._expire_locked()

    def memory_bytes(self) -> int:
        """The state the live sessions hold, as the memory cap counts it."""
        with self._lock:
            return self._total_bytes()

    # --- internals (called with the lock held) ----------------------------------------------------
    def _check_room_locked(self, client: str | None, nbytes: int) -> None:
        if nbytes > self.max_bytes:
            raise CapacityExceeded("dataset", f"this session needs {_mib(nbytes)}, more than the "
                                              f"{_mib(self.max_bytes)} allowed")
        if client is not None:
            held = sum(1 for c in self._clients.values() if c == client) + self._loading[client]
            if held >= self.max_sessions_per_client:
                wait, when = self._retry_after_locked(client)
                raise TooManyRequests("sessions", f"{client} holds {held} live sessions, the most one "
                                                  f"client may (limit {self.max_sessions_per_client}); "
                                                  "delete one you no longer need "
                                                  f"(DELETE /api/sessions/{{id}}) or retry later{when}",
                                      retry_after=wait)
        held = len(self._sessions) + sum(self._loading.values())
        if held >= self.max_sessions:
            wait, when = self._retry_after_locked(None)
            raise RetryLater("sessions", f"the server holds {held} live sessions "
                                         f"(limit {self.max_sessions}) and evicts none in use; "
                                         f"retry later{when}", retry_after=wait)
        total = self._total_bytes()
        if total + nbytes > self.max_bytes:
            wait, when = self._retry_after_locked(None)
            raise RetryLater("memory", f"the live sessions hold {_mib(total)}; with this one "
                                       f"({_mib(nbytes)}) that is over the {_mib(self.max_bytes)} allowed, "
                                       f"and none in use is evicted; retry later{when}",
                             retry_after=wait)

    def _retry_after_locked(self, client: str | None) -> tuple[float, str]:
        """``(seconds to advise, words on when room comes)``: the soonest idle expiry, at most
        MAX_RETRY_AFTER."""
        now = time.time()
        idle = [s.last_used + self.idle_seconds - now for sid, s in self._sessions.items()
                if s.running is None and (client is None or self._clients.get(sid) == client)]
        if not idle:
            return BUSY_RETRY_AFTER, " (every session is in use)"
        soonest = max(0.0, min(idle))
        return min(MAX_RETRY_AFTER, soonest), f" (the soonest idle session expires in {soonest:.0f} s)"

    def _release_locked(self, client: str | None) -> None:
        self._loading[client] -= 1
        if self._loading[client] <= 0:
            del self._loading[client]

    def _why_gone_locked(self, session_id: str) -> str:
        gone = self._gone.get(session_id)
        if gone == "expired":
            return f"session {session_id!r} expired after {self.idle_seconds:.0f} s idle and was dropped"
        if gone == "deleted":
            return f"session {session_id!r} was deleted"
        return f"no such session {session_id!r}"

    def _drop_locked(self, session_id: str, why: Gone) -> None:
        self._sessions.pop(session_id, None)
        self._clients.pop(session_id, None)
        self._gone[session_id] = why
        self._gone.move_to_end(session_id)
        while len(self._gone) > GONE_MEMORY:
            self._gone.popitem(last=False)

    def _total_bytes(self) -> int:
        return sum(s.nbytes() for s in self._sessions.values())

    def _expire_locked(self) -> None:
        now = time.time()
        for sid, session in list(self._sessions.items()):
            if session.running is None and now - session.last_used > self.idle_seconds:
                self._drop_locked(sid, "expired")
