"""Lesson commands for the ``vision-lab`` CLI; :func:`register` adds them to the main Typer app.

    vision-lab grade LESSON SUBMISSION.py [--out results.json] [--seed N] [--json]
    vision-lab grade LESSON --reference [--out results.json] [--seed N]
    vision-lab lesson list [--json]
    vision-lab lesson validate LESSON [--no-mutants] [--json]
    vision-lab lesson run LESSON --report DIR [--dataset NAME] [--seed N]
    vision-lab lesson seed LESSON [--set N]
    vision-lab lesson stats LESSON [--json]
    vision-lab worker tcp://HOST:PORT [--nthreads N] [--name NAME] [--unsafe-sandbox]
    vision-lab grade-all LESSON FOLDER --out DIR

``grade --seed N`` grades with the assignment seed N (``$VISION_LAB_ASSIGNMENT_SEED`` when no
``--seed`` is given): the same file gets the same score every time, and the score the server gives
when N is the lesson's stored seed (``vision-lab lesson seed LESSON`` prints it). Without either it
is a practice run on fresh data, said so on stderr, not a grade. ``lesson seed`` and ``lesson stats``
read the submissions database of the lesson server (``$VISION_LAB_DATABASE_URL``, else the default
SQLite file).

LESSON is a lesson id (``01-calibration``), its name (``calibration``) or the path of a lesson
folder. ``grade`` exits 0 whenever grading ran (whatever the score) and writes Gradescope's
results.json to ``--out`` (or prints it with ``--json``). A problem with what was asked for (an
unknown lesson, a missing file, a lesson that breaks the format) prints one line
``error: <field>: <reason>`` on stderr and exits 2, like every ``vision-lab`` command.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from lab.core.errors import InvalidValue, LabError

if TYPE_CHECKING:
    from lab.lessons.store import SubmissionQueue

EXIT_USAGE = 2

#: The assignment seed of ``vision-lab grade`` when ``--seed`` is not given.
SEED_VARIABLE = "VISION_LAB_ASSIGNMENT_SEED"

PRACTICE_NOTE = "practice run: fresh data, not a grade; give --seed (the assignment seed) to grade"


def _error(field: str, reason: str) -> None:
    typer.echo(f"error: {field}: {reason}".replace("\r", " ").replace("\n", " "), err=True)


@contextlib.contextmanager
def _user_errors() -> Iterator[None]:
    try:
        yield
    except LabError as exc:
        _error(exc.field, exc.reason)
        raise typer.Exit(EXIT_USAGE) from None
    except OSError as exc:
        where = getattr(exc, "filename", None)
        _error("file" if where else "os", f"{exc.strerror or exc}{f': {where}' if where else ''}")
        raise typer.Exit(EXIT_USAGE) from None


def _read_submission(path: Path) -> str:
    if not path.is_file():
        raise InvalidValue("SUBMISSION", f"no file {str(path)!r}")
    try:
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InvalidValue("SUBMISSION", f"{str(path)!r} is not UTF-8 text: save it as UTF-8 Python "
                                         "source") from None


def _assignment_seed(seed: int | None) -> int | None:
    """``--seed``, else ``$VISION_LAB_ASSIGNMENT_SEED``, else None (a practice run); checked like the
    server's seeds (0 .. 2**31 - 1)."""
    from lab.lessons.store import check_seed

    if seed is not None:
        return check_seed(seed, field="--seed")
    text = os.environ.get(SEED_VARIABLE, "").strip()
    if not text:
        return None
    if not text.isdigit():
        raise InvalidValue(SEED_VARIABLE, f"an assignment seed is an integer, not {text[:40]!r}")
    return check_seed(int(text), field=SEED_VARIABLE)


