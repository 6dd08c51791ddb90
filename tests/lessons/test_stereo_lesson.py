"""lessons/03-stereo beyond the generic checks of test_every_lesson.py: students' own correct solutions
(SciPy's uniform_filter; cv2.boxFilter on the whole volume; summed-area tables with the expanded
square) score full marks on several assignment seeds (and how long grading takes), the starter
scores zero, each wrong implementation loses exactly the checks its docstring lists, and every check
it fails carries a hint named on its ``# cause:`` line and no other.

Assignment seeds are fixed here; each fixture is graded once per module (:func:`graded`).
"""

from __future__ import annotations

import ast
import re
import time

import numpy as np
import pytest

from lab.core import Image
from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules.stereo import cost_volume, left_right_check, winner_take_all

from lesson_helpers import REPO, SUBMISSIONS, failed, graded_once, submission

SEED = 20261122
WRONG = sorted(p.name for p in (SUBMISSIONS / "stereo").glob("wrong_*.py"))
CORRECT = sorted(p.name for p in (SUBMISSIONS / "stereo").glob("correct_*.py"))

COST = "SSD and NCC cost volumes"
WTA = "Winner-take-all"
LR = "Left-right consistency check"


@pytest.fixture(scope="module")
def stereo_lesson():
    return load_lesson(REPO / "lessons" / "03-stereo")


@pytest.fixture(scope="module")
def graded(stereo_lesson):
    """``graded(name)``: the report of fixture ``name`` under SEED, graded once per module."""
    return graded_once(stereo_lesson, "stereo", SEED)


def listed_failures(name: str) -> set[str]:
    doc = ast.get_docstring(ast.parse(submission("stereo", name))) or ""
    return {line[2:].strip() for line in doc.partition("Fails exactly these checks")[2].splitlines()
            if line.startswith("- ")}


def causes(name: str) -> set[str]:
    """The hint names of fixture ``name``'s ``# cause:`` line."""
    found = re.search(r"^# cause: (.+)$", submission("stereo", name), re.M)
    assert found, f"{name} has no '# cause:' line"
    return {c.strip() for c in found.group(1).split(",")}


def hint_names(output: str) -> set[str]:
    return set(re.findall(r"^Hint: .* \[([^\]]+)\]$", output, re.M))


def test_the_lesson_grades_the_three_steps_of_block_matching(stereo_lesson):
    assert stereo_lesson.module == "stereo" and stereo_lesson.points == 20.0
    assert [t.step for t in stereo_lesson.tasks] == ["cost_volume", "winner_take_all", "left_right_check"]
    assert {d.dataset for d in stereo_lesson.datasets.values()} == {"synthetic", "motorcycle"}
    synthetic = stereo_lesson.datasets["synthetic"]
    assert synthetic.seed is None and len(synthetic.variants) == 2  # two draws from the assignment seed
    assert len(WRONG) >= 10 and len(CORRECT) >= 2


def test_reference_full_marks_and_starter_zero(stereo_lesson):
    assert grade(stereo_lesson, reference=True, seed=SEED).score == 20.0
    starter = grade(stereo_lesson, stereo_lesson.starter, seed=SEED)
    assert starter.score == 0.0
    assert all("NotImplementedError" in t.output for t in starter.tests)


@pytest.mark.parametrize("name", ["solution.py", *CORRECT])
def test_correct_solutions_score_full_marks_and_grading_time_is_reported(stereo_lesson, name):
    """Correct code written differently from the reference (other box filters, other argmin formulations,
    the right image's disparities by loops or its own volume) gets full marks on several assignment
    seeds; the time one grading takes is printed (pytest -s)."""
    source = submission("stereo", name)
    for seed in (SEED, 3, 11):
        started = time.perf_counter()
        report = grade(stereo_lesson, source, seed=seed)
        seconds = time.perf_counter() - started
        assert report.score == 20.0, (seed, failed(report))
    print(f"\ngrading {name} took {seconds:.1f} s")


@pytest.mark.parametrize("name", WRONG)
def test_each_wrong_implementation_loses_exactly_its_checks(graded, name):
    report = graded(name)
    expected = listed_failures(name)
    assert expected and expected <= {t.name for t in report.tests}
    lost = failed(report)
    assert set(lost) == expected
    assert report.score == 20.0 - sum(t.max_score for t in report.tests if t.name in lost)
    for output in lost.values():
        assert ("Failed:" in output and ("Expected:" in output or "the reference gets" in output)) \
            or "returned a value of the wrong form" in output  # a volume one disparity short


@pytest.mark.parametrize("name", WRONG)
def test_every_check_a_mistake_fails_names_its_cause_and_no_other(graded, name):
    """Each failed check carries a hint named on the fixture's ``# cause:`` line (a [hints] key, a function
    of lessons/03-stereo/mistakes.py or a generic mutant), and none outside it."""
    wanted = causes(name)
    for check, output in failed(graded(name)).items():
        given = hint_names(output)
        assert given & wanted, f"{check}: no hint of {sorted(wanted)}:\n{output}"
        assert given <= wanted, f"{check}: hints {sorted(given - wanted)} name another mistake"


