"""Interactions of the diffusion module: scrub a sampler's steps, noise to shape, with the predicted x0 beside
it.

* **Scrub the steps** of the last sampling run (the ``trace`` value: x_t and the predicted x0 at up
  to 101 frames): a slider picks the frame. Points: the cloud ``x_t`` in the scene and, beside it
  (shifted along +x by 1.3 times the data's width), the cloud of predicted clean samples ``x0_hat``;
  the trajectories of a few samples from the noise to the current frame as line segments. Digits:
  two image grids (x_t and x0_hat) in the Images tab.
* **Sample again** with the sampler, step count and guidance scale chosen here: changing the
  guidance scale or the step count re-runs the ``sample`` step (the result and the scrubber update);
  its other controls (count, eta, label) stay those of the last run. The inputs show the controls
  of the run being scrubbed.
  The schedule and its SNR are plotted by the generic drawing (the ``schedule_plot`` and ``snr_plot``
  curves); the scrubber says which noise level (sigma = sqrt((1 - abar) / abar)) a frame is at.

The math is in the typed functions below (tested directly); the class only wires it to viser.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lab.core.errors import InvalidValue
from lab.modules.diffusion import DIGIT_SHAPE, SamplingTrace, digit_grid
from lab.viewer.interactions import Interaction, InteractionContext, LegendEntry, NamedHandles, Swatch

#: Colours (RGB, 0-255): x_t blue, the predicted x0 orange, the paths green; none of them the greys and
#: :data:`lab.viewer.renderers.CLOUD_COLORS` the session's own clouds (training points, samples) are drawn in.
NOISY_COLOR = (40, 110, 255)
CLEAN_COLOR = (255, 140, 40)
TRAJECTORY_COLOR = (60, 190, 60)
#: The scrubber's points are this share of the scene's extent: larger than the session's clouds' (0.006), so
#: x_t stays visible over the samples it ends as.
POINT_SHARE = 0.012
#: How many samples' trajectories are drawn.
TRAJECTORIES = 16
#: Where x0_hat is drawn: shifted along +x by this many widths of the data.
BESIDE = 1.3


# ----------------------------------------------------------------------------------------------------
# Pure math
# ----------------------------------------------------------------------------------------------------
def last_sample_params(history: Sequence[Any]) -> dict[str, Any]:
    """The controls of the last successful ``sample`` run in a session's ``history`` ({} when none)."""
    for record in reversed(history):
        if record.step == "sample" and record.status == "ok":
            return dict(record.params)
    return {}


def frame_index(trace: SamplingTrace, index: int) -> int:
    """``index`` checked against the trace's frames (``InvalidValue`` naming the range)."""
    if not 0 <= int(index) < trace.frames:
        raise InvalidValue("frame", f"must be in [0, {trace.frames - 1}] (the trace has {trace.frames} "
                                    f"frames), got {index}")
    return int(index)


def as_3d(points: np.ndarray) -> np.ndarray:
    """``(N, 2)`` or ``(N, 3)`` -> ``(N, 3)`` float64 (2D points at z = 0)."""
    points = np.asarray(points, dtype=np.float64)
    return points if points.shape[1] == 3 else np.concatenate([points,
                                                               np.zeros((len(points),
                                                                         3 - points.shape[1]))], 1)


def beside_offset(trace: SamplingTrace) -> np.ndarray:
    """``(3,)`` shift of the x0_hat cloud: along +x by ``BESIDE`` times the width of the final samples."""
    final = as_3d(trace.x_t[-1])
    width = float(np.ptp(final[:, 0])) if len(final) else 1.0
    return np.array([BESIDE * max(width, 1e-6), 0.0, 0.0])


def frame_clouds(trace: SamplingTrace, index: int) -> tuple[np.ndarray, np.ndarray]:
    """The two clouds ``(M, 3)`` of frame ``index``: x_t where it is, x0_hat shifted beside it."""
    index = frame_index(trace, index)
    return as_3d(trace.x_t[index]), as_3d(trace.x0[index]) + beside_offset(trace)


def trajectory_segments(trace: SamplingTrace, index: int, *, count: int = TRAJECTORIES) -> np.ndarray:
    """``(count * index, 2, 3)`` line segments of the first ``count`` samples' paths from frame 0 to
    ``index``."""
    index = frame_index(trace, index)
    paths = np.stack([as_3d(frame[:count]) for frame in trace.x_t[:index + 1]])  # (F, K, 3)
    if index == 0:
        return np.zeros((0, 2, 3))
    return np.stack([paths[:-1], paths[1:]], axis=2).reshape(-1, 2, 3)


