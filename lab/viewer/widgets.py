"""Controls as viser widgets: which widget shows a :class:`~lab.core.step.Control`, how it is built from
the control's schema, how its value is read back, and how a value is shown in it.

A step's keyword-only parameters become :class:`~lab.core.step.Control` objects (``lab.core.step``);
this module turns each into the matching widget (slider, number, checkbox, dropdown, text, vector)
with the control's range, default and description as its hint. Values read from a widget are raw:
the step's schema checks them when it runs (:meth:`lab.core.step.StepSpec.coerce_controls`).
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np

from lab.core.errors import LabError
from lab.core.step import Control

#: The widget kinds of :func:`widget_kind`.
WidgetKind = Literal["checkbox", "dropdown", "text", "vector2", "vector3", "slider", "number"]


def nice_step(span: float, *values: float | None) -> float:
    """A round slider step giving about 100 positions over ``span`` (0.01 for [0, 1]), made finer
    until every one of ``values`` (the minimum, the default) lies on a step."""
    step = 0.01 if not np.isfinite(span) or span <= 0 else float(10.0 ** math.floor(math.log10(span / 100.0)))
    for _ in range(6):
        if all(abs(v / step - round(v / step)) < 1e-6 for v in values if v is not None):
            break
        step /= 10.0
    return step


def control_hint(control: Control) -> str:
    """The hover text of a control's widget: its description, range and default."""
    parts = [control.description] if control.description else []
    if control.minimum is not None or control.maximum is not None:
        lo = "-inf" if control.minimum is None else f"{control.minimum:g}"
        hi = "inf" if control.maximum is None else f"{control.maximum:g}"
        parts.append(f"range [{lo}, {hi}]")
    if not control.required:
        parts.append(f"default {control.default!r}")
    return "; ".join(parts)


def widget_kind(control: Control) -> WidgetKind:
    """Which viser widget shows a control: slider, number, checkbox, dropdown, text, vector2/3."""
    if control.kind == "bool":
        return "checkbox"
    if control.kind == "choice":
        return "dropdown"
    if control.kind == "str":
        return "text"
    if control.kind == "tuple":
        numeric = all(k in ("int", "float") for k in control.item_kinds)
        if numeric and len(control.item_kinds) == 2:
            return "vector2"
        if numeric and len(control.item_kinds) == 3:
            return "vector3"
        return "text"
    if control.minimum is None or control.maximum is None:
        return "number"
    if control.kind == "int":
        return "slider" if control.maximum - control.minimum <= 1000 else "number"
    return "slider"


def _text_of(control: Control, value: Any) -> str:
    if control.kind == "tuple":
        return ", ".join(str(v) for v in value) if value is not None else ""
    return "" if value is None else str(value)


def add_control_widget(gui: Any, control: Control, value: Any = None) -> Any:
    """Add the widget of ``control`` (showing ``value``, else its default) and return its handle."""
    kind = widget_kind(control)
    value = control.default if value is None else value
    hint = control_hint(control) or None
    label = control.name
    if kind == "checkbox":
        return gui.add_checkbox(label, bool(value), hint=hint)
    if kind == "dropdown":
        options = [str(c) for c in control.choices]
        initial = str(value) if value is not None and str(value) in options else options[0]
        return gui.add_dropdown(label, options, initial_value=initial, hint=hint)
    if kind == "text":
        return gui.add_text(label, _text_of(control, value), hint=hint)
    if kind in ("vector2", "vector3"):
        return _add_vector(gui, control, value, hint)
    return _add_number(gui, control, value, hint, slider=kind == "slider")


def _add_vector(gui: Any, control: Control, value: Any, hint: str | None) -> Any:
    n = len(control.item_kinds)
    initial = tuple(float(v) for v in value) if value is not None else (0.0,) * n
    lows = None if control.minimum is None else (float(control.minimum),) * n
    highs = None if control.maximum is None else (float(control.maximum),) * n
    step = 1.0 if all(k == "int" for k in control.item_kinds) else None
    add = gui.add_vector2 if n == 2 else gui.add_vector3
    return add(control.name, initial, min=lows, max=highs, step=step, hint=hint)


def _add_number(gui: Any, control: Control, value: Any, hint: str | None, *, slider: bool) -> Any:
    is_int = control.kind == "int"
    cast: type[int] | type[float] = int if is_int else float
    if value is None:  # a required number: start at its lower bound (or 0)
        value = control.minimum if control.minimum is not None else 0
    number = cast(value)
    lo = None if control.minimum is None else cast(control.minimum)
    hi = None if control.maximum is None else cast(control.maximum)
    if slider and lo is not None and hi is not None:
        step = 1 if is_int else nice_step(hi - lo, lo, number)
        return gui.add_slider(control.name, min=lo, max=hi, step=step, initial_value=number, hint=hint)
    return gui.add_number(control.name, number, min=lo, max=hi, step=1 if is_int else None, hint=hint)


def widget_value(control: Control, handle: Any) -> Any:
    """The raw value a widget holds (checked later by :meth:`Control.coerce`)."""
    value = handle.value
    if isinstance(value, tuple):
        return list(value)
    if control.kind == "tuple" and isinstance(value, str) and "str" in control.item_kinds:
        # text items: split on commas only (the core's parser also splits "640x480" on the x)
        return [item.strip() for item in value.strip().strip("()[]").split(",")]
    return value


def show_value(control: Control, handle: Any, value: Any) -> None:
    """Put ``value`` (a checked control value, e.g. what a step ran with) into the control's widget."""
    kind = widget_kind(control)
    if kind == "checkbox":
        handle.value = bool(value)
    elif kind == "dropdown":
        handle.value = str(value)
    elif kind == "text":
        handle.value = _text_of(control, value)
    elif kind in ("vector2", "vector3"):
        handle.value = tuple(float(v) for v in value)
    elif value is not None:
        handle.value = int(value) if control.kind == "int" else float(value)


def same_as_default(control: Control, value: Any) -> bool:
    """Whether a widget's raw ``value`` is the control's default once checked (False when it is invalid)."""
    try:
        return bool(control.coerce(value) == control.default)
    except LabError:
        return False


__all__ = ["WidgetKind", "add_control_widget", "control_hint", "nice_step", "same_as_default", "show_value",
           "widget_kind", "widget_value"]
