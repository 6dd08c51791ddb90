"""The SfM module's viewer interactions: points coloured by reprojection error, and a point's track.

* :class:`TrackExplorer` - pick a 3D point (by index, or by a click ray: the point nearest to it)
  and see its track: a ray from every camera that observes it, and a table of its observations
  (image, observed pixel, reprojected pixel, error).
* the same panel draws the point cloud coloured by each point's mean reprojection error (the model's
  ``errors``, green 0 px to red at the scale chosen), next to the photo-coloured cloud the generic
  drawing shows; the cameras of the final step are already tinted by their mean error
  (``Cameras.colors``).

It reads the most refined :class:`~lab.data.reconstruction.SparseModel` of the session, by the
stage names the SfM pipeline lists in its ``views`` (:data:`MODEL_VIEWS`). Cameras appearing as they
register and bundle adjustment's cost falling come from the generic drawing of the incremental
step's progress snapshots (``Progress.values``: cameras and points). The math is in pure functions
(:func:`latest_model`, :func:`track_observations`, :func:`nearest_point_to_ray`), tested directly.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lab.core import InvalidValue, MissingInput
from lab.data.reconstruction import SparseModel
from lab.modules.sfm import error_colors
from lab.viewer.interactions import Interaction, InteractionContext, LegendEntry, Swatch

#: The model stages the interaction reads (in the SfM pipeline's ``views``), the most refined first.
MODEL_VIEWS = ("adjusted_model", "filtered_model", "model")


@dataclass(frozen=True)
class TrackObservation:
    """One observation of a point: ``view`` (image index), ``name``, ``observed`` and ``reprojected`` pixels,
    ``error_px`` and the camera ``center`` ``(3,)``."""

    view: int
    name: str
    observed: np.ndarray
    reprojected: np.ndarray
    error_px: float
    center: np.ndarray


def latest_model(state: Mapping[str, Any]) -> SparseModel | None:
    """The most refined model in ``state`` (bundle-adjusted, filtered, incremental: :data:`MODEL_VIEWS`),
    or None."""
    return next((state[name] for name in MODEL_VIEWS if isinstance(state.get(name), SparseModel)), None)


def track_observations(model: SparseModel, index: int) -> list[TrackObservation]:
    """Every observation of point ``index``: where it was seen, where the model reprojects it, the error."""
    if not 0 <= int(index) < len(model.points):
        raise InvalidValue("point", f"no point {index}: the model has points 0 to {len(model.points) - 1}")
    kp, views, point = model.observations()
    X = model.points[int(index)]
    out = []
    for keypoint, view in zip(kp[point == int(index)], views[point == int(index)], strict=True):
        view = int(view)
        R, t = model.R[view], model.t[view]
        x = model.K[view] @ (R @ X + t)
        reprojected = x[:2] / x[2]
        observed = model.keypoints.xy[keypoint]
        out.append(TrackObservation(view, model.names[view], observed.copy(), reprojected,
                                    float(np.linalg.norm(reprojected - observed)), -R.T @ t))
    return out


def nearest_point_to_ray(points: np.ndarray, origin: Any, direction: Any) -> int:
    """Index of the point (in front of ``origin``) nearest to the ray ``origin + s direction``, s > 0."""
    points = np.asarray(points, dtype=np.float64)
    if not len(points):
        raise InvalidValue("points", "there are no points to pick")
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    v = points - np.asarray(origin, dtype=np.float64)
    along = v @ d
    distance = np.linalg.norm(v - along[:, None] * d, axis=1)
    distance = np.where(along > 0, distance, np.inf)
    if not np.isfinite(distance).any():
        raise InvalidValue("ray", "no point lies in front of the click")
    return int(np.argmin(distance))


class TrackExplorer(Interaction):
    """Colour points by reprojection error; pick a point and see its track's observations."""

    title = "Tracks and errors"

    def __init__(self, ctx: InteractionContext) -> None:
        super().__init__(ctx)
        gui = ctx.gui
        self.info = self.track(gui.add_markdown("Run **reconstruct_incrementally** to explore tracks."))
        self.by_error = self.track(gui.add_checkbox("colour points by error", initial_value=False))
        self.scale = self.track(gui.add_number("error scale (px)", initial_value=1.0, min=0.05, max=50.0,
                                               step=0.05))
        self.index = self.track(gui.add_number("point", initial_value=0, min=0, step=1))
        self.show = self.track(gui.add_button("Show its track", hint="rays from the cameras that see it"))
        self.table = self.track(gui.add_markdown(""))
        self.by_error.on_update(ctx.guarded(lambda _: self.draw_errors()))
        self.scale.on_update(ctx.guarded(lambda _: self.draw_errors()))
        self.show.on_click(ctx.guarded(lambda _: self.pick_point(int(self.index.value))))
        self.model: SparseModel | None = None
        self.seen: tuple[int, ...] = ()
        self.nodes: dict[str, Any] = {}
        self.picked: list[TrackObservation] = []

    # --- public, tested ---------------------------------------------------------------------------
    def pick_point(self, index: int) -> list[TrackObservation]:
        """Draw point ``index``'s track (a ray per observing camera) and list its observations."""
        model = self._require()
        observations = track_observations(model, index)
        X = model.points[int(index)]
        starts = np.array([o.center for o in observations])
        ends = np.repeat(X[None], len(observations), axis=0)
        colors = error_colors(np.array([o.error_px for o in observations]), float(self.scale.value))
        self._put("track", lambda: self.ctx.scene.add_line_segments(
            self.ctx.node("track"), points=np.stack([starts, ends], axis=1).astype(np.float32),
            colors=np.repeat(colors[:, None], 2, axis=1).astype(np.float32), thickness=2.0,
            thickness_units="screen"))
        self._put("point", lambda: self.ctx.scene.add_icosphere(
            self.ctx.node("point"), radius=0.01 * max(self.ctx.extent(), 1e-3), color=(255, 220, 0),
            position=tuple(float(v) for v in X)))
        rows = ["| image | observed (px) | reprojected (px) | error (px) |", "|---|---|---|---|"]
        rows += [f"| {o.name} | ({o.observed[0]:.2f}, {o.observed[1]:.2f}) | ({o.reprojected[0]:.2f}, "
                 f"{o.reprojected[1]:.2f}) | {o.error_px:.3f} |" for o in observations]
        heading = f"**Point {int(index)}**: seen in {len(observations)} images"
        self.table.content = heading + "\n\n" + "\n".join(rows)
        self.picked = observations
        return observations

    def click_ray(self, ray_origin: Any, ray_direction: Any) -> list[TrackObservation]:
        """Pick the point nearest to a click ray (``scene.on_pointer_event``) and show its track."""
        model = self._require()
        index = nearest_point_to_ray(model.points, ray_origin, ray_direction)
        self.index.value = index
        return self.pick_point(index)

    def draw_errors(self) -> np.ndarray | None:
        """Draw (or hide) the cloud coloured by reprojection error; returns the colours drawn."""
        if not self.by_error.value or self.model is None:
            self._drop("errors")
            return None
        colors = error_colors(self.model.errors, float(self.scale.value))
        points = self.model.points.astype(np.float32)
        self._put("errors", lambda: self.ctx.scene.add_point_cloud(
            self.ctx.node("errors"), points=points, colors=colors.astype(np.float32),
            point_size=0.006 * max(self.ctx.extent(), 1e-3)))
        return colors

    def scene_nodes(self) -> list[str]:
        return sorted(self.nodes)

    def legend(self) -> list[LegendEntry]:
        """The cloud by reprojection error and the picked point's track, when drawn."""
        scale = float(self.scale.value)
        ends = (np.clip(error_colors(np.array([0.0, scale]), scale), 0, 1) * 255 + 0.5).astype(int)
        green, red = ((int(r), int(g), int(b)) for r, g, b in ends)
        by_error = (Swatch(green, "0 px"), Swatch(red, f"{scale:g} px or more (slider)"))
        entries = []
        if "errors" in self.nodes and self.model is not None:
            entries.append(LegendEntry("points by error", "points", len(self.model.points), by_error,
                                       "each point's mean reprojection error, green to red"))
        if "track" in self.nodes:
            entries.append(LegendEntry("picked track", "rays", len(self.picked), by_error,
                                       "a ray from each camera that sees the yellow point, by its error"))
        return entries

    # --- the viewer's hooks -------------------------------------------------------------------------
    def update(self, state: Mapping[str, Any]) -> None:
        model = latest_model(self.ctx.values(MODEL_VIEWS, state))
        key = () if model is None else (id(model),)
        if key == self.seen:
            return
        self.seen = key
        self.model = model
        self._drop("track")
        self._drop("point")
        self.table.content = ""
        if model is None:
            self.info.content = "Run **reconstruct_incrementally** to explore tracks."
            self._drop("errors")
            return
        self.info.content = f"{len(model.points)} points: pick one to see its track."
        self.index.max = max(len(model.points) - 1, 0)
        self.draw_errors()

    def close(self) -> None:
        for name in list(self.nodes):
            self._drop(name)
        super().close()

    # --- helpers ------------------------------------------------------------------------------------
    def _require(self) -> SparseModel:
        if self.model is None:
            raise MissingInput("model", "no reconstruction yet: run reconstruct_incrementally first")
        return self.model

    def _put(self, name: str, make: Callable[[], Any]) -> None:
        self._drop(name)
        self.nodes[name] = make()

    def _drop(self, name: str) -> None:
        handle = self.nodes.pop(name, None)
        if handle is not None:
            with contextlib.suppress(Exception):  # removed with its parent already
                handle.remove()


INTERACTIONS = [TrackExplorer]

__all__ = [
    "INTERACTIONS", "MODEL_VIEWS", "TrackExplorer", "TrackObservation", "error_colors", "latest_model",
    "nearest_point_to_ray", "track_observations",
]
