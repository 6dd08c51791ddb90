"""Step introspection: a typed function's signature becomes inputs, controls and a JSON Schema.

A step (DESIGN.md section 1) is a pure function. Positional parameters are *inputs* read from the
session's state by name; keyword-only parameters are *controls*, whose annotation and default
become the viewer's widget, the REST schema, the CLI option and what a lesson may fix. The return
value is a frozen dataclass whose fields are written back into state by name, except fields
declared with :func:`metric`, which are the numbers a user should see; or one value, written
under the name given by ``-> Annotated[T, "name"]`` (default: the step's name). Lesson steps use
the one-value form, so a student's function returns a plain array. Long steps are generators that
yield :class:`Progress` and return the result.

    def detect(images: ImageSet, *, window: Annotated[int, Range(3, 21)] = 11,
               method: Literal["a", "b"] = "a", rng: np.random.Generator) -> DetectResult: ...
"""

from __future__ import annotations

import collections.abc
import dataclasses
import enum
import inspect
import re
import typing
from dataclasses import dataclass
from collections.abc import Callable, Mapping
from typing import Annotated, Any, Literal, TypeVar, dataclass_transform, get_args

import numpy as np

from lab.core.errors import InvalidControl

#: Keyword names supplied by the runner, never shown as controls.
RUNNER_SUPPLIED = frozenset({"rng", "device"})

#: The kinds of control a front end draws: a number field, a checkbox, a text box, a dropdown, a tuple.
ControlKind = Literal["float", "int", "bool", "str", "choice", "tuple"]
ScalarKind = Literal["float", "int", "bool", "str"]

_T = TypeVar("_T")


class _WarningsMarker:
    """The marker inside :data:`Warnings` (``Annotated`` metadata): this field goes to the run record."""

    def __repr__(self) -> str:
        return "Warnings"


#: A result field typed ``Warnings`` carries the step's warnings to the run record (and the
#: viewer's status line); it is never written to state. ``warnings: Warnings = ()``.
Warnings = Annotated[tuple[str, ...], _WarningsMarker()]


@dataclass(frozen=True)
class Range:
    """Inclusive bounds of a numeric control: ``Annotated[float, Range(0.1, 10.0)]``."""

    minimum: float | None = None
    maximum: float | None = None


@dataclass(frozen=True)
class Progress:
    """A snapshot yielded by a long step: the viewer animates it, REST streams it, the CLI shows a bar.

    ``values`` holds typed values to draw as a live preview (e.g. the current point cloud).
    """

    iteration: int
    total: int | None = None
    loss: float | None = None
    message: str = ""
    values: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"iteration": self.iteration, "total": self.total,
                "loss": None if self.loss is None else float(self.loss), "message": self.message}


def metric(description: str = "", *, unit: str = "") -> Any:
    """Declare a result field as a metric: recorded in history and shown, not written to state.

    Metrics are scalars (float, int, bool).
    """
    return dataclasses.field(metadata={"metric": True, "description": description, "unit": unit})


@dataclass_transform(frozen_default=True, field_specifiers=(dataclasses.field, metric))
def step_result(cls: type[_T]) -> type[_T]:
    """Make ``cls`` a frozen dataclass that a step returns: each field is written to state by name.

    The mark is what tells a result apart from a value type: a step annotated ``-> Image`` writes
    one value (an image), a step annotated ``-> Calibration`` (marked) writes Calibration's fields.
    Fields declared with :func:`metric` are metrics; a field typed :data:`Warnings` goes to the run
    record. Corresponds to ``@dataclasses.dataclass(frozen=True)`` plus that mark.
    """
    made = dataclasses.dataclass(frozen=True)(cls)
    made.__step_result__ = True  # type: ignore[attr-defined]
    return made


def is_step_result(annotation: Any) -> bool:
    """Whether ``annotation`` is a class marked with :func:`step_result` (not one inherited from)."""
    return isinstance(annotation, type) and annotation.__dict__.get("__step_result__", False) is True


