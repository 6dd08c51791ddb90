"""Axes of the viewer's uPlot charts that uPlot's defaults get wrong for the lab's curves.

uPlot labels the ticks of a log axis with at most three decimals, so 1e-4 reads "0" (a log scale
has no 0); :func:`log_axis` gives the decades with their own labels instead (JSON: viser sends the
options as data, not functions). A chart's x axis ends where the data ends (:func:`x_scale`: a
7-iteration run ends at 7, whatever its planned total).

:func:`set_uplot` changes a drawn chart in place (its handle kept: see :mod:`lab.viewer.renderers` on why
the viewer never removes and re-adds a GUI chart or picture to change it).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def spans_decades(y: np.ndarray) -> bool:
    """Whether values are plotted on a log scale: all positive, spanning more than two decades."""
    y = y[np.isfinite(y)]
    return bool(y.size and y.min() > 0 and y.max() / y.min() > 100)


#: Axis options that keep uPlot's look (grid lines, no tick marks) once an axis is given.
PLAIN_AXIS: dict[str, Any] = {"ticks": {"show": False}, "grid": {"show": True}}


def decade_label(exponent: int) -> str:
    """The tick label of ``10 ** exponent``: ``1e-5``, ``1e-4``, ``0.001`` ... ``1000``, ``1e4`` (never "0";
    at most five characters, so it fits uPlot's axis)."""
    if -3 <= exponent < 0:
        return f"{10.0 ** exponent:.{-exponent}f}"
    if 0 <= exponent <= 3:
        return str(10 ** exponent)
    return f"1e{exponent}"


def log_axis(y: np.ndarray) -> dict[str, Any]:
    """The uPlot axis of positive values ``y`` on a log scale: a tick and label at each decade they span."""
    y = y[np.isfinite(y) & (y > 0)]
    if not y.size:
        return {}
    lo, hi = math.floor(math.log10(float(y.min()))), math.ceil(math.log10(float(y.max())))
    exponents = range(lo, max(hi, lo + 1) + 1)
    return {**PLAIN_AXIS, "splits": [10.0 ** k for k in exponents],
            "values": [decade_label(k) for k in exponents]}


def x_scale(x: np.ndarray) -> dict[str, Any]:
    """The uPlot x scale of a chart: numbers (not time), from the first x to the last one."""
    x = x[np.isfinite(x)]
    if not x.size:
        return {"time": False}
    lo, hi = float(x.min()), float(x.max())
    return {"time": False, "range": [lo, hi if hi > lo else lo + 1.0]}


def chart_axes(x: np.ndarray, y: np.ndarray) -> tuple[dict[str, Any], tuple[dict[str, Any], ...] | None]:
    """``scales`` and ``axes`` of ``gui.add_uplot`` for series ``y`` (1 or 2-D) over ``x``: the x axis ends
    at the last x, the y axis is logarithmic, from the decade below the values to the one above, with a
    label per decade, when the values span decades."""
    scales: dict[str, Any] = {"x": x_scale(x)}
    values = np.asarray(y, dtype=np.float64).ravel()
    if not spans_decades(values):
        return scales, None
    axis = log_axis(values)
    splits = axis["splits"]  # the y range is the decades labelled (uPlot draws given ticks even outside it)
    scales["y"] = {"distr": 3, "log": 10, "range": [splits[0], splits[-1]]}
    return scales, (dict(PLAIN_AXIS), axis)


def _same_columns(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> bool:
    return len(a) == len(b) and all(np.shape(x) == np.shape(y) and np.array_equal(x, y, equal_nan=True)
                                    for x, y in zip(a, b, strict=True))


#: The chart options :func:`set_uplot` changes in place (the others are fixed when the chart is added).
UPLOT_FIELDS = ("data", "series", "scales", "axes", "title")


def set_uplot(handle: Any, **options: Any) -> None:
    """Change a viser uPlot chart (``handle``) in place: ``data``, ``series``, ``scales``, ``axes``, ``title``
    (each given one is set, and only when it differs: viser sends each change as its own update message).

    The chart keeps its GUI element, so the browser never gets an update for an element it removed (viser's
    client applies a frame's updates after its removals, and logs "Tried to update non-existent component"
    for an element replaced within one frame). When the number of series changes, the data and the series
    are set in the order that never leaves the page a series without its data column (uPlot draws a data
    column without a series, not a series without data): data first when they grow, series first when they
    shrink."""
    unknown = sorted(set(options) - set(UPLOT_FIELDS))
    if unknown:
        raise TypeError(f"set_uplot sets {list(UPLOT_FIELDS)}, not {unknown}")
    order = list(UPLOT_FIELDS)
    if "series" in options and len(options["series"]) < len(handle.series):
        order = ["series", "data", *order[2:]]
    for name in order:
        if name not in options:
            continue
        value = options[name]
        if name == "data":
            value = tuple(np.asarray(column, dtype=np.float64) for column in value)
            if _same_columns(handle.data, value):
                continue
        elif name == "series":
            value = tuple(value)
        if name != "data" and getattr(handle, name) == value:
            continue
        setattr(handle, name, value)


__all__ = ["PLAIN_AXIS", "UPLOT_FIELDS", "chart_axes", "decade_label", "log_axis", "set_uplot",
           "spans_decades", "x_scale"]
