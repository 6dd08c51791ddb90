"""The diffusion module's interaction: scrub a sampler's frames (points and digits), re-sample from its
controls. Pure math on a hand-made trace first, then the interaction in a ClientView on tiny trained
models."""

from __future__ import annotations

import numpy as np
import pytest

from lab.core.errors import InvalidValue
from lab.modules.diffusion import PIPELINE, SamplingTrace
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.interactions import interactions_for
from lab.core.pipeline import RunRecord
from lab.viewer.interactions.diffusion import (SamplerScrubber, beside_offset, digit_frames, frame_caption,
                                               frame_clouds, last_sample_params, trajectory_segments)

TINY = {"iterations": 60, "hidden": 16, "layers": 1, "batch_size": 64}


def make_trace(kind="points", dim=2, frames=4, m=5):
    rng = np.random.default_rng(0)
    x_t = rng.standard_normal((frames, m, dim))
    x0 = rng.standard_normal((frames, m, dim))
    return SamplingTrace(x_t, x0, np.arange(frames), np.r_[np.inf, np.linspace(2, 0, frames - 1)],
                         np.full(m, -1), kind, "ddim", frames - 1)


def test_frame_clouds_put_x0_beside_x_t():
    trace = make_trace()
    noisy, clean = frame_clouds(trace, 2)
    np.testing.assert_allclose(noisy[:, :2], trace.x_t[2], rtol=1e-6)
    assert np.all(noisy[:, 2] == 0)
    offset = beside_offset(trace)
    assert offset[0] == pytest.approx(1.3 * np.ptp(trace.x_t[-1][:, 0]),
                                      rel=1e-6) and offset[1] == offset[2] == 0
    np.testing.assert_allclose(clean[:, :2] - offset[:2], trace.x0[2], rtol=1e-5, atol=1e-6)


def test_trajectories_join_consecutive_frames():
    trace = make_trace(dim=3, frames=4, m=5)
    assert trajectory_segments(trace, 0).shape == (0, 2, 3)
    segments = trajectory_segments(trace, 3, count=2)
    assert segments.shape == (6, 2, 3)
    np.testing.assert_allclose(segments[0], [trace.x_t[0][0], trace.x_t[1][0]], rtol=1e-6)
    np.testing.assert_allclose(segments[-1], [trace.x_t[2][1], trace.x_t[3][1]], rtol=1e-6)


def test_last_sample_params_are_those_of_the_last_successful_sample_run():
    def record(step, status="ok", **params):
        return RunRecord(step, params, 0, 0.1, {}, status)

    assert last_sample_params([]) == {}
    history = [record("sample", steps=8, count=100), record("train_denoiser", iterations=5),
               record("sample", "failed", steps=3, guidance_scale=2.0)]
    assert last_sample_params(history) == {"steps": 8, "count": 100}


def test_digit_frames_and_caption():
    trace = make_trace("digits", dim=64, frames=3, m=12)
    noisy, clean = digit_frames(trace, 1)
    assert noisy.shape == clean.shape == (19, 91)  # 2 rows x 10 columns of 8 x 8 digits, 1 px gaps
    assert frame_caption(trace, 0) == "ddim step 0 of 2 (pure noise)"
    assert frame_caption(trace, 2) == "ddim step 2 of 2 (clean)"
    with pytest.raises(InvalidValue, match=r"\[0, 2\]"):
        digit_frames(trace, 3)
    with pytest.raises(InvalidValue, match="not 8 x 8 digits"):
        digit_frames(make_trace(), 0)


@pytest.fixture
def view(server, store):
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    view.open_session(store.create(PIPELINE, "two_moons", {"count": 300, "held_out": 300}))
    return view


def scrubber(view) -> SamplerScrubber:
    return next(i for i in view.interactions if isinstance(i, SamplerScrubber))


def test_the_interaction_is_found_by_the_pipeline_name():
    assert interactions_for("diffusion") == [SamplerScrubber]