def grade_command(
    lesson: Annotated[str, typer.Argument(help="Lesson id (01-calibration), name (calibration) or folder.")],
    submission: Annotated[Path | None, typer.Argument(help="The student's .py file.")] = None,
    reference: Annotated[bool, typer.Option("--reference",
                                            help="Grade the lab's own implementation.")] = False,
    out: Annotated[Path | None, typer.Option("--out", help="Write Gradescope's results.json here.")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="The assignment seed: every hidden dataset is "
                                                            "derived from N (default: "
                                                            "$VISION_LAB_ASSIGNMENT_SEED, else a practice "
                                                            "run on fresh data).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print results.json instead of a summary.")] = False,
    unsafe_sandbox: Annotated[bool, typer.Option(
        "--unsafe-sandbox", help="Run the submission without the bubblewrap sandbox, with Python's audit "
                                 "hook only. For trusted code only, never for a class.")] = False,
) -> None:
    """Grade a submission (or the reference) and write Gradescope's results.json.

    Submissions run in the bubblewrap sandbox (docs/sandbox.md); where it cannot run, grading
    stops with an error naming the fix (exit 2) unless ``--unsafe-sandbox`` is given. Without an
    assignment seed (``--seed``, ``$VISION_LAB_ASSIGNMENT_SEED``) it is a practice run, said on stderr.
    """
    from lab.lessons.format import find_lesson
    from lab.lessons.grader import grade
    from lab.lessons.isolation import allow_unsafe

    if unsafe_sandbox:
        allow_unsafe(True)
    with _user_errors():
        if reference == (submission is not None):
            raise InvalidValue("SUBMISSION", "give a submission file, or --reference to grade the lab's own "
                                             "implementation (not both)")
        assignment_seed = _assignment_seed(seed)
        found = find_lesson(lesson)
        source = None if reference or submission is None else _read_submission(submission)
        report = grade(found, source, reference=reference, seed=assignment_seed,
                       practice=assignment_seed is None)
        results = report.results_json()
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(results, indent=2), encoding="utf-8")
    if assignment_seed is None:
        typer.echo(PRACTICE_NOTE, err=True)
    if as_json:
        typer.echo(json.dumps(results, indent=2))
        return
    typer.echo(report.output.splitlines()[0])
    for test in report.tests:
        mark = "PASS" if test.status == "passed" else "FAIL"
        typer.echo(f"  {mark} {test.score:g}/{test.max_score:g}  {test.name}")
    failed = [t for t in report.tests if t.status == "failed"]
    if failed:
        typer.echo("")
        for test in failed:
            typer.echo(f"--- {test.name}\n{test.output}\n")
    if out is not None:
        typer.echo(f"results.json written to {out}")


def list_command(as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False) -> None:
    """List the lessons."""
    from lab.lessons.format import LessonCatalog

    with _user_errors():
        catalog = LessonCatalog()
        lessons = []
        for lesson_id in catalog.ids():
            try:
                lessons.append(catalog.get(lesson_id).summary())
            except LabError as exc:
                lessons.append({"id": lesson_id, "title": lesson_id, "error": str(exc)})
    if as_json:
        typer.echo(json.dumps(lessons, indent=2))
        return
    if not lessons:
        typer.echo(f"no lessons in {catalog.root}")
    for entry in lessons:
        detail = entry.get("error") or (f"module {entry['module_title']}, {entry['points']:g} points, tasks: "
                                        + ", ".join(t["step"] for t in entry["tasks"]))
        typer.echo(f"{entry['id']}  {entry['title']}  ({detail})")


def validate_command(
    lesson: Annotated[str, typer.Argument(help="Lesson id, name or folder.")],
    mutants: Annotated[bool, typer.Option("--mutants/--no-mutants",
                                          help="Mutation-test the checks (lab.lessons.validate).")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="Print the mutation report as JSON.")] = False,
) -> None:
    """Check a lesson folder against the format and its module, then mutation-test its checks: every check
    must be failed by some mutant of the reference, every mutant caught (or documented as correct in
    [tasks.correct_mutants]). Exits 2 when it does not validate."""
    from lab.lessons.format import find_lesson
    from lab.lessons.validate import mutation_report

    with _user_errors():
        found = find_lesson(lesson)
    typer.echo(f"{found.id}: format ok ({len(found.tasks)} tasks, {sum(len(t.checks) for t in found.tasks)} "
               f"checks, {found.points:g} points)", err=as_json)
    for warning in found.warnings:
        typer.echo(f"warning: {warning}", err=True)
    if not mutants:
        return
    with _user_errors():
        report = mutation_report(found)
    typer.echo(json.dumps(report.to_json(), indent=2) if as_json else report.text())
    if not report.ok:
        _error("lesson", f"{found.id} does not validate: {len(report.problems)} problems (listed above)")
        raise typer.Exit(EXIT_USAGE)


