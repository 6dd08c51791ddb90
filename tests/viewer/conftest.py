"""Fixtures shared by the viewer tests: a store (the viser server is tests/conftest.py's)."""

from __future__ import annotations

import pytest

from lab.core import SessionStore


@pytest.fixture
def store():
    return SessionStore(max_sessions=8)
