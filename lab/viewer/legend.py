"""The scene's legend: what each drawn 3D value is and what its colours mean, read from the typed values.

Every 3D value type of :mod:`lab.core.values` says how it is drawn (:func:`legend_entry`): a point
cloud's points in their own colours or grey, camera frustums tinted per camera, segments, a mesh,
Gaussians. Colours a value gives are grouped: a few distinct colours are listed with the items
they mark (camera 0, 3 ...), many are "their own colours" (an image's). The legend names each
value by its state name and the step that wrote it, so every module gets one without code of
its own; :class:`ScenePanel` shows it with a "Fit view" button in the viewer.
"""

from __future__ import annotations

import html
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from lab.core.values import Cameras, GaussianSplats, Mesh, PointCloud, Segments3D
from lab.viewer.renderers import (DEFAULT_CAMERA_COLOR, DEFAULT_MESH_COLOR, DEFAULT_POINT_COLOR,
                                  default_cloud_colors)

#: At most this many distinct colours are listed one by one; more are "their own colours".
MAX_LISTED_COLORS = 6
SEGMENT_DEFAULT_COLOR = (20, 20, 20)

RGB = tuple[int, int, int]


@dataclass(frozen=True)
class Swatch:
    """One colour of a legend entry and what it marks ("all 54 points", "cameras 0, 3")."""

    color: RGB
    marks: str


@dataclass(frozen=True)
class LegendEntry:
    """How one state value is drawn: ``kind`` ("points", "cameras", ...), how many, its colours."""

    name: str
    kind: str
    count: int
    swatches: tuple[Swatch, ...]
    note: str = ""

    def text(self, producer: str = "") -> str:
        """One line of plain text (tests, logs): ``points cloud (triangulate): 412 points, grey``."""
        by = f" ({producer})" if producer else ""
        colours = "; ".join(f"#{_hex(s.color)} {s.marks}" for s in self.swatches)
        return f"{self.name}{by}: {self.count} {self.kind}" + (f", {colours}" if colours else "") \
            + (f", {self.note}" if self.note else "")


def _hex(color: RGB) -> str:
    return "".join(f"{int(c):02x}" for c in color)


def _items(indices: np.ndarray, noun: str) -> str:
    shown = ", ".join(str(int(i)) for i in indices[:8])
    more = f" and {len(indices) - 8} more" if len(indices) > 8 else ""
    return f"{noun} {shown}{more}" if len(indices) > 1 else f"{noun} {int(indices[0])}"


