"""``vision-lab serve --workers 2`` for real: two worker processes on 127.0.0.1 sharing one database (a
SQLite file, then a database on a real PostgreSQL server), behind a tiny path-routing proxy.

- a submission made through one worker is graded (by w0) and visible, with its result, through the other,
  and on the instructor's listing of either;
- a session made on one worker answers 421 on the other, naming the owner and its address, and the
  proxy's documented rule (``/api/sessions/<worker>-*`` to that worker, the rest round-robin) reaches it;
- killing a worker (SIGKILL, no shutdown) loses no submission: the one it took is graded anyway, and the
  grading w0 was running when it was killed is graded once after the supervisor restarts w0.
"""

from __future__ import annotations

import http.server
import itertools
import json
import os
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "lessons"))
from lesson_helpers import FIXTURES, REPO, submission
from postgres_server import new_database, start


def _bindable(port: int) -> bool:
    with socket.socket() as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_ports(count: int) -> int:
    """A base port with ``count`` consecutive free ports from it."""
    for _ in range(200):
        base = random.randrange(20000, 60000)
        if all(_bindable(base + i) for i in range(count)):
            return base
    raise AssertionError("no consecutive free ports")


def request(url: str, method: str = "GET", body: bytes | None = None,
            headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    call = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(call, timeout=20) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as error:
        return error.code, dict(error.headers), error.read()


def get_json(url: str) -> dict:
    status, _, body = request(url)
    assert status == 200, (url, status, body)
    return json.loads(body)


def upload(base: str, text: str) -> str:
    boundary = uuid.uuid4().hex
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"s.py\"\r\n"
            f"Content-Type: text/x-python\r\n\r\n{text}\r\n--{boundary}--\r\n").encode()
    status, _, answer = request(base + "/api/lessons/00-toy/submissions", "POST", body,
                                {"Content-Type": f"multipart/form-data; boundary={boundary}"})
    assert status == 202, answer
    return json.loads(answer)["id"]


class Proxy:
    """The README's routing rule: ``/api/sessions/<worker>-*`` to that worker, the rest round-robin."""

    ROUTE = re.compile(r"^/api/sessions/(w[0-9]+)-")

    def __init__(self, workers: dict[str, str]) -> None:
        turns = itertools.cycle(sorted(workers))
        self.seen: list[str] = []
        proxy = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def _forward(self) -> None:
                owner = Proxy.ROUTE.match(self.path)
                target = workers[owner.group(1) if owner else next(turns)]
                length = int(self.headers.get("Content-Length") or 0)
                headers = {k: v for k, v in self.headers.items()
                           if k.lower() in ("content-type", "authorization")}
                status, answer_headers, body = request(target + self.path, self.command,
                                                       self.rfile.read(length) if length else None, headers)
                proxy.seen.append(answer_headers.get("x-vision-lab-worker", "?"))
                self.send_response(status)
                for key in ("Content-Type", "x-vision-lab-worker"):
                    if key in answer_headers:
                        self.send_header(key, answer_headers[key])
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            do_GET = do_POST = do_PUT = do_DELETE = _forward

            def log_message(self, *args) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def children(parent: int) -> dict[str, int]:
    """The worker processes of supervisor ``parent``: worker id -> pid (from /proc)."""
    found = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            command = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == parent and b"--worker-id" in command:
            found[command[command.index(b"--worker-id") + 1].decode()] = int(entry)
    return found


def wait_until(condition, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = condition()
        except OSError:
            value = None
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request, tmp_path) -> str:
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'submissions.sqlite'}"
    return new_database(start())