def is_warnings(annotation: Any) -> bool:
    """Whether a result field's annotation is :data:`Warnings`."""
    return typing.get_origin(annotation) is Annotated and any(
        isinstance(extra, _WarningsMarker) for extra in get_args(annotation)[1:])


@dataclass(frozen=True)
class Control:
    """One keyword-only parameter of a step, with everything a front end needs to show it."""

    name: str
    kind: ControlKind
    default: Any
    description: str = ""
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[Any, ...] = ()
    item_kinds: tuple[ScalarKind, ...] = ()  # for kind == "tuple"
    required: bool = False

    def json_schema(self) -> dict[str, Any]:
        schema: dict[str, Any]
        base = {"float": "number", "int": "integer", "bool": "boolean", "str": "string"}
        if self.kind in base:
            schema = {"type": base[self.kind]}
        elif self.kind == "choice":
            schema = {"enum": list(self.choices)}
        else:  # tuple
            schema = {"type": "array", "prefixItems": [{"type": base[k]} for k in self.item_kinds],
                      "minItems": len(self.item_kinds), "maxItems": len(self.item_kinds)}
        if self.minimum is not None:
            schema["minimum"] = self.minimum
        if self.maximum is not None:
            schema["maximum"] = self.maximum
        if not self.required:
            schema["default"] = list(self.default) if isinstance(self.default, tuple) else self.default
        schema["title"] = self.name
        if self.description:
            schema["description"] = self.description
        return schema

    def coerce(self, value: Any) -> Any:
        """Check and convert a user-supplied value (JSON, CLI text or Python); raise InvalidControl."""
        where = self.name
        if self.kind == "choice":
            if value in self.choices:
                return value
            if isinstance(value, str):
                for choice in self.choices:
                    if str(choice) == value:
                        return choice
            raise InvalidControl(where, f"must be one of {list(self.choices)}, got {value!r}")
        if self.kind == "tuple":
            if isinstance(value, str):  # "9x6", "9, 6", "(9 6)"; an "x" splits only numbers
                numeric = all(k in ("int", "float") for k in self.item_kinds)
                separators = r"[,x\s]+" if numeric else r"\s*,\s*"
                value = [v for v in re.split(separators, value.strip("()[] ")) if v]
            if not isinstance(value, (list, tuple)) or len(value) != len(self.item_kinds):
                raise InvalidControl(where, f"must be a list of {len(self.item_kinds)} values, got {value!r}")
            return tuple(_coerce_scalar(f"{where}[{i}]", k, v, self.minimum, self.maximum)
                         for i, (k, v) in enumerate(zip(self.item_kinds, value, strict=True)))
        return _coerce_scalar(where, self.kind, value, self.minimum, self.maximum)


def coerce_controls(controls: tuple[Control, ...], params: Mapping[str, Any] | None, *,
                    owner: str, noun: str = "control") -> dict[str, Any]:
    """Defaults overridden by ``params``, each checked by :meth:`Control.coerce`; unknown names are an error.

    The one way every front end checks a step's controls and a dataset's options: both raise
    :class:`InvalidControl` naming the control. ``owner`` names the step or dataset in messages.
    """
    given = dict(params or {})
    values: dict[str, Any] = {}
    for control in controls:
        if control.name in given:
            values[control.name] = control.coerce(given.pop(control.name))
        elif control.required:
            raise InvalidControl(control.name, f"{owner} needs {control.name!r}")
        else:
            values[control.name] = control.default
    if given:
        unknown = next(iter(given))
        raise InvalidControl(unknown, f"{owner} has no {noun} {unknown!r}; "
                                      f"{noun}s are {[c.name for c in controls]}")
    return values


