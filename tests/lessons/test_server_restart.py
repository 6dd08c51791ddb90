"""A real server killed in the middle of grading loses no submission: restarted, it grades them all.

The server is ``uvicorn --factory lab.api.lessons:standalone_app`` on 127.0.0.1 with a SQLite file,
the toy lesson, and one grading worker. Some submissions are slow (their ``make_noisy`` sleeps),
so the server is killed (SIGKILL, no shutdown) while one is being graded.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
import uuid

import pytest

from lesson_helpers import FIXTURES, REPO, submission


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Server:
    def __init__(self, database: str, port: int, log) -> None:
        env = {**os.environ, "VISION_LAB_DATABASE_URL": database, "VISION_LAB_LESSONS_DIR": str(FIXTURES / "lessons"),
               "PYTHONPATH": os.pathsep.join([str(FIXTURES), str(REPO)]), "VISION_LAB_GRADING_WORKERS": "1"}
        self.base = f"http://127.0.0.1:{port}"
        self.process = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--factory", "lab.api.lessons:standalone_app", "--host", "127.0.0.1",
             "--port", str(port), "--log-level", "warning"], env=env, cwd=str(REPO), stdout=log, stderr=log)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise AssertionError("the server exited at start-up")
            try:
                self.get("/api/lessons")
                return
            except OSError:
                time.sleep(0.2)
        raise AssertionError("the server did not start")

    def get(self, path: str):
        with urllib.request.urlopen(self.base + path, timeout=10) as response:
            return json.loads(response.read())

    def submit(self, text: str) -> str:
        boundary = uuid.uuid4().hex
        body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"s.py\"\r\n"
                f"Content-Type: text/x-python\r\n\r\n{text}\r\n--{boundary}--\r\n").encode()
        request = urllib.request.Request(self.base + "/api/lessons/00-toy/submissions", data=body, method="POST",
                                         headers={"Content-Type": f"multipart/form-data; boundary={boundary}"})
        with urllib.request.urlopen(request, timeout=10) as response:
            assert response.status == 202
            return json.loads(response.read())["id"]

    def kill(self) -> None:
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(timeout=10)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.kill()


@pytest.mark.timeout(240)
def test_killed_during_grading_restarts_and_grades_every_submission(tmp_path):
    database = f"sqlite:///{tmp_path / 'submissions.sqlite'}"
    slow = submission("toy", "solution.py").replace(
        "def make_noisy(images, *, sigma=0.05, rng):\n",
        "def make_noisy(images, *, sigma=0.05, rng):\n    import time\n    time.sleep(0.3)\n")
    texts = [slow, submission("toy", "solution.py"), slow, submission("toy", "wrong_sums.py")]
    with open(tmp_path / "server.log", "w") as log:
        server = Server(database, free_port(), log)
        try:
            ids = [server.submit(text) for text in texts]
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                if any(server.get(f"/api/submissions/{i}")["status"] == "running" for i in ids):
                    break
                time.sleep(0.05)
            else:
                raise AssertionError("no submission started grading")
            interrupted = [i for i in ids if server.get(f"/api/submissions/{i}")["status"] == "running"]
            server.kill()  # no shutdown: the running grading is cut off
        finally:
            server.stop()

        server = Server(database, free_port(), log)
        try:
            deadline = time.monotonic() + 120
            results = {}
            while time.monotonic() < deadline and len(results) < len(ids):
                for i in ids:
                    body = server.get(f"/api/submissions/{i}")
                    if body["status"] in ("done", "error"):
                        results[i] = body
                time.sleep(0.2)
        finally:
            server.stop()
    assert set(results) == set(ids), (tmp_path / "server.log").read_text()
    assert [results[i]["status"] for i in ids] == ["done"] * 4
    assert [results[i]["score"] for i in ids] == [6.0, 6.0, 6.0, 2.0]
    assert interrupted and all(results[i]["attempts"] == 2 for i in interrupted)
