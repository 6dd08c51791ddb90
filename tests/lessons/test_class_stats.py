"""The instructor's view of a class (lab.lessons.stats): per check, the share that failed and the hints; the
score distribution; the flags; through the service's REST route and ``vision-lab lesson stats``."""

from __future__ import annotations

import json

import pytest
import typer
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from lab.api.lessons import build_app
from lab.lessons.cli import register
from lab.lessons.format import LessonCatalog
from lab.lessons.service import LessonService
from lab.lessons.stats import (FAILS_EVERYONE, NEVER_FAILS, class_stats, format_table, hint_names,
                               latest_per_student)
from lab.lessons.store import Submission, SubmissionQueue

from lesson_helpers import FIXTURES, wait_done

TOY = str(FIXTURES / "lessons" / "00-toy")


def check_row(name: str, failed: bool = False, *, hints: tuple[str, ...] = (), extra: list[str] | None = None,
             points: float = 2.0) -> dict:
    output = "Failed: value: differs" if failed else "Passed: value"
    output += "".join(f"\nHint: {h}" for h in hints)
    row = {"name": name, "score": 0.0 if failed else points, "max_score": points,
           "status": "failed" if failed else "passed", "output": output, "visibility": "visible"}
    if extra is not None:
        row["extra_data"] = {"task": "t", "hints": extra}
    return row


def results(*tests: dict, max_score: float | None = None) -> dict:
    top = sum(t["max_score"] for t in tests) if max_score is None else max_score
    return {"score": sum(t["score"] for t in tests), "tests": list(tests),
            "extra_data": {"lesson": "00-toy", "max_score": top, "seeds": {"small": [1]}}}


def a_class() -> list[dict]:
    """Six submissions: "easy" never fails, "hard" fails everyone, "middle" fails three (hints), "new" is in
    four results only."""
    rows = []
    for k in range(6):
        middle_fails = k < 3
        hints = {0: ("you transposed it [transposed]", "clip them [noisy_without_clipping]"),
                 1: ("you transposed it [transposed]",),
                 2: ("your pixels leave [0, 1]",)}.get(k, ())
        tests = [check_row("easy"), check_row("hard", True),
                 check_row("middle", middle_fails, hints=hints, extra=["transposed"] if k == 1 else None)]
        if k < 4:
            tests.append(check_row("new"))
        rows.append(results(*tests, max_score=8.0))
    return rows


def test_shares_hints_and_flags_of_a_crafted_class():
    stats = class_stats(a_class(), lesson="00-toy")
    by_name = {c.name: c for c in stats.checks}
    assert [c.name for c in stats.checks] == ["easy", "hard", "middle", "new"]  # the order of the results
    assert stats.submissions == 6
    assert (by_name["easy"].failed, by_name["easy"].graded, by_name["easy"].flag) == (0, 6, NEVER_FAILS)
    hard = by_name["hard"]
    assert (hard.failed, hard.share_failed, hard.flag) == (6, 1.0, FAILS_EVERYONE)
    middle = by_name["middle"]
    assert (middle.failed, middle.share_failed, middle.flag) == (3, 0.5, "")
    # a hint is counted once per submission (the [name] of its line and extra_data.hints are the same hint)
    assert [(h.name, h.count) for h in middle.hints] == [("transposed", 2), ("noisy_without_clipping", 1),
                                                        ("your pixels leave [0, 1]", 1)]
    assert by_name["new"].graded == 4 and by_name["new"].flag == ""  # never failed, but on 4 < 5 submissions
    assert [c.name for c in stats.flagged()] == ["easy", "hard"]


def test_flags_need_enough_submissions():
    few = class_stats(a_class()[:4])
    assert not few.flagged()
    flags = {c.name: c.flag for c in class_stats(a_class()[:4], min_submissions=4).checks}
    assert flags["hard"] == FAILS_EVERYONE


def test_hint_names_from_the_output_and_extra_data():
    test = check_row("x", True, hints=("you ignore scale [scale_ignored]", "a plain hint", "in [0, 1]"),
                    extra=["scaled", "scale_ignored"])
    assert hint_names(test) == ["scale_ignored", "a plain hint", "in [0, 1]", "scaled"]
    assert hint_names({"output": "Failed: x\nno hint here"}) == []


def test_the_score_distribution_of_a_six_point_lesson():
    scores = [0.0, 1.5, 3.0, 3.0, 5.999, 6.0, 6.0]
    rows = [{"score": s, "tests": [], "extra_data": {"max_score": 6.0}} for s in scores]
    distribution = class_stats(rows).scores
    assert distribution.count == 7 and distribution.max_score == 6.0
    assert distribution.min == 0.0 and distribution.max == 6.0 and distribution.median == 3.0
    assert distribution.mean == pytest.approx(sum(scores) / 7)
    assert [(b.low, b.high) for b in distribution.bins] == [(k, k + 1) for k in range(6)] + [(6.0, 6.0)]
    assert [b.count for b in distribution.bins] == [1, 1, 0, 2, 0, 1, 2]  # 5.999 is not full marks


