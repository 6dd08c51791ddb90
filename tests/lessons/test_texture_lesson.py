"""lessons/07-texture: the reference scores full marks and the starter zero, students' own solutions
(written as lesson.md suggests, or with OpenCV) score full marks on several assignment seeds, each
wrong implementation loses exactly the checks its docstring lists, and the messages say what to
fix: every check a wrong fixture fails carries a hint named on its ``# cause:`` line, and no other.

Issue 15's failures of this lesson, each with its fixture:
- a cut breaking ties to the right scored 20/20 (the check data never tied): the overlaps now have
  variants quantised to multiples of 1/8 and 1/4 (``procedural(quantize=...)``), where many paths
  tie exactly (wrong_cut_ties_to_the_right.py, mistakes.cut_ties_to_the_right);
- distances by the expanded square lost the match check when their smallest entry was a rounding-level
  negative (match_window: "high <= 0"): match_window reads those as 0 and candidates_within always
  keeps the smallest (correct_expanded_distances.py);
- a transposed distance map got no hint naming it (wrong_distances_transposed.py).

Assignment seeds are fixed here; each fixture is graded once per module (:func:`graded`).
"""

from __future__ import annotations

import ast
import importlib.util
import re
import time

import numpy as np
import pytest

from lab.core import InvalidValue
from lab.data.textures import procedural
from lab.lessons.format import load_lesson
from lab.lessons.grader import grade
from lab.modules.texture import (candidates_within, match_window, min_error_boundary_cut, min_error_cut,
                                 pick_query_window)

from lesson_helpers import REPO, SUBMISSIONS, failed, graded_once, submission

SEED = 20011999
WRONG = sorted(p.name for p in (SUBMISSIONS / "texture").glob("wrong_*.py"))
CORRECT = sorted(p.name for p in (SUBMISSIONS / "texture").glob("correct_*.py"))
CUT = "Minimum-error boundary cut"
SSD = "Masked, Gaussian-weighted SSD"


@pytest.fixture(scope="module")
def texture_lesson():
    return load_lesson(REPO / "lessons" / "07-texture")


@pytest.fixture(scope="module")
def graded(texture_lesson):
    """``graded(name)``: the report of fixture ``name`` under SEED, graded once per module."""
    return graded_once(texture_lesson, "texture", SEED)


def listed_failures(name: str) -> set[str]:
    doc = ast.get_docstring(ast.parse(submission("texture", name))) or ""
    return {line[2:].strip() for line in doc.partition("Fails exactly these checks")[2].splitlines()
            if line.startswith("- ")}


def causes(name: str) -> set[str]:
    """The hint names of fixture ``name``'s ``# cause:`` line."""
    found = re.search(r"^# cause: (.+)$", submission("texture", name), re.M)
    assert found, f"{name} has no '# cause:' line"
    return {c.strip() for c in found.group(1).split(",")}


def hint_names(output: str) -> set[str]:
    return set(re.findall(r"^Hint: .* \[([^\]]+)\]$", output, re.M))