def digit_frames(trace: SamplingTrace, index: int) -> tuple[np.ndarray, np.ndarray]:
    """The digit grids (x_t, x0_hat) of frame ``index`` as ``(H, W)`` float32 images in [0, 1]."""
    index = frame_index(trace, index)
    if trace.kind != "digits" or trace.x_t.shape[2] != DIGIT_SHAPE[0] * DIGIT_SHAPE[1]:
        raise InvalidValue("trace", f"holds {trace.kind}, not 8 x 8 digits")
    return digit_grid(trace.x_t[index]).pixels, digit_grid(trace.x0[index]).pixels


def frame_caption(trace: SamplingTrace, index: int) -> str:
    """One line saying where frame ``index`` is: sampler step and noise level."""
    index = frame_index(trace, index)
    sigma = float(trace.noise_level[index])
    level = "pure noise" if not np.isfinite(sigma) else ("clean" if sigma == 0 else f"sigma = {sigma:.3g}")
    return f"{trace.sampler} step {int(trace.step[index])} of {trace.steps} ({level})"


def _rgb8(pixels: np.ndarray, scale: int = 4) -> np.ndarray:
    gray = np.clip(np.asarray(pixels, dtype=np.float32) * 255 + 0.5, 0, 255).astype(np.uint8)
    gray = np.repeat(np.repeat(gray, scale, axis=0), scale, axis=1)
    return np.stack([gray] * 3, axis=2)


