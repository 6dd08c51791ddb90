"""Module-specific viewer interactions: what the generic, per-value-type drawing cannot do.

Every value of a session is drawn by its renderer (:mod:`lab.viewer.renderers`); a module adds an
*interaction* only for what needs a click, a drag or linked views: click a pixel and see its
epipolar line, click a pixel and see its matching-cost curves, scrub a sampler's steps.

A module's interactions live in ``lab/viewer/interactions/<pipeline name>.py``, which defines
``INTERACTIONS: list[type[Interaction]]``. Nothing else registers them: when a tab opens a session
of pipeline ``<name>``, the viewer imports that file if it exists and builds each interaction with
an :class:`InteractionContext` (the tab's scene and GUI, a folder of its own, the session, and
ways to run a step or restart the dataset). After every redraw the viewer calls
:meth:`Interaction.update` with the session's state; when the tab shows another session it calls
:meth:`Interaction.close`.

An interaction reads the session's values through :meth:`InteractionContext.value` (or
:meth:`InteractionContext.values`) only, by the names its pipeline lists in ``views``
(``Pipeline.build(views=...)``): a name the pipeline does not list is refused with a clear error,
and a contract test (``tests/viewer/test_views_contract.py``) checks every name the interaction
files read against their pipeline's views, and every view against what the steps and datasets
provide. So renaming a state value in a module fails a test, not a browser. Interactions import no
other interaction: camera math they share is in :mod:`lab.geometry.camera_views`, drawing in
:mod:`lab.viewer.drawing`.

Interactions keep their math in pure functions (tested directly) and their GUI wiring thin; a
failing callback is shown in the tab (``ctx.show_error``), never raised into viser.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import logging
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

import numpy as np

from lab.core.errors import LabError, UnknownName
from lab.core.pipeline import Session
from lab.viewer.legend import LegendEntry, Swatch

log = logging.getLogger("lab.viewer")

#: Scene nodes of interactions go under this root (the generic drawing owns ``/lab``).
EXPLORE_ROOT = "/explore"

H = TypeVar("H")


class StateView(Mapping[str, Any]):
    """Some values of a session's state, by the names an interaction declared it reads
    (:meth:`InteractionContext.values`): iterating gives the declared names that exist; reading any other
    name raises :class:`~lab.core.errors.UnknownName` instead of quietly giving nothing."""

    def __init__(self, state: Mapping[str, Any], names: tuple[str, ...], module: str) -> None:
        self._state = state
        self._names = names
        self._module = module

    def _check(self, name: object) -> None:
        if name not in self._names:
            raise UnknownName("view", f"the {self._module} interaction read {name!r} without declaring it: "
                                      f"it declared {list(self._names)} (pass the name to ctx.values)")

    def __getitem__(self, name: str) -> Any:
        self._check(name)
        return self._state[name]

    def __contains__(self, name: object) -> bool:
        self._check(name)
        return name in self._state

    def __iter__(self) -> Iterator[str]:
        return iter([name for name in self._names if name in self._state])

    def __len__(self) -> int:
        return sum(1 for name in self._names if name in self._state)


@dataclass
class InteractionContext:
    """What an interaction may use in the tab it lives in.

    ``folder`` is a GUI folder made for this interaction in the main panel; ``images`` and
    ``plots`` are the tabs of the left media panel. ``run(step, controls)`` runs a step as its Run
    button would (in the tab's worker thread, with the steps that depend on it when the tab re-runs
    dependants; errors shown in the tab). ``restart(options, *, run_to=None, params=None, carry=None)
    -> bool`` opens a new session of the same module and dataset with these dataset options (e.g. a
    baseline slider on a synthetic rig), then runs what step ``run_to`` needs (the core's plan, as
    its "Run to here" button) with ``params`` (``{step: controls}``, or a function of the new session
    returning them; the rest from the step widgets), and hands ``carry`` to the new session's
    interactions as ``ctx.carried``; it returns False (error shown) when it could not. ``extent()``
    is the size of the 3D content, for marker sizes. Session values are read with :meth:`value`.
    """

    scene: Any
    gui: Any
    folder: Any
    images: Any
    plots: Any
    session: Session
    is_client: bool
    show_error: Callable[[BaseException], None]
    run: Callable[[str, dict[str, Any]], None]
    restart: Callable[..., bool]
    extent: Callable[[], float]
    #: What the interactions of the previous session handed over through ``restart(carry=...)``.
    carried: Any = None
    #: The tab's browser camera (viser's ``CameraHandle``: pose, fov, aspect, ``on_update``), None for the
    #: server-wide scene (NeRF's training preview follows it).
    camera: Any = None

    def value(self, name: str, state: Mapping[str, Any] | None = None) -> Any:
        """State value ``name``: of ``state`` (the copy :meth:`Interaction.update` got) or, without it, of the
        session now; None while no step has made it.

        ``name`` must be one of the pipeline's ``views`` (the names its interactions may read), else
        :class:`~lab.core.errors.UnknownName` says so: a renamed value fails here, clearly, and in the
        contract test, instead of drawing nothing.
        """
        self._check(name)
        source = self.session.state if state is None else state
        return source.get(name)

    def values(self, names: Iterable[str], state: Mapping[str, Any] | None = None) -> StateView:
        """The values ``names`` of ``state`` (or of the session now) as a read-only mapping, for the pure
        functions that take a state: each name is checked as :meth:`value` checks it, and reading a name
        not in ``names`` from the mapping is refused too (so every name read is declared)."""
        wanted = tuple(names)
        for name in wanted:
            self._check(name)
        return StateView(self.session.state if state is None else state, wanted, self.session.pipeline.name)

    def _check(self, name: str) -> None:
        views = self.session.pipeline.views
        if name not in views:
            module = self.session.pipeline.name
            raise UnknownName("view", f"the {module} interactions read {name!r}, which pipeline {module!r} "
                                      f"does not list in its views {sorted(views)}: add it to views= in "
                                      f"lab.modules.{module}, or read a value the pipeline has")

    def node(self, *parts: str) -> str:
        """A scene node name under this module's root: ``/explore/<module>/<parts...>``."""
        return "/".join((EXPLORE_ROOT, self.session.pipeline.name, *parts))

    def attempt(self, action: Callable[[], H]) -> H | None:
        """Run ``action`` now and return what it returns; what it raises is shown in the tab (as a viser
        callback's error would be) and None is returned: the public actions of interactions (a pick, a
        move) use it, so a script or a test calling them gets None instead of an exception."""
        result: list[H | None] = [None]

        def run() -> None:
            result[0] = action()

        self.guarded(run)()
        return result[0]

    def guarded(self, action: Callable[..., Any]) -> Callable[..., None]:
        """``action`` wrapped for a viser callback: what it raises is shown in the tab, not raised."""

        def call(*args: Any, **kwargs: Any) -> None:
            try:
                action(*args, **kwargs)
            except Exception as exc:
                if not isinstance(exc, LabError):
                    log.error("interaction callback failed:\n%s", traceback.format_exc())
                self.show_error(exc)

        return call


