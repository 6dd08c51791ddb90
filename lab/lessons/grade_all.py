"""``vision-lab grade-all LESSON FOLDER``: a folder of submissions graded through the server's own path.

Every ``*.py`` of the folder becomes a submission of the lesson (its student: the file's name
without ``.py``) in the submissions database, graded by the same dispatcher and Dask jobs as the
REST uploads (the embedded cluster, or ``VISION_LAB_DASK_SCHEDULER``'s workers), with the lesson's
assignment seed. A progress bar counts the graded ones on a terminal; then ``--out DIR`` gets
``scores.csv`` (student, file, status, score, max score, submission id) and, per student,
Gradescope's ``results.json`` (``DIR/<student>/results.json``).
"""

from __future__ import annotations

import csv
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from lab.core.errors import InvalidValue
from lab.lessons.service import LessonService
from lab.lessons.store import Submission
from lab.lessons.submission import check_upload


@dataclass(frozen=True)
class Graded:
    """A folder's submissions once every one is graded (``done`` or ``error``)."""

    lesson: str
    submissions: tuple[Submission, ...]


def grade_folder(service: LessonService, lesson: str, folder: Path, *, timeout_s: float = 3600.0,
                 progress: bool = False) -> Graded:
    """Submit every ``*.py`` of ``folder`` as a submission of ``lesson`` and wait until all are graded."""
    files = sorted(p for p in folder.glob("*.py") if p.is_file()) if folder.is_dir() else []
    if not files:
        raise InvalidValue("FOLDER", f"{str(folder)!r} holds no .py submission")
    found = service.catalog.get(lesson)
    service.start()
    ids = [service.submit(found.id, path.name, check_upload(path.read_bytes(), path.name,
                                                            limit=service.max_submission_bytes),
                          student=path.stem) for path in files]
    deadline = time.monotonic() + timeout_s
    bar = _bar(len(ids)) if progress else None
    try:
        while True:
            rows = [service.queue.get(i) for i in ids]
            graded = [r for r in rows if r is not None and r.status in ("done", "error")]
            if bar is not None:
                bar[0].update(bar[1], completed=len(graded))
            if len(graded) == len(ids) or time.monotonic() > deadline:
                break
            time.sleep(0.2)
    finally:
        if bar is not None:
            bar[0].stop()
    return Graded(found.id, tuple(r for r in rows if r is not None))


def _bar(total: int):  # -> (rich Progress, its task)
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    bar = Progress(TextColumn("grading"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                   console=Console(file=sys.stderr))
    bar.start()
    return bar, bar.add_task("grading", total=total)


def export(graded: Graded, out: Path) -> Path:
    """Write ``scores.csv`` and each student's Gradescope ``results.json`` under ``out``; the CSV's path."""
    out.mkdir(parents=True, exist_ok=True)
    table = out / "scores.csv"
    with table.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["student", "file", "status", "score", "max_score", "submission"])
        for row in graded.submissions:
            writer.writerow([row.student, row.filename, row.status, "" if row.score is None else row.score,
                             "" if row.max_score is None else row.max_score, row.id])
            if row.results is not None:
                folder = out / row.student
                folder.mkdir(exist_ok=True)
                (folder / "results.json").write_text(json.dumps(row.results, indent=2), encoding="utf-8")
    return table


__all__ = ["Graded", "export", "grade_folder"]
