"""A client that hangs up mid-stream ends its event stream quietly: no exception, no ERROR log record."""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from api_helpers import make_client, new_session, running_step, wait_until

from lab.core import SessionStore


def _scope(path: str) -> dict[str, Any]:
    return {"type": "http", "asgi": {"version": "3.0", "spec_version": "2.3"}, "http_version": "1.1",
            "method": "GET", "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"",
            "headers": [(b"host", b"testserver"), (b"accept", b"text/event-stream")],
            "client": ("127.0.0.1", 50000), "server": ("testserver", 80), "root_path": "", "state": {}}


async def _hang_up(app: Any, path: str) -> list[bytes]:
    """Stream ``path`` through a slow socket (each write takes a while, as under TCP backpressure) and
    hang up while events are still waiting to be written."""
    requested, bodies = False, []

    async def receive() -> dict[str, Any]:
        nonlocal requested
        if not requested:
            requested = True
            return {"type": "http.request", "body": b"", "more_body": False}
        await asyncio.sleep(0.3)
        return {"type": "http.disconnect"}

    async def send(message: dict[str, Any]) -> None:
        if message["type"] == "http.response.body":
            bodies.append(message.get("body", b""))
            await asyncio.sleep(0.2)

    await app(_scope(path), receive, send)
    return bodies


def test_a_client_that_hangs_up_mid_stream_leaves_no_traceback(gate, caplog):
    with make_client(SessionStore()) as client:
        sid = new_session(client, "gated")
        client.post(f"/api/sessions/{sid}/run-until/mean_intensity", json={})
        assert client.post(f"/api/sessions/{sid}/steps/crawl", params={"wait": "false"},
                           json={"iterations": 50}).status_code == 202
        wait_until(lambda: running_step(client, sid) == "crawl", "crawl to start")
        gate.release(30)  # many progress events wait in the run's monitor
        wait_until(lambda: client.get(f"/api/sessions/{sid}").json()["progress"]["iteration"] >= 20,
                   "the events to pile up")
        with caplog.at_level(logging.DEBUG):
            bodies = asyncio.run(_hang_up(client.app, f"/api/sessions/{sid}/events"))
        assert any(b"event: progress" in body for body in bodies)  # it was streaming when the client left
        assert len(bodies) < 30  # and it stopped: the rest was never written
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert errors == [], [r.getMessage() for r in errors]
        gate.release(100)
