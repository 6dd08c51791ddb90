"""Click a pixel of the left image: every matching cost over disparity at that pixel (Plots tab).

The left image of the rectified pair is drawn as a clickable plane in the left camera's frustum in
the 3D scene (viser scene images are clickable, GUI images are not), or a pixel is typed: the cost
over disparity of every matching cost (SSD, NSSD, SAD, ZSAD, NCC, rank, census) and of the
session's aggregated volume, each normalised to [0, 1] so that they share an axis, each minimum
marked, and the true disparity when known. The rectified rig (both cameras and the baseline) is
drawn before ``reconstruct_points`` draws its cameras. Reference: R. Szeliski, *Computer Vision:
Algorithms and Applications*, 2nd ed. (2022), section 12.3 (matching costs).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lab.core.errors import InvalidValue, LabError, MissingInput
from lab.core.values import Image, Points2D
from lab.geometry.camera_views import click_to_pixel, image_placement, lift_pixels
from lab.modules.stereo import COSTS, cost_curves
from lab.viewer.drawing import draw_overlays, frustum_segments
from lab.viewer.interactions import Interaction, InteractionContext, LegendEntry, NamedHandles, Swatch
from lab.viewer.interactions.stereo.maps import truth_disparity
from lab.viewer.plots import set_uplot
from lab.viewer.renderers import FRUSTUM_MAX_SIDE, overlay_view

#: Colours (RGB, 0-255) of what the interactions draw.
PICK_COLOR = (255, 210, 0)


CAMERA_COLORS = ((40, 90, 200), (230, 120, 20))


BASELINE_COLOR = (80, 80, 80)


#: Series colours of the cost plot (one per cost of :data:`lab.modules.stereo.COSTS`, then "aggregated").
COST_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#111111")


TRUTH_COLOR = "#17becf"


#: the rectified pair, its cost volumes and what places it in 3D (:class:`CostCurveExplorer`),
COST_READS = ("left", "right", "K", "baseline", "cost_volume", "aggregated_cost", "disparity_wta", "depth",
              "cameras")


def check_pick(x: Any, y: Any, width: int, height: int) -> tuple[int, int]:
    """A picked pixel as integer column and row ``(x, y)`` inside a ``width x height`` image.

    ``x``, ``y`` may be fractional (a click): each is rounded to the nearest pixel centre; the image
    covers ``[-0.5, width - 0.5) x [-0.5, height - 0.5)`` (pixel centres are integers, DESIGN.md 3).
    Raises :class:`InvalidValue` naming the image's range otherwise.
    """
    try:
        u, v = float(x), float(y)
    except (TypeError, ValueError):
        raise InvalidValue("pixel", f"expected two numbers (x, y), got ({x!r}, {y!r})") from None
    if not (math.isfinite(u) and math.isfinite(v)):
        raise InvalidValue("pixel", f"(x, y) must be finite numbers, got ({u}, {v})")
    if not (-0.5 <= u < width - 0.5 and -0.5 <= v < height - 0.5):
        raise InvalidValue("pixel", f"({u:g}, {v:g}) is outside the left image ({width} x {height}: x in "
                                    f"0..{width - 1}, y in 0..{height - 1})")
    return min(math.floor(u + 0.5), width - 1), min(math.floor(v + 0.5), height - 1)


def click_to_left_pixel(ray_origin: Any, ray_direction: Any, K: np.ndarray, width: int, height: int,
                        depth: float) -> tuple[int, int]:
    """The pixel of the left image a click's ray (world = rectified left camera frame) lands on.

    The left image is drawn on the plane ``Z = depth`` of the left camera (``R = I``, ``t = 0``);
    :func:`lab.geometry.camera_views.click_to_pixel` intersects the ray with it and projects
    the point with ``K``; :func:`check_pick` rounds and bounds it.
    """
    uv = click_to_pixel(ray_origin, ray_direction, K, np.eye(3), np.zeros(3), depth)
    return check_pick(uv[0], uv[1], width, height)


def normalize_curves(costs: np.ndarray) -> np.ndarray:
    """Each row of ``costs`` ``(S, D)`` mapped to [0, 1] by its own minimum and maximum (a flat row: 0).

    Costs differ in unit and range (SSD in gray levels squared, census in bits, NCC in [0, 2]);
    normalised, they share one axis and keep their minima where they were.
    """
    costs = np.asarray(costs, dtype=np.float64)
    low = np.nanmin(costs, axis=1, keepdims=True)
    span = np.nanmax(costs, axis=1, keepdims=True) - low
    return np.where(span > 0, (costs - low) / np.where(span > 0, span, 1.0), 0.0)


@dataclass(frozen=True)
class CostCurves:
    """The costs of one left pixel over the disparities, as gathered for the plot.

    ``pixel`` ``(x, y)``; ``disparities`` ``(D,)`` = ``0 .. max_disparity``; ``costs`` ``(S, D)`` raw and
    ``normalized`` ``(S, D)`` in [0, 1] (:func:`normalize_curves`), one row per ``labels`` entry (the
    costs, then "aggregated" for the session's volume when given); ``minima`` ``(S,)`` each row's
    argmin (first on ties, as ``winner_take_all``); ``truth`` the true disparity at the pixel (None
    when unknown); ``window`` the matching window.
    """

    pixel: tuple[int, int]
    disparities: np.ndarray
    costs: np.ndarray
    normalized: np.ndarray
    labels: tuple[str, ...]
    minima: np.ndarray
    truth: float | None
    window: int

    def minimum(self, label: str) -> int:
        """The disparity where series ``label`` is lowest."""
        if label not in self.labels:
            raise InvalidValue("label", f"no curve {label!r}; curves are {list(self.labels)}")
        return int(self.minima[self.labels.index(label)])


def gather_cost_curves(left: Image, right: Image, x: int, y: int, *, window: int, max_disparity: int,
                       costs: tuple[str, ...] = COSTS, aggregated_cost: np.ndarray | None = None,
                       truth_disparity: np.ndarray | None = None) -> CostCurves:
    """Every matching cost of left pixel ``(x, y)`` over ``d = 0 .. max_disparity``, normalised, minima found.

    The costs come from :func:`lab.modules.stereo.cost_curves` (each cost computed by
    ``cost_volume`` on a crop around the pixel: the values of the full volume); ``aggregated_cost``
    (the session's volume) adds its column at the pixel, whose minimum is the session's
    winner-take-all disparity. ``truth_disparity`` ``(H, W)`` (-1 unknown) gives the true disparity.
    Raises :class:`InvalidValue` for a pixel outside the image.
    """
    x, y = check_pick(x, y, left.width, left.height)
    curve = cost_curves(left, right, x, y, costs=costs, window=window, max_disparity=max_disparity,
                        aggregated_cost=aggregated_cost)
    raw = np.asarray(curve.y, dtype=np.float64)
    truth = None
    if truth_disparity is not None and np.shape(truth_disparity) == (left.height, left.width):
        value = float(np.asarray(truth_disparity)[y, x])
        truth = value if value >= 0 and math.isfinite(value) else None
    minima = np.array([int(np.nanargmin(row)) if np.isfinite(row).any() else -1 for row in raw],
                      dtype=np.int64)
    return CostCurves((x, y), np.asarray(curve.x, dtype=np.float64), raw, normalize_curves(raw),
                      tuple(curve.labels),
                      minima, truth, int(window))


def cost_plot(curves: CostCurves, *, session_cost: str | None = None) -> dict[str, Any]:
    """Keyword arguments of ``gui.add_uplot`` for :class:`CostCurves`: the normalised curves, a marker at each
    minimum, and the true disparity as a vertical line.

    uPlot shares one x array among its series, so the true disparity (fractional) is inserted into
    the disparities twice, the curves linearly interpolated there (what uPlot draws anyway) and the
    truth series is 0 then 1.1 at it (NaN elsewhere: a gap). A marker series is NaN except at its
    curve's minimum. The session's cost (``session_cost``) is drawn thicker.
    """
    x = curves.disparities
    insert_at = None
    if curves.truth is not None:
        insert_at = int(np.searchsorted(x, curves.truth))
        xs = np.insert(x, insert_at, [curves.truth, curves.truth])
    else:
        xs = x.copy()

    def on_grid(row: np.ndarray) -> np.ndarray:
        if insert_at is None or curves.truth is None:
            return row.copy()
        value = float(np.interp(curves.truth, x, row))
        return np.insert(row, insert_at, [value, value])

    def index_of(d: int) -> int:  # position of disparity d in xs
        return int(d) + (2 if insert_at is not None and int(d) >= insert_at else 0)

    data: list[np.ndarray] = [xs.astype(np.float64)]
    series: list[dict[str, Any]] = [{"label": "disparity (px)"}]
    markers: list[tuple[np.ndarray, dict[str, Any]]] = []
    for s, label in enumerate(curves.labels):
        color = COST_COLORS[COSTS.index(label)] if label in COSTS else COST_COLORS[-1]
        chosen = label == session_cost or label == "aggregated"
        name = label + (" (session's cost)" if label == session_cost else "")
        if label == "aggregated":
            name = "aggregated (session's volume)"
        row = on_grid(curves.normalized[s])
        data.append(row)
        series.append({"label": f"{name}: min at {int(curves.minima[s])}", "stroke": color,
                       "width": 3 if chosen else 1.5, **({"dash": [6, 4]} if label == "aggregated" else {})})
        marker = np.full(len(xs), np.nan)
        if curves.minima[s] >= 0:
            marker[index_of(curves.minima[s])] = row[index_of(curves.minima[s])]
        markers.append((marker, {"label": f"min {label}", "stroke": color, "width": 0,
                                 "points": {"show": True, "size": 10 if chosen else 7, "fill": color}}))
    for marker, entry in markers:
        data.append(marker)
        series.append(entry)
    if insert_at is not None:
        line = np.full(len(xs), np.nan)
        line[insert_at], line[insert_at + 1] = 0.0, 1.1
        data.append(line)
        series.append({"label": f"true disparity {curves.truth:.2f}", "stroke": TRUTH_COLOR, "width": 2,
                       "dash": [3, 3]})
    return {"data": tuple(data), "series": tuple(series),
            "scales": {"x": {"time": False}, "y": {"range": [-0.05, 1.15]}}, "legend": {"live": False}}


@dataclass(frozen=True)
class MatchingSettings:
    """The cost volume the session built (or would build): its ``cost``, ``window`` and ``max_disparity``,
    and ``source`` saying where they come from."""

    cost: str
    window: int
    max_disparity: int
    source: str


def last_params(history: list[Any], step: str) -> dict[str, Any] | None:
    """The controls of the last successful run of ``step`` in a session's history (None: never ran)."""
    for record in reversed(history):
        if record.step == step and record.status == "ok":
            return dict(record.params)
    return None


def matching_settings(state: Mapping[str, Any], history: list[Any], defaults: Mapping[str, Any], width: int,
                      truth_disparity: np.ndarray | None = None) -> MatchingSettings:
    """The cost, window and disparity range of the session's cost volume, else the step's defaults.

    With ``cost_volume`` in state: the controls of the last successful ``cost_volume`` run, the range
    checked against the volume's depth. Otherwise the step's defaults (``defaults``), the range
    widened to the true disparities when known, and at most ``width - 1``.
    """
    params = last_params(history, "cost_volume")
    volume = state.get("cost_volume")
    if params is not None and volume is not None and np.ndim(volume) == 3:
        return MatchingSettings(str(params["cost"]), int(params["window"]), int(np.shape(volume)[2]) - 1,
                                "the session's cost volume")
    top = int(defaults.get("max_disparity", 64)) or max(16, width // 4)  # 0: auto, estimated when it runs
    if truth_disparity is not None and np.any(np.asarray(truth_disparity) >= 0):
        top = max(top, math.ceil(float(np.max(truth_disparity))) + 2)
    return MatchingSettings(str(defaults.get("cost", "census")), int(defaults.get("window", 5)),
                            max(1, min(top, width - 1)), "the cost_volume step's defaults (not run yet)")


def rig_segments(K: np.ndarray, baseline: float, width: int, height: int, depth: float) -> np.ndarray:
    """Line segments ``(2, 8, 2, 3)`` of the rectified pair's frustums: the left camera at the origin, the
    right one at ``(baseline, 0, 0)``, both looking along +z, each image outline at depth ``depth`` and the
    four rays from its centre to the outline's corners."""
    corners_px = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5],
                           [-0.5, height - 0.5]])
    out = []
    for centre in (np.zeros(3), np.array([float(baseline), 0.0, 0.0])):
        out.append(frustum_segments(centre, lift_pixels(K, np.eye(3), -centre, corners_px, depth)))
    return np.array(out, dtype=np.float32)


