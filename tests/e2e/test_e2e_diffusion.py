"""End to end: the diffusion module's step scrubber in headless chromium, driven as a student drives it.

A tiny denoiser on two moons (100 schedule steps, 60 training iterations) samples 100 points with
8 DDIM steps over REST; the session opens at ``?session=ID``. In the page: the scrubber starts at
the last frame and the scene's x_t cloud is the trace's last frame; typing frame 3 moves the cloud
to the trace's frame 3 (x0_hat beside it, the first 16 samples' paths drawn), frame 0 is pure noise
with no paths; picking the DDPM sampler and typing 4 steps samples again with only those changed
(the 100 points kept), and a guidance scale on this unconditional model shows a clear error and
keeps the run. Uses the lab server and browser fixtures of ``test_browser.py`` and ``lab_api`` /
``viewer_page`` of ``conftest.py``; screenshots go to ``test-output/``.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from test_browser import OUTPUT, TIMEOUT_MS, browser, lab_server  # noqa: F401  (fixtures)

SCRUBBER = "Sampler steps"
SMALL = {"count": 300, "held_out": 300}
RUN = {"noise_schedule": {"timesteps": 100},
       "train_denoiser": {"iterations": 60, "hidden": 16, "layers": 1, "batch_size": 64},
       "sample": {"sampler": "ddim", "steps": 8, "count": 100}}
NODE = "/explore/diffusion"
FLOAT16 = 5e-3  # the page holds point positions as float16


def cloud(view, name: str) -> np.ndarray | None:
    points = view.node_points(f"{NODE}/{name}")
    return None if points is None else points[:, :2]


@pytest.mark.e2e
def test_diffusion_scrubber_moves_through_the_trace_and_resamples_from_its_controls(
        lab_server, lab_api, viewer_page):  # noqa: F811
    viewer_url = lab_server[1]
    session_id = lab_api.create("diffusion", "two_moons", SMALL)
    for step, controls in RUN.items():  # the schedule, the training and the sampling, as a script runs them
        lab_api.run(session_id, step, controls)
    trace = lab_api.value(session_id, "trace")
    x_t, x0 = np.array(trace["x_t"], dtype=np.float64), np.array(trace["x0"], dtype=np.float64)
    assert x_t.shape == (9, 100, 2)

    view = viewer_page(f"{viewer_url}/?session={session_id}")
    page = view.page
    scrubber = view.folder(SCRUBBER)
    scrubber.get_by_text("ddim step 8 of 8 (clean)", exact=True).wait_for(timeout=TIMEOUT_MS)
    assert view.slider_value(scrubber, "frame") == (8, 8)
    assert view.slider_value(scrubber, "steps")[0] == 8  # the inputs show the run being scrubbed
    last = view.eventually(lambda: cloud(view, "x_t"), lambda c: c is not None)
    np.testing.assert_allclose(last, x_t[8], atol=FLOAT16 * max(1.0, np.abs(x_t[8]).max()))

    # scrub to frame 3: the x_t cloud is the trace's frame 3, x0_hat beside it, 16 paths of 3 segments
    view.type_numbers(scrubber, "frame", 3)
    sigma = float(trace["noise_level"][3])
    scrubber.get_by_text(f"ddim step 3 of 8 (sigma = {sigma:.3g})", exact=True).wait_for(timeout=TIMEOUT_MS)
    tolerance = FLOAT16 * max(1.0, np.abs(x_t[3]).max())
    third = view.eventually(lambda: cloud(view, "x_t"),
                            lambda c: c is not None and np.allclose(c, x_t[3], atol=tolerance))
    np.testing.assert_allclose(third, x_t[3], atol=tolerance)
    assert not np.allclose(third, x_t[8], atol=10 * tolerance)  # it moved
    beside = cloud(view, "x0")
    shift = 1.3 * np.ptp(x_t[8][:, 0])
    np.testing.assert_allclose(beside, x0[3] + [shift, 0.0],
                               atol=FLOAT16 * max(1.0, np.abs(x0[3]).max() + shift))
    paths = view.node_points(f"{NODE}/trajectories")
    assert paths.shape == (16 * 3 * 2, 3)
    np.testing.assert_allclose(paths[:2, :2], [x_t[0][0], x_t[1][0]], atol=tolerance * 2)
    page.screenshot(path=str(OUTPUT / "e2e-diffusion-frame3.png"))

    # frame 0 is the noise the sampler started from: no paths yet
    view.type_numbers(scrubber, "frame", 0)
    scrubber.get_by_text("ddim step 0 of 8 (pure noise)", exact=True).wait_for(timeout=TIMEOUT_MS)
    assert view.eventually(lambda: view.scene_nodes(f"{NODE}/"),
                           lambda n: f"{NODE}/trajectories" not in n) == \
        [f"{NODE}/x0", f"{NODE}/x_t"]
    np.testing.assert_allclose(cloud(view, "x_t"), x_t[0], atol=FLOAT16 * max(1.0, np.abs(x_t[0]).max()))

    # another sampler and 4 steps: sampled again with those, the rest of the run (100 points) kept
    view.choose(scrubber, "sampler", "ddpm")
    view.type_numbers(scrubber, "steps", 4)
    scrubber.get_by_text("ddpm step 4 of 4 (clean)", exact=True).wait_for(timeout=TIMEOUT_MS)
    assert view.slider_value(scrubber, "frame") == (4, 4)
    history = lab_api.history(session_id)
    assert history[-1]["step"] == "sample" and history[-1]["status"] == "ok"
    ran = {k: history[-1]["params"][k] for k in ("sampler", "steps", "count")}
    assert ran == {"sampler": "ddpm", "steps": 4, "count": 100}
    again = np.array(lab_api.value(session_id, "trace")["x_t"], dtype=np.float64)
    assert again.shape == (5, 100, 2)
    tolerance = FLOAT16 * max(1.0, np.abs(again[4]).max())
    resampled = view.eventually(lambda: cloud(view, "x_t"), lambda c: c is not None and c.shape == (100, 2)
                                and np.allclose(c, again[4], atol=tolerance))
    np.testing.assert_allclose(resampled, again[4], atol=tolerance)

    # a guidance scale on an unconditional model: a clear error in the tab, the run kept
    view.type_numbers(scrubber, "guidance scale", 2)
    page.get_by_text(re.compile(r"guidance_scale.*trained without labels")).first.wait_for(timeout=TIMEOUT_MS)
    scrubber.get_by_text("ddpm step 4 of 4 (clean)", exact=True).wait_for(timeout=TIMEOUT_MS)
    history = lab_api.history(session_id)
    assert [(r["step"], r["status"]) for r in history[-2:]] == [("sample", "ok"), ("sample", "failed")]
    page.screenshot(path=str(OUTPUT / "e2e-diffusion-resampled.png"))