def test_scrubbing_points_and_resampling(view):
    part = scrubber(view)
    assert part.trace is None and part.bounds() is None
    with pytest.raises(InvalidValue, match="train the denoiser"):
        part.resample()
    view.run_with("noise_schedule", {"timesteps": 100})
    view.run_with("train_denoiser", TINY)
    view.run_with("sample", {"sampler": "euler", "steps": 8, "count": 100})
    view.refresh(force=True)
    trace = view.session.state["trace"]
    assert part.trace is trace and part.index == trace.frames - 1 == 8
    # the folder's inputs show the run being scrubbed, and showing them did not re-sample
    assert (part.sampler_choice.value, part.steps_input.value, part.guidance_input.value) == ("euler", 8, 0.0)
    assert [r.step for r in view.session.history] == ["noise_schedule", "train_denoiser", "sample"]
    noisy, clean = part.clouds
    np.testing.assert_allclose(noisy[:, :2], view.session.state["generated"][:100], atol=1e-5)
    assert clean[:, 0].min() > noisy[:, 0].min()  # beside, along +x
    part.show_frame(3)
    assert part.segments.shape == (16 * 3, 2, 3) and "step 3 of 8" in part.status_md.content
    assert {"x_t", "x0", "paths"} <= set(part.nodes.names())
    box = part.bounds()
    assert box.shape == (2, 3) and np.all(box[0] <= box[1])
    part.show_frame(0)
    assert "paths" not in part.nodes.names() and "pure noise" in part.status_md.content
    # a bad frame is a clear error shown in the tab, not an exception out of a callback
    part.ctx.guarded(part.show_frame)(99)
    assert view.errors and "frame" in str(view.errors[-1])
    # re-sampling with other controls updates the trace
    part.resample(steps=4)
    view.refresh(force=True)
    assert view.session.state["trace"].steps == 4 and part.trace.steps == 4 and part.index == 4
    # only the step count changed: the sampler shown and the last run's sample count are kept
    assert view.session.history[-1].params["sampler"] == "euler"
    assert len(view.session.state["generated"]) == 100
    # guidance on an unconditional model: a clear error, the old result kept
    part.resample(guidance_scale=2.0)
    view.refresh(force=True)
    assert "guidance_scale" in str(view.errors[-1]) and part.trace.steps == 4


def test_the_scrubber_survives_a_reset(view):
    view.run_with("noise_schedule", {"timesteps": 50})
    view.run_with("train_denoiser", TINY)
    view.run_with("sample", {"steps": 5, "count": 50})
    view.refresh(force=True)
    part = scrubber(view)
    assert part.clouds is not None
    view.reset("train_denoiser")
    view.refresh(force=True)
    assert part.trace is None and part.clouds is None and not part.nodes.names()
    with pytest.raises(InvalidValue, match="no sampling run"):
        part.show_frame(0)


def test_digits_show_image_grids(server, store):
    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    view.open_session(store.create(PIPELINE, "digits", {}))
    view.run_with("noise_schedule", {"timesteps": 50})
    view.run_with("train_denoiser", {**TINY, "conditional": True})
    view.run_with("sample", {"steps": 5, "count": 20, "guidance_scale": 1.0})
    view.refresh(force=True)
    part = scrubber(view)
    assert part.trace.kind == "digits" and part.image_handles is not None
    noisy, _clean = part.grids
    assert noisy.shape == (19, 91)
    part.show_frame(0)
    assert not np.allclose(part.grids[0], noisy)  # the first frame is noise


def test_the_samples_read_apart_from_the_training_points_and_the_legend_says_which_is_which(server, store):
    from lab.viewer.legend import legend_entries
    from lab.viewer.renderers import DEFAULT_POINT_COLOR, PLAIN_MESH_OPACITY, default_cloud_colors
    from lab.viewer.interactions.diffusion import CLEAN_COLOR, NOISY_COLOR, TRAJECTORY_COLOR

    view = ClientView(server, store, ModuleCatalog([PIPELINE]), is_client=False, background=False)
    view.open_session(store.create(PIPELINE, "shape_3d", {"count": 300, "held_out": 300}))
    view.run_with("noise_schedule", {"timesteps": 100})
    view.run_with("train_denoiser", TINY)
    view.run_with("sample", {"sampler": "ddim", "steps": 6, "count": 100})
    part = scrubber(view)
    part.show_frame(3)
    state = dict(view.session.state)
    # every cloud of the session and of the scrubber in a colour of its own
    session_colours = default_cloud_colors(state)
    assert "samples" in session_colours and "points" in session_colours
    colours = [*session_colours.values(), NOISY_COLOR, CLEAN_COLOR, TRAJECTORY_COLOR]
    assert len(set(colours)) == len(colours)
    assert session_colours["samples"] != DEFAULT_POINT_COLOR
    # the target shape is see-through (the samples on and in it show), and says so
    mesh = next(e for e in legend_entries(state) if e.name == "mesh")
    assert "see-through" in mesh.swatches[0].marks and 0 < PLAIN_MESH_OPACITY < 0.5
    # the scrubber's drawings are in the legend with the frame shown
    legend = {e.name: e for e in part.legend()}
    assert set(legend) == {"scrubbed x_t", "scrubbed x0_hat", "sample paths"}
    assert not set(legend) & set(state)  # never a session value's name (the legend would read as if it were)
    [swatch] = legend["scrubbed x_t"].swatches
    assert swatch.color == NOISY_COLOR and "frame 3 of 6" in swatch.marks
    assert legend["scrubbed x_t"].count == 100 and legend["sample paths"].count == 16 * 3
    view.session.reset("sample")
    view.refresh(force=True)
    assert part.legend() == []
