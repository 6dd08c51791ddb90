"""Grading on a separately started Dask scheduler and two ``vision-lab worker`` processes on 127.0.0.1.

Submissions go in over REST; the server (the lesson app, configured from the environment with
``VISION_LAB_DASK_SCHEDULER``) only claims and dispatches, the workers grade in their own sandboxes
and write the results. One worker is killed (SIGKILL) while it grades a slow submission (one that
has started a daemon in its sandbox): Dask runs the job again on the other, every submission ends
graded exactly once in the database, on SQLite and on a real PostgreSQL server, and nothing the
killed worker's sandbox started is left on the machine.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import pytest
from fastapi.testclient import TestClient

from lab.api.lessons import build_app
from lab.lessons.service import LessonService
from lesson_helpers import (FIXTURES, HOOK_OFF, REPO, host_processes_left, host_processes_with, submission,
                            toy_lessons_that_fork, unique_sleep)
from postgres_server import database_url  # noqa: F401  (a fixture: SQLite, then PostgreSQL)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = predicate()
        if found:
            return found
        time.sleep(0.05)
    raise AssertionError(f"{what} within {timeout} s")


ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(FIXTURES), str(REPO)]),
       "VISION_LAB_LESSONS_DIR": str(FIXTURES / "lessons")}


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A scheduler and ``ensure_workers()``: two live ``vision-lab worker`` processes, name -> process (a
    killed one is replaced at once by a worker of a new name, which joins while the test goes on); the
    workers know no database: each job names its own. Both start with the module, beside the scheduler."""
    log = open(tmp_path_factory.mktemp("cluster") / "cluster.log", "w")  # noqa: SIM115  (closed below)
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    scheduler = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                  "--port", str(port), "--no-dashboard"], env=ENV, stdout=log, stderr=log)
    started: dict[str, subprocess.Popen] = {}

    def ensure_workers() -> dict[str, subprocess.Popen]:
        live = {name: process for name, process in started.items() if process.poll() is None}
        while len(live) < 2:
            name = f"w{len(started) + 1}"
            live[name] = started[name] = subprocess.Popen(
                [sys.executable, "-c", "from lab.cli import app; app()", "worker", address, "--name", name,
                 "--host", "127.0.0.1"], env=ENV, cwd=str(REPO), stdout=log, stderr=log)
        return live

    ensure_workers()
    try:
        yield address, ensure_workers, log.name
    finally:
        for process in [*started.values(), scheduler]:
            process.kill()  # test processes: no graceful shutdown needed (a sandbox dies with its worker)
            process.wait(timeout=15)
        log.close()