def node_points(handle: Any) -> np.ndarray | None:
    """``(N, 3)`` world points a viser scene node covers: its points (a point cloud, line segments) or
    vertices (a mesh), an image's four corners, else its origin (a label, a GLB mesh), moved by the node's
    own pose; None for a GUI handle. (A node under a parent frame is taken as if the parent were the
    identity: the interactions draw under plain frames.)"""
    if not (hasattr(handle, "wxyz") and hasattr(handle, "position")):
        return None
    try:
        local = None
        for name in ("points", "vertices"):
            value = getattr(handle, name, None)
            if isinstance(value, np.ndarray) and value.size:
                local = value.reshape(-1, 3).astype(np.float64)
                break
        if local is None and hasattr(handle, "render_width"):
            w, h = float(handle.render_width) / 2.0, float(handle.render_height) / 2.0
            local = np.array([[-w, -h, 0.0], [w, -h, 0.0], [w, h, 0.0], [-w, h, 0.0]])
        if local is None:
            local = np.zeros((1, 3))
        import viser.transforms as vtf

        rotation = vtf.SO3(np.asarray(handle.wxyz, dtype=np.float64)).as_matrix()
        return local @ rotation.T + np.asarray(handle.position, dtype=np.float64)
    except Exception:  # a handle already removed, or one of another kind: it covers nothing known
        return None


def handles_bounds(handles: Iterable[Any]) -> np.ndarray | None:
    """``(2, 3)`` min and max corner of the scene nodes among ``handles`` (:func:`node_points`), or None."""
    chunks = [p for p in (node_points(h) for h in handles) if p is not None and len(p)]
    if not chunks:
        return None
    points = np.concatenate(chunks)
    points = points[np.all(np.isfinite(points), axis=1)]
    return np.stack([points.min(axis=0), points.max(axis=0)]) if len(points) else None


