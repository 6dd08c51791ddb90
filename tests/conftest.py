"""Fixtures shared by every test folder: a quiet viser server on a free loopback port."""

from __future__ import annotations

import contextlib
import io

import pytest


@pytest.fixture
def server():
    import viser

    with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner on start and stop
        srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    with contextlib.redirect_stdout(io.StringIO()):
        srv.stop()
