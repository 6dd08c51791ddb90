"""``vision-lab grade`` and ``vision-lab lesson ...`` through lab.lessons.cli.register on a Typer app."""

from __future__ import annotations

import json

import pytest
import typer
from typer.testing import CliRunner

from lab.lessons.cli import register

from lesson_helpers import FIXTURES, SUBMISSIONS

TOY = str(FIXTURES / "lessons" / "00-toy")


@pytest.fixture(scope="module")
def app():
    application = typer.Typer()

    @application.callback()
    def main() -> None:
        """vision-lab (test)"""

    register(application)
    return application


def run(app, *args, env=None):
    return CliRunner().invoke(app, [str(a) for a in args], env=env)


def test_grade_writes_results_json_and_prints_a_summary(app, tmp_path):
    out = tmp_path / "out" / "results.json"
    result = run(app, "grade", TOY, SUBMISSIONS / "toy" / "wrong_ignores_scale.py", "--out", out, "--seed", 3)
    assert result.exit_code == 0, result.output
    assert "5 / 6 points" in result.stdout
    assert "  FAIL 0/1  Mean intensity: scale = 3" in result.stdout and "PASS 1/1" in result.stdout
    assert "Hint: you ignore the control scale" in result.stdout
    results = json.loads(out.read_text())
    assert results["score"] == 5.0 and len(results["tests"]) == 6


def test_grade_json_and_reference(app):
    result = run(app, "grade", TOY, "--reference", "--json")
    assert result.exit_code == 0
    assert json.loads(result.stdout)["score"] == 6.0


@pytest.mark.parametrize("args,field", [
    ([TOY], "SUBMISSION"),
    ([TOY, SUBMISSIONS / "toy" / "solution.py", "--reference"], "SUBMISSION"),
    (["no-such-lesson", SUBMISSIONS / "toy" / "solution.py"], "lesson"),
    ([TOY, "missing.py"], "SUBMISSION"),
])
def test_grade_usage_errors_are_one_line_and_exit_2(app, args, field):
    result = run(app, "grade", *args)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {field}: ")


def test_grade_refuses_a_file_that_is_not_utf8(app, tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_bytes(b"x = '\xff'\n")
    result = run(app, "grade", TOY, bad)
    assert result.exit_code == 2 and "not UTF-8" in result.stderr


def test_lesson_list_and_validate(app, tmp_path):
    result = run(app, "lesson", "list", env={"VISION_LAB_LESSONS_DIR": str(FIXTURES / "lessons")})
    assert result.exit_code == 0 and "00-toy  Toy lesson: noise and means" in result.stdout
    result = run(app, "lesson", "list", "--json", env={"VISION_LAB_LESSONS_DIR": str(FIXTURES / "lessons")})
    assert json.loads(result.stdout)[0]["points"] == 6.0
    result = run(app, "lesson", "validate", TOY)
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith("00-toy: format ok (2 tasks, 6 checks, 6 points)")
    assert "0 surviving; 0 checks no mutant fails" in result.stdout and "means_summed" in result.stdout
    broken = tmp_path / "00-broken"
    broken.mkdir()
    (broken / "tasks.toml").write_text("[lesson]\n")
    result = run(app, "lesson", "validate", broken)
    assert result.exit_code == 2 and result.stderr.startswith("error: 00-broken/lesson.md: is missing")


def test_lesson_validate_fails_a_lesson_with_a_check_no_mutant_fails(app, tmp_path):
    """A check that cannot fail grades nothing: widen one check's tolerance until every mutant passes it, and
    the surviving mutants and the check are named, exit 2."""
    import shutil

    lesson = tmp_path / "00-toy"
    shutil.copytree(TOY, lesson)
    text = (lesson / "tasks.toml").read_text()
    wide = text.replace('params = { scale = 3 }\ncompare = "allclose"\nrtol = 1e-6',
                        'params = { scale = 3 }\ncompare = "below"\nbound = 1e9')
    assert wide != text
    (lesson / "tasks.toml").write_text(wide)
    result = run(app, "lesson", "validate", lesson)
    assert result.exit_code == 2, result.output
    assert "Mean intensity: scale = 3: no mutant fails this check" in result.stdout
    assert result.stderr.startswith("error: lesson: 00-toy does not validate")


def test_lesson_run_writes_a_report(app, tmp_path):
    result = run(app, "lesson", "run", TOY, "--report", tmp_path / "report", "--seed", 4)
    assert result.exit_code == 0, result.output
    assert "mean_intensity" in result.stdout and "report written to" in result.stdout
    assert (tmp_path / "report" / "index.html").is_file() and (tmp_path / "report" / "scene.html").is_file()
    result = run(app, "lesson", "run", TOY, "--report", tmp_path / "r2", "--dataset", "nope")
    assert result.exit_code == 2 and result.stderr.startswith("error: --dataset: no dataset 'nope'")


def test_grade_with_the_hook_switched_off_cannot_reach_the_reference(app, tmp_path):
    cheat = tmp_path / "cheat.py"
    cheat.write_text('import sys\nsys.modules["lab.lessons.child"].Guard.__call__ = lambda self, event, args: None\n'
                     "from lab.modules.calibration import estimate_homographies, estimate_intrinsics\n")
    result = run(app, "grade", "01-calibration", cheat, "--seed", 1)
    assert result.exit_code == 0, result.output
    assert ": 0 / 20 points" in result.stdout and "No module named 'lab.modules'" in result.stdout


def test_grade_without_bubblewrap_exits_2_naming_the_fix(app, monkeypatch):
    from lab.lessons import isolation

    monkeypatch.setattr(isolation, "default_isolation", lambda: isolation.Isolation(bwrap="/nonexistent/bwrap"))
    result = run(app, "grade", TOY, SUBMISSIONS / "toy" / "solution.py")
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: sandbox: ") and "--unsafe-sandbox" in lines[0]


def test_grade_with_unsafe_sandbox_runs_with_the_audit_hook_only(app, monkeypatch):
    from lab.lessons import isolation

    monkeypatch.setattr(isolation, "_unsafe_allowed", False)  # restored after the test
    result = run(app, "grade", TOY, SUBMISSIONS / "toy" / "solution.py", "--unsafe-sandbox", "--seed", 2)
    assert result.exit_code == 0, result.output
    assert "6 / 6 points" in result.stdout
    assert isolation.default_isolation().mode == "unsafe"