def colour_groups(colors: np.ndarray | None, count: int, default: RGB, *, noun: str,
                  plural: str) -> tuple[tuple[Swatch, ...], str]:
    """The swatches of ``count`` items coloured ``colors`` (``(N, 3)`` in [0, 1], or None: ``default``), and a
    note when there are too many colours to list."""
    if count == 0:
        return (), ""
    if colors is None:
        return (Swatch(default, f"all {count} {plural}" if count > 1 else f"the {noun}"),), ""
    rgb = (np.clip(np.asarray(colors, dtype=np.float64), 0.0, 1.0) * 255.0 + 0.5).astype(int)
    unique, inverse = np.unique(rgb, axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    if len(unique) > MAX_LISTED_COLORS:
        return (), f"each of the {plural} in its own colour ({len(unique)} colours: an image's, or a value's)"
    swatches = []
    for k, color in enumerate(unique):
        members = np.flatnonzero(inverse == k)
        marks = _items(members, noun) if plural in ("cameras", "views") else f"{len(members)} {plural}"
        swatches.append(Swatch((int(color[0]), int(color[1]), int(color[2])), marks))
    return tuple(swatches), ""


def legend_entry(name: str, value: Any, *, point_color: RGB = DEFAULT_POINT_COLOR) -> LegendEntry | None:
    """How ``value`` is drawn in the 3D scene, or None for a value that is not drawn there; a point cloud
    without colours is drawn in ``point_color`` (its :func:`~lab.viewer.renderers.default_cloud_colors`)."""
    if isinstance(value, PointCloud):
        swatches, note = colour_groups(value.colors, len(value), point_color, noun="point", plural="points")
        return LegendEntry(name, "points", len(value), swatches, note)
    if isinstance(value, Cameras):
        swatches, note = colour_groups(value.colors, len(value), DEFAULT_CAMERA_COLOR, noun="camera",
                                       plural="cameras")
        image = f"each carrying its view of {value.image!r}; click one to show it" if value.image else ""
        return LegendEntry(name, "cameras", len(value), swatches, "; ".join(t for t in (note, image) if t))
    if isinstance(value, Segments3D):
        swatches, note = colour_groups(value.colors, len(value.start), SEGMENT_DEFAULT_COLOR, noun="segment",
                                       plural="segments")
        return LegendEntry(name, "segments", len(value.start), swatches, note)
    if isinstance(value, Mesh):
        if value.vertex_colors is None:
            surface = (Swatch(DEFAULT_MESH_COLOR, "the surface (see-through)"),)
            return LegendEntry(name, "triangles", len(value.faces), surface)
        return LegendEntry(name, "triangles", len(value.faces), (), "coloured per vertex (its texture)")
    if isinstance(value, GaussianSplats):
        return LegendEntry(name, "Gaussians", len(value.centers), (), "each its own colour and opacity")
    return None


def legend_entries(state: Mapping[str, Any], names: Iterable[str] | None = None) -> list[LegendEntry]:
    """The legend of the values ``names`` of ``state`` (default: all) that are drawn in 3D, in name order."""
    chosen = sorted(state) if names is None else [n for n in names if n in state]
    colors = default_cloud_colors(state)
    entries = (legend_entry(n, state[n], point_color=colors.get(n, DEFAULT_POINT_COLOR)) for n in chosen)
    return [entry for entry in entries if entry is not None]


class Explains(Protocol):
    """What draws in 3D and says what its drawing means: a module's interaction (``Interaction.legend``)."""

    @property
    def title(self) -> str: ...

    def legend(self) -> list[LegendEntry]: ...


def interaction_entries(interactions: Iterable[Explains]) -> list[tuple[LegendEntry, str]]:
    """The legend entries of what ``interactions`` draw, each with the title of the interaction that draws it;
    an interaction whose ``legend()`` fails is left out (the legend is an explanation, never an error)."""
    found = []
    for interaction in interactions:
        try:
            entries = list(interaction.legend())
        except Exception:  # an interaction's bug must not take the legend down
            continue
        found += [(entry, interaction.title) for entry in entries]
    return found


def legend_html(entries: Iterable[LegendEntry], producers: Mapping[str, str] | None = None) -> str:
    """The legend as HTML for viser's ``gui.add_html``: a line per value, a square per colour."""
    producers = producers or {}
    rows = []
    for entry in entries:
        by = f" <span style='opacity:.6'>({html.escape(producers[entry.name])})</span>" \
            if producers.get(entry.name) else ""
        swatches = "".join(
            f"<div style='margin-left:1em'><span style='display:inline-block;width:.8em;height:.8em;"
            f"background:#{_hex(s.color)};border:1px solid #888;margin-right:.4em'></span>"
            f"{html.escape(s.marks)}</div>" for s in entry.swatches)
        note = (f"<div style='margin-left:1em;opacity:.75'>{html.escape(entry.note)}</div>"
                if entry.note else "")
        rows.append(f"<div style='margin:.2em 0'><b>{html.escape(entry.name)}</b>{by}: {entry.count} "
                    f"{html.escape(entry.kind)}{swatches}{note}</div>")
    if not rows:
        return "<div style='opacity:.6;font-size:.85em'>Nothing drawn in 3D yet.</div>"
    return "<div style='font-size:.85em;line-height:1.3'>" + "".join(rows) + "</div>"


#: The viewer's "how to use this" strip: what a newcomer needs to get going, in three short lines.
HOW_TO = (
    "Pick a module and dataset below, then **Run all** — or open a step and **Run** it; a changed control "
    "marks later steps *stale*. **Scene** explains the colours, **Fit view** frames them; drag to orbit, "
    "scroll to zoom, click a camera's picture."
)


def add_how_to(gui: Any, *, order: float = 0.5) -> Any:
    """The "How to use this" strip at the top of the panel (a folder a user can fold away)."""
    folder = gui.add_folder("How to use this", order=order, expand_by_default=True)
    with folder:
        gui.add_markdown(HOW_TO)
    return folder


class ScenePanel:
    """A "Scene" folder of the viewer: the legend of what is drawn and a "Fit view" button."""

    def __init__(self, gui: Any, *, on_fit: Callable[[], None], order: float = 2.7) -> None:
        self.folder = gui.add_folder("Scene: legend and view", order=order, expand_by_default=True)
        with self.folder:
            self.fit_button = gui.add_button("Fit view", hint="Point the camera at everything drawn")
            self.legend = gui.add_html(legend_html([]))
        self.fit_button.on_click(lambda _event: on_fit())
        self._shown = ""

    def show(self, state: Mapping[str, Any], producers: Mapping[str, str] | None = None,
             interactions: Iterable[Explains] = ()) -> str:
        """Update the legend to ``state``'s 3D values and what ``interactions`` draw; returns the HTML."""
        drawn = interaction_entries(interactions)
        by = {**(producers or {}), **{entry.name: title for entry, title in drawn}}
        content = legend_html([*legend_entries(state), *(entry for entry, _ in drawn)], by)
        if content != self._shown:
            self.legend.content = content
            self._shown = content
        return content


__all__ = ["HOW_TO", "Explains", "LegendEntry", "ScenePanel", "Swatch", "add_how_to", "colour_groups",
           "interaction_entries", "legend_entries", "legend_entry", "legend_html"]
