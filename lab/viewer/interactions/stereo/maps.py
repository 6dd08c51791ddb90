"""Disparity and error maps of the stereo module (Images tab): a stage's disparity against the truth.

The disparity of a chosen stage (winner-take-all, sub-pixel, final; by default the latest)
colour-mapped on the scale of the true disparity, the true disparity itself, and the bad-pixel
error map against it (green right, red wrong, blue a hole where the truth has a disparity) with its
bad-pixel rate, when the session has a truth. Reference: D. Scharstein and R. Szeliski, IJCV 47
(2002), section 5.1 (bad-pixel rates).
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
from lab.modules.stereo import colorize_disparity, disparity_errors, error_map
from lab.viewer.interactions import Interaction, InteractionContext
from lab.viewer.renderers import PANEL_MIN_SIDE, overlay_view

#: Disparity stages, by the state value that holds them (latest last).
STAGES: dict[str, str] = {"winner-take-all": "disparity_wta", "sub-pixel": "disparity_subpixel",
                          "final": "disparity"}


#: The state values each interaction reads (through ``ctx.values``; each one of the pipeline's views):
#: the disparity stages and what scales them (:class:`DisparityMaps`),
MAPS_READS = ("left", "cost_volume", *STAGES.values())


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
                      error_map(disparity, truth,
                                threshold=threshold), scores, float(scale), float(threshold))


def truth_disparity(session: Any, left: Any) -> np.ndarray | None:
    truth = session.truth.get("disparity")
    if truth is None or not isinstance(left, Image) or np.shape(truth) != (left.height, left.width):
        return None
    return np.asarray(truth, dtype=np.float64)


def panel_picture(image: Image) -> np.ndarray:
    return overlay_view(image, [], min_side=PANEL_MIN_SIDE)


def display_scale(state: Mapping[str, Any], truth: np.ndarray | None) -> float | None:
    """The top of the disparity colour map: the largest true disparity (so both maps use every colour), else
    the searched range (the cost volume's depth)."""
    if truth is not None and np.any(truth >= 0):
        return float(truth.max())
    volume = state.get("cost_volume")
    if volume is not None and np.ndim(volume) == 3:
        return float(np.shape(volume)[2] - 1)
    return None


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
                                                        hint="which disparity map to show: the latest "
                                                             "computed, or a stage of the pipeline"))
        self.threshold_input = self.track(gui.add_number(
            "bad if off by (px)", 2.0, min=0.1, max=64.0, step=0.1,
            hint="error threshold of the error map (bad-2: 2 px)"))
        self.summary_md = self.track(gui.add_markdown(""))
        with ctx.images:
            self.panel_folder = self.track(gui.add_folder("Stereo maps", order=1000.0))
            with self.panel_folder:
                blank = np.zeros((8, 8, 3), np.uint8)
                self.disparity_panel = self.track(gui.add_image(blank, label="disparity", format="png",
                                                                visible=False))
                self.truth_panel = self.track(gui.add_image(blank, label="true disparity", format="png",
                                                            visible=False))
                self.error_panel = self.track(gui.add_image(blank, label="error map", format="png",
                                                            visible=False))
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

        return self.ctx.attempt(act)

    def update(self, state: Mapping[str, Any]) -> None:
        state = self.ctx.values(MAPS_READS, state)
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
                stage = self.stage_choice.value
                self.summary_md.content = ("No disparity yet: run the steps up to winner_take_all."
                                           if stage == "latest" else f"No {stage} disparity yet.")
                return None
            stage, disparity = found
            truth = truth_disparity(self.ctx.session, state.get("left"))
            maps = stereo_maps(stage, disparity, truth, threshold=float(self.threshold_input.value),
                               scale=display_scale(state, truth))
            self.maps = maps
            self.disparity_panel.image = panel_picture(maps.disparity)
            self.disparity_panel.label = (f"disparity ({stage}), turbo 0..{maps.scale:.0f} px"
                                          + (", holes black" if stage == "final" else ""))
            self.disparity_panel.visible = True
            if maps.truth is None or maps.errors is None:
                self.truth_panel.visible = self.error_panel.visible = False
                self.summary_md.content = (f"Showing the **{stage}** disparity in the Images panel. This "
                                           "dataset has no ground truth: no error map.")
                return maps
            key = f"{maps.threshold:g}".replace(".", "_")
            bad_all, bad_pred = maps.scores.get(f"bad{key}_all", 0.0), maps.scores.get(f"bad{key}_pred", 0.0)
            self.truth_panel.image = panel_picture(maps.truth)
            self.truth_panel.label = "true disparity (same colours; black: unknown)"
            self.truth_panel.visible = True
            self.error_panel.image = panel_picture(maps.errors)
            self.error_panel.label = (f"errors of the {stage} disparity: green within {maps.threshold:g} px, "
                                      f"red off by more ({bad_pred:.1%} of predicted pixels), blue hole")
            self.error_panel.visible = True
            self.summary_md.content = (f"**{stage}** disparity against the truth: bad-{maps.threshold:g} "
                                       f"**{bad_all:.1%}** of all pixels with a truth (holes count), "
                                       f"{bad_pred:.1%} of the predicted ones; coverage "
                                       f"{maps.scores.get('coverage', 0.0):.1%}, mean error "
                                       f"{maps.scores.get('epe_px', 0.0):.2f} px.")
            return maps


__all__ = ["MAPS_READS", "STAGES", "DisparityMaps", "StereoMaps", "disparity_stage", "display_scale",
           "panel_picture", "stereo_maps", "truth_disparity"]
