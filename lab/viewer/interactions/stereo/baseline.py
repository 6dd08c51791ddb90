"""Baseline and depth resolution (Plots tab): how the depth uncertainty depends on the baseline.

The depth uncertainty ``u_z = z^2 u_d / (f B)`` over depth for the current baseline and the
previous ones; on the synthetic rig a slider restarts the session with another baseline and runs
the pipeline to the point cloud again (the core's plan for ``reconstruct_points``). Reference:
R. Szeliski, *Computer Vision: Algorithms and Applications*, 2nd ed. (2022), section 12.1 (depth
from disparity and its uncertainty).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lab.core.errors import InvalidControl, InvalidValue
from lab.core.values import Image
from lab.modules.stereo import MAX_VOLUME_ENTRIES, depth_from_disparity
from lab.viewer.interactions import Interaction, InteractionContext
from lab.viewer.interactions.stereo.costs import last_params
from lab.viewer.plots import set_uplot

BASELINE_COLORS = ("#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b")


#: The step a restart with another baseline runs to (with what it needs: the point cloud).
RUN_TO = "reconstruct_points"


#: Previous baselines kept for comparison in the uncertainty plot.
MAX_PREVIOUS_BASELINES = 5


#: Points of the uncertainty curve over depth.
UNCERTAINTY_SAMPLES = 96


#: the calibration and depths of the pair (:class:`BaselineExplorer`), and the photos a restart sizes.
BASELINE_READS = ("K", "baseline", "calibration", "depth")


RESTART_READS = ("left_raw",)


def searchable_disparity(truth_disparity: np.ndarray | None, width: int, height: int, current: int) -> int:
    """A ``max_disparity`` that covers the true disparities (their maximum + 2), at least ``current``, at most
    ``width - 1`` and small enough for a cost volume of :data:`MAX_VOLUME_ENTRIES` entries.

    A wider baseline makes every disparity larger (``d = f B / Z``): the search range must grow with it.
    """
    top = int(current)
    if truth_disparity is not None and np.any(np.asarray(truth_disparity) >= 0):
        top = max(top, math.ceil(float(np.max(truth_disparity))) + 2)
    return max(1, min(top, width - 1, MAX_VOLUME_ENTRIES // max(width * height, 1) - 1))


def depth_uncertainty_curve(depths: np.ndarray, *, focal_px: float, baseline: float,
                            disparity_std: float) -> np.ndarray:
    """``u_z = z^2 u_d / (f B)`` ``(N,)`` at the depths ``depths`` ``(N,)`` (metres), first-order propagation
    of a disparity uncertainty ``u_d`` (pixels) through ``z = f B / d``.

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
    _, uncertainty = depth_from_disparity((fB / depths)[None, :], K, baseline,
                                          disparity_std=float(disparity_std))
    return uncertainty[0]


def depth_range(truth_depth: np.ndarray | None, state_depth: np.ndarray | None) -> tuple[float, float]:
    """Depths ``(near, far)`` the uncertainty plot spans: the true depths' range, else the 1st-99th percentile
    of the session's depths, else 0.5 to 10 m."""
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
                     preview: BaselineRecord | None = None, samples: int = UNCERTAINTY_SAMPLES) -> dict[str,
                                                                                                        Any]:
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
    return {"data": tuple(data), "series": tuple(series), "scales": {"x": {"time": False}},
            "legend": {"live": False}}


#: The key under which a baseline change hands the previous baselines to the restarted session's explorer.
CARRY_KEY = "stereo.previous_baselines"