class CostCurveExplorer(Interaction):
    """Click a pixel of the left image (a plane in the left camera's frustum in 3D, or the number inputs):
    every matching cost over disparity at that pixel, normalised, minima marked, the true disparity (Plots
    tab)."""

    title = "Matching costs of a pixel"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        self.lock = threading.RLock()
        self.nodes = NamedHandles()
        self.curves: CostCurves | None = None
        self.settings: MatchingSettings | None = None
        self.left: Image | None = None
        self.right: Image | None = None
        self.K: np.ndarray | None = None
        self.baseline: float | None = None
        self.depth = 1.0  # depth of the left image plane in the scene
        self._state: Mapping[str, Any] = {}
        self._key: tuple | None = None
        self._syncing = False
        self._base: tuple[int, np.ndarray] | None = None
        self._rig_key: tuple | None = None
        self._plot: Any = None
        gui = ctx.gui
        self.source_md = self.track(gui.add_markdown("Run rectify_pair: the costs compare the rectified "
                                                     "pair."))
        self.x_input = self.track(gui.add_number("x (column)", 0, min=0, step=1,
                                                 hint="a pixel of the left image"))
        self.y_input = self.track(gui.add_number("y (row)", 0, min=0, step=1,
                                                 hint="a pixel of the left image"))
        self.pick_button = self.track(gui.add_button("Show cost curves",
                                                     hint="the pixel above (or click the left image in the "
                                                          "3D scene)"))
        self.pick_md = self.track(gui.add_markdown(""))
        self.pick_button.on_click(lambda _: ctx.guarded(self._pick_from_inputs)())
        self.x_input.on_update(lambda _: None if self._syncing else ctx.guarded(self._pick_from_inputs)())
        self.y_input.on_update(lambda _: None if self._syncing else ctx.guarded(self._pick_from_inputs)())

    # --- public actions ------------------------------------------------------------------------------
    def pick_pixel(self, x: float, y: float) -> CostCurves | None:
        """Show the cost curves of left pixel ``(x, y)``; None (error shown) when invalid."""
        return self.ctx.attempt(lambda: self._pick(x, y))

    def click_image(self, ray_origin: Any, ray_direction: Any) -> CostCurves | None:
        """A click on the left image plane in the scene (its ray in world = left camera coordinates)."""
        return self.ctx.attempt(lambda: self._click(ray_origin, ray_direction))

    def scene_nodes(self) -> list[str]:
        """Names of the scene nodes drawn now."""
        with self.lock:
            return self.nodes.names()

    def plot_config(self) -> dict[str, Any] | None:
        """What the Plots tab shows now (``gui.add_uplot`` keyword arguments), None before a pick."""
        with self.lock:
            if self.curves is None:
                return None
            return cost_plot(self.curves, session_cost=self._session_cost())

    def legend(self) -> list[LegendEntry]:
        """The rig (baseline, the left image as a clickable plane) and the picked pixel's ray."""
        with self.lock:
            if self.K is None or self.left is None:
                return []
            rig = (Swatch(BASELINE_COLOR, f"the baseline B = {self.baseline or 0.0:.3g} m"),
                   Swatch(CAMERA_COLORS[0], "left camera"), Swatch(CAMERA_COLORS[1], "right camera"))
            entries = [LegendEntry("stereo rig", "cameras", 2, rig,
                                   "the left image as a plane in front of its camera: click a pixel")]
            if self.curves is not None:
                entries.append(LegendEntry("picked pixel", "ray", 1, (Swatch(
                    PICK_COLOR, "its ray to the depth of its disparity, and the point there"),)))
            return entries

    def bounds(self) -> np.ndarray | None:
        with self.lock:
            if self.K is None or self.left is None:
                return None
            corners = lift_pixels(self.K, np.eye(3), np.zeros(3), np.array(
                [[0.0, 0.0], [self.left.width - 1.0, self.left.height - 1.0]]), self.depth)
            points = np.concatenate([np.zeros((1, 3)), corners, [[self.baseline or 0.0, 0.0, 0.0]]])
            return np.stack([points.min(axis=0), points.max(axis=0)])

    # --- wiring ----------------------------------------------------------------------------------------
    def _pick_from_inputs(self) -> None:
        self._pick(self.x_input.value, self.y_input.value)

    def _click(self, ray_origin: Any, ray_direction: Any) -> CostCurves:
        with self.lock:
            left, _, _ = self._require_pair()
            if self.K is None:
                raise MissingInput("K", "the rectified camera matrix is missing: run rectify_pair")
            x, y = click_to_left_pixel(ray_origin, ray_direction, self.K, left.width, left.height, self.depth)
            return self._pick(x, y)

    def _require_pair(self) -> tuple[Image, Image, MatchingSettings]:
        """The rectified pair and the cost volume's settings; :class:`MissingInput` before the pair."""
        if self.left is None or self.right is None or self.settings is None:
            raise MissingInput("left", "no rectified pair yet: run rectify_pair")
        return self.left, self.right, self.settings

    def _session_cost(self) -> str | None:
        settings = self.settings
        return settings.cost if settings is not None and settings.source.startswith("the session") else None

    def _pick(self, x: Any, y: Any) -> CostCurves:
        with self.lock:
            left, right, settings = self._require_pair()
            volume = self._state.get("aggregated_cost")
            size = (left.height, left.width)
            if volume is not None and (np.ndim(volume) != 3 or np.shape(volume)[:2] != size):
                volume = None
            curves = gather_cost_curves(left, right, x, y, window=settings.window,
                                        max_disparity=settings.max_disparity, aggregated_cost=volume,
                                        truth_disparity=truth_disparity(self.ctx.session, left))
            self.curves = curves
            self._syncing = True
            try:
                self.x_input.value, self.y_input.value = curves.pixel
            finally:
                self._syncing = False
            self._draw_plot()
            self._draw_pick()
            self._draw_texture()
            return curves

    # --- redraw on new state ---------------------------------------------------------------------------
    def update(self, state: Mapping[str, Any]) -> None:
        state = self.ctx.values(COST_READS, state)
        key = tuple(id(state.get(n)) for n in ("left", "right", "K", "baseline", "cost_volume",
                                               "aggregated_cost",
                                               "disparity_wta", "depth", "cameras"))
        with self.lock:
            if key == self._key:
                return
            self._key = key
            self._state = state
            left, right = state.get("left"), state.get("right")
            if not isinstance(left, Image) or not isinstance(right, Image):
                self.left = self.right = self.K = self.curves = None
                self._rig_key = None
                self.nodes.clear()
                self._remove_plot()
                self.source_md.content = "Run rectify_pair: the costs compare the rectified pair."
                self.pick_md.content = ""
                return
            pair_changed = left is not self.left
            self.left, self.right = left, right
            K = state.get("K")
            self.K = np.asarray(K, dtype=np.float64) if K is not None and np.shape(K) == (3, 3) else None
            baseline = state.get("baseline")
            self.baseline = float(baseline) if baseline is not None else None
            session = self.ctx.session
            truth = truth_disparity(session, left)
            defaults = {c.name: c.default for c in session.pipeline.step("cost_volume").controls}
            self.settings = matching_settings(state, list(session.history), defaults, left.width, truth)
            self.depth = self._plane_depth()
            self.x_input.max, self.y_input.max = left.width - 1, left.height - 1
            s = self.settings
            ours = s.source.startswith("the session")
            which = f"; its cost: **{s.cost}**)" if ours else ")"
            self.source_md.content = (f"Costs with a {s.window} x {s.window} window over disparities "
                                      f"0..{s.max_disparity} ({s.source}{which}. Click the left image in the "
                                      "3D scene or type a pixel; the curves are in the Plots panel, each "
                                      "scaled to [0, 1].")
            rig_key = (id(left), id(K), id(baseline), self._state.get("cameras") is None)
            if rig_key != self._rig_key:  # redraw the planes and frustums only when they change
                self._rig_key = rig_key
                self._draw_rig()
            if self.curves is None or pair_changed:
                start = self.curves.pixel if self.curves is not None else (left.width // 2, left.height // 2)
                self.curves = None
                try:
                    self._pick(*start)
                except LabError:  # the old pixel is outside a new, smaller pair
                    self._pick(left.width // 2, left.height // 2)
            else:
                self._pick(*self.curves.pixel)

    def _plane_depth(self) -> float:
        """Where the left image is drawn: a quarter of the scene's median true depth, else 3 baselines."""
        depth = self.ctx.session.truth.get("depth")
        if depth is not None:
            z = np.asarray(depth, dtype=np.float64)
            z = z[np.isfinite(z) & (z > 0)]
            if z.size:
                return 0.25 * float(np.median(z))
        return 3.0 * (self.baseline if self.baseline and self.baseline > 0 else 1.0)

    # --- drawing ---------------------------------------------------------------------------------------
    def _draw_rig(self) -> None:
        """The left image as a clickable plane in the left frustum; both cameras while ``cameras`` is not
        drawn."""
        scene, ctx = self.ctx.scene, self.ctx
        self.nodes.drop("rig")
        if self.K is None or self.left is None:
            return
        width, height = self.left.width, self.left.height
        B = self.baseline or 0.0
        if self._state.get("cameras") is None and B > 0:  # reconstruct_points draws them (generic Cameras)
            segments = rig_segments(self.K, B, width, height, self.depth)
            for index, name in enumerate(("left", "right")):
                self._draw_camera(index, name, segments[index], (B * index, 0.0, 0.0))
        else:
            for index, name in enumerate(("left", "right")):
                self._draw_camera(index, name, None, (B * index, 0.0, 0.0))
        if B > 0:
            self.nodes.put("rig/baseline", lambda: scene.add_line_segments(
                ctx.node("rig", "baseline"), points=np.array([[[0.0, 0.0, 0.0], [B, 0.0, 0.0]]], np.float32),
                colors=BASELINE_COLOR, thickness=3.0, thickness_units="screen"))
            self.nodes.put("rig/baseline_label", lambda: scene.add_label(
                ctx.node("rig", "baseline_label"), f"B = {B:.3g} m", position=(B / 2.0, 0.0, 0.0)))
        self._draw_texture(force=True)

    def _draw_texture(self, *, force: bool = False) -> None:
        """The left image (with the picked pixel circled) on its plane at ``self.depth``."""
        if self.K is None or self.left is None:
            return
        if self._base is None or self._base[0] != id(self.left):
            self._base = (id(self.left), overlay_view(self.left, [], max_side=FRUSTUM_MAX_SIDE))
        overlays = []
        if self.curves is not None:
            overlays.append(Points2D(np.array([self.curves.pixel], np.float64),
                                     colors=np.array([PICK_COLOR], np.float64) / 255.0))
        texture = draw_overlays(self.left, overlays, base=self._base[1])
        handle = self.nodes.handles.get("rig/left/image")
        if handle is not None and not force:
            handle.image = texture
            return
        placement = image_placement(self.K, np.eye(3), np.zeros(3), self.left.width, self.left.height,
                                    self.depth)
        handle = self.nodes.put("rig/left/image", lambda: self.ctx.scene.add_image(
            self.ctx.node("rig", "left", "image"), texture, placement.render_width, placement.render_height,
            format="jpeg", jpeg_quality=85, wxyz=(1.0, 0.0, 0.0, 0.0), position=placement.position,
            cast_shadow=False, receive_shadow=False))
        handle.on_click(lambda event: self.ctx.guarded(
            lambda: self._click(event.ray_origin, event.ray_direction))())

    def _draw_camera(self, index: int, name: str, segments: np.ndarray | None,
                     centre: tuple[float, float, float]) -> None:
        """Camera ``name``'s label at its centre, and its frustum when ``segments`` are given."""
        scene, node = self.ctx.scene, self.ctx.node
        if segments is not None:
            self.nodes.put(f"rig/{name}/frustum", lambda: scene.add_line_segments(
                node("rig", name, "frustum"), points=segments, colors=CAMERA_COLORS[index], thickness=2.0,
                thickness_units="screen"))
        self.nodes.put(f"rig/{name}/label", lambda: scene.add_label(node("rig", name, "label"),
                                                                    f"{name} camera", position=centre))

    def _draw_pick(self) -> None:
        """The picked pixel's ray from the left camera to its depth (the session's, else the truth's)."""
        self.nodes.drop("pick")
        curves, left = self.curves, self.left
        if curves is None or self.K is None or left is None:
            return
        x, y = curves.pixel
        z = None
        for depth in (self._state.get("depth"), self.ctx.session.truth.get("depth")):
            if depth is not None and np.shape(depth) == (left.height, left.width) and depth[y, x] > 0:
                z = float(depth[y, x])
                break
        far = z if z is not None else 4.0 * self.depth
        ends = lift_pixels(self.K, np.eye(3), np.zeros(3), np.array([[x, y]], np.float64), far)[0]
        on_plane = lift_pixels(self.K, np.eye(3), np.zeros(3), np.array([[x, y]], np.float64),
                               0.995 * self.depth)[0]
        self.nodes.put("pick/ray", lambda: self.ctx.scene.add_line_segments(
            self.ctx.node("pick", "ray"), points=np.array([[[0.0, 0.0, 0.0], ends]],
                                                          np.float32), colors=PICK_COLOR,
            thickness=2.0, thickness_units="screen"))
        self.nodes.put("pick/pixel", lambda: self.ctx.scene.add_icosphere(
            self.ctx.node("pick", "pixel"), radius=0.01 * self.depth, color=PICK_COLOR,
            position=tuple(on_plane)))
        if z is not None:
            self.nodes.put("pick/point", lambda: self.ctx.scene.add_icosphere(
                self.ctx.node("pick", "point"), radius=0.02 * self.depth, color=PICK_COLOR,
                position=tuple(ends)))

    def _remove_plot(self) -> None:
        self.untrack(self._plot)
        self._plot = None

    def _draw_plot(self) -> None:
        curves, left = self.curves, self.left
        if curves is None or left is None:
            return
        config = cost_plot(curves, session_cost=self._session_cost())
        title = f"matching costs at ({curves.pixel[0]}, {curves.pixel[1]}), each scaled to [0, 1]"
        if self._plot is not None:  # changed in place, whatever its shape (set_uplot says why)
            set_uplot(self._plot, data=config["data"], series=config["series"], scales=config["scales"],
                      title=title)
        else:
            with self.ctx.plots:
                self._plot = self.track(self.ctx.gui.add_uplot(
                    config["data"], config["series"], scales=config["scales"], legend=config["legend"],
                    title=title, aspect=1.4, order=1000.0))
        session_cost = self._session_cost()
        rows = ["| cost | min at d | |", "|---|---|---|"]
        for label, d in zip(curves.labels, curves.minima, strict=True):
            note = []
            if label == session_cost:
                note.append("session's cost")
            if label == "aggregated":
                note.append("= winner-take-all")
            if curves.truth is not None:
                note.append(f"{d - curves.truth:+.1f} px from the truth")
            rows.append(f"| {label} | {int(d)} | {', '.join(note)} |")
        truth = (f"true disparity **{curves.truth:.2f} px**" if curves.truth is not None
                 else "no true disparity here")
        wta = self._state.get("disparity_wta")
        chosen = ""
        if wta is not None and np.shape(wta) == (left.height, left.width):
            chosen_d = int(np.asarray(wta)[curves.pixel[1]][curves.pixel[0]])
            chosen = f"; the session's winner-take-all: **{chosen_d}**"
        self.pick_md.content = (f"Pixel ({curves.pixel[0]}, {curves.pixel[1]}): {truth}{chosen}.\n\n"
                                + "\n".join(rows))

    def close(self) -> None:
        with self.lock:
            self.nodes.clear()
            self._plot = None
        super().close()


__all__ = ["COST_READS", "CostCurveExplorer", "CostCurves", "MatchingSettings", "check_pick",
           "click_to_left_pixel", "cost_plot", "gather_cost_curves", "last_params", "matching_settings",
           "normalize_curves", "rig_segments"]