def test_the_missing_window_aggregation_is_told_what_to_fix(graded):
    lost = failed(graded("wrong_no_window_aggregation.py"))
    assert set(lost) == {name for name in listed_failures("wrong_no_window_aggregation.py")}
    ssd = lost[f"{COST}: synthetic pair, SSD over 5 x 5 windows: the reference's cost volume"]
    assert ssd.startswith("Check: synthetic pair, SSD over 5 x 5 windows: the reference's cost volume\n")
    assert "Failed on 2 of the 2 variants" in ssd and "a rendered rectified pair" in ssd
    assert "Expected:\n" in ssd and "Got:\n" in ssd
    assert "Hint: your costs are those of single pixels (window = 1)" in ssd
    ncc = lost[f"{COST}: motorcycle, NCC over 5 x 5 windows: the reference's cost volume (1 - NCC)"]
    assert "every window is flat and NCC is 0" in ncc
    wta = lost[f"{COST}: synthetic pair, SSD: winner-take-all on your cost volume is as accurate as on the "
               "reference's (bad-2 over all pixels)"]
    assert "metric bad2_all after running the pipeline to winner_take_all on your cost_volume" in wta
    assert "Hint: your costs are those of single pixels" in wta


def test_the_window_sum_instead_of_the_mean_is_recognised(graded):
    lost = failed(graded("wrong_ssd_sum_not_mean.py"))
    assert len(lost) == 2  # winner-take-all does not see the factor
    for output in lost.values():
        assert ("Hint: your SSD is the window's sum, the lab's is its mean: divide by window * window"
                in output)


def test_the_exact_left_right_match_is_recognised(graded):
    lost = failed(graded("wrong_lr_check_exact_match.py"))
    assert all(name.startswith(LR) for name in lost) and len(lost) == 3
    mask = lost[f"{LR}: synthetic pair, max_difference = 1: the reference's mask"]
    assert "Hint: your mask keeps only pixels whose two disparities are equal" in mask
    assert f"{LR}: synthetic pair, max_difference = 0: the reference's mask" not in lost
    pipeline = lost[f"{LR}: synthetic pair: the filtered disparity map built on your mask, bad-2 over all "
                    "pixels as the reference's"]
    assert "after running the pipeline to filter_disparity on your consistent" in pipeline


@pytest.mark.parametrize("fixture,task,hint", [
    ("wrong_cost_shift_direction.py", COST, "your volume compares left pixel x with right pixel x + d"),
    ("wrong_shift_wraps_around.py", COST, "your shift wraps around to the right image's other edge"),
    ("wrong_box_filter_reflects_borders.py", COST, "your window means reflect the image"),
    ("wrong_wta_argmax.py", WTA, "you keep the disparity of the highest cost"),
    ("wrong_wta_last_of_ties.py", WTA, "of equal lowest costs you keep the last disparity"),
    ("wrong_lr_check_direction.py", LR, "you read the right image's disparity at x + d_L"),
    ("wrong_lr_check_left_disparity.py", LR, "with the left image's own disparity at x - d_L"),
    ("wrong_lr_check_keeps_outside.py", LR, "must fail the check: you compare them with column 0"),
])
def test_mistakes_visible_only_in_the_steps_inputs_are_named(graded, fixture, task, hint):
    """lessons/03-stereo/mistakes.py: the grader runs the known wrong implementation on the same inputs, so
    a shift the wrong way, a border rule, an argmax or the other tie rule gets its hint on every check
    it fails, and no other wrong fixture is told it."""
    lost = failed(graded(fixture))
    assert lost and all(name.startswith(task) for name in lost)
    for output in lost.values():
        assert any(hint in line for line in output.splitlines() if line.startswith("Hint: ")), output
    for other in WRONG:
        if other != fixture:
            assert not any(hint in output for output in failed(graded(other)).values()), other


def test_the_tie_rule_is_graded_where_costs_tie(graded):
    """Costs tie left of the border (several disparities compare the same repeated column 0): the
    last-of-ties loop loses both disparity checks, and the filtered map (those pixels are holes) is
    unaffected."""
    lost = failed(graded("wrong_wta_last_of_ties.py"))
    assert set(lost) == {f"{WTA}: synthetic pair: the reference's disparities on an SSD volume",
                         f"{WTA}: motorcycle: the reference's disparities on an NCC volume (the first of "
                         "equal costs, as near the left border)"}
    for output in lost.values():
        assert "[winner_take_all_last_of_ties]" in output


def test_the_lessons_conventions_are_the_modules():
    """What lesson.md and starter.py promise, on a tiny pair: flat NCC windows cost 1, ties take the first
    disparity, and a match left of the right image fails the check."""
    flat = Image(np.full((9, 12), 0.5, np.float32))
    volume = cost_volume(flat, flat, cost="ncc", window=3, max_disparity=4)
    np.testing.assert_array_equal(volume, 1.0)
    assert np.all(winner_take_all(volume) == 0)
    consistent = left_right_check(volume, np.full((9, 12), 2), max_difference=2)  # d_R = 0 on ties
    assert not consistent[:, :2].any() and consistent[:, 2:].all()


def test_lesson_md_says_how_the_data_is_drawn():
    text = (REPO / "lessons" / "03-stereo" / "lesson.md").read_text()
    assert "assignment's secret seed" in text and "fresh hidden seed" not in text
    assert "two\ndraws" in text or "two draws" in text
