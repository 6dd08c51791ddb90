"""A real PostgreSQL server for the store's tests: Debian's binaries (``apt-get install postgresql``),
started once.

The server is made in a temporary folder (``initdb --auth=trust``, listening on 127.0.0.1 only, a
port of its own) the first time a test asks for it and stopped when the test process exits; each test
gets a fresh database on it (:func:`database_url`). As root (CI), the server runs as the ``postgres``
user, since PostgreSQL refuses to run as root. Without the binaries the tests that need it fail, saying
how to install them (the README's test command does).

Import the fixtures into a test module: ``from postgres_server import postgresql_url, database_url``.
"""

from __future__ import annotations

import atexit
import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
import uuid

import pytest

_server: dict[str, object] = {}


def binaries() -> str | None:
    """The folder of the newest installed PostgreSQL's ``initdb`` and ``pg_ctl`` (None: not installed)."""
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"), key=lambda p: int(p.split("/")[4]))
    if found:
        return os.path.dirname(found[-1])
    on_path = shutil.which("pg_ctl")
    return os.path.dirname(on_path) if on_path else None


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _as_server_user(command: list[str]) -> list[str]:
    return ["runuser", "-u", "postgres", "--", *command] if os.geteuid() == 0 else command


def start() -> str:
    """Start the server (once per test process); its base URL ``postgresql+psycopg://postgres@127.0.0.1:PORT``."""
    if "url" in _server:
        return str(_server["url"])
    folder = binaries()
    if folder is None:
        # the README's test command installs it: a missing server is a set-up error, never a skipped test
        pytest.fail("PostgreSQL is not installed (apt-get install -y postgresql, as the README's test "
                    "command does): the store's PostgreSQL tests need its server binaries in "
                    "/usr/lib/postgresql/*/bin")
    root = tempfile.mkdtemp(prefix="vision-lab-pg-")
    data = os.path.join(root, "data")
    if os.geteuid() == 0:
        user = pwd.getpwnam("postgres")
        os.chown(root, user.pw_uid, user.pw_gid)
    port = _free_port()
    subprocess.run(_as_server_user([f"{folder}/initdb", "-D", data, "-U", "postgres", "--auth=trust",
                                    "-E", "UTF8", "--no-sync"]), check=True, capture_output=True, timeout=120)
    options = f"-c listen_addresses=127.0.0.1 -p {port} -k {root} -c fsync=off -c max_connections=200"
    subprocess.run(_as_server_user([f"{folder}/pg_ctl", "-D", data, "-o", options, "-l",
                                    os.path.join(root, "log"), "-w", "-t", "60", "start"]),
                   check=True, capture_output=True, timeout=90)

    def stop() -> None:
        subprocess.run(_as_server_user([f"{folder}/pg_ctl", "-D", data, "-m", "immediate", "stop"]),
                       capture_output=True, timeout=60, check=False)
        shutil.rmtree(root, ignore_errors=True)

    atexit.register(stop)
    _server["url"] = f"postgresql+psycopg://postgres@127.0.0.1:{port}"
    return str(_server["url"])


def new_database(base: str) -> str:
    """A fresh, empty database on the server at ``base``; its URL."""
    import psycopg

    name = "t_" + uuid.uuid4().hex[:16]
    plain = base.replace("postgresql+psycopg://", "postgresql://")
    deadline = time.monotonic() + 30
    while True:
        try:
            with psycopg.connect(plain + "/postgres", autocommit=True) as connection:
                connection.execute(f'CREATE DATABASE "{name}"')
            return f"{base}/{name}"
        except psycopg.OperationalError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


@pytest.fixture(scope="session")
def postgresql_url() -> str:
    """The running test server's base URL (started on first use)."""
    return start()


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request, tmp_path) -> str:
    """A fresh database: a SQLite file, then a database on the real PostgreSQL server."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'submissions.sqlite'}"
    return new_database(start())