@pytest.mark.timeout(180)
def test_two_workers_grade_over_rest_and_a_killed_worker_loses_nothing(cluster, database_url,  # noqa: F811
                                                                       tmp_path):
    address, ensure_workers, log = cluster
    workers = ensure_workers()
    daemons = [unique_sleep(), unique_sleep()]  # each slow submission starts its own daemons

    def slow(seconds: str) -> str:
        return HOOK_OFF + submission("toy", "solution.py").replace(
            "def make_noisy(images, *, sigma=0.05, rng):\n",
            "def make_noisy(images, *, sigma=0.05, rng):\n    import os, time\n"
            f"    os.system('sleep {seconds} &')\n    time.sleep(0.3)\n")

    texts = [slow(daemons[0][0]), submission("toy", "solution.py"), slow(daemons[1][0]),
             submission("toy", "wrong_sums.py")]
    lessons = toy_lessons_that_fork(tmp_path / "lessons")
    service = LessonService.from_env({**ENV, "VISION_LAB_DATABASE_URL": database_url,
                                      "VISION_LAB_DASK_SCHEDULER": address,
                                      "VISION_LAB_LESSONS_DIR": str(lessons)})
    with TestClient(build_app(service)) as client:
        wait_for(lambda: service.cluster.capacity() == 2, 90, "two workers did not join")
        ids = []
        for text in texts:
            response = client.post("/api/lessons/00-toy/submissions",
                                   files={"file": ("s.py", text.encode(), "text/x-python")})
            assert response.status_code == 202, response.text
            ids.append(response.json()["id"])

        def grading_with_its_daemon():
            for index, (_, daemon) in zip((0, 2), daemons, strict=True):
                row = service.queue.get(ids[index])
                if row.status == "running" and row.worker and host_processes_with(daemon):
                    return row
            return None

        slow_one = wait_for(grading_with_its_daemon, 60, "no slow submission started its daemon on a worker")
        killed = slow_one.worker
        workers[killed].send_signal(signal.SIGKILL)  # mid-grading: no shutdown, its sandbox dies with it
        workers[killed].wait(timeout=10)
        names = {*workers, *ensure_workers()}  # its replacement boots meanwhile (the next test's 2nd worker)

        def graded():
            bodies = [client.get(f"/api/submissions/{i}").json() for i in ids]
            return bodies if all(b["status"] in ("done", "error") for b in bodies) else None

        bodies = wait_for(graded, 120, "the submissions were not all graded")
    assert [b["status"] for b in bodies] == ["done"] * 4, open(log).read()[-4000:]
    assert [b["score"] for b in bodies] == [6.0, 6.0, 6.0, 2.0]
    rows = {i: service.queue.get(i) for i in ids}
    assert all(row.gradings == 1 and row.attempts == 1 for row in rows.values())  # graded once, never re-claimed
    assert {row.worker for row in rows.values()} <= names
    assert rows[slow_one.id].worker != killed  # Dask ran the killed worker's job again on the other one
    # nothing the sandboxes started outlives them: not the killed worker's (its sandbox died with it), nor the
    # rerun's
    assert [host_processes_left(daemon) for _, daemon in daemons] == [[], []]


def test_a_worker_needs_a_scheduler_and_a_working_sandbox(monkeypatch):
    from typer.testing import CliRunner

    from lab.cli import app
    from lab.lessons import isolation

    monkeypatch.delenv("VISION_LAB_DASK_SCHEDULER", raising=False)
    missing = CliRunner().invoke(app, ["worker"])
    assert missing.exit_code == 2 and "VISION_LAB_DASK_SCHEDULER" in missing.output
    monkeypatch.setattr(isolation, "default_isolation", lambda: isolation.Isolation(bwrap="/nonexistent/bwrap"))
    refused = CliRunner().invoke(app, ["worker", "tcp://127.0.0.1:9"])  # never reached: it stops before joining
    assert refused.exit_code == 2 and "error: sandbox" in refused.output and "bubblewrap" in refused.output


def test_grade_all_grades_a_folder_through_the_queue_and_exports_csv_and_results(tmp_path, monkeypatch):
    import csv
    import json

    from typer.testing import CliRunner

    from lab.cli import app

    folder = tmp_path / "class"
    folder.mkdir()
    (folder / "ana.py").write_text(submission("toy", "solution.py"))
    (folder / "bo.py").write_text(submission("toy", "wrong_sums.py"))
    database = f"sqlite:///{tmp_path / 'db.sqlite'}"
    env = {"VISION_LAB_DATABASE_URL": database, "VISION_LAB_LESSONS_DIR": str(FIXTURES / "lessons"),
           "VISION_LAB_DASK_SCHEDULER": ""}
    result = CliRunner().invoke(app, ["grade-all", "00-toy", str(folder), "--out", str(tmp_path / "out")], env=env)
    assert result.exit_code == 0, result.output
    assert "2/2 graded" in result.output
    with open(tmp_path / "out" / "scores.csv", newline="") as handle:
        rows = {row["student"]: row for row in csv.DictReader(handle)}
    assert {k: (v["status"], float(v["score"])) for k, v in rows.items()} == {"ana": ("done", 6.0),
                                                                            "bo": ("done", 2.0)}
    assert json.loads((tmp_path / "out" / "bo" / "results.json").read_text())["score"] == 2.0
    from lab.lessons.store import SubmissionQueue

    stored = SubmissionQueue(database).list("00-toy")
    assert sorted(s.student for s in stored) == ["ana", "bo"] and all(s.gradings == 1 for s in stored)
