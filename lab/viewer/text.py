"""What the viewer writes in its GUI: numbers, metrics, values, history, step labels and errors.

Pure functions (no viser): each returns the Markdown or the text one GUI element shows, so they are
tested directly and shared by the tab (:mod:`lab.viewer.view`) and the lesson mode
(:mod:`lab.viewer.lesson`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from lab.core.errors import LabError
from lab.core.pipeline import RunRecord
from lab.core.step import StepSpec
from lab.core.values import VALUE_TYPES
from lab.viewer.renderers import OVERLAY_TYPES

#: The mark in a step's folder label for each status it can show (``running`` is the viewer's own).
STATUS_MARK = {"done": "✓", "stale": "↻", "ready": "›", "blocked": "·", "running": "…", "failed": "✗"}


def format_number(value: Any) -> str:
    """A metric or control value as short text: 4 significant digits, scientific when tiny or huge."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if value == 0 or 1e-3 <= abs(value) < 1e5:
            return f"{value:.4g}"
        return f"{value:.3e}"
    if isinstance(value, (list, tuple)):
        if not value:
            return "[]"
        numbers = [v for v in value if isinstance(v, (int, float))]
        if len(value) <= 4:
            return "[" + ", ".join(format_number(v) for v in value) + "]"
        if numbers:
            return f"{len(value)} values, max {format_number(max(numbers))}"
        return f"{len(value)} values"
    return str(value)


def cell(text: str) -> str:
    """Text safe inside a Markdown table cell."""
    return str(text).replace("|", "\\|").replace("\n", " ")


def metrics_markdown(spec: StepSpec, metrics: Mapping[str, Any], warnings: Iterable[str] = ()) -> str:
    """A step's metrics as a Markdown table (units from its ``metric()`` fields); warnings below."""
    described = {o.name: o for o in spec.outputs if o.is_metric}
    lines = []
    if metrics:
        lines += ["| metric | value |", "|---|---|"]
        for name, value in metrics.items():
            out = described.get(name)
            unit = f" {out.unit}" if out is not None and out.unit else ""
            label = name if out is not None else f"{name} (evaluation)"
            lines.append(f"| {label} | {cell(format_number(value))}{unit} |")
    for warning in warnings:
        lines.append(f"\n⚠ {warning}")
    return "\n".join(lines)


def value_summary(name: str, value: Any) -> str:
    """One line of the Values folder: a state value's name, type and size (small arrays in full)."""
    type_name = type(value).__name__
    if isinstance(value, np.ndarray):
        text = f"`{name}`: array {tuple(value.shape)} {value.dtype}"
        if value.size <= 16 and value.dtype.kind in "fiub":
            text += "  \n`" + np.array2string(value, precision=4, suppress_small=True, max_line_width=60) \
                .replace("\n", " ") + "`"
        return text
    if isinstance(value, (int, float, str, bool, np.generic)):
        return f"`{name}`: {format_number(value) if not isinstance(value, str) else value}"
    if isinstance(value, OVERLAY_TYPES):
        return f"`{name}`: {type_name} ({len(value)}), drawn on `{value.image}`"
    if type(value) in VALUE_TYPES.values():
        size = f" ({len(value)})" if hasattr(value, "__len__") else ""
        return f"`{name}`: {type_name}{size}"
    return f"`{name}`: {type_name}"


def history_markdown(history: Sequence[RunRecord], limit: int = 12) -> str:
    """The last runs of a session's history, newest first, as a Markdown table."""
    records = history[-limit:]
    if not records:
        return "No step has run yet."
    start = len(history) - len(records)
    rows = []
    for i, record in enumerate(records):
        status = record.status if not record.error else f"{record.status}: {record.error[:60]}"
        rows.append(f"| {start + i + 1} | {record.step} | {cell(status)} | {record.seconds:.3f} |")
    return "\n".join(["| # | step | status | seconds |", "|---|---|---|---|", *rows[::-1]])


def step_label(index: int, spec: StepSpec, status: str, *, why: str = "") -> str:
    """The label of a step's folder: its number, title, status mark and status, and for a failed step
    ``why`` (``2. Mean intensity ✓ done``; ``8. Extract mesh ✗ failed: see the error at the top``; in
    lesson mode ``2. Homographies ✗ failed: your code failed``)."""
    label = f"{index + 1}. {spec.title} {STATUS_MARK.get(status, '')} {status}"
    return label + (f": {why}" if status == "failed" and why else "")


def stale_note(spec: StepSpec, ran_with: Mapping[str, Any] | None, shown: Mapping[str, Any] | None) -> str:
    """Why a stale step is stale: the controls that differ from those its outputs came from (``ran_with``,
    the session's; ``shown``, the widgets', checked), else that it reads the output of a stale step."""
    changed = []
    for control in spec.controls:
        before = (ran_with or {}).get(control.name)
        now = (shown or {}).get(control.name, before)
        if before != now:
            changed.append(f"`{control.name}` {format_number(before)} → {format_number(now)}")
    if changed:
        why = "its controls changed since it ran: " + ", ".join(changed)
    else:
        why = "it reads the output of a step that is stale"
    return f"↻ **Stale**: {why}. Press Run (or Run all) to bring it up to date."


def error_text(exc: BaseException) -> str:
    """An error as the tab shows it: ``kind: field: reason`` for a :class:`LabError`, else its type
    and text."""
    if isinstance(exc, LabError):
        return f"{exc.kind}: {exc.field}: {exc.reason}"
    return f"{type(exc).__name__}: {exc}"


__all__ = ["STATUS_MARK", "cell", "error_text", "format_number", "history_markdown", "metrics_markdown",
           "stale_note", "step_label", "value_summary"]
