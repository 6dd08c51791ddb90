"""Paths and helpers shared by the lesson tests (imported by name: conftest modules are not importable safely)."""

from __future__ import annotations

import sys
from pathlib import Path

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
SUBMISSIONS = FIXTURES / "submissions"
REPO = Path(__file__).resolve().parents[2]

if str(FIXTURES) not in sys.path:  # the toy lesson's module "toy_lesson_pipeline:PIPELINE"
    sys.path.insert(0, str(FIXTURES))


#: A submission's first line that switches the child's audit hook off (what holds then is bubblewrap alone).
HOOK_OFF = 'import sys\nsys.modules["lab.lessons.child"].Guard.__call__ = lambda self, event, args: None\n'


def submission(*parts: str) -> str:
    """The text of a fixture submission, e.g. ``submission("toy", "solution.py")``."""
    return SUBMISSIONS.joinpath(*parts).read_text(encoding="utf-8")


def failed(report) -> dict[str, str]:
    """The failed tests of a grade report, name -> output."""
    return {t.name: t.output for t in report.tests if t.status == "failed"}


def hint_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("Hint: ")]


def graded_once(lesson, folder: str, seed: int):
    """``report(name)``: fixture ``submissions/<folder>/<name>`` graded under ``seed``, once per ``graded_once``."""
    from lab.lessons.grader import grade

    reports = {}

    def report(name: str):
        if name not in reports:
            reports[name] = grade(lesson, submission(folder, name), seed=seed)
        return reports[name]

    return report


def assert_every_failure_names_its_mistake(report, hints: dict[str, str], name: str) -> None:
    """Every check fixture ``name`` fails carries its hint ``hints[name]`` and no other fixture's."""
    lost = failed(report)
    assert lost
    for check, output in lost.items():
        found = hint_lines(output)
        assert any(hints[name] in line for line in found), f"{check}: {output}"
        for other, hint in hints.items():
            if other != name:
                assert not any(hint in line for line in found), f"{check} got the hint of {other}"


def wait_done(client, submission_id: str, timeout: float = 30.0) -> dict:
    """Poll ``GET /api/submissions/{id}`` until it is graded (done or error); its body."""
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        body = client.get(f"/api/submissions/{submission_id}").json()
        if body["status"] in ("done", "error"):
            return body
        time.sleep(0.05)
    raise AssertionError(f"submission {submission_id} not graded in {timeout} s")


def toy_lessons_that_fork(folder, processes: int = 4):
    """A lessons folder holding a copy of the toy lesson whose sandbox may start ``processes`` processes (by
    default a submission cannot fork at all, and a test of what its daemons leave behind proves nothing)."""
    import shutil

    shutil.copytree(FIXTURES / "lessons" / "00-toy", folder / "00-toy")
    tasks = folder / "00-toy" / "tasks.toml"
    tasks.write_text(tasks.read_text().replace("[limits]\n", f"[limits]\nprocesses = {processes}\n", 1))
    return folder


def host_processes_with(text: str) -> list[int]:
    """Host processes whose command line (arguments joined by NUL) holds ``text``."""
    from pathlib import Path

    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if text.encode() in (entry / "cmdline").read_bytes():
                    found.append(int(entry.name))
            except OSError:
                pass
    return found


def host_processes_left(text: str, *, within_s: float = 15.0) -> list[int]:
    """Host processes whose command line holds ``text``, once the kernel has had ``within_s`` to tear a
    namespace down (its processes are killed when its pid 1 ends, not at the instant the grader returns)."""
    import time

    deadline = time.monotonic() + within_s
    while host_processes_with(text) and time.monotonic() < deadline:
        time.sleep(0.05)
    return host_processes_with(text)


def unique_sleep() -> tuple[str, str]:
    """``(seconds, cmdline)``: a ``sleep`` duration no other process on the machine uses (a shared machine's
    shells run plain ``sleep 300``s), and the command line text of ``sleep <seconds>`` to look for."""
    import secrets

    seconds = f"300.{secrets.randbelow(10**6):06d}"
    return seconds, f"sleep\x00{seconds}\x00"


class HostWatch:
    """Records the host processes whose command line holds ``text`` while it runs (a thread polling /proc)."""

    def __init__(self, text: str) -> None:
        import threading

        self.text = text
        self.seen: set[int] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            self.seen.update(host_processes_with(self.text))

    def __enter__(self) -> HostWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
