"""Fixtures for the REST API tests (helpers and the test pipelines are in api_helpers.py)."""

from __future__ import annotations

from typing import Generator

import pytest
from api_helpers import _GATE, Gate, make_client
from fastapi.testclient import TestClient

from lab.core import SessionStore


@pytest.fixture
def gate() -> Generator[Gate, None, None]:
    _GATE["current"] = current = Gate()
    yield current
    current.release(100)  # let any step still waiting finish


@pytest.fixture
def store() -> SessionStore:
    return SessionStore(max_sessions=8, idle_seconds=3600.0, max_bytes=64 * 2**20)


@pytest.fixture
def client(store: SessionStore) -> Generator[TestClient, None, None]:
    with make_client(store) as test_client:
        yield test_client