@pytest.mark.timeout(300)
def test_two_workers_share_submissions_route_sessions_and_lose_nothing_when_killed(database, tmp_path):
    base = free_ports(2)
    viewer = free_ports(2)
    urls = {"w0": f"http://127.0.0.1:{base}", "w1": f"http://127.0.0.1:{base + 1}"}
    env = {**os.environ, "VISION_LAB_DATABASE_URL": database,
           "VISION_LAB_LESSONS_DIR": str(FIXTURES / "lessons"),
           "PYTHONPATH": os.pathsep.join([str(FIXTURES), str(REPO)]), "VISION_LAB_GRADING_WORKERS": "1",
           "VISION_LAB_NO_WARMUP": "1"}
    log = open(tmp_path / "serve.log", "w")  # noqa: SIM115 - closed in finally
    supervisor = subprocess.Popen([sys.executable, "-m", "lab", "serve", "--workers", "2",
                                   "--host", "127.0.0.1", "--port", str(base), "--viewer-port", str(viewer),
                                   "--no-warmup"],
                                  env=env, cwd=str(REPO), stdout=log, stderr=log)
    proxy = Proxy(urls)
    try:
        for name, url in urls.items():
            health = wait_until(lambda url=url: get_json(url + "/api/health"), 120, f"worker at {url}")
            assert (health["worker"], health["grading"]) == (name, name == "w0")

        answered = {request(proxy.url + "/api/health")[1]["x-vision-lab-worker"] for _ in range(2)}
        assert answered == {"w0", "w1"}  # the proxy spreads what is not a session's

        # sessions: made on one worker, sticky to it
        status, headers, body = request(proxy.url + "/api/sessions", "POST", json.dumps(
            {"module": "calibration"}).encode(), {"Content-Type": "application/json"})
        assert status == 201, body
        session = json.loads(body)["id"]
        owner = headers["x-vision-lab-worker"]
        other = "w1" if owner == "w0" else "w0"
        assert session.startswith(owner + "-")
        for _ in range(3):  # the proxy routes it to its owner every time (the rest round-robin)
            assert get_json(f"{proxy.url}/api/sessions/{session}")["id"] == session
        status, headers, body = request(f"{urls[other]}/api/sessions/{session}")
        assert status == 421 and headers["x-vision-lab-worker"] == other
        error = json.loads(body)
        assert (error["error"], error["field"]) == ("misdirected", "session")
        assert (error["worker"], error["url"]) == (owner, urls[owner])
        assert request(f"{urls[other]}/api/sessions/{session}/steps/detect_corners", "POST", b"{}",
                       {"Content-Type": "application/json"})[0] == 421
        assert request(f"{urls[other]}/api/sessions/{session}", "DELETE")[0] == 421

        # submissions: made through w1, graded by w0, read through either
        slow = submission("toy", "solution.py").replace(
            "def make_noisy(images, *, sigma=0.05, rng):\n",
            "def make_noisy(images, *, sigma=0.05, rng):\n    import time\n    time.sleep(0.7)\n")
        texts = [slow, submission("toy", "wrong_sums.py"), slow]
        ids = [upload(urls["w1"], text) for text in texts]
        pids = children(supervisor.pid)
        os.kill(pids["w1"], signal.SIGKILL)  # the worker that took them dies: they are in the database
        running = wait_until(lambda: [i for i in ids if get_json(
            f"{urls['w0']}/api/submissions/{i}")["status"] == "running"], 60, "a grading to start on w0")
        os.kill(pids["w0"], signal.SIGKILL)  # the grading worker dies mid-grading: the supervisor restarts it

        def all_graded():
            bodies = [get_json(f"{urls['w1']}/api/submissions/{i}") for i in ids]
            return bodies if all(b["status"] in ("done", "error") for b in bodies) else None

        results = wait_until(all_graded, 180, "every submission graded after the restarts")
        new_pids = children(supervisor.pid)
        assert new_pids["w0"] != pids["w0"] and new_pids["w1"] != pids["w1"]
        assert [r["status"] for r in results] == ["done"] * 3, results
        assert [r["score"] for r in results] == [6.0, 2.0, 6.0]
        assert all(r["gradings"] == 1 for r in results)  # each graded exactly once in the database
        assert all(r["attempts"] == 2 for r in results if r["id"] in running)
        assert results[1]["results"]["tests"]  # the result itself, read through the worker that did not grade
        listed = get_json(f"{urls['w1']}/api/lessons/00-toy/submissions")
        assert {s["id"] for s in listed["submissions"]} == set(ids) and listed["counts"]["done"] == 3
        stats = [get_json(f"{urls[name]}/api/lessons/00-toy/stats") for name in ("w0", "w1")]
        assert stats[0] == stats[1]
        # the killed worker's sessions went with it: the restarted one says it does not hold it
        assert request(f"{urls[owner]}/api/sessions/{session}")[0] == 404
    finally:
        proxy.close()
        last = children(supervisor.pid)
        supervisor.send_signal(signal.SIGTERM)
        try:
            supervisor.wait(timeout=30)
        except subprocess.TimeoutExpired:
            supervisor.kill()
        log.close()
    assert supervisor.returncode == 0, (tmp_path / "serve.log").read_text()[-3000:]
    for pid in last.values():  # stopping the supervisor stopped its workers
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
