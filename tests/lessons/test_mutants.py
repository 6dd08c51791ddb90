"""The mutants of lab/lessons/mutants.py and the generic detectors that name a student's mistake with them
(lab/lessons/checks.py, lab/lessons/messages.py): each on a known answer, each refusing what it does not
apply to, none triggered by the right answer."""

from __future__ import annotations

import numpy as np
import pytest

from lab.lessons import checks, messages, mutants
from lab.lessons.grader import grade

from lesson_helpers import submission


def pick_smallest(costs: np.ndarray, weights: np.ndarray, mask: np.ndarray, *, axis: int = 0) -> np.ndarray:
    """A reference of the shape the lessons' steps have: two same-shaped arrays, a mask, a control."""
    return np.argmin(np.where(mask, costs * weights, np.inf), axis=axis)


def by_name(function) -> dict[str, mutants.Mutant]:
    return {m.name: m for m in mutants.generic_mutants(function)}


COSTS = np.array([[1.0, 2.0, 1.0], [3.0, 2.0, 0.5], [1.0, 5.0, 4.0]])
WEIGHTS = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 2.0]])
MASK = np.array([[True, True, True], [True, True, False], [True, True, True]])


def test_a_step_gets_output_input_and_patch_mutants():
    names = set(by_name(pick_smallest))
    assert {"transposed", "negated", "float32", "shifted_first_axis", "argmax_for_argmin",
            "ties_other_way"} <= names
    assert {"swapped(costs, weights)", "swapped(costs, mask)", "mask_dropped(mask)"} <= names


def test_swapped_arguments_and_a_dropped_mask_call_the_reference_on_changed_inputs():
    found = by_name(pick_smallest)
    swapped = found["swapped(costs, weights)"](pick_smallest)(COSTS, WEIGHTS, MASK)
    np.testing.assert_array_equal(swapped, pick_smallest(WEIGHTS, COSTS, MASK))
    dropped = found["mask_dropped(mask)"](pick_smallest)(COSTS, WEIGHTS, MASK)
    np.testing.assert_array_equal(dropped, pick_smallest(COSTS, WEIGHTS, np.ones_like(MASK)))
    with pytest.raises(mutants.NotApplicable):  # bool mask and float costs: not the same kind of value
        found["swapped(costs, mask)"](pick_smallest)(COSTS, WEIGHTS, MASK.astype(float)[:2])
    with pytest.raises(mutants.NotApplicable):  # a mask that masks nothing cannot be dropped
        found["mask_dropped(mask)"](pick_smallest)(COSTS, WEIGHTS, np.ones_like(MASK))


def test_numpy_patches_change_the_call_only_and_say_when_they_do_not_apply():
    found = by_name(pick_smallest)
    original = np.argmin
    np.testing.assert_array_equal(pick_smallest(COSTS, WEIGHTS, MASK), [0, 0, 0])  # the first of equal minima
    ties = found["ties_other_way"](pick_smallest)(COSTS, WEIGHTS, MASK)
    np.testing.assert_array_equal(ties, [2, 1, 0])  # the last of equal minima
    largest = found["argmax_for_argmin"](pick_smallest)(COSTS, WEIGHTS, np.ones_like(MASK))
    np.testing.assert_array_equal(largest, np.argmax(COSTS * WEIGHTS, axis=0))
    assert np.argmin is original and np.argmin(np.array([2, 1, 1])) == 1  # NumPy is itself again
    with pytest.raises(mutants.NotApplicable):
        found["argmin_for_argmax"](pick_smallest)(COSTS, WEIGHTS, MASK)  # it never calls np.argmax


@pytest.mark.parametrize("name,array", [("transposed", np.zeros(4)), ("transposed", np.zeros((2, 3))),
                                        ("inverse", np.zeros((3, 3))), ("reversed", np.zeros(5)),
                                        ("float32", np.zeros(3, dtype=np.float32)),
                                        ("negated", np.zeros(3))])
def test_output_transforms_refuse_what_they_do_not_apply_to(name, array):
    with pytest.raises(mutants.NotApplicable):
        mutants.transform(name, array)


def test_a_typed_result_has_its_first_array_transformed():
    from lab.data.reconstruction import PointCloud

    cloud = PointCloud(np.arange(9.0).reshape(3, 3))
    negated = by_name(lambda points: points)["negated"](lambda points: cloud)(None)
    assert isinstance(negated, PointCloud)
    np.testing.assert_array_equal(negated.xyz, -cloud.xyz)


