"""Helpers for the REST API tests: an app serving the toy pipeline and a gated one.

``gated`` adds a long step (``crawl``) that waits for the test after every progress snapshot, so a
test can hold a step *running* for as long as it needs (busy, cancel, live event streams), and
steps reading a camera matrix and a point cloud (uploads with extra checks, PLY).
"""

from __future__ import annotations

import threading
import time
from typing import Annotated, Any, Callable, Generator

import numpy as np
from fastapi.testclient import TestClient
from toy_pipeline import TOY, add_noise, evaluate_means, gradients, mean_intensity

from lab.core.step import step_result
from lab.api import create_app
from lab.core import Pipeline, PointCloud, Progress, Range, SessionStore

UPLOAD_LIMIT = 200_000


class Gate:
    """Permits the ``crawl`` step waits for, one after each progress snapshot."""

    def __init__(self) -> None:
        self.permits = threading.Semaphore(0)

    def release(self, count: int = 1) -> None:
        for _ in range(count):
            self.permits.release()


_GATE: dict[str, Gate] = {"current": Gate()}


def crawl(means: np.ndarray, *, iterations: Annotated[int, Range(1, 50)] = 3
          ) -> Generator[Progress, None, Annotated[np.ndarray, "crawled"]]:
    """A long step that waits for the test to release it after every snapshot."""
    gate = _GATE["current"]
    for i in range(iterations):
        yield Progress(iteration=i + 1, total=iterations, loss=1.0 / (i + 1), message=f"step {i + 1}")
        if not gate.permits.acquire(timeout=20):
            raise RuntimeError("the test never released the gate")
    return means * 2


def focal(K: np.ndarray) -> Annotated[np.ndarray, "focal"]:
    """(fx, fy) of a camera matrix K (3, 3)."""
    return np.array([K[0, 0], K[1, 1]])


def centroid(cloud: PointCloud) -> Annotated[np.ndarray, "center"]:
    """Mean of a point cloud's xyz, (3,)."""
    return cloud.xyz.mean(axis=0)


GATED = Pipeline.build(name="gated", title="Gated", summary="Toy steps plus a long step the test controls.",
                       steps=[add_noise, mean_intensity, crawl, focal, centroid], datasets=[gradients],
                       evaluations={"mean_intensity": evaluate_means})
PIPELINES = {"toy": TOY, "gated": GATED}


def make_client(store: SessionStore, **kwargs: Any) -> TestClient:
    options: dict[str, Any] = dict(modules=PIPELINES.__getitem__, module_names=list(PIPELINES),
                                   viewer_url="http://127.0.0.1:9999", max_upload_bytes=UPLOAD_LIMIT)
    raise_server_exceptions = kwargs.pop("raise_server_exceptions", True)
    options.update(kwargs)
    return TestClient(create_app(store, **options), raise_server_exceptions=raise_server_exceptions)


def new_session(client: TestClient, module: str = "toy", **body: Any) -> str:
    response = client.post("/api/sessions", json={"module": module, **body})
    assert response.status_code == 201, response.text
    return response.json()["id"]


def snapshot(client: TestClient, session_id: str) -> dict[str, Any]:
    """What must not change when a request is refused: values, step status, version, history, metrics."""
    body = client.get(f"/api/sessions/{session_id}").json()
    return {key: body[key] for key in ("values", "steps", "version", "history", "metrics", "running")}


def assert_error(response, status: int, field: str, kind: str | None = None) -> dict[str, Any]:
    """The response is a JSON error body naming ``field`` (and ``kind`` when given) with a reason."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json")
    body = response.json()
    assert body["field"] == field, body
    assert isinstance(body["reason"], str) and body["reason"], body
    if kind is not None:
        assert body["error"] == kind, body
    return body


def wait_until(predicate: Callable[[], bool], what: str, timeout: float = 20.0) -> None:
    """Poll ``predicate`` until true (a guard against hanging, not a timing assertion)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting for {what}")
        time.sleep(0.01)


def running_step(client: TestClient, session_id: str) -> str | None:
    return client.get(f"/api/sessions/{session_id}").json()["running"]


def parse_events(lines) -> Generator[tuple[str, dict[str, Any]], None, None]:
    """``(event name, JSON data)`` of each server-sent event in an iterator of text lines."""
    import json

    name, data = "message", []
    for line in lines:
        if line == "":
            if data:
                yield name, json.loads("\n".join(data))
            name, data = "message", []
        elif line.startswith("event:"):
            name = line[6:].strip()
        elif line.startswith("data:"):
            data.append(line[5:].strip())