def run_command(
    lesson: Annotated[str, typer.Argument(help="Lesson id, name or folder.")],
    report: Annotated[Path, typer.Option("--report",
                                         help="Folder to write index.html, scene.html and images to.")],
    dataset: Annotated[str | None, typer.Option("--dataset", help="A dataset of the lesson's tasks.toml "
                                                                  "(default: its first) or of the module.")
                       ] = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the data and of every step.")] = 0,
) -> None:
    """Run a lesson's reference pipeline headless and write an HTML report (metrics, images, 3D scene)."""
    from lab.lessons.format import find_lesson
    from lab.lessons.report import write_report

    with _user_errors():
        found = find_lesson(lesson)
        index = write_report(found, report, dataset=dataset, seed=seed)
    summary = json.loads((report / "report.json").read_text(encoding="utf-8"))
    for step in summary["steps"]:
        metrics = {k: v for k, v in step["metrics"].items() if not isinstance(v, list)}
        shown = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                          for k, v in list(metrics.items())[:6])
        typer.echo(f"{step['step']:<24} {step['seconds']:7.3f} s  {shown}")
    if summary["error"]:
        typer.echo(f"stopped: {summary['error']}", err=True)
    typer.echo(f"report written to {index}")


def _open_queue() -> SubmissionQueue:
    """The lesson server's submissions database (``$VISION_LAB_DATABASE_URL`` or the default file)."""
    from lab.lessons.store import SubmissionQueue

    return SubmissionQueue()


def seed_command(
    lesson: Annotated[str, typer.Argument(help="Lesson id, name or folder.")],
    set_seed: Annotated[int | None, typer.Option("--set", help="Store N (0 .. 2**31 - 1) as the lesson's "
                                                               "assignment seed.")] = None,
) -> None:
    """Print the lesson's assignment seed (drawn and stored on first use), or set it (for instructors).

    The seed is the server's: the database of ``$VISION_LAB_DATABASE_URL`` (else the default SQLite
    file). After setting it, regrade the class (POST /api/lessons/{id}/regrade) so every submission
    uses it.
    """
    from lab.lessons.format import find_lesson
    from lab.lessons.store import check_seed

    with _user_errors():
        found = find_lesson(lesson)
        queue = _open_queue()
        try:
            seed = (queue.assignment_seed(found.id) if set_seed is None
                    else queue.set_assignment_seed(found.id, check_seed(set_seed, field="--set")))
        finally:
            queue.close()
    typer.echo(str(seed))


def stats_command(
    lesson: Annotated[str, typer.Argument(help="Lesson id, name or folder.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the statistics as JSON.")] = False,
) -> None:
    """The class's results (for instructors): per check the share that failed it and the hints given, the
    score distribution, and the checks that never fail or fail everyone; the latest graded submission of
    each student counts."""
    from lab.lessons.format import find_lesson
    from lab.lessons.stats import class_stats, format_table, latest_per_student

    with _user_errors():
        found = find_lesson(lesson)
        queue = _open_queue()
        try:
            stats = class_stats(latest_per_student(queue.list(found.id, limit=None)), lesson=found.id)
        finally:
            queue.close()
    typer.echo(json.dumps(stats.to_json(), indent=2) if as_json else format_table(stats))