def test_same_set_matches_items_in_any_order_and_up_to_sign_where_asked():
    rng = np.random.default_rng(0)
    items = rng.normal(size=(4, 3, 4))
    assert checks.same_set(items[[2, 0, 3, 1]], items).passed
    assert not checks.same_set(items[[2, 0, 3, 1]] + 1e-3, items).passed
    flipped = items[[1, 0, 2, 3]] * np.array([1, -1, 1, -1])[:, None, None]
    assert not checks.same_set(flipped, items).passed
    assert checks.same_set(flipped, items, up_to="sign").passed
    duplicate = items[[0, 0, 2, 3]]  # each expected item is matched once
    outcome = checks.same_set(duplicate, items)
    assert not outcome.passed and "expected item 1" in outcome.expected


def test_a_reflection_is_named_and_a_rotation_is_not():
    from scipy.spatial.transform import Rotation

    rotations = Rotation.random(4, random_state=1).as_matrix()
    poses = np.concatenate([rotations, np.ones((4, 3, 1))], axis=2)
    reflected = poses.copy()
    reflected[2, :, :3] *= -1
    assert "has det -1 (item 2 of 4): a reflection, not a rotation" in checks.reflection(reflected, poses)
    assert checks.reflection(poses, poses) is None
    assert checks.permuted(reflected[[1, 0, 2, 3]], poses) is None  # a reflection is not "another order"


def test_dtype_differences_name_the_dtype_and_the_size():
    expected = np.linspace(0.1, 1.0, 7)
    text = checks.dtype_difference(expected.astype(np.float32), expected)
    assert "float32" in text and "float64" in text and "rounding" in text
    assert "integers" in checks.dtype_difference(np.floor(expected * 10).astype(int), expected * 10)
    assert checks.dtype_difference(expected, expected) is None
    assert checks.dtype_difference((expected + 1e-3).astype(np.float32), expected) is None  # not rounding


def test_a_wrong_shape_and_nan_get_a_named_hint():
    assert checks.structure_hint(np.zeros((5, 1)), np.zeros(5)).name == "shape"
    assert checks.structure_hint(np.zeros((3, 2)), np.zeros((2, 3))).name == "shape"
    assert checks.structure_hint(np.array([1.0, np.nan]), np.zeros(2)).name == "nan"
    assert checks.structure_hint(np.zeros(5), np.zeros(5)) is None


def test_a_detector_that_is_not_sure_asks():
    expected = np.arange(40.0)
    shifted = np.roll(expected, 1)
    got = shifted.copy()
    got[:3] = -7.0  # the edge filled another way: 37 of 40 entries match the shift
    mutant = by_name(pick_smallest)["shifted_first_axis"]
    (hint,) = messages.partial_match([(mutant, shifted)], got, expected)
    assert hint.name == "shifted_first_axis" and hint.text.endswith("is that the mistake?")
    assert "92 %" in hint.text
    assert messages.partial_match([(mutant, shifted)], expected, expected) == []  # the reference: no hint


def test_hint_lines_carry_their_names():
    text = messages.hints_text([checks.Hint("transposed", "rows and columns swapped"),
                                checks.Hint("other", "rows and columns swapped")])
    assert text == "\nHint: rows and columns swapped [transposed]"
    assert messages.hint_names("Failed: x\nHint: values in [0, 1] [clip]\nHint: no name here") == ["clip"]


@pytest.mark.parametrize("change,hint", [
    ("-np.array(", "negated"),
    ("np.float32(2.0) * np.array(", "scaled"),
])
def test_generic_hints_name_the_mistake_on_the_toy_lesson(toy_lesson, change, hint):
    """The toy lesson names no hint for these: the generic detectors do, tagged with their names."""
    source = submission("toy", "solution.py")
    assert "    return np.array(" in source
    report = grade(toy_lesson, source.replace("    return np.array(", f"    return {change}", 1), seed=3)
    lost = [t for t in report.tests if t.status == "failed" and t.task == "means"]
    assert lost and all(hint in t.hints for t in lost if "normalized" not in t.name), [t.output for t in lost]
    assert all(f"[{hint}]" in t.output for t in lost if hint in t.hints)