def fixture_module(name: str):
    spec = importlib.util.spec_from_file_location(name[:-3], SUBMISSIONS / "texture" / name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_lesson_has_two_tasks_on_steps_of_the_texture_module(texture_lesson):
    assert texture_lesson.module == "texture" and texture_lesson.points == 20.0
    assert [t.step for t in texture_lesson.tasks] == ["window_distances", "min_error_cut"]
    assert len(WRONG) >= 10 and len(CORRECT) >= 2


def test_reference_full_marks_and_starter_zero(texture_lesson):
    reference = grade(texture_lesson, reference=True, seed=SEED)
    assert reference.score == reference.max_score == 20.0
    starter = grade(texture_lesson, texture_lesson.starter, seed=SEED)
    assert starter.score == 0.0
    assert all(t.status == "failed" and "NotImplementedError" in t.output for t in starter.tests)


@pytest.mark.parametrize("name", ["solution.py", *CORRECT])
def test_correct_solutions_score_full_marks_on_several_assignment_seeds(texture_lesson, name):
    """Correct code written differently (loops; the expanded square with scipy.signal.correlate and a DP
    with back-pointers; cv2.matchTemplate in float32) gets full marks whatever the assignment seed, and
    grading one submission takes well under a second of work (printed with -s)."""
    source = submission("texture", name)
    for seed in (SEED, 1, 2, 3, 4, 5):
        started = time.perf_counter()
        report = grade(texture_lesson, source, seed=seed)
        seconds = time.perf_counter() - started
        assert report.score == 20.0, (seed, failed(report))
    print(f"\ngrading {name} took {seconds:.2f} s")


@pytest.mark.parametrize("name", WRONG)
def test_each_wrong_implementation_loses_exactly_its_checks(graded, name):
    report = graded(name)
    expected = listed_failures(name)
    assert expected and expected <= {t.name for t in report.tests}
    lost = failed(report)
    assert set(lost) == expected
    assert report.score == 20.0 - sum(t.max_score for t in report.tests if t.name in lost)
    for output in lost.values():
        assert "Failed:" in output and ("Expected:" in output or "the reference gets" in output)


@pytest.mark.parametrize("name", WRONG)
def test_every_check_a_mistake_fails_names_its_cause_and_no_other(graded, name):
    """Each failed check carries a hint named on the fixture's ``# cause:`` line (a [hints] key, a function
    of mistakes.py or a generic mutant), and none outside it."""
    wanted = causes(name)
    for check, output in failed(graded(name)).items():
        given = hint_names(output)
        assert given & wanted, f"{check}: no hint of {sorted(wanted)}:\n{output}"
        assert given <= wanted, f"{check}: hints {sorted(given - wanted)} name another mistake"


def test_the_unweighted_ssd_is_told_to_use_the_gaussian(graded):
    report = graded("wrong_unweighted.py")
    output = failed(report)[f"{SSD}: gray sample: the reference's distances to every window"]
    assert output.startswith("Check: gray sample: the reference's distances to every window\n")
    assert "a 24 x 24 grayscale procedural texture" in output
    assert "Hint: your distances are the unweighted SSD" in output and "sigma = w / 6.4" in output


def test_the_missing_normalization_is_recognised(graded):
    report = graded("wrong_not_normalized.py")
    output = failed(report)[f"{SSD}: gray sample: the reference's distances to every window"]
    assert "Hint: divide each sum by the total weight of the known pixels" in output


def test_a_transposed_distance_map_is_named(graded):
    """Issue 15: the generic transposed detector was not tried on the distance map. Every check the
    transposed map fails, the match drawn from it included, says it is transposed."""
    lost = failed(graded("wrong_distances_transposed.py"))
    assert len(lost) == 5
    for output in lost.values():
        assert "Hint: your distance map is transposed" in output and "[distances_transposed]" in output


def test_a_jumping_cut_fails_the_connectivity_check_with_the_reference_value(graded):
    report = graded("wrong_row_argmin_cut.py")
    output = failed(report)[f"{CUT}: the cut is connected: neighbouring rows at most one column apart"]
    assert "metric cut_max_step after running the pipeline to join_blocks" in output
    assert "the reference gets 1" in output


def test_the_cut_checks_run_on_data_with_exact_ties(texture_lesson):
    """The overlaps' batteries hold quantised variants, and on them a cut breaking ties to the right is
    not the reference's on any of the tests' assignment seeds (it is the same on continuous data)."""
    for name, quantize in (("overlap", 8), ("wide", 4)):
        data = texture_lesson.datasets[name]
        options = [data.options_of(k) for k in range(len(data.variants))]
        assert {o.get("quantize", 0) for o in options} == {0, quantize}
        assert "ties" in data.describe(1)
    lost = failed(grade(texture_lesson, submission("texture", "wrong_cut_ties_to_the_right.py"), seed=7))
    ties = "the reference's cut (the leftmost of equal totals on ties)"
    assert set(lost) == {f"{CUT}: a 24 x 6 overlap: {ties}", f"{CUT}: a 20 x 10 overlap: {ties}"}
    for output in lost.values():
        assert "Variant 1:" not in output and "rounded to multiples of" in output
        assert "[cut_ties_to_the_right]" in output and "take the leftmost" in output


def test_quantised_textures_tie_exactly(texture_lesson):
    """procedural(quantize=8): values are multiples of 1/8, so squared differences and their sums are exact
    and equal path costs tie: the rightmost-on-ties cut (mistakes.py) differs from the reference's cut
    on most overlaps, and costs exactly as much."""
    ties_right = texture_lesson.mistakes["cut_ties_to_the_right"]
    rng = np.random.default_rng(3)
    differ = 0
    for seed in range(20):
        pixels = procedural(pattern="noise", size=40, quantize=8, seed=seed).state["sample"].pixels
        assert np.array_equal(pixels * 8, np.rint(pixels * 8))
        (t1, l1), (t2, l2) = rng.integers(0, 17, size=(2, 2))
        errors = (pixels[t1:t1 + 24, l1:l1 + 6].astype(np.float64) - pixels[t2:t2 + 24, l2:l2 + 6]) ** 2
        cut, other = min_error_boundary_cut(errors), ties_right(errors)
        rows = np.arange(24)
        assert errors[rows, cut].sum() == errors[rows, other].sum()
        differ += not np.array_equal(cut, other)
    assert differ >= 15


def test_the_expanded_square_gets_a_match_also_when_its_best_distance_is_below_zero():
    """Issue 15: the expansion q^2 - 2 q s + s^2 gives -5.7e-17 where the query's own window is compared;
    match_window kept no candidate ("high <= 0"). Now a rounding-level negative reads as 0, and the
    match is the query's origin on every seed, those with a negative best distance included."""
    expanded = fixture_module("correct_expanded_distances.py")
    negative = 0
    for seed in range(30):
        sample = procedural(pattern="blobs", size=24, seed=seed).state["sample"]
        query = pick_query_window(sample, window=7, known_fraction=0.5, rng=np.random.default_rng(seed))
        distances = expanded.window_distances(sample, query.query_window, query.query_mask)
        negative += distances.min() < 0
        match = match_window(sample, distances, rng=np.random.default_rng(seed))
        assert match.chosen_match.tolist() == query.query_origin.tolist()
    assert negative >= 3  # the fixture does exercise the case


def test_candidates_keep_the_smallest_entry_whatever_its_sign():
    assert candidates_within(np.array([[-5.7e-17, 0.2], [0.0, 0.3]]), 0.1).tolist() == [0]
    assert candidates_within(np.array([0.5, 0.52, 0.6]), 0.1).tolist() == [0, 1]


def test_match_window_refuses_distances_that_are_no_rounding(texture_lesson):
    """A clearly negative or NaN distance is the student's value, named in the message (not a crash)."""
    sample = procedural(pattern="blobs", size=24, seed=0).state["sample"]
    distances = np.full((18, 18), 0.1)
    distances[3, 4] = -0.05
    with pytest.raises(InvalidValue, match=r"negative entries, the smallest -0\.05.*never negative"):
        match_window(sample, distances, rng=np.random.default_rng(0))
    distances[3, 4] = np.nan
    with pytest.raises(InvalidValue, match="1 NaN"):
        match_window(sample, distances, rng=np.random.default_rng(0))


def test_the_cut_mistakes_on_a_known_surface(texture_lesson):
    """The wrong cuts of mistakes.py on a surface where each differs from the cut: the cheapest path avoids
    the 0 of the first row (its neighbours below cost 9), the greedy walk takes it; the cheapest path
    is the last column, which a cut that never steps left cannot reach from the top row's best start."""
    errors = np.array([[5.0, 0.0, 5.0, 1.0],
                       [9.0, 9.0, 9.0, 1.0],
                       [9.0, 9.0, 9.0, 1.0],
                       [0.0, 9.0, 9.0, 1.0]])
    mistakes = texture_lesson.mistakes
    assert min_error_cut(errors).tolist() == [3, 3, 3, 3]
    assert mistakes["cut_greedy_from_first_row"](errors).tolist() == [1, 0, 0, 0]
    assert mistakes["cut_each_row_alone"](errors).tolist() == [1, 3, 3, 0]
    assert mistakes["cut_bottom_to_top"](np.array([[0.0, 1.0], [1.0, 0.0]])).tolist() == [1, 0]
    ties = np.zeros((3, 3))
    assert min_error_cut(ties).tolist() == [0, 0, 0]
    assert mistakes["cut_ties_to_the_right"](ties).tolist() == [2, 2, 2]
    left_turn = np.array([[9.0, 0.0], [0.0, 9.0]])
    assert min_error_cut(left_turn).tolist() == [1, 0]
    assert mistakes["cut_never_stepping_left"](left_turn).tolist() == [0, 0]


def test_lesson_md_states_the_rules_the_checks_grade():
    text = (REPO / "lessons" / "07-texture" / "lesson.md").read_text()
    assert "On ties, take the **leftmost** column" in text
    assert "5e-6" in text and "float32" in text and "rounded to" in text
    assert "fresh, hidden seeds" not in text
