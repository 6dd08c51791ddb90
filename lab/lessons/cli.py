"""Lesson commands for the ``vision-lab`` CLI; :func:`register` adds them to the main Typer app.

    vision-lab grade LESSON SUBMISSION.py [--out results.json] [--seed N] [--json]
    vision-lab grade LESSON --reference [--out results.json] [--seed N]
    vision-lab lesson list [--json]
    vision-lab lesson validate LESSON
    vision-lab lesson run LESSON --report DIR [--dataset NAME] [--seed N]

LESSON is a lesson id (``01-calibration``), its name (``calibration``) or the path of a lesson
folder. ``grade`` exits 0 whenever grading ran (whatever the score) and writes Gradescope's
results.json to ``--out`` (or prints it with ``--json``). A problem with what was asked for (an
unknown lesson, a missing file, a lesson that breaks the format) prints one line
``error: <field>: <reason>`` on stderr and exits 2, like every ``vision-lab`` command.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer

from lab.core.errors import InvalidValue, LabError

EXIT_USAGE = 2


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


def grade_command(
    lesson: Annotated[str, typer.Argument(help="Lesson id (01-calibration), name (calibration) or folder.")],
    submission: Annotated[Path | None, typer.Argument(help="The student's .py file.")] = None,
    reference: Annotated[bool, typer.Option("--reference",
                                            help="Grade the lab's own implementation.")] = False,
    out: Annotated[Path | None, typer.Option("--out", help="Write Gradescope's results.json here.")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Derive every dataset's seed from N (default: "
                                                            "fresh secret seeds).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print results.json instead of a summary.")] = False,
    unsafe_sandbox: Annotated[bool, typer.Option(
        "--unsafe-sandbox", help="Run the submission without the bubblewrap sandbox, with Python's audit "
                                 "hook only. For trusted code only, never for a class.")] = False,
) -> None:
    """Grade a submission (or the reference) and write Gradescope's results.json.

    Submissions run in the bubblewrap sandbox (docs/sandbox.md); where it cannot run, grading
    stops with an error naming the fix (exit 2) unless ``--unsafe-sandbox`` is given.
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
        found = find_lesson(lesson)
        source = None if reference or submission is None else _read_submission(submission)
        report = grade(found, source, reference=reference, seed=seed)
        results = report.results_json()
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(results, indent=2), encoding="utf-8")
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
        detail = entry.get("error") or (f"module {entry['module']}, {entry['points']:g} points, tasks: "
                                        + ", ".join(t["step"] for t in entry["tasks"]))
        typer.echo(f"{entry['id']}  {entry['title']}  ({detail})")


def validate_command(lesson: Annotated[str, typer.Argument(help="Lesson id, name or folder.")]) -> None:
    """Check a lesson folder against the format and its module (for instructors)."""
    from lab.lessons.format import find_lesson

    with _user_errors():
        found = find_lesson(lesson)
    typer.echo(f"{found.id}: ok ({len(found.tasks)} tasks, {sum(len(t.checks) for t in found.tasks)} checks, "
               f"{found.points:g} points)")


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


def register(app: typer.Typer) -> None:
    """Add ``grade`` and the ``lesson`` sub-commands to the ``vision-lab`` app."""
    app.command("grade", help="Grade a submission (or --reference) and write Gradescope's "
                              "results.json.")(grade_command)
    lesson_app = typer.Typer(help="Lessons: list, validate, run one headless with an HTML report.",
                             no_args_is_help=True)
    lesson_app.command("list")(list_command)
    lesson_app.command("validate")(validate_command)
    lesson_app.command("run")(run_command)
    app.add_typer(lesson_app, name="lesson")


__all__ = ["grade_command", "list_command", "register", "run_command", "validate_command"]
