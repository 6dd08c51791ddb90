"""An instructor's view of a class: per check, how many graded submissions failed it and with which
hints; the score distribution; the checks that never fail or fail everyone.

:func:`class_stats` is a pure function over stored results.json dicts (Gradescope's format, as
:meth:`lab.lessons.grader.GradeReport.results_json` writes them); :func:`latest_per_student` picks
what it counts from a lesson's submissions: the latest ``done`` submission of each student (a
submission without a student name counts on its own). ``vision-lab lesson stats LESSON`` and
``GET /api/lessons/{id}/stats`` show it.

A hint is a line of a test's ``output`` that starts with ``Hint: ``; it is counted under its name,
the trailing ``[name]`` of the line when there is one (else its text), and under every name of
``test["extra_data"]["hints"]`` when the grader lists them there. A check is flagged ``never fails``
when no submission failed it and ``fails everyone`` when every one did, only once at least
``min_submissions`` submissions were graded on it (fewer decide nothing).
"""

from __future__ import annotations

import math
import re
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from lab.lessons.store import Submission

#: Submissions a check needs before it can be flagged "never fails" or "fails everyone".
MIN_SUBMISSIONS = 5

#: Largest maximum score histogrammed one point per bin; above it, ten equal bins.
POINT_BINS_UP_TO = 20

NEVER_FAILS = "never fails"
FAILS_EVERYONE = "fails everyone"

#: The trailing ``[name]`` of a hint line: a name of tasks.toml's ``[hints]``, a detector, a mistake.
_HINT_NAME = re.compile(r"\s\[([\w.:-]+)\]\s*$")


@dataclass(frozen=True)
class HintCount:
    """A hint given on a check, and on how many submissions."""

    name: str
    count: int

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "count": self.count}


@dataclass(frozen=True)
class CheckStats:
    """One check (a test of results.json, by name) over the class."""

    name: str
    max_score: float
    graded: int  # submissions whose results have this check
    failed: int
    hints: tuple[HintCount, ...]  # most given first
    flag: str = ""  # "", NEVER_FAILS or FAILS_EVERYONE

    @property
    def share_failed(self) -> float:
        return self.failed / self.graded if self.graded else 0.0

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "max_score": self.max_score, "graded": self.graded, "failed": self.failed,
                "share_failed": round(self.share_failed, 6), "hints": [h.to_json() for h in self.hints],
                "flag": self.flag}


@dataclass(frozen=True)
class ScoreBin:
    """Scores in ``[low, high)``; the last bin is ``[max, max]``: full marks."""

    low: float
    high: float
    count: int

    def to_json(self) -> dict[str, Any]:
        return {"low": self.low, "high": self.high, "count": self.count}


@dataclass(frozen=True)
class ScoreDistribution:
    """The class's scores: summary numbers (None without a submission) and a histogram over 0 .. max."""

    count: int
    max_score: float
    mean: float | None
    median: float | None
    min: float | None
    max: float | None
    bins: tuple[ScoreBin, ...]

    def to_json(self) -> dict[str, Any]:
        return {"count": self.count, "max_score": self.max_score, "mean": self.mean, "median": self.median,
                "min": self.min, "max": self.max, "bins": [b.to_json() for b in self.bins]}


@dataclass(frozen=True)
class ClassStats:
    """What :func:`class_stats` found: the checks in the order of the results, and the scores."""

    lesson: str
    submissions: int
    min_submissions: int
    checks: tuple[CheckStats, ...]
    scores: ScoreDistribution

    def flagged(self) -> tuple[CheckStats, ...]:
        return tuple(c for c in self.checks if c.flag)

    def to_json(self) -> dict[str, Any]:
        return {"lesson": self.lesson, "submissions": self.submissions,
                "min_submissions": self.min_submissions, "checks": [c.to_json() for c in self.checks],
                "scores": self.scores.to_json(),
                "flagged": [{"name": c.name, "flag": c.flag} for c in self.flagged()]}


def latest_per_student(submissions: Iterable[Submission]) -> list[dict[str, Any]]:
    """The results of each student's latest ``done`` submission (by upload time); a submission without a
    student name is one of its own."""
    latest: dict[str, Submission] = {}
    for submission in submissions:
        if submission.status != "done" or not isinstance(submission.results, dict):
            continue
        key = f"student:{submission.student}" if submission.student else f"id:{submission.id}"
        kept = latest.get(key)
        if kept is None or (submission.created, submission.id) > (kept.created, kept.id):
            latest[key] = submission
    return [s.results for s in sorted(latest.values(), key=lambda s: (s.created, s.id)) if s.results]


def hint_names(test: Mapping[str, Any]) -> list[str]:
    """The hints a test of results.json gave, by name, each once."""
    names: list[str] = []
    for line in str(test.get("output") or "").splitlines():
        if line.startswith("Hint: "):
            found = _HINT_NAME.search(line)
            names.append(found.group(1) if found else line[len("Hint: "):].strip())
    extra = test.get("extra_data")
    if isinstance(extra, Mapping) and isinstance(extra.get("hints"), list):
        names.extend(str(name) for name in extra["hints"])
    return list(dict.fromkeys(n for n in names if n))