def _coerce_scalar(where: str, kind: str, value: Any, minimum: float | None, maximum: float | None) -> Any:
    if kind == "bool":
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "on", "false", "0", "no", "off"):
            return value.lower() in ("true", "1", "yes", "on")
        raise InvalidControl(where, f"must be true or false, got {value!r}")
    if kind == "str":
        if not isinstance(value, str):
            raise InvalidControl(where, f"must be a string, got {type(value).__name__}")
        return value
    if isinstance(value, bool) or value is None:
        raise InvalidControl(where, f"must be a number, got {value!r}")
    if isinstance(value, str):
        try:
            value = float(value) if kind == "float" else int(value, 10)
        except ValueError:
            wanted = "a number" if kind == "float" else "an integer"
            raise InvalidControl(where, f"must be {wanted}, got {value!r}") from None
    if kind == "int":
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            value = int(value)
        if not isinstance(value, (int, np.integer)):
            raise InvalidControl(where, f"must be an integer, got {value!r}")
        value = int(value)
    else:
        if not isinstance(value, (int, float, np.integer, np.floating)):
            raise InvalidControl(where, f"must be a number, got {type(value).__name__}")
        value = float(value)
        if not np.isfinite(value):
            raise InvalidControl(where, f"must be finite, got {value!r}")
    if minimum is not None and value < minimum:
        raise InvalidControl(where, f"must be at least {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise InvalidControl(where, f"must be at most {maximum}, got {value}")
    return value


@dataclass(frozen=True)
class Input:
    """One positional parameter: a state value read by name, with its expected type."""

    name: str
    annotation: Any
    optional: bool = False


@dataclass(frozen=True)
class Output:
    """One result field written back to state (or a metric, which is not)."""

    name: str
    annotation: Any
    is_metric: bool = False
    description: str = ""
    unit: str = ""
    is_warnings: bool = False


@dataclass(frozen=True)
class StepSpec:
    """Everything the runner and the front ends know about a step, derived from its signature."""

    name: str
    func: Callable[..., Any]
    title: str
    summary: str
    doc: str
    inputs: tuple[Input, ...]
    controls: tuple[Control, ...]
    outputs: tuple[Output, ...]
    result_type: Any
    is_generator: bool
    runner_args: tuple[str, ...]

    @property
    def writes(self) -> tuple[str, ...]:
        """State names this step writes (metrics and a :data:`Warnings` field go to the run record)."""
        return tuple(o.name for o in self.outputs if not o.is_metric and not o.is_warnings)

    @property
    def reads(self) -> tuple[str, ...]:
        return tuple(i.name for i in self.inputs)

    def control(self, name: str) -> Control:
        for control in self.controls:
            if control.name == name:
                return control
        raise InvalidControl(name, f"step {self.name!r} has no control {name!r}; "
                                   f"controls are {[c.name for c in self.controls]}")

    def coerce_controls(self, params: Mapping[str, Any] | None) -> dict[str, Any]:
        """Defaults overridden by ``params``, each checked; unknown names are an error
        (:func:`coerce_controls`)."""
        return coerce_controls(self.controls, params, owner=f"step {self.name!r}")

    def json_schema(self) -> dict[str, Any]:
        """JSON Schema of the request body: an object of controls."""
        return {
            "title": self.title,
            "type": "object",
            "properties": {c.name: c.json_schema() for c in self.controls},
            "required": [c.name for c in self.controls if c.required],
            "additionalProperties": False,
        }

    def describe(self) -> dict[str, Any]:
        """The step as JSON for ``GET /api/modules/{module}``."""
        return {
            "name": self.name,
            "title": self.title,
            "summary": self.summary,
            "doc": self.doc,
            "inputs": [{"name": i.name, "type": type_name(i.annotation), "optional": i.optional}
                       for i in self.inputs],
            "controls": self.json_schema(),
            "outputs": [{"name": o.name, "type": type_name(o.annotation)} for o in self.outputs
                        if not o.is_metric and not o.is_warnings],
            "metrics": [{"name": o.name, "description": o.description, "unit": o.unit}
                        for o in self.outputs if o.is_metric],
            "long": self.is_generator,
        }


def type_name(annotation: Any) -> str:
    """A short readable name of an annotation (``ImageSet``, ``ndarray``, ``float | None``)."""
    if annotation is inspect.Parameter.empty:
        return "any"
    if isinstance(annotation, type):
        return annotation.__name__
    text = str(annotation).replace("typing.", "").replace("numpy.", "").replace("lab.core.values.", "")
    return re.sub(r"<class '([\w.]+)'>", lambda m: m.group(1).rsplit(".", 1)[-1], text)


def _docstring_params(doc: str) -> dict[str, str]:
    """``name: text`` items of an ``Args:`` / ``Controls:`` section (Google style), continuation lines
    joined."""
    found: dict[str, str] = {}
    item_indent: int | None = None
    current: str | None = None
    in_section = False
    for raw in doc.splitlines():
        line = raw.strip()
        indent = len(raw) - len(raw.lstrip())
        if re.fullmatch(r"(Args|Arguments|Controls|Inputs|Parameters)\s*:", line):
            in_section, item_indent, current = True, None, None
            continue
        if not in_section:
            continue
        if not line:
            continue
        if indent == 0:  # the next section ("Returns:", "Reference:" ...) or prose ends this one
            in_section, current = False, None
            continue
        match = re.match(r"(\w+)\s*(?:\([^)]*\))?\s*:\s*(.*)$", line)
        if match and (item_indent is None or indent <= item_indent):
            item_indent = indent
            current = match.group(1)
            found[current] = match.group(2).strip()
        elif current is not None:
            found[current] = f"{found[current]} {line}".strip()
    return found


def _control_from(name: str, annotation: Any, default: Any, description: str) -> Control:
    rng = Range()
    if typing.get_origin(annotation) is Annotated:
        annotation, *extras = typing.get_args(annotation)
        for extra in extras:
            if isinstance(extra, Range):
                rng = extra
            elif isinstance(extra, str) and not description:
                description = extra
    required = default is inspect.Parameter.empty
    default = None if required else default
    origin = typing.get_origin(annotation)
    common = dict(name=name, default=default, description=description, minimum=rng.minimum,
                  maximum=rng.maximum, required=required)
    if origin is Literal:
        return Control(kind="choice", choices=tuple(typing.get_args(annotation)), **common)
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        raise TypeError(f"control {name!r}: use Literal[...] for choices (one way to do it; "
                        "an Enum's members would not survive JSON and CLI text)")
    if origin is tuple:
        kinds = tuple(_scalar_kind(name, a) for a in typing.get_args(annotation))
        if not kinds or Ellipsis in typing.get_args(annotation):
            raise TypeError(f"control {name!r}: tuples must have a fixed length")
        return Control(kind="tuple", item_kinds=kinds, **common)
    return Control(kind=_scalar_kind(name, annotation), **common)


def _scalar_kind(name: str, annotation: Any) -> ScalarKind:
    kinds: tuple[tuple[ScalarKind, type], ...] = (
        ("bool", bool), ("int", int), ("float", float), ("str", str))
    for kind, cls in kinds:
        if annotation is cls:
            return kind
    raise TypeError(f"control {name!r} has annotation {annotation!r}; controls must be float, int, "
                    "bool, str, Literal[...] or a fixed tuple of those")


def _result_type(hints: dict[str, Any]) -> tuple[Any, bool]:
    ret = hints.get("return", inspect.Parameter.empty)
    origin = typing.get_origin(ret)
    if origin in (collections.abc.Generator, collections.abc.Iterator, typing.Generator):
        args = typing.get_args(ret)
        return (args[2] if len(args) == 3 else inspect.Parameter.empty), True
    return ret, False


def describe_step(func: Callable[..., Any], *, name: str | None = None) -> StepSpec:
    """Introspect ``func`` into a :class:`StepSpec` (raises TypeError when the signature breaks the rules)."""
    name = name or func.__name__
    signature = inspect.signature(func)
    hints = typing.get_type_hints(func, include_extras=True)
    doc = inspect.getdoc(func) or ""
    described = _docstring_params(doc)
    inputs: list[Input] = []
    controls: list[Control] = []
    runner: list[str] = []
    for param in signature.parameters.values():
        annotation = hints.get(param.name, inspect.Parameter.empty)
        if param.kind in (param.POSITIONAL_ONLY, param.POSITIONAL_OR_KEYWORD):
            optional = param.default is not inspect.Parameter.empty
            if optional and param.default is not None:
                raise TypeError(f"step {name}: input {param.name!r} may only default to None")
            inputs.append(Input(param.name, annotation, optional))
        elif param.kind == param.KEYWORD_ONLY:
            if param.name in RUNNER_SUPPLIED:
                runner.append(param.name)
            else:
                controls.append(_control_from(param.name, annotation, param.default,
                                              described.get(param.name, "")))
        else:
            raise TypeError(f"step {name}: *args and **kwargs are not allowed")
    result_type, is_generator = _result_type(hints)
    if is_generator != inspect.isgeneratorfunction(func) and inspect.isgeneratorfunction(func):
        is_generator = True
    outputs: list[Output] = []
    if isinstance(result_type, type) and dataclasses.is_dataclass(result_type) \
            and not is_step_result(result_type) and not _is_value_type(result_type):
        raise TypeError(f"step {name}: returns dataclass {result_type.__name__}, which is neither a value "
                        "type of lab.core.values nor marked @step_result; mark it to write its fields by "
                        "name")
    if is_step_result(result_type):
        field_hints = typing.get_type_hints(result_type, include_extras=True)
        for f in dataclasses.fields(result_type):
            hint = field_hints.get(f.name, f.type)
            outputs.append(Output(f.name, hint, bool(f.metadata.get("metric")),
                                  f.metadata.get("description", ""), f.metadata.get("unit", ""),
                                  is_warnings=is_warnings(hint)))
    elif result_type is not inspect.Parameter.empty and result_type is not None:
        output_name = name
        if typing.get_origin(result_type) is Annotated:  # -> Annotated[np.ndarray, "homographies"]
            result_type, *extras = typing.get_args(result_type)
            output_name = next((e for e in extras if isinstance(e, str)), name)
        outputs.append(Output(output_name, result_type))
    summary = doc.split("\n\n", 1)[0].replace("\n", " ").strip()
    title = name.replace("_", " ").capitalize()
    return StepSpec(name=name, func=func, title=title, summary=summary, doc=doc, inputs=tuple(inputs),
                    controls=tuple(controls), outputs=tuple(outputs), result_type=result_type,
                    is_generator=is_generator, runner_args=tuple(runner))


def _is_value_type(annotation: Any) -> bool:
    """A drawn value type (``lab.core.values``): a step returning one writes one value."""
    return isinstance(annotation, type) and annotation.__module__ == "lab.core.values"


@dataclass(frozen=True)
class StepOutcome:
    """A step's return value split by destination: state ``values``, ``metrics`` and ``warnings``."""

    values: dict[str, Any]
    metrics: dict[str, Any]
    warnings: tuple[str, ...] = ()


def result_to_values(spec: StepSpec, result: Any) -> StepOutcome:
    """Split a step's return value into state values, metrics and warnings, checking the type."""
    if not is_step_result(spec.result_type):
        return StepOutcome({spec.outputs[0].name: result} if spec.outputs else {}, {})
    if not isinstance(result, spec.result_type):
        raise TypeError(f"step {spec.name} must return {spec.result_type.__name__}, "
                        f"got {type(result).__name__}")
    values: dict[str, Any] = {}
    metrics: dict[str, Any] = {}
    warnings: tuple[str, ...] = ()
    for out in spec.outputs:
        value = getattr(result, out.name)
        if out.is_metric:
            metrics[out.name] = _metric_value(value)
        elif out.is_warnings:
            warnings += tuple(str(w) for w in (value or ()))
        else:
            values[out.name] = value
    return StepOutcome(values, metrics, warnings)


def _metric_value(value: Any) -> Any:
    """Metrics are JSON scalars or short lists of numbers (per-view RMS)."""
    if isinstance(value, (bool, np.bool_, str)):
        return value if isinstance(value, str) else bool(value)
    if isinstance(value, (list, tuple, np.ndarray)):
        return [float(v) for v in np.asarray(value, dtype=np.float64).ravel()]
    if isinstance(value, (int, np.integer)):
        return int(value)
    return float(value)