# ----------------------------------------------------------------------------------------------------
# The interaction
# ----------------------------------------------------------------------------------------------------
class SamplerScrubber(Interaction):
    """Scrub a sampler's steps (points: x_t and x0_hat clouds, trajectories; digits: image grids) and
    re-sample."""

    title = "Sampler steps"

    def __init__(self, ctx: InteractionContext) -> None:  # the viewer builds it inside ``with ctx.folder``
        super().__init__(ctx)
        gui = ctx.gui
        self.trace: SamplingTrace | None = None
        self.index = 0
        self.clouds: tuple[np.ndarray, np.ndarray] | None = None
        self.segments = np.zeros((0, 2, 3))
        self.grids: tuple[np.ndarray, np.ndarray] | None = None
        self.nodes = NamedHandles()
        self.status_md = self.track(gui.add_markdown("Run **sample** to scrub its steps."))
        self.slider = self.track(gui.add_slider("frame", 0, 1, 1, 0, hint="scrub the sampler's steps"))
        self.sampler_choice = self.track(gui.add_dropdown("sampler", ("ddim", "ddpm", "euler", "heun", "sde"),
                                                          initial_value="ddim"))
        self.steps_input = self.track(gui.add_slider("steps", 1, 200, 1, 50,
                                                     hint="sampler steps (re-samples)"))
        self.guidance_input = self.track(gui.add_slider("guidance scale", 0.0, 10.0, 0.5, 0.0,
                                                        hint="classifier-free guidance w (conditional "
                                                             "models)"))
        self.sample_button = self.track(gui.add_button("Sample again"))
        # set while update() shows the run's controls (viser calls on_update for those too)
        self.syncing = False
        self.slider.on_update(ctx.guarded(lambda _: self.show_frame(int(self.slider.value))))
        self.sample_button.on_click(ctx.guarded(lambda _: self.resample()))
        self.steps_input.on_update(ctx.guarded(lambda _: None if self.syncing else self.resample()))
        self.guidance_input.on_update(ctx.guarded(lambda _: None if self.syncing else self.resample()))
        self.image_handles: list[Any] | None = None

    # --- actions (public: tests and scripts call them) -----------------------------------------------
    def resample(self, **controls: Any) -> None:
        """Run ``sample`` again with this folder's sampler, steps and guidance scale (``controls`` override
        them); its other controls (count, eta, label ...) stay those of the last ``sample`` run."""
        if self.ctx.value("model") is None:
            raise InvalidValue("model", "train the denoiser first (step train_denoiser)")
        params = {**last_sample_params(self.ctx.session.history), "sampler": str(self.sampler_choice.value),
                  "steps": int(self.steps_input.value)}
        params["guidance_scale"] = float(self.guidance_input.value)
        params.update(controls)
        self.ctx.run("sample", params)

    def show_frame(self, index: int) -> None:
        """Draw frame ``index`` of the trace (clear error when there is none or it is out of range)."""
        if self.trace is None:
            raise InvalidValue("trace", "no sampling run yet: run step sample")
        self.index = frame_index(self.trace, index)
        self.status_md.content = frame_caption(self.trace, self.index)
        if self.trace.kind == "digits":
            self.grids = digit_frames(self.trace, self.index)
            self._draw_digits()
        else:
            self.clouds = frame_clouds(self.trace, self.index)
            self.segments = trajectory_segments(self.trace, self.index)
            self._draw_points()

    # --- redraw --------------------------------------------------------------------------------------
    def update(self, state: Mapping[str, Any]) -> None:
        trace = self.ctx.value("trace", state)
        if trace is self.trace:
            return
        self.trace = trace if isinstance(trace, SamplingTrace) else None
        if self.trace is None:
            self._clear()
            self.status_md.content = "Run **sample** to scrub its steps."
            return
        self._show_controls_of(self.trace)
        last = self.trace.frames - 1
        self.slider.max = max(last, 1)
        self.slider.value = last
        self.show_frame(last)

    def _show_controls_of(self, trace: SamplingTrace) -> None:
        """Set the sampler, steps and guidance inputs to those of the run shown (without re-sampling)."""
        guidance = float(last_sample_params(self.ctx.session.history).get("guidance_scale", 0.0))
        self.syncing = True
        try:
            if trace.sampler in self.sampler_choice.options:
                self.sampler_choice.value = trace.sampler
            self.steps_input.max = max(int(self.steps_input.max), int(trace.steps))
            self.steps_input.value = int(trace.steps)
            self.guidance_input.max = max(float(self.guidance_input.max), guidance)
            self.guidance_input.value = guidance
        finally:
            self.syncing = False

    def bounds(self) -> np.ndarray | None:
        if self.clouds is None:
            return None
        both = np.concatenate(self.clouds)
        return np.stack([both.min(axis=0), both.max(axis=0)])

    def legend(self) -> list[LegendEntry]:
        if self.clouds is None or self.trace is None:
            return []
        frame = f"frame {self.index} of {self.trace.frames - 1}"
        entries = [LegendEntry("scrubbed x_t", "points", len(self.clouds[0]),
                               (Swatch(NOISY_COLOR, f"the samples at {frame} (slider 'frame')"),),
                               "noise at frame 0; at the last frame the generated samples"),
                   LegendEntry("scrubbed x0_hat", "points", len(self.clouds[1]),
                               (Swatch(CLEAN_COLOR, "the clean samples the model predicts from x_t"),),
                               "drawn beside x_t (shifted along +x)")]
        if len(self.segments):
            paths = Swatch(TRAJECTORY_COLOR, f"the paths of {TRAJECTORIES} samples so far")
            entries.append(LegendEntry("sample paths", "segments", len(self.segments), (paths,)))
        return entries

    def _draw_points(self) -> None:
        scene, node = self.ctx.scene, self.ctx.node
        size = POINT_SHARE * max(self.ctx.extent(), 1e-3)
        assert self.clouds is not None
        noisy, clean = (cloud.astype(np.float32) for cloud in self.clouds)
        self.nodes.put("x_t", lambda: scene.add_point_cloud(node("x_t"), noisy, NOISY_COLOR, point_size=size))
        self.nodes.put("x0", lambda: scene.add_point_cloud(node("x0"), clean, CLEAN_COLOR, point_size=size))
        if len(self.segments):
            segments = self.segments.astype(np.float32)
            self.nodes.put("paths", lambda: scene.add_line_segments(node("trajectories"), segments,
                                                                    TRAJECTORY_COLOR, thickness=0.2 * size))
        else:
            self.nodes.drop_exact("paths")

    def _draw_digits(self) -> None:
        assert self.grids is not None
        noisy, clean = (_rgb8(g) for g in self.grids)
        if self.image_handles is None:
            with self.ctx.images:
                self.image_handles = [self.track(self.ctx.gui.add_image(noisy, label="x_t (sampler step)")),
                                      self.track(self.ctx.gui.add_image(clean, label="predicted x0"))]
        else:
            self.image_handles[0].image = noisy
            self.image_handles[1].image = clean

    def close(self) -> None:
        self.nodes.clear()
        super().close()

    def _clear(self) -> None:
        self.nodes.clear()
        self.clouds = None
        self.grids = None
        self.segments = np.zeros((0, 2, 3))


INTERACTIONS = [SamplerScrubber]

__all__ = ["INTERACTIONS", "SamplerScrubber", "as_3d", "beside_offset", "digit_frames", "frame_caption",
           "frame_clouds", "frame_index", "last_sample_params", "trajectory_segments"]