def test_a_hundred_point_lesson_has_ten_point_bins_and_no_submissions_no_numbers():
    rows = [{"score": s, "tests": [{"max_score": 100.0}]} for s in (0.0, 9.9, 10.0, 95.0, 100.0)]
    distribution = class_stats(rows).scores
    assert len(distribution.bins) == 11
    assert distribution.bins[1].low == 10.0 and distribution.bins[-1].low == 100.0
    assert [b.count for b in distribution.bins] == [2, 1, 0, 0, 0, 0, 0, 0, 0, 1, 1]
    empty = class_stats([])
    assert empty.submissions == 0 and empty.scores.mean is None and empty.checks == ()
    assert "0 graded" in format_table(empty)


def submission(student: str, created: float, status: str = "done", score: float = 1.0, *,
               sid: str = "") -> Submission:
    payload = results(check_row("only", failed=score == 0.0, points=1.0)) if status == "done" else None
    return Submission(id=sid or f"{student}-{created}", lesson="00-toy", student=student, filename="a.py",
                      source="", status=status, created=created, started=None, finished=None, attempts=1,
                      score=score, max_score=1.0, results=payload, error=None)


def test_only_the_latest_done_submission_of_each_student_counts():
    counted = latest_per_student([
        submission("ana", 1.0, score=0.0), submission("ana", 3.0, score=1.0),
        submission("ana", 4.0, status="queued"), submission("ana", 5.0, status="error"),
        submission("bo", 2.0, score=0.0),
        submission("", 1.0, score=0.0, sid="x1"), submission("", 2.0, score=0.0, sid="x2"),
    ])
    assert sorted(r["score"] for r in counted) == [0.0, 0.0, 0.0, 1.0]  # ana's latest done, bo, two anonymous
    assert class_stats(counted).checks[0].failed == 3


def test_to_json_is_plain_json_and_the_table_names_the_flags():
    stats = class_stats(a_class(), lesson="00-toy")
    body = json.loads(json.dumps(stats.to_json()))
    assert body["lesson"] == "00-toy" and body["submissions"] == 6
    assert body["flagged"] == [{"name": "easy", "flag": NEVER_FAILS},
                               {"name": "hard", "flag": FAILS_EVERYONE}]
    assert body["checks"][2]["share_failed"] == 0.5
    assert body["checks"][2]["hints"][0] == {"name": "transposed", "count": 2}
    assert sum(b["count"] for b in body["scores"]["bins"]) == 6
    table = format_table(stats)
    assert "never fails" in table and "fails everyone" in table and "transposed x2" in table


# --- through the service: REST and CLI ----------------------------------------------------------------
def crafted_grader(by_source: dict[str, dict]):
    return lambda job: by_source[job.source]


def test_rest_stats_for_an_instructor(tmp_path):
    by_source = {"pass": results(check_row("a"), check_row("b")),
                 "fail": results(check_row("a", True, hints=("no [transposed]",)), check_row("b"))}
    service = LessonService(catalog=LessonCatalog(FIXTURES / "lessons"),
                            queue=SubmissionQueue(f"sqlite:///{tmp_path / 'db.sqlite'}"), poll_s=0.05,
                            grade=crafted_grader(by_source), instructor_token="s3cret")
    auth = {"Authorization": "Bearer s3cret"}
    with TestClient(build_app(service)) as client:
        for student, source in (("ana", "fail"), ("bo", "fail"), ("ana", "pass")):
            response = client.post("/api/lessons/toy/submissions", data={"student": student},
                                   files={"file": ("a.py", source.encode(), "text/x-python")})
            assert wait_done(client, response.json()["id"])["status"] == "done"
        assert client.get("/api/lessons/00-toy/stats").status_code == 403
        body = client.get("/api/lessons/toy/stats", headers=auth).json()
        assert client.get("/api/lessons/stereo/stats", headers=auth).status_code == 404
    assert body["lesson"] == "00-toy" and body["submissions"] == 2  # ana's latest, bo's
    assert body["checks"][0] == {"name": "a", "max_score": 2.0, "graded": 2, "failed": 1, "share_failed": 0.5,
                                 "hints": [{"name": "transposed", "count": 1}], "flag": ""}
    assert body["scores"]["min"] == 2.0 and body["scores"]["max"] == 4.0


@pytest.fixture()
def cli():
    application = typer.Typer()

    @application.callback()
    def main() -> None:
        """vision-lab (test)"""

    register(application)
    return lambda *args, env=None: CliRunner().invoke(application, [str(a) for a in args], env=env)


def test_cli_stats_table_and_json(cli, tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    queue = SubmissionQueue(url)
    for k, payload in enumerate(a_class()):
        submission_id = queue.submit("00-toy", "a.py", "x = 1", student=f"s{k}")
        assert queue.claim().id == submission_id
        queue.finish(submission_id, payload)
    queue.close()
    env = {"VISION_LAB_DATABASE_URL": url}
    table = cli("lesson", "stats", TOY, env=env)
    assert table.exit_code == 0, table.output
    assert "00-toy: 6 graded" in table.stdout and "<- never fails" in table.stdout
    as_json = cli("lesson", "stats", TOY, "--json", env=env)
    assert as_json.exit_code == 0 and json.loads(as_json.stdout)["checks"][1]["flag"] == FAILS_EVERYONE


def test_cli_stats_of_an_unknown_lesson_is_one_error_line_and_exit_2(cli, tmp_path):
    env = {"VISION_LAB_DATABASE_URL": f"sqlite:///{tmp_path}/d.sqlite"}
    result = cli("lesson", "stats", "no-such-lesson", env=env)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: lesson: ")
