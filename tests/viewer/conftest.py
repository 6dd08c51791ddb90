"""Fixtures shared by the viewer tests: a quiet viser server on a free loopback port, a store."""

from __future__ import annotations

import contextlib
import io

import pytest
import viser

from lab.core import SessionStore


@pytest.fixture
def server():
    with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner on start and stop
        srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    with contextlib.redirect_stdout(io.StringIO()):
        srv.stop()


@pytest.fixture
def store():
    return SessionStore(max_sessions=8)
