"""Step introspection: signature -> inputs, controls, outputs, JSON Schema; control coercion."""

from __future__ import annotations

from typing import Annotated, Generator, Literal

import jsonschema
import numpy as np
import pytest

from lab.core.step import step_result
from lab.core import InvalidControl, Progress, Range, describe_step, metric
from lab.core.values import ImageSet, Points2D


@step_result
class Found:
    corners: Points2D
    count: int = metric("corners found")


def find(images: ImageSet, mask: np.ndarray | None = None, *,
         window: Annotated[int, Range(3, 21)] = 11,
         sigma: Annotated[float, Range(0.0, 5.0)] = 1.5,
         method: Literal["harris", "shi_tomasi"] = "harris",
         refine: bool = True,
         size: tuple[int, int] = (9, 6),
         label: str = "corners",
         rng: np.random.Generator) -> Found:
    """Find corners.

    A longer paragraph that is not the summary.

    Args:
        images: the views.
        window: side of the search window
            in pixels.
        sigma: smoothing.
        method: which detector.

    Reference: somewhere.
    """
    raise NotImplementedError


def homography(points: np.ndarray, *, normalize: bool = True) -> Annotated[np.ndarray, "homographies"]:
    """One value, named by the annotation."""
    return points


def long_step(x: np.ndarray, *, n: Annotated[int, Range(1, 10)] = 3) -> Generator[Progress, None, Found]:
    """A generator step."""
    yield Progress(0)
    raise NotImplementedError


def test_inputs_controls_outputs_are_read_from_the_signature():
    spec = describe_step(find)
    assert spec.reads == ("images", "mask")
    assert [i.optional for i in spec.inputs] == [False, True]
    assert [c.name for c in spec.controls] == ["window", "sigma", "method", "refine", "size", "label"]
    assert spec.runner_args == ("rng",)
    assert spec.writes == ("corners",)
    assert [o.name for o in spec.outputs if o.is_metric] == ["count"]
    assert spec.summary == "Find corners."
    assert not spec.is_generator


def test_docstring_describes_controls_with_continuation_lines():
    spec = describe_step(find)
    assert spec.control("window").description == "side of the search window in pixels."
    assert spec.control("method").description == "which detector."
    assert spec.control("refine").description == ""


def test_json_schema_is_valid_and_validates_requests():
    schema = describe_step(find).json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    assert validator.is_valid({"window": 5, "method": "shi_tomasi", "size": [7, 5]})
    assert not validator.is_valid({"window": 50})
    assert not validator.is_valid({"method": "sobel"})
    assert not validator.is_valid({"unknown": 1})
    props = schema["properties"]
    assert props["window"] == {"type": "integer", "minimum": 3, "maximum": 21, "default": 11, "title": "window",
                               "description": "side of the search window in pixels."}
    assert props["method"]["enum"] == ["harris", "shi_tomasi"]
    assert props["size"]["default"] == [9, 6]


def test_single_value_output_is_named_by_annotation_and_generators_are_detected():
    assert describe_step(homography).writes == ("homographies",)
    spec = describe_step(long_step)
    assert spec.is_generator
    assert spec.result_type is Found


@pytest.mark.parametrize("params, expected", [
    ({}, {"window": 11, "sigma": 1.5, "method": "harris", "refine": True, "size": (9, 6), "label": "corners"}),
    ({"window": "7", "sigma": "0.5", "refine": "false", "size": "7x5"},
     {"window": 7, "sigma": 0.5, "method": "harris", "refine": False, "size": (7, 5), "label": "corners"}),
    ({"window": 7.0, "size": [3, 4]}, {"window": 7, "size": (3, 4)}),
])
def test_controls_are_coerced_from_json_and_cli_text(params, expected):
    values = describe_step(find).coerce_controls(params)
    for key, value in expected.items():
        assert values[key] == value and type(values[key]) is type(value)


@pytest.mark.parametrize("params, field, words", [
    ({"window": 2}, "window", "at least 3"),
    ({"window": 22}, "window", "at most 21"),
    ({"window": 7.5}, "window", "integer"),
    ({"window": "seven"}, "window", "integer"),
    ({"window": True}, "window", "number"),
    ({"sigma": float("nan")}, "sigma", "finite"),
    ({"method": "sobel"}, "method", "one of"),
    ({"refine": "maybe"}, "refine", "true or false"),
    ({"size": [1, 2, 3]}, "size", "2 values"),
    ({"label": 3}, "label", "string"),
    ({"windw": 3}, "windw", "controls are"),
])
def test_bad_controls_name_the_field_and_the_reason(params, field, words):
    with pytest.raises(InvalidControl) as info:
        describe_step(find).coerce_controls(params)
    assert info.value.field == field
    assert words in info.value.reason


def test_signatures_that_break_the_rules_are_refused():
    def star(*images):  # noqa: ANN002
        return None

    def bad_control(images: ImageSet, *, mapping: dict = None):  # noqa: RUF013
        return None

    def bad_input_default(images: ImageSet = 3):  # noqa: ANN001
        return None

    for func in (star, bad_control, bad_input_default):
        with pytest.raises(TypeError):
            describe_step(func)