class NamedHandles:
    """Scene nodes and GUI handles by name: :meth:`put` replaces (removing the old handle first),
    :meth:`drop` removes a name and everything under it (``name/...``), :meth:`clear` removes all;
    :meth:`bounds` is the box of the scene nodes held."""

    def __init__(self) -> None:
        self.handles: dict[str, Any] = {}

    def put(self, name: str, make: Callable[[], H]) -> H:
        self.drop_exact(name)
        handle = make()
        self.handles[name] = handle
        return handle

    def drop_exact(self, name: str) -> None:
        old = self.handles.pop(name, None)
        if old is not None:
            with contextlib.suppress(Exception):  # gone with its parent already
                old.remove()

    def drop(self, prefix: str) -> None:
        for name in [n for n in self.handles if n == prefix or n.startswith(prefix + "/")]:
            self.drop_exact(name)

    def names(self) -> list[str]:
        return sorted(self.handles)

    def bounds(self) -> np.ndarray | None:
        """``(2, 3)`` min and max corner of the scene nodes held (:func:`handles_bounds`), or None."""
        return handles_bounds(list(self.handles.values()))

    def clear(self) -> None:
        for name in list(self.handles):
            self.drop_exact(name)


class Interaction:
    """Base class of a module's interaction. Subclasses build their GUI in ``__init__`` (the viewer
    has entered ``ctx.folder`` already: GUI elements added there land in it), redraw in
    :meth:`update`, and :meth:`track` every handle they add so that :meth:`close` removes it."""

    #: The label of the interaction's GUI folder.
    title: ClassVar[str] = "Explore"

    def __init__(self, ctx: InteractionContext) -> None:
        self.ctx = ctx
        self.handles: list[Any] = []

    def track(self, handle: H) -> H:
        """Remember ``handle`` (a scene node or GUI element) so :meth:`close` removes it."""
        self.handles.append(handle)
        return handle

    def untrack(self, handle: Any) -> None:
        """Remove ``handle`` now (when it is still there) and forget it (a plot redrawn in another shape)."""
        if handle is None:
            return
        with contextlib.suppress(Exception):  # gone with its parent already
            handle.remove()
        if handle in self.handles:
            self.handles.remove(handle)

    def update(self, state: Mapping[str, Any]) -> None:
        """Called after every redraw with a copy of the session's state: redraw what depends on it
        (cheaply: compare the identity of the values used last time)."""

    def bounds(self) -> np.ndarray | None:
        """``(2, 3)`` min and max corner of what this interaction draws in 3D, or None: the tab frames it with
        the session's 3D values (:mod:`lab.viewer.camera`). The default: the box of the scene nodes it
        :meth:`track` s and of those in its ``nodes`` (a :class:`NamedHandles`, when it keeps one); an
        interaction whose nodes say too little (a GLB mesh is only its origin) says it itself."""
        nodes = getattr(self, "nodes", None)
        held = list(nodes.handles.values()) if isinstance(nodes, NamedHandles) else []
        return handles_bounds([*self.handles, *held])

    def legend(self) -> list[LegendEntry]:
        """What this interaction draws in 3D and what its colours mean, for the scene legend (none by
        default): an entry per drawing, e.g. ``LegendEntry("x_t", "points", 2000, (Swatch((90, 140, 255),
        "the samples at the frame shown"),))``."""
        return []

    def pixel_clicked(self, image_name: str, view: int, pixel: np.ndarray) -> bool:
        """A click on pixel ``(u, v)`` of view ``view`` of image set ``image_name``, on a camera frustum's
        picture; True when this interaction takes it (the click then does not select the view)."""
        return False

    def close(self) -> None:
        """Remove everything this interaction added."""
        for handle in reversed(self.handles):
            with contextlib.suppress(Exception):  # gone with its parent already
                handle.remove()
        self.handles.clear()


def interactions_for(module: str) -> list[type[Interaction]]:
    """The interaction classes of pipeline ``module`` (none when it has no interactions file)."""
    name = f"{__name__}.{module}"
    try:
        found = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        found = None
    if found is None:
        return []
    classes = getattr(importlib.import_module(name), "INTERACTIONS", [])
    return [c for c in classes if isinstance(c, type) and issubclass(c, Interaction)]


__all__ = ["EXPLORE_ROOT", "Interaction", "InteractionContext", "LegendEntry", "NamedHandles", "StateView",
           "Swatch", "handles_bounds", "interactions_for", "node_points"]