def chain_params(session: Any, params: Mapping[str, Mapping[str, Any]],
                 state: Mapping[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """The controls to run a restarted rig with: the old session's ``params``, with the cost volume's
    disparity range widened to cover the new true disparities (d = f B / Z grows with the baseline), capped by
    the image width (of ``left_raw`` in ``state``, the new session's state by default)."""
    chained = {name: dict(p) for name, p in params.items()}
    left_raw = (session.state if state is None else state).get("left_raw")
    if isinstance(left_raw, Image):
        current = chained.get("cost_volume", {}).get(
            "max_disparity", session.pipeline.step("cost_volume").control("max_disparity").default)
        chained.setdefault("cost_volume", {})["max_disparity"] = searchable_disparity(
            session.truth.get("disparity"), left_raw.width, left_raw.height, int(current))
    return chained


class BaselineExplorer(Interaction):
    """How depth resolution depends on the baseline: ``u_z = z^2 u_d / (f B)`` over depth, now and for the
    previous
    baselines; on the synthetic rig a slider restarts the session with another baseline and runs it to the
    cloud."""

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
        session = ctx.session
        gui = ctx.gui
        self.option = next((o for d in session.pipeline.datasets if d.name == session.dataset
                            for o in d.options if o.name == "baseline"), None)
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
                                                          hint="restart the dataset with the baseline above "
                                                               "and run the steps to the point cloud"))
            slider = self.slider
            self.apply_button.on_click(lambda _: ctx.guarded(lambda: self._apply(float(slider.value)))())
            self.slider.on_update(lambda _: ctx.guarded(self._preview)())
        carried = ctx.carried if isinstance(ctx.carried, dict) else {}
        self.previous = list(carried.get(CARRY_KEY, ()))

    # --- public actions ------------------------------------------------------------------------------
    def set_baseline(self, baseline: float) -> bool:
        """Restart the session with ``baseline`` (metres) and run it to the point cloud (in the tab's worker).

        Returns True when the restart happened; False (error shown in the tab) for a dataset without a
        baseline option or a baseline out of range.
        """
        return bool(self.ctx.attempt(lambda: self._apply(baseline)))

    def plot_config(self) -> dict[str, Any] | None:
        """What the Plots tab shows now (``gui.add_uplot`` keyword arguments)."""
        with self.lock:
            if self.current is None:
                return None
            return uncertainty_plot(self.current, self.previous, *self.near_far,
                                    preview=self._preview_record())

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
            raise InvalidValue("baseline", f"dataset {session.dataset!r} has no baseline option: the slider "
                                           "works on the synthetic rig (open the synthetic dataset)")
        try:
            value = float(baseline)
        except (TypeError, ValueError):
            raise InvalidControl("baseline", f"expected a number of metres, got {baseline!r}") from None
        value = float(self.option.coerce(value))  # range checked: InvalidControl names it
        with self.lock:
            previous = list(self.previous)
            if self.current is not None:
                previous = [self.current, *[r for r in previous if not math.isclose(r.baseline,
                                                                                    self.current.baseline)]]
            previous = [r for r in previous if not math.isclose(r.baseline, value)][:MAX_PREVIOUS_BASELINES]
        params = {name: dict(controls) for name,
                  controls in session.ran_with.items()}  # what the outputs came from
        return self.ctx.restart({"baseline": value}, run_to=RUN_TO,
                                params=lambda fresh: chain_params(fresh, params, self.ctx.values(
                                    RESTART_READS, fresh.state)), carry={CARRY_KEY: previous})

    # --- redraw ----------------------------------------------------------------------------------------
    def update(self, state: Mapping[str, Any]) -> None:
        state = self.ctx.values(BASELINE_READS, state)
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
        self.untrack(self._plot)
        self._plot = None

    def _draw(self) -> None:
        c = self.current
        if c is None:
            return
        config = uncertainty_plot(c, self.previous, *self.near_far, preview=self._preview_record())
        title = "depth uncertainty u_z = z² u_d / (f B) (m) over depth"
        if self._plot is not None:  # changed in place, however many baselines it shows (set_uplot says why)
            set_uplot(self._plot, data=config["data"], series=config["series"])
        else:
            with self.ctx.plots:
                self._plot = self.track(self.ctx.gui.add_uplot(
                    config["data"], config["series"], scales=config["scales"], legend=config["legend"],
                    title=title, aspect=1.4, order=1001.0))
        near, far = self.near_far
        mid = 0.5 * (near + far)
        u_mid = depth_uncertainty_curve(np.array([mid]), focal_px=c.focal_px, baseline=c.baseline,
                                        disparity_std=c.disparity_std)[0]
        # depth between disparities d and d - 1 px, to first order
        step_mid = mid * mid / (c.focal_px * c.baseline)
        lines = [f"Baseline **B = {c.baseline:.3g} m**, f = {c.focal_px:.1f} px, u_d = {c.disparity_std:g} "
                 f"px: at z = {mid:.2f} m, u_z = **{u_mid * 100:.2f} cm** and one pixel of disparity spans "
                 f"{step_mid * 100:.1f} cm of depth. u_z grows with z² and shrinks with B."]
        for record in self.previous:
            u = depth_uncertainty_curve(np.array([mid]), focal_px=record.focal_px, baseline=record.baseline,
                                        disparity_std=record.disparity_std)[0]
            lines.append(f"B = {record.baseline:.3g} m (before): u_z = {u * 100:.2f} cm at {mid:.2f} m.")
        preview = self._preview_record()
        if preview is not None:
            u = depth_uncertainty_curve(np.array([mid]), focal_px=preview.focal_px, baseline=preview.baseline,
                                        disparity_std=preview.disparity_std)[0]
            lines.append(f"Slider: B = {preview.baseline:.3g} m would give u_z = {u * 100:.2f} cm at "
                         f"{mid:.2f} m (dotted; press the button to apply it).")
        if self.slider is None:
            lines.append("The baseline slider works on the synthetic dataset (its rig can be rebuilt); this "
                         "pair's baseline is fixed.")
        else:
            lines.append("Move the slider and press the button: a new session with that baseline runs to the "
                         "point cloud; the curves of the previous baselines stay for comparison.")
        self.summary_md.content = "  \n".join(lines)

    def close(self) -> None:
        with self.lock:
            self._plot = None
        super().close()


__all__ = ["BASELINE_READS", "CARRY_KEY", "RESTART_READS", "RUN_TO", "BaselineExplorer", "BaselineRecord",
           "chain_params", "depth_range", "depth_uncertainty_curve", "searchable_disparity",
           "uncertainty_plot"]