def worker_command(
    scheduler: Annotated[str | None, typer.Argument(
        help="The Dask scheduler's address, tcp://host:port (default: $VISION_LAB_DASK_SCHEDULER).")] = None,
    nthreads: Annotated[int, typer.Option("--nthreads", min=1, help="Gradings this worker runs at once "
                                                                    "(each uses about one core).")] = 1,
    name: Annotated[str | None, typer.Option("--name", help="The worker's name (recorded with each "
                                                            "submission it grades).")] = None,
    host: Annotated[str | None, typer.Option("--host", help="Address the worker listens on (default: the "
                                                            "one facing the scheduler).")] = None,
    unsafe_sandbox: Annotated[bool, typer.Option(
        "--unsafe-sandbox", help="Grade without the bubblewrap sandbox, with Python's audit hook only. For "
                                 "trusted code only, never for a class.")] = False,
) -> None:
    """Start a Dask worker that grades submissions (the server's jobs) until it is stopped.

    The server sends jobs to the scheduler when ``VISION_LAB_DASK_SCHEDULER`` names it; each job
    runs the submission in the bubblewrap sandbox here and writes its result into the database the
    job names, which this machine must reach. Without a working sandbox the worker does not start
    (exit 2, naming the fix).
    """
    from lab.lessons.cluster import SCHEDULER_VARIABLE

    with _user_errors():
        address = scheduler or os.environ.get(SCHEDULER_VARIABLE, "")
        if not address:
            raise InvalidValue("SCHEDULER", f"give the scheduler's address (tcp://host:port) or set "
                                            f"${SCHEDULER_VARIABLE}")
        from lab.lessons.worker import run_worker

        run_worker(address, nthreads=nthreads, name=name, host=host, unsafe_sandbox=unsafe_sandbox)


def grade_all_command(
    lesson: Annotated[str, typer.Argument(help="Lesson id (01-calibration) or name (calibration).")],
    folder: Annotated[Path, typer.Argument(help="A folder of submissions, one .py per student.")],
    out: Annotated[Path, typer.Option("--out", help="Write scores.csv and each student's results.json "
                                                    "here.")] = Path("grades"),
    unsafe_sandbox: Annotated[bool, typer.Option(
        "--unsafe-sandbox", help="Grade without the bubblewrap sandbox (trusted code only).")] = False,
) -> None:
    """Grade a folder of submissions through the server's path (the submissions database, Dask jobs,
    the lesson's assignment seed) and export the scores (CSV) and Gradescope's results.json."""
    from lab.lessons.grade_all import export, grade_folder
    from lab.lessons.isolation import allow_unsafe

    if unsafe_sandbox:
        allow_unsafe(True)
    with _user_errors():
        from lab.lessons.service import LessonService

        service = LessonService.from_env()
        try:
            service.start()
            if service.sandbox_problem is not None:
                from lab.lessons.isolation import SandboxUnavailable

                raise SandboxUnavailable(service.sandbox_problem)
            graded = grade_folder(service, lesson, folder, progress=sys.stderr.isatty())
        finally:
            service.stop()
        table = export(graded, out)
    done = [s for s in graded.submissions if s.status == "done"]
    typer.echo(f"{len(done)}/{len(graded.submissions)} graded; scores in {table}")


def register(app: typer.Typer) -> None:
    """Add ``grade`` and the ``lesson`` sub-commands to the ``vision-lab`` app."""
    app.command("grade", help="Grade a submission (or --reference) and write Gradescope's "
                              "results.json.")(grade_command)
    app.command("worker", help="Start a Dask worker that grades the server's submissions.")(worker_command)
    app.command("grade-all", help="Grade a folder of submissions; scores.csv and results.json per "
                                  "student.")(grade_all_command)
    lesson_app = typer.Typer(help="Lessons: list, validate, run one headless with an HTML report; an "
                                  "assignment's seed and a class's results.", no_args_is_help=True)
    lesson_app.command("list")(list_command)
    lesson_app.command("validate")(validate_command)
    lesson_app.command("run")(run_command)
    lesson_app.command("seed")(seed_command)
    lesson_app.command("stats")(stats_command)
    app.add_typer(lesson_app, name="lesson")


__all__ = [
    "grade_all_command",
    "grade_command",
    "list_command",
    "register",
    "run_command",
    "seed_command",
    "stats_command",
    "validate_command",
    "worker_command",
]
