"""Every sandbox abuse of the issue is contained: a clear failed test, the other task unaffected, in time.

Each fixture under tests/fixtures/submissions/abuse/ is a toy-lesson submission whose
``mean_intensity`` misbehaves while ``make_noisy`` is right (so its two checks must still pass),
except the ones that break the whole file (syntax error, a loop or a forbidden import at import
time, a misnamed function), which must fail every check with the reason. Limits are tiny so the
tests stay fast; the bound on the grading time is generous (the machine is shared) but shows the
grader returns within its own timeout plus a few seconds.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from lab.lessons.grader import Grader, SandboxedSubmission, draw_seeds

from lesson_helpers import SUBMISSIONS

LIMITS = dict(call_timeout_s=2.0, cpu_seconds=4.0, memory_mb=300.0, total_timeout_s=20.0, output_kb=4.0,
              result_mb=1.0, file_size_mb=1.0)
SLACK_S = 10.0  # "within its timeout plus a few seconds", generous for a loaded machine

# fixture -> (words the failed check's message must contain, whether the whole file fails)
CASES = {
    "infinite_loop": (["did not finish within the time limit of 2 s"], False),
    "sleeps": (["did not finish within the time limit"], False),
    "allocates": (["ran out of memory", "Unable to allocate"], False),
    "allocates_python": (["ran out of memory", "MemoryError"], False),
    "forks": (["creating a process (fork)"], False),
    "runs_program": (["running a program (subprocess)"], False),
    "ctypes_fork": (["ctypes"], False),
    "raises": (["raised ValueError: boom after 3 images", 'File "submission.py", line'], False),
    "prints_megabytes": (["printed", "remove your debugging prints", "xxxx"], False),
    "wrong_shape": (["has shape (3, 1); expected shape (3,)"], False),
    "returns_nan": (["NaN or infinite"], False),
    "wrong_type": (["must return ndarray", "got list"], False),
    "imports_reference": (["importing 'lab.modules' is not allowed"], False),
    "imports_grader": (["importing 'lab.lessons.grader' is not allowed"], False),
    "opens_network": (["not allowed", "host name"], False),
    "reads_files": (["reading /etc/passwd is not allowed"], False),
    "reads_reference_source": (["lab/modules/__init__.py is not allowed"], False),
    "writes_big_file": (["File too large"], False),
    "writes_elsewhere": (["writing /tmp/vision-lab-abuse-marker.txt is not allowed"], False),
    "kills_parent": (["signalling a process (os.kill)"], False),
    "exits": (["ended the process running it"], False),
    "huge_result": (["MB of data; the limit is 1 MB"], False),
    "unpicklable": (["cannot be sent back", "generator"], False),
    "evil_pickle": (["cannot be sent back", "submission.Evil"], False),
    "syntax_error": (["could not be loaded", "SyntaxError", "line 6"], True),
    "import_time_loop": (["could not be loaded", "did not finish within the time limit"], True),
    "imports_reference_at_top": (["could not be loaded", "importing 'lab.modules.calibration' is not allowed"], True),
    "missing_function": (["defines no function 'mean_intensity'", "mean_intensities"], True),
}
MARKERS = [Path("/tmp/vision-lab-abuse-marker.txt"), Path("/tmp/vision-lab-evil-marker")]


def grade_fixture(lesson, name: str, **changes):
    limits = lesson.limits.replace(**{**LIMITS, **changes})
    submission = SandboxedSubmission((SUBMISSIONS / "abuse" / f"{name}.py").read_text(), limits)
    grader = Grader(lesson, submission, seeds=draw_seeds(lesson, 0), limits=limits)
    started = time.monotonic()
    report = grader.run()
    return report, time.monotonic() - started, submission.sandbox.pids


def test_every_abuse_fixture_has_a_case():
    assert {p.stem for p in (SUBMISSIONS / "abuse").glob("*.py")} == set(CASES) | {"burns_cpu"}


@pytest.mark.parametrize("name", sorted(CASES))
def test_abuse_is_contained_with_a_clear_failed_test(toy_lesson, name):
    for marker in MARKERS:
        marker.unlink(missing_ok=True)
    words, whole_file = CASES[name]
    report, elapsed, pids = grade_fixture(toy_lesson, name)
    assert elapsed < LIMITS["total_timeout_s"] + SLACK_S
    means = [t for t in report.tests if t.task == "means"]
    noise = [t for t in report.tests if t.task == "noise"]
    assert all(t.status == "failed" and t.score == 0 for t in means)
    first = means[0].output
    for word in words:
        assert word in first, f"{word!r} not in:\n{first}"
    if whole_file:
        assert all(t.status == "failed" for t in noise)
        assert all(t.output for t in report.tests)
    else:
        assert all(t.status == "passed" for t in noise), [t.output for t in noise]
    assert report.score == sum(t.score for t in report.tests)
    for pid in pids:  # no child outlives the grading run
        assert not Path(f"/proc/{pid}").exists()
    for marker in MARKERS:
        assert not marker.exists()


def test_after_a_timeout_the_task_is_not_called_again(toy_lesson):
    report, elapsed, pids = grade_fixture(toy_lesson, "infinite_loop")
    means = [t for t in report.tests if t.task == "means"]
    assert all("Not run: mean_intensity() failed on an earlier check" in t.output for t in means[1:])
    assert len(pids) == 1  # the killed child is not restarted: no later task needs it


def test_the_grader_returns_within_its_total_timeout(toy_lesson):
    report, elapsed, _ = grade_fixture(toy_lesson, "sleeps", call_timeout_s=60.0, total_timeout_s=3.0)
    assert elapsed < 3.0 + SLACK_S
    means = [t for t in report.tests if t.task == "means"]
    assert "did not finish within the time limit" in means[0].output
    report, elapsed, _ = grade_fixture(toy_lesson, "import_time_loop", call_timeout_s=60.0, total_timeout_s=3.0)
    assert elapsed < 3.0 + SLACK_S
    assert all("could not be loaded" in t.output for t in report.tests)


def test_the_cpu_limit_fails_a_busy_loop_before_the_wall_clock(toy_lesson):
    report, elapsed, _ = grade_fixture(toy_lesson, "burns_cpu", cpu_seconds=1.0, call_timeout_s=60.0,
                                       total_timeout_s=90.0)
    first = [t for t in report.tests if t.task == "means"][0]
    assert "CPU time" in first.output and elapsed < 60.0