def class_stats(results: Sequence[Mapping[str, Any]], *, lesson: str = "",
                min_submissions: int = MIN_SUBMISSIONS) -> ClassStats:
    """Per check: graded, failed, their share and the hints; the score distribution; the flags. ``results``
    are results.json dicts, one per counted submission (see :func:`latest_per_student`)."""
    graded: dict[str, int] = {}
    failed: dict[str, int] = {}
    points: dict[str, float] = {}
    hints: dict[str, dict[str, int]] = {}
    for result in results:
        for test in result.get("tests") or []:
            name = str(test.get("name", ""))
            graded[name] = graded.get(name, 0) + 1
            points[name] = max(points.get(name, 0.0), float(test.get("max_score") or 0.0))
            if test.get("status") == "failed":
                failed[name] = failed.get(name, 0) + 1
                given = hints.setdefault(name, {})
                for hint in hint_names(test):
                    given[hint] = given.get(hint, 0) + 1
    checks = tuple(
        CheckStats(name=name, max_score=points[name], graded=count, failed=failed.get(name, 0),
                   hints=tuple(HintCount(h, c) for h, c in sorted(hints.get(name, {}).items(),
                                                                    key=lambda item: (-item[1], item[0]))),
                   flag=_flag(count, failed.get(name, 0), min_submissions))
        for name, count in graded.items())
    return ClassStats(lesson=lesson, submissions=len(results), min_submissions=min_submissions, checks=checks,
                      scores=score_distribution(results))


def _flag(graded: int, failed: int, min_submissions: int) -> str:
    if graded < max(1, min_submissions):
        return ""
    return NEVER_FAILS if failed == 0 else FAILS_EVERYONE if failed == graded else ""


def _max_score(result: Mapping[str, Any]) -> float:
    extra = result.get("extra_data")
    if isinstance(extra, Mapping) and isinstance(extra.get("max_score"), (int, float)):
        return float(extra["max_score"])
    return float(sum(float(t.get("max_score") or 0.0) for t in result.get("tests") or []))


def score_distribution(results: Sequence[Mapping[str, Any]]) -> ScoreDistribution:
    """Mean, median, min, max and a histogram: one bin per point up to :data:`POINT_BINS_UP_TO` points, else
    ten equal bins; the last bin holds full marks only."""
    scores = [float(r.get("score") or 0.0) for r in results]
    top = max((_max_score(r) for r in results), default=0.0)
    width = 1.0 if top <= POINT_BINS_UP_TO else top / 10
    edges = [min(k * width, top) for k in range(math.ceil(top / width - 1e-9) + 1)] if top > 0 else [0.0]
    counts = [0] * len(edges)  # bin k: [edges[k], edges[k + 1]); the last: full marks
    for score in scores:
        if score >= top - 1e-9 * max(1.0, top):
            counts[-1] += 1
        else:
            index = min(max(int(score // width), 0), len(edges) - 2)
            counts[index] += 1
    bins = tuple(ScoreBin(low=edges[k], high=edges[k + 1] if k + 1 < len(edges) else top, count=counts[k])
                 for k in range(len(edges)))
    return ScoreDistribution(
        count=len(scores), max_score=top, mean=statistics.fmean(scores) if scores else None,
        median=statistics.median(scores) if scores else None, min=min(scores, default=None),
        max=max(scores, default=None), bins=bins)


def format_table(stats: ClassStats) -> str:
    """A readable table of :func:`class_stats` for the CLI."""
    lines = [f"{stats.lesson}: {stats.submissions} graded submission(s) (the latest of each student)"]
    if not stats.submissions:
        return lines[0]
    width = max(len(c.name) for c in stats.checks) if stats.checks else 5
    lines.append(f"  {'check':<{width}}  {'failed':>12}  hints")
    for check in stats.checks:
        given = ", ".join(f"{h.name} x{h.count}" for h in check.hints) or "-"
        flag = f"  <- {check.flag}" if check.flag else ""
        lines.append(f"  {check.name:<{width}}  {check.failed:>4}/{check.graded:<4} {check.share_failed:4.0%}"
                     f"  {given}{flag}")
    scores = stats.scores
    lines.append(f"scores out of {scores.max_score:g}: mean {scores.mean:.2f}, median {scores.median:g}, "
                 f"min {scores.min:g}, max {scores.max:g}")
    tallest = max(b.count for b in scores.bins) or 1
    for score_bin in scores.bins:
        label = (f"{score_bin.low:g}" if score_bin.low == score_bin.high
                 else f"{score_bin.low:g}-{score_bin.high:g}")
        bar = "#" * round(30 * score_bin.count / tallest)
        lines.append(f"  {label:>11}  {score_bin.count:>4}  {bar}")
    if stats.submissions < stats.min_submissions:
        lines.append(f"(checks are flagged from {stats.min_submissions} submissions on)")
    return "\n".join(lines)


__all__ = ["CheckStats", "ClassStats", "HintCount", "ScoreBin", "ScoreDistribution", "class_stats",
           "format_table", "hint_names", "latest_per_student", "score_distribution"]
