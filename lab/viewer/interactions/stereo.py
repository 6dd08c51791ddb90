"""Interactions of the stereo module: what the generic drawing of a stereo session cannot show.

What the generic drawing shows already (:mod:`lab.viewer.renderers`): the photos and the rectified
pair (``left_raw``, ``right_raw``, ``left``, ``right``: Images), the final colour-mapped disparity
(``disparity_image``, after ``filter_disparity``), the point cloud (``points3d``) and both
rectified cameras as frustums (``cameras``, written by ``reconstruct_points`` with the right
camera ``baseline`` metres along x). The disparities of the earlier stages, the ground truth and
the errors are arrays, which it does not draw. So:

* **Disparity and error maps** (Images tab): the disparity of a chosen stage (winner-take-all,
  sub-pixel, final; by default the latest) colour-mapped on the scale of the true disparity, the
  true disparity itself, and the bad-pixel error map against it (green right, red wrong, blue a
  hole where the truth has a disparity) with its bad-pixel rate, when the session has a truth.
* **Matching costs of a pixel** (Plots tab): click a pixel of the left image, shown as a plane in
  the left camera's frustum in the 3D scene (viser scene images are clickable, GUI images are
  not), or type it: the cost over disparity of every matching cost (SSD, NSSD, SAD, ZSAD, NCC, rank,
  census) and of the session's aggregated volume, each normalised to [0, 1] so that they share an
  axis, each minimum marked, and the true disparity when known. The rectified rig (both cameras and
  the baseline) is drawn before ``reconstruct_points`` draws its cameras.
* **Baseline and depth resolution** (Plots tab): the depth uncertainty ``u_z = z^2 u_d / (f B)`` over
  depth for the current baseline and the previous ones; on the synthetic rig a slider restarts the
  session with another baseline and runs the pipeline to the point cloud again.

The math is in the typed functions below (tested directly); the classes only wire it to viser.
References: D. Scharstein and R. Szeliski, IJCV 47 (2002), sections 3 and 5.1 (costs, winner-take-all,
bad-pixel rates); R. Szeliski, *Computer Vision: Algorithms and Applications*, 2nd ed. (2022),
sections 12.1 (depth from disparity and its uncertainty) and 12.3 (matching costs).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any, Callable, Literal, Mapping

import numpy as np

from lab.core.errors import InvalidControl, InvalidValue, LabError, MissingInput
from lab.core.values import Image, Points2D
from lab.modules.stereo import (COSTS, MAX_VOLUME_ENTRIES, colorize_disparity, cost_curves, depth_from_disparity,
                                disparity_errors, error_map)
from lab.viewer.interactions import NamedHandles
from lab.viewer.interactions import Interaction, InteractionContext
from lab.viewer.interactions.epipolar import click_to_pixel, draw_overlays, image_placement, lift_pixels
from lab.viewer.renderers import FRUSTUM_MAX_SIDE, PANEL_MIN_SIDE, overlay_view

#: Colours (RGB, 0-255) of what the interactions draw.
PICK_COLOR = (255, 210, 0)
CAMERA_COLORS = ((40, 90, 200), (230, 120, 20))
BASELINE_COLOR = (80, 80, 80)
#: Series colours of the cost plot (one per cost of :data:`lab.modules.stereo.COSTS`, then "aggregated").
COST_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#111111")
TRUTH_COLOR = "#17becf"
BASELINE_COLORS = ("#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b")

#: Disparity stages, by the state value that holds them (latest last).
STAGES: dict[str, str] = {"winner-take-all": "disparity_wta", "sub-pixel": "disparity_subpixel",
                          "final": "disparity"}
#: The step a restart with another baseline runs to (with what it needs: the point cloud).
RUN_TO = "reconstruct_points"
#: Previous baselines kept for comparison in the uncertainty plot.
MAX_PREVIOUS_BASELINES = 5
#: Points of the uncertainty curve over depth.
UNCERTAINTY_SAMPLES = 96


# ----------------------------------------------------------------------------------------------------
# Pure math
# ----------------------------------------------------------------------------------------------------
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
        raise InvalidValue("pixel", f"({u:g}, {v:g}) is outside the left image ({width} x {height}: x in 0..{width - 1}"
                                    f", y in 0..{height - 1})")
    return min(int(math.floor(u + 0.5)), width - 1), min(int(math.floor(v + 0.5)), height - 1)


def click_to_left_pixel(ray_origin: Any, ray_direction: Any, K: np.ndarray, width: int, height: int,
                        depth: float) -> tuple[int, int]:
    """The pixel of the left image a click's ray (world = rectified left camera frame) lands on.

    The left image is drawn on the plane ``Z = depth`` of the left camera (``R = I``, ``t = 0``);
    :func:`lab.viewer.interactions.epipolar.click_to_pixel` intersects the ray with it and projects
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
    minima = np.array([int(np.nanargmin(row)) if np.isfinite(row).any() else -1 for row in raw], dtype=np.int64)
    return CostCurves((x, y), np.asarray(curve.x, dtype=np.float64), raw, normalize_curves(raw), tuple(curve.labels),
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
        if insert_at is None:
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
    top = int(defaults.get("max_disparity", 64))
    if truth_disparity is not None and np.any(np.asarray(truth_disparity) >= 0):
        top = max(top, int(math.ceil(float(np.max(truth_disparity)))) + 2)
    return MatchingSettings(str(defaults.get("cost", "census")), int(defaults.get("window", 5)),
                            max(1, min(top, width - 1)), "the cost_volume step's defaults (not run yet)")


def searchable_disparity(truth_disparity: np.ndarray | None, width: int, height: int, current: int) -> int:
    """A ``max_disparity`` that covers the true disparities (their maximum + 2), at least ``current``, at most
    ``width - 1`` and small enough for a cost volume of :data:`MAX_VOLUME_ENTRIES` entries.

    A wider baseline makes every disparity larger (``d = f B / Z``): the search range must grow with it.
    """
    top = int(current)
    if truth_disparity is not None and np.any(np.asarray(truth_disparity) >= 0):
        top = max(top, int(math.ceil(float(np.max(truth_disparity)))) + 2)
    return max(1, min(top, width - 1, MAX_VOLUME_ENTRIES // max(width * height, 1) - 1))


def depth_uncertainty_curve(depths: np.ndarray, *, focal_px: float, baseline: float,
                            disparity_std: float) -> np.ndarray:
    """``u_z = z^2 u_d / (f B)`` ``(N,)`` at the depths ``depths`` ``(N,)`` (metres), first-order propagation of a
    disparity uncertainty ``u_d`` (pixels) through ``z = f B / d``.

    Computed with the module's :func:`lab.modules.stereo.depth_from_disparity` at the disparities
    ``d = f B / z`` of those depths (so it is the step's own formula). Reference: Szeliski (2022),
    section 12.1; Hartley & Zisserman (2nd ed.), section 5.2.
    """
    depths = np.asarray(depths, dtype=np.float64)
    if depths.ndim != 1 or not np.all(np.isfinite(depths)) or np.any(depths <= 0):
        raise InvalidValue("depths", "expected positive, finite depths (metres) in a 1-D array")
    if not (math.isfinite(focal_px) and focal_px > 0):
        raise InvalidValue("focal_px", f"expected a positive focal length in pixels, got {focal_px}")
    fB = float(focal_px) * float(baseline)
    K = np.array([[float(focal_px), 0.0, 0.0], [0.0, float(focal_px), 0.0], [0.0, 0.0, 1.0]])
    _, uncertainty = depth_from_disparity((fB / depths)[None, :], K, baseline, disparity_std=float(disparity_std))
    return uncertainty[0]


def depth_range(truth_depth: np.ndarray | None, state_depth: np.ndarray | None) -> tuple[float, float]:
    """Depths ``(near, far)`` the uncertainty plot spans: the true depths' range, else the 1st-99th percentile of
    the session's depths, else 0.5 to 10 m."""
    for depth, robust in ((truth_depth, False), (state_depth, True)):
        if depth is None:
            continue
        z = np.asarray(depth, dtype=np.float64)
        z = z[np.isfinite(z) & (z > 0)]
        if z.size >= 2:
            near, far = (np.percentile(z, [1, 99]) if robust else (z.min(), z.max()))
            if far > near:
                return float(near), float(far)
    return 0.5, 10.0


@dataclass(frozen=True)
class BaselineRecord:
    """One baseline shown in the uncertainty plot: ``baseline`` (m), ``focal_px``, ``disparity_std`` (px)."""

    baseline: float
    focal_px: float
    disparity_std: float


def uncertainty_plot(current: BaselineRecord, previous: list[BaselineRecord], near: float, far: float, *,
                     preview: BaselineRecord | None = None, samples: int = UNCERTAINTY_SAMPLES) -> dict[str, Any]:
    """Keyword arguments of ``gui.add_uplot``: ``u_z`` over depth for the current baseline, the previous ones
    and (``preview``) the slider's baseline not applied yet, each :func:`depth_uncertainty_curve` on one depth
    grid ``near .. far`` of ``samples`` points."""
    depths = np.linspace(near, far, samples)
    data: list[np.ndarray] = [depths]
    series: list[dict[str, Any]] = [{"label": "depth z (m)"}]
    records = [(current, " (now)"), *[(r, "") for r in previous]]
    if preview is not None:
        records.append((preview, " (slider, not applied)"))
    for i, (record, note) in enumerate(records):
        data.append(depth_uncertainty_curve(depths, focal_px=record.focal_px, baseline=record.baseline,
                                            disparity_std=record.disparity_std))
        style: dict[str, Any] = {"width": 3} if i == 0 else {"width": 1.5, "dash": [6, 4]}
        if note.startswith(" (slider"):
            style = {"width": 2, "dash": [2, 3]}
        series.append({"label": f"B = {record.baseline:.3g} m{note}",
                       "stroke": BASELINE_COLORS[i % len(BASELINE_COLORS)], **style})
    return {"data": tuple(data), "series": tuple(series), "scales": {"x": {"time": False}}, "legend": {"live": False}}


def disparity_stage(state: Mapping[str, Any], stage: str) -> tuple[str, np.ndarray] | None:
    """The disparity map of ``stage`` (a key of :data:`STAGES`, or "latest": the last one computed) as
    ``(stage, (H, W) float64)``, None when the session has not computed it."""
    if stage == "latest":
        for name in reversed(STAGES):
            if state.get(STAGES[name]) is not None:
                return name, np.asarray(state[STAGES[name]], dtype=np.float64)
        return None
    if stage not in STAGES:
        raise InvalidValue("stage", f"expected one of {['latest', *STAGES]}, got {stage!r}")
    value = state.get(STAGES[stage])
    return None if value is None else (stage, np.asarray(value, dtype=np.float64))


@dataclass(frozen=True)
class StereoMaps:
    """The maps shown for one disparity stage: ``disparity`` (colour-mapped), ``truth`` (the true disparity on
    the same scale, or None), ``errors`` (the bad-pixel map, or None), ``scores`` (bad-pixel rates, coverage,
    end-point error: :func:`lab.modules.stereo.disparity_errors`; {} without truth), ``scale`` (the
    disparity shown at the top of the colour map)."""

    stage: str
    disparity: Image
    truth: Image | None
    errors: Image | None
    scores: dict[str, float]
    scale: float
    threshold: float


def stereo_maps(stage: str, disparity: np.ndarray, truth_disparity: np.ndarray | None, *, threshold: float,
                scale: float | None = None) -> StereoMaps:
    """Colour-map a disparity stage and, with a truth of the same size, the truth and the error map.

    Both maps use one scale (``scale``, else the largest true or computed disparity), with the
    module's :func:`~lab.modules.stereo.colorize_disparity`; errors come from
    :func:`~lab.modules.stereo.error_map` (bad: more than ``threshold`` px off).
    """
    if not (math.isfinite(threshold) and threshold > 0):
        raise InvalidControl("threshold", f"must be a positive number of pixels, got {threshold}")
    disparity = np.asarray(disparity, dtype=np.float64)
    truth = None if truth_disparity is None else np.asarray(truth_disparity, dtype=np.float64)
    if truth is not None and truth.shape != disparity.shape:
        truth = None
    if scale is None or scale <= 0:
        tops = [float(a.max()) for a in (disparity, truth) if a is not None and np.any(a >= 0)]
        scale = max(tops) if tops else 1.0
    shown = colorize_disparity(disparity, max_disparity=scale, name=f"disparity ({stage})")
    if truth is None:
        return StereoMaps(stage, shown, None, None, {}, float(scale), float(threshold))
    scores = disparity_errors(disparity, truth, thresholds=(float(threshold),))
    return StereoMaps(stage, shown, colorize_disparity(truth, max_disparity=scale, name="true disparity"),
                      error_map(disparity, truth, threshold=threshold), scores, float(scale), float(threshold))


def rig_segments(K: np.ndarray, baseline: float, width: int, height: int, depth: float) -> np.ndarray:
    """Line segments ``(2, 8, 2, 3)`` of the rectified pair's frustums: the left camera at the origin, the right
    one at ``(baseline, 0, 0)``, both looking along +z, each image outline at depth ``depth`` and the four
    rays from its centre to the outline's corners."""
    corners_px = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    out = []
    for centre in (np.zeros(3), np.array([float(baseline), 0.0, 0.0])):
        corners = lift_pixels(K, np.eye(3), -centre, corners_px, depth)
        spokes = np.stack([np.repeat(centre[None], 4, axis=0), corners], axis=1)
        outline = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
        out.append(np.concatenate([spokes, outline]))
    return np.array(out, dtype=np.float32)


# ----------------------------------------------------------------------------------------------------
# Guarded actions
# ----------------------------------------------------------------------------------------------------
def _safely(ctx: InteractionContext, action: Callable[[], Any]) -> Any:
    """Run ``action``; what it raises is shown in the tab (as a viser callback's error would be). Returns its
    result, None on error."""
    result: list[Any] = [None]

    def run() -> None:
        result[0] = action()

    ctx.guarded(run)()
    return result[0]


def _truth_disparity(session: Any, left: Any) -> np.ndarray | None:
    truth = session.truth.get("disparity")
    if truth is None or not isinstance(left, Image) or np.shape(truth) != (left.height, left.width):
        return None
    return np.asarray(truth, dtype=np.float64)


def _panel(image: Image) -> np.ndarray:
    return overlay_view(image, [], min_side=PANEL_MIN_SIDE)


def _display_scale(state: Mapping[str, Any], truth: np.ndarray | None) -> float | None:
    """The top of the disparity colour map: the largest true disparity (so both maps use every colour), else
    the searched range (the cost volume's depth)."""
    if truth is not None and np.any(truth >= 0):
        return float(truth.max())
    volume = state.get("cost_volume")
    if volume is not None and np.ndim(volume) == 3:
        return float(np.shape(volume)[2] - 1)
    return None


# ----------------------------------------------------------------------------------------------------
# Interaction 1: disparity and error maps
# ----------------------------------------------------------------------------------------------------
class DisparityMaps(Interaction):
    """The disparity of a stage colour-mapped, the true disparity and the bad-pixel error map (Images tab)."""

    title = "Disparity and error maps"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        self.lock = threading.RLock()
        self.maps: StereoMaps | None = None
        self._key: tuple | None = None
        self._state: Mapping[str, Any] = {}
        gui = ctx.gui
        self.stage_choice = self.track(gui.add_dropdown("stage", ("latest", *STAGES), initial_value="latest",
                                                        hint="which disparity map to show: the latest computed, or "
                                                             "a stage of the pipeline"))
        self.threshold_input = self.track(gui.add_number("bad if off by (px)", 2.0, min=0.1, max=64.0, step=0.1,
                                                         hint="error threshold of the error map (bad-2: 2 px)"))
        self.summary_md = self.track(gui.add_markdown(""))
        with ctx.images:
            self.panel_folder = self.track(gui.add_folder("Stereo maps", order=1000.0))
            with self.panel_folder:
                blank = np.zeros((8, 8, 3), np.uint8)
                self.disparity_panel = self.track(gui.add_image(blank, label="disparity", format="png", visible=False))
                self.truth_panel = self.track(gui.add_image(blank, label="true disparity", format="png", visible=False))
                self.error_panel = self.track(gui.add_image(blank, label="error map", format="png", visible=False))
        self.stage_choice.on_update(lambda _: ctx.guarded(self._redraw)())
        self.threshold_input.on_update(lambda _: ctx.guarded(self._redraw)())

    # --- public actions (what the GUI or a test does) ----------------------------------------------
    def show(self, stage: str = "latest", threshold: float | None = None) -> StereoMaps | None:
        """Show the maps of ``stage`` with this error threshold; None (error shown) when invalid."""

        def act() -> StereoMaps | None:
            if stage not in ("latest", *STAGES):
                raise InvalidValue("stage", f"expected one of {['latest', *STAGES]}, got {stage!r}")
            if threshold is not None and not (math.isfinite(float(threshold)) and float(threshold) > 0):
                raise InvalidControl("threshold", f"must be a positive number of pixels, got {threshold}")
            self.stage_choice.value = stage
            if threshold is not None:
                self.threshold_input.value = float(threshold)
            return self._redraw()

        return _safely(self.ctx, act)

    def update(self, state: Mapping[str, Any]) -> None:
        key = tuple(id(state.get(n)) for n in ("left", "cost_volume", *STAGES.values()))
        with self.lock:
            if key == self._key:
                return
            self._key = key
            self._state = state
            self._redraw()

    def _redraw(self) -> StereoMaps | None:
        with self.lock:
            state = self._state
            found = disparity_stage(state, str(self.stage_choice.value))
            if found is None:
                self.maps = None
                for panel in (self.disparity_panel, self.truth_panel, self.error_panel):
                    panel.visible = False
                self.summary_md.content = ("No disparity yet: run the steps up to winner_take_all." if self.stage_choice
                                           .value == "latest" else f"No {self.stage_choice.value} disparity yet.")
                return None
            stage, disparity = found
            truth = _truth_disparity(self.ctx.session, state.get("left"))
            maps = stereo_maps(stage, disparity, truth, threshold=float(self.threshold_input.value),
                               scale=_display_scale(state, truth))
            self.maps = maps
            self.disparity_panel.image = _panel(maps.disparity)
            self.disparity_panel.label = (f"disparity ({stage}), turbo 0..{maps.scale:.0f} px"
                                          + (", holes black" if stage == "final" else ""))
            self.disparity_panel.visible = True
            if maps.truth is None:
                self.truth_panel.visible = self.error_panel.visible = False
                self.summary_md.content = (f"Showing the **{stage}** disparity in the Images panel. This dataset has "
                                           "no ground truth: no error map.")
                return maps
            key = f"{maps.threshold:g}".replace(".", "_")
            bad_all, bad_pred = maps.scores.get(f"bad{key}_all", 0.0), maps.scores.get(f"bad{key}_pred", 0.0)
            self.truth_panel.image = _panel(maps.truth)
            self.truth_panel.label = "true disparity (same colours; black: unknown)"
            self.truth_panel.visible = True
            self.error_panel.image = _panel(maps.errors)
            self.error_panel.label = (f"errors of the {stage} disparity: green within {maps.threshold:g} px, red off "
                                      f"by more ({bad_pred:.1%} of predicted pixels), blue hole")
            self.error_panel.visible = True
            self.summary_md.content = (f"**{stage}** disparity against the truth: bad-{maps.threshold:g} "
                                       f"**{bad_all:.1%}** of all pixels with a truth (holes count), "
                                       f"{bad_pred:.1%} of the predicted ones; coverage "
                                       f"{maps.scores.get('coverage', 0.0):.1%}, mean error "
                                       f"{maps.scores.get('epe_px', 0.0):.2f} px.")
            return maps


# ----------------------------------------------------------------------------------------------------
# Interaction 2: click a pixel -> the cost curves of every cost
# ----------------------------------------------------------------------------------------------------
class CostCurveExplorer(Interaction):
    """Click a pixel of the left image (a plane in the left camera's frustum in 3D, or the number inputs): every
    matching cost over disparity at that pixel, normalised, minima marked, the true disparity (Plots tab)."""

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
        self._plot_shape: tuple[int, ...] | None = None
        gui = ctx.gui
        self.source_md = self.track(gui.add_markdown("Run rectify_pair: the costs compare the rectified pair."))
        self.x_input = self.track(gui.add_number("x (column)", 0, min=0, step=1, hint="a pixel of the left image"))
        self.y_input = self.track(gui.add_number("y (row)", 0, min=0, step=1, hint="a pixel of the left image"))
        self.pick_button = self.track(gui.add_button("Show cost curves", hint="the pixel above (or click the left "
                                                                                "image in the 3D scene)"))
        self.pick_md = self.track(gui.add_markdown(""))
        self.pick_button.on_click(lambda _: ctx.guarded(self._pick_from_inputs)())
        self.x_input.on_update(lambda _: None if self._syncing else ctx.guarded(self._pick_from_inputs)())
        self.y_input.on_update(lambda _: None if self._syncing else ctx.guarded(self._pick_from_inputs)())

    # --- public actions ------------------------------------------------------------------------------
    def pick_pixel(self, x: float, y: float) -> CostCurves | None:
        """Show the cost curves of left pixel ``(x, y)``; None (error shown) when invalid."""
        return _safely(self.ctx, lambda: self._pick(x, y))

    def click_image(self, ray_origin: Any, ray_direction: Any) -> CostCurves | None:
        """A click on the left image plane in the scene (its ray in world = left camera coordinates)."""
        return _safely(self.ctx, lambda: self._click(ray_origin, ray_direction))

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
            self._require_pair()
            if self.K is None:
                raise MissingInput("K", "the rectified camera matrix is missing: run rectify_pair")
            x, y = click_to_left_pixel(ray_origin, ray_direction, self.K, self.left.width, self.left.height,
                                       self.depth)
            return self._pick(x, y)

    def _require_pair(self) -> None:
        if self.left is None or self.right is None:
            raise MissingInput("left", "no rectified pair yet: run rectify_pair")

    def _session_cost(self) -> str | None:
        return self.settings.cost if self.settings is not None and self.settings.source.startswith("the session") \
            else None

    def _pick(self, x: Any, y: Any) -> CostCurves:
        with self.lock:
            self._require_pair()
            settings = self.settings
            volume = self._state.get("aggregated_cost")
            if volume is not None and (np.ndim(volume) != 3 or np.shape(volume)[:2] != (self.left.height,
                                                                                         self.left.width)):
                volume = None
            curves = gather_cost_curves(self.left, self.right, x, y, window=settings.window,
                                        max_disparity=settings.max_disparity, aggregated_cost=volume,
                                        truth_disparity=_truth_disparity(self.ctx.session, self.left))
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
        key = tuple(id(state.get(n)) for n in ("left", "right", "K", "baseline", "cost_volume", "aggregated_cost",
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
            truth = _truth_disparity(session, left)
            defaults = {c.name: c.default for c in session.pipeline.step("cost_volume").controls}
            self.settings = matching_settings(state, list(session.history), defaults, left.width, truth)
            self.depth = self._plane_depth()
            self.x_input.max, self.y_input.max = left.width - 1, left.height - 1
            s = self.settings
            ours = s.source.startswith("the session")
            self.source_md.content = (f"Costs with a {s.window} x {s.window} window over disparities "
                                      f"0..{s.max_disparity} ({s.source}" + (f"; its cost: **{s.cost}**)" if ours
                                                                            else ")")
                                      + ". Click the left image in the 3D scene or type a pixel; the curves are in "
                                        "the Plots panel, each scaled to [0, 1].")
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
        """The left image as a clickable plane in the left frustum; both cameras while ``cameras`` is not drawn."""
        scene, ctx = self.ctx.scene, self.ctx
        self.nodes.drop("rig")
        if self.K is None or self.left is None:
            return
        width, height = self.left.width, self.left.height
        B = self.baseline or 0.0
        if self._state.get("cameras") is None and B > 0:  # reconstruct_points draws them (generic Cameras)
            segments = rig_segments(self.K, B, width, height, self.depth)
            for index, name in enumerate(("left", "right")):
                self.nodes.put(f"rig/{name}/frustum", lambda index=index, name=name: scene.add_line_segments(
                    ctx.node("rig", name, "frustum"), points=segments[index], colors=CAMERA_COLORS[index],
                    thickness=2.0, thickness_units="screen"))
        for name, centre in (("left", (0.0, 0.0, 0.0)), ("right", (B, 0.0, 0.0))):
            self.nodes.put(f"rig/{name}/label", lambda name=name, centre=centre: scene.add_label(
                ctx.node("rig", name, "label"), f"{name} camera", position=centre))
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
        placement = image_placement(self.K, np.eye(3), np.zeros(3), self.left.width, self.left.height, self.depth)
        handle = self.nodes.put("rig/left/image", lambda: self.ctx.scene.add_image(
            self.ctx.node("rig", "left", "image"), texture, placement.render_width, placement.render_height,
            format="jpeg", jpeg_quality=85, wxyz=(1.0, 0.0, 0.0, 0.0), position=placement.position,
            cast_shadow=False, receive_shadow=False))
        handle.on_click(lambda event: self.ctx.guarded(
            lambda: self._click(event.ray_origin, event.ray_direction))())

    def _draw_pick(self) -> None:
        """The picked pixel's ray from the left camera to its depth (the session's, else the truth's)."""
        self.nodes.drop("pick")
        curves = self.curves
        if curves is None or self.K is None:
            return
        x, y = curves.pixel
        z = None
        for depth in (self._state.get("depth"), self.ctx.session.truth.get("depth")):
            if depth is not None and np.shape(depth) == (self.left.height, self.left.width) and depth[y, x] > 0:
                z = float(depth[y, x])
                break
        far = z if z is not None else 4.0 * self.depth
        ends = lift_pixels(self.K, np.eye(3), np.zeros(3), np.array([[x, y]], np.float64), far)[0]
        on_plane = lift_pixels(self.K, np.eye(3), np.zeros(3), np.array([[x, y]], np.float64), 0.995 * self.depth)[0]
        self.nodes.put("pick/ray", lambda: self.ctx.scene.add_line_segments(
            self.ctx.node("pick", "ray"), points=np.array([[[0.0, 0.0, 0.0], ends]], np.float32), colors=PICK_COLOR,
            thickness=2.0, thickness_units="screen"))
        self.nodes.put("pick/pixel", lambda: self.ctx.scene.add_icosphere(
            self.ctx.node("pick", "pixel"), radius=0.01 * self.depth, color=PICK_COLOR, position=tuple(on_plane)))
        if z is not None:
            self.nodes.put("pick/point", lambda: self.ctx.scene.add_icosphere(
                self.ctx.node("pick", "point"), radius=0.02 * self.depth, color=PICK_COLOR, position=tuple(ends)))

    def _remove_plot(self) -> None:
        if self._plot is not None:
            try:
                self._plot.remove()
            except Exception:
                pass
            if self._plot in self.handles:
                self.handles.remove(self._plot)
        self._plot = None
        self._plot_shape = None

    def _draw_plot(self) -> None:
        curves = self.curves
        config = cost_plot(curves, session_cost=self._session_cost())
        shape = tuple(len(a) for a in config["data"])
        title = f"matching costs at ({curves.pixel[0]}, {curves.pixel[1]}), each scaled to [0, 1]"
        if self._plot is not None and shape == self._plot_shape:
            self._plot.data = config["data"]
            self._plot.series = config["series"]
            self._plot.title = title
        else:
            self._remove_plot()
            with self.ctx.plots:
                self._plot = self.track(self.ctx.gui.add_uplot(
                    config["data"], config["series"], scales=config["scales"], legend=config["legend"], title=title,
                    aspect=1.4, order=1000.0))
            self._plot_shape = shape
        session_cost = self._session_cost()
        rows = ["| cost | min at d | |", "|---|---|---|"]
        for label, d in zip(curves.labels, curves.minima):
            note = []
            if label == session_cost:
                note.append("session's cost")
            if label == "aggregated":
                note.append("= winner-take-all")
            if curves.truth is not None:
                note.append(f"{d - curves.truth:+.1f} px from the truth")
            rows.append(f"| {label} | {int(d)} | {', '.join(note)} |")
        truth = f"true disparity **{curves.truth:.2f} px**" if curves.truth is not None else "no true disparity here"
        wta = self._state.get("disparity_wta")
        chosen = ""
        if wta is not None and np.shape(wta) == (self.left.height, self.left.width):
            chosen = f"; the session's winner-take-all: **{int(np.asarray(wta)[curves.pixel[1], curves.pixel[0]])}**"
        self.pick_md.content = (f"Pixel ({curves.pixel[0]}, {curves.pixel[1]}): {truth}{chosen}.\n\n" + "\n".join(rows))

    def close(self) -> None:
        with self.lock:
            self.nodes.clear()
            self._plot = None
        super().close()


# ----------------------------------------------------------------------------------------------------
# Interaction 3: baseline and depth resolution
# ----------------------------------------------------------------------------------------------------
#: The key under which a baseline change hands the previous baselines to the restarted session's explorer.
CARRY_KEY = "stereo.previous_baselines"


def chain_params(session: Any, params: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """The controls to run a restarted rig with: the old session's ``params``, with the cost volume's disparity range
    widened to cover the new true disparities (d = f B / Z grows with the baseline), capped by the image width."""
    chained = {name: dict(p) for name, p in params.items()}
    left_raw = session.state.get("left_raw")
    if isinstance(left_raw, Image):
        current = chained.get("cost_volume", {}).get(
            "max_disparity", session.pipeline.step("cost_volume").control("max_disparity").default)
        chained.setdefault("cost_volume", {})["max_disparity"] = searchable_disparity(
            session.truth.get("disparity"), left_raw.width, left_raw.height, int(current))
    return chained


class BaselineExplorer(Interaction):
    """How depth resolution depends on the baseline: ``u_z = z^2 u_d / (f B)`` over depth, now and for the previous
    baselines; on the synthetic rig a slider restarts the session with another baseline and runs it to the cloud."""

    title = "Baseline and depth resolution"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        self.lock = threading.RLock()
        self.previous: list[BaselineRecord] = []
        self.current: BaselineRecord | None = None
        self.near_far: tuple[float, float] = (0.5, 10.0)
        self._key: tuple | None = None
        self._state: Mapping[str, Any] = {}
        self._plot: Any = None
        self._plot_series = -1
        session = ctx.session
        gui = ctx.gui
        self.option = next((o for d in session.pipeline.datasets if d.name == session.dataset for o in d.options
                            if o.name == "baseline"), None)
        self.summary_md = self.track(gui.add_markdown(""))
        self.slider = None
        if self.option is not None:
            lo = float(self.option.minimum if self.option.minimum is not None else 0.01)
            hi = float(self.option.maximum if self.option.maximum is not None else 2.0)
            value = float(session.options.get("baseline", self.option.default))
            self.slider = self.track(gui.add_slider("baseline (m)", min=lo, max=hi, step=0.01,
                                                    initial_value=min(max(value, lo), hi),
                                                    hint="distance between the cameras of the synthetic rig"))
            self.apply_button = self.track(gui.add_button("New session with this baseline",
                                                          hint="restart the dataset with the baseline above and run "
                                                               "the steps to the point cloud"))
            self.apply_button.on_click(lambda _: ctx.guarded(lambda: self._apply(float(self.slider.value),
                                                                                 wait=False))())
            self.slider.on_update(lambda _: ctx.guarded(self._preview)())
        carried = ctx.carried if isinstance(ctx.carried, dict) else {}
        self.previous = list(carried.get(CARRY_KEY, ()))

    # --- public actions ------------------------------------------------------------------------------
    def set_baseline(self, baseline: float) -> bool:
        """Restart the session with ``baseline`` (metres) and run it to the point cloud (in the tab's worker).

        Returns True when the restart happened; False (error shown in the tab) for a dataset without a
        baseline option or a baseline out of range.
        """
        return bool(_safely(self.ctx, lambda: self._apply(baseline)))

    def plot_config(self) -> dict[str, Any] | None:
        """What the Plots tab shows now (``gui.add_uplot`` keyword arguments)."""
        with self.lock:
            if self.current is None:
                return None
            return uncertainty_plot(self.current, self.previous, *self.near_far, preview=self._preview_record())

    def _preview_record(self) -> BaselineRecord | None:
        """The slider's baseline when it differs from the session's (drawn dotted before it is applied)."""
        if self.slider is None or self.current is None:
            return None
        value = float(self.slider.value)
        if math.isclose(value, self.current.baseline, rel_tol=1e-9, abs_tol=1e-9):
            return None
        return BaselineRecord(value, self.current.focal_px, self.current.disparity_std)

    def _preview(self) -> None:
        with self.lock:
            if self.current is not None:
                self._draw()

    # --- wiring ----------------------------------------------------------------------------------------
    def _apply(self, baseline: Any) -> bool:
        session = self.ctx.session
        if self.option is None:
            raise InvalidValue("baseline", f"dataset {session.dataset!r} has no baseline option: the slider works on "
                                           "the synthetic rig (open the synthetic dataset)")
        try:
            value = float(baseline)
        except (TypeError, ValueError):
            raise InvalidControl("baseline", f"expected a number of metres, got {baseline!r}") from None
        value = float(self.option.coerce(value))  # range checked: InvalidControl names it
        with self.lock:
            previous = list(self.previous)
            if self.current is not None:
                previous = [self.current, *[r for r in previous if not math.isclose(r.baseline, self.current.baseline)]]
            previous = [r for r in previous if not math.isclose(r.baseline, value)][:MAX_PREVIOUS_BASELINES]
        params = {name: dict(controls) for name, controls in session.ran_with.items()}  # what the outputs came from
        return self.ctx.restart({"baseline": value}, run_to=RUN_TO,
                                params=lambda fresh: chain_params(fresh, params), carry={CARRY_KEY: previous})

    # --- redraw ----------------------------------------------------------------------------------------
    def update(self, state: Mapping[str, Any]) -> None:
        key = tuple(id(state.get(n)) for n in ("K", "baseline", "calibration", "depth"))
        with self.lock:
            if key == self._key:
                return
            self._key = key
            self._state = state
            session = self.ctx.session
            calibration = state.get("calibration")
            K = state.get("K")
            if K is None and calibration is not None:
                K = getattr(calibration, "K_left", None)
            baseline = state.get("baseline")
            if baseline is None and calibration is not None:
                baseline = getattr(calibration, "baseline", None)
            if K is None or baseline is None or not float(baseline) > 0:
                self.current = None
                self._remove_plot()
                self.summary_md.content = "No calibrated pair: no depth uncertainty to show."
                return
            std = last_params(list(session.history), "reconstruct_points") or {}
            u_d = float(std.get("disparity_std", session.pipeline.step("reconstruct_points")
                                .control("disparity_std").default))
            self.current = BaselineRecord(float(baseline), float(np.asarray(K)[0, 0]), u_d)
            self.near_far = depth_range(session.truth.get("depth"), state.get("depth"))
            self._draw()

    def _remove_plot(self) -> None:
        if self._plot is not None:
            try:
                self._plot.remove()
            except Exception:
                pass
            if self._plot in self.handles:
                self.handles.remove(self._plot)
        self._plot = None
        self._plot_series = -1

    def _draw(self) -> None:
        config = uncertainty_plot(self.current, self.previous, *self.near_far, preview=self._preview_record())
        title = "depth uncertainty u_z = z² u_d / (f B) (m) over depth"
        if self._plot is not None and self._plot_series == len(config["series"]):
            self._plot.data = config["data"]
            self._plot.series = config["series"]
        else:
            self._remove_plot()
            with self.ctx.plots:
                self._plot = self.track(self.ctx.gui.add_uplot(
                    config["data"], config["series"], scales=config["scales"], legend=config["legend"], title=title,
                    aspect=1.4, order=1001.0))
            self._plot_series = len(config["series"])
        c = self.current
        near, far = self.near_far
        mid = 0.5 * (near + far)
        u_mid = depth_uncertainty_curve(np.array([mid]), focal_px=c.focal_px, baseline=c.baseline,
                                        disparity_std=c.disparity_std)[0]
        step_mid = mid * mid / (c.focal_px * c.baseline)  # depth between disparities d and d - 1 px, to first order
        lines = [f"Baseline **B = {c.baseline:.3g} m**, f = {c.focal_px:.1f} px, u_d = {c.disparity_std:g} px: at "
                 f"z = {mid:.2f} m, u_z = **{u_mid * 100:.2f} cm** and one pixel of disparity spans "
                 f"{step_mid * 100:.1f} cm of depth. u_z grows with z² and shrinks with B."]
        for record in self.previous:
            u = depth_uncertainty_curve(np.array([mid]), focal_px=record.focal_px, baseline=record.baseline,
                                        disparity_std=record.disparity_std)[0]
            lines.append(f"B = {record.baseline:.3g} m (before): u_z = {u * 100:.2f} cm at {mid:.2f} m.")
        preview = self._preview_record()
        if preview is not None:
            u = depth_uncertainty_curve(np.array([mid]), focal_px=preview.focal_px, baseline=preview.baseline,
                                        disparity_std=preview.disparity_std)[0]
            lines.append(f"Slider: B = {preview.baseline:.3g} m would give u_z = {u * 100:.2f} cm at {mid:.2f} m "
                         "(dotted; press the button to apply it).")
        if self.slider is None:
            lines.append("The baseline slider works on the synthetic dataset (its rig can be rebuilt); this pair's "
                         "baseline is fixed.")
        else:
            lines.append("Move the slider and press the button: a new session with that baseline runs to the point "
                         "cloud; the curves of the previous baselines stay for comparison.")
        self.summary_md.content = "  \n".join(lines)

    def close(self) -> None:
        with self.lock:
            self._plot = None
        super().close()


INTERACTIONS: list[type[Interaction]] = [DisparityMaps, CostCurveExplorer, BaselineExplorer]

__all__ = ["INTERACTIONS", "DisparityMaps", "CostCurveExplorer", "BaselineExplorer", "CostCurves", "MatchingSettings",
           "StereoMaps", "BaselineRecord", "STAGES", "check_pick", "click_to_left_pixel", "normalize_curves",
           "gather_cost_curves", "cost_plot", "last_params", "chain_params", "matching_settings", "searchable_disparity",
           "depth_uncertainty_curve", "depth_range", "uncertainty_plot", "disparity_stage", "stereo_maps",
           "rig_segments"]
