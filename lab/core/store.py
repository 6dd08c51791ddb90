"""The live-session store: sessions by id, with idle expiry and caps on count and memory."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

from lab.core.errors import CapacityExceeded, Forbidden, UnknownName
from lab.core.pipeline import DatasetSpec, Pipeline, Session, open_session


class SessionStore:
    """Holds live sessions for the API and the viewer (one process, shared by both).

    Sessions idle longer than ``idle_seconds`` expire. When a new session would exceed
    ``max_sessions`` or the state of all sessions exceeds ``max_bytes``, the least recently used
    idle sessions are evicted; if that is not enough, creating fails with CapacityExceeded.

    ``data_root`` (a folder; default None = anywhere) is where datasets that read the server's
    disk (option ``path``) may read: set it when serving beyond 127.0.0.1, so that a browser or a
    script cannot load ``/etc`` or another student's folder. :meth:`check_path` enforces it for
    the viewer and the REST API alike.
    """

    def __init__(self, *, max_sessions: int = 64, idle_seconds: float = 3600.0,
                 max_bytes: int = 4 * 1024**3, data_root: str | os.PathLike | None = None) -> None:
        self.max_sessions = max_sessions
        self.idle_seconds = idle_seconds
        self.max_bytes = max_bytes
        self.data_root = Path(data_root).resolve() if data_root is not None else None
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._sessions)

    def __contains__(self, session_id: str) -> bool:
        return session_id in self._sessions

    def ids(self) -> list[str]:
        return list(self._sessions)

    def check_path(self, spec: DatasetSpec, options: dict[str, Any] | None) -> None:
        """Refuse (Forbidden, field ``path``) a ``path`` option outside :attr:`data_root`."""
        if self.data_root is None or not spec.takes_path:
            return
        path = (options or {}).get("path")
        if path in (None, ""):
            return
        resolved = Path(str(path)).expanduser().resolve()
        if resolved != self.data_root and self.data_root not in resolved.parents:
            raise Forbidden("path", f"{str(path)!r} is outside the folder this server reads data from "
                                    f"({self.data_root}); put the data there or ask whoever runs the server")

    def create(self, pipeline: Pipeline, dataset: str | None = None, options: dict[str, Any] | None = None,
               *, seed: int = 0) -> Session:
        self.check_path(pipeline.dataset(dataset), options)
        session = open_session(pipeline, dataset, options, seed=seed)  # loading errors leave the store as it was
        return self.add(session)

    def add(self, session: Session) -> Session:
        with self._lock:
            self._expire_locked()
            if session.nbytes() > self.max_bytes:
                raise CapacityExceeded("dataset", f"this session needs {session.nbytes() / 2**20:.0f} MiB, "
                                                  f"more than the {self.max_bytes / 2**20:.0f} MiB allowed")
            while len(self._sessions) >= self.max_sessions or self._total_bytes() + session.nbytes() > self.max_bytes:
                if not self._evict_one_locked():
                    raise CapacityExceeded("sessions", f"the server holds {len(self._sessions)} busy sessions "
                                                       f"(limit {self.max_sessions}); try again later")
            self._sessions[session.id] = session
        return session

    def get(self, session_id: str) -> Session:
        with self._lock:
            self._expire_locked()
            session = self._sessions.get(session_id)
        if session is None:
            raise UnknownName("session", f"no session {session_id!r} (it may have expired after "
                                         f"{self.idle_seconds:.0f} s idle)")
        session.last_used = time.time()
        return session

    def delete(self, session_id: str) -> None:
        with self._lock:
            session = self._sessions.pop(session_id, None)
        if session is None:
            raise UnknownName("session", f"no session {session_id!r}")
        session.cancel()

    def check_memory(self) -> None:
        """Evict idle sessions while the total state is over the cap (called after a step grows state)."""
        with self._lock:
            while self._total_bytes() > self.max_bytes and self._evict_one_locked():
                pass

    def _total_bytes(self) -> int:
        return sum(s.nbytes() for s in self._sessions.values())

    def _expire_locked(self) -> None:
        now = time.time()
        for sid, session in list(self._sessions.items()):
            if session.running is None and now - session.last_used > self.idle_seconds:
                del self._sessions[sid]

    def _evict_one_locked(self) -> bool:
        idle = [s for s in self._sessions.values() if s.running is None]
        if not idle:
            return False
        oldest = min(idle, key=lambda s: s.last_used)
        del self._sessions[oldest.id]
        return True
