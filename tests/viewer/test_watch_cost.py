"""What watching a long step costs (issue 16): a burst of progress snapshots draws a bounded number of
previews, each the latest values; a slow preview makes the next wait; the step's result is always drawn;
a preview value that did not change is not sent again. And a done step's label stays "done", and its value
drawn, while a later step of the plan runs, though the plan dropped that value for a moment (SfM's shared
names).

The panel's clock is a fake one the test steps advance, so the counts do not depend on the machine."""

from __future__ import annotations

import itertools
import math
from collections.abc import Generator

import numpy as np
import pytest

from lab.core import Image, ImageSet, Loaded, Pipeline, PointCloud, Progress
from lab.core.step import step_result
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.progress import PREVIEW_SECONDS, PREVIEW_SHARE
from lab.viewer.text import step_label


class FakeClock:
    """``time.monotonic`` and ``time.thread_time`` for the progress panel (a step thread always busy):
    advanced by the steps below, never by itself."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


CLOCK = FakeClock()
#: Seconds between two snapshots of :func:`burst` (fake), and what one preview draw costs (fake).
GAP = {"snapshot": 0.01, "preview": 0.0}
SNAPSHOTS = 100
#: The value every snapshot of :func:`same_preview` carries: one object, unchanged.
SAME = PointCloud(np.zeros((5, 3)))


@step_result
class Grown:
    final: PointCloud


def burst(images: ImageSet) -> Generator[Progress, None, Grown]:
    """A long step: SNAPSHOTS snapshots, GAP["snapshot"] (fake) seconds apart, each with a bigger cloud."""
    for i in range(SNAPSHOTS):
        CLOCK.now += GAP["snapshot"]
        yield Progress(i + 1, SNAPSHOTS, 1.0 / (i + 1), values={"growing": PointCloud(np.zeros((i + 1, 3)))})
    return Grown(PointCloud(np.ones((SNAPSHOTS, 3))))


def same_preview(images: ImageSet) -> Generator[Progress, None, Grown]:
    """A long step whose snapshots (a fake second apart) carry the same preview value."""
    for i in range(10):
        CLOCK.now += 1.0
        yield Progress(i + 1, 10, 1.0, values={"fixed": SAME})
    return Grown(PointCloud(np.ones((3, 3))))


def blank() -> Loaded:
    return Loaded({"images": ImageSet((Image(np.zeros((4, 4), np.float32)),))})


WATCHED = Pipeline.build(name="watched", title="Watched", summary="", steps=[burst, same_preview],
                         datasets=[blank])


def make_view(server, store, modules) -> ClientView:
    view = ClientView(server, store, ModuleCatalog(modules), is_client=False, background=False)
    view.start({})
    view.progress.clock = view.progress.cpu_clock = CLOCK
    return view


def record_previews(view: ClientView) -> list[tuple[float, int, dict]]:
    """(fake time, the iteration reported last, values) of every preview the panel draws; a draw costs
    GAP["preview"] fake seconds."""
    drawn: list[tuple[float, int, dict]] = []
    draw = view.progress.preview

    def preview(values):
        drawn.append((CLOCK.now, view.progress.state.iteration, dict(values)))
        CLOCK.now += GAP["preview"]
        draw(values)

    view.progress.preview = preview
    return drawn


def sent(server, kind: str, name: str) -> list[object]:
    """Record the scene messages of viser type ``kind`` for node ``name`` that the server sends."""
    from viser import _messages

    messages: list[object] = []
    interface = server.scene._websock_interface
    queue = interface.queue_message
    cls = getattr(_messages, kind)

    def spy(message):
        if isinstance(message, cls) and getattr(message, "name", None) == name:
            messages.append(message)
        return queue(message)

    interface.queue_message = spy
    return messages


@pytest.fixture
def cheap_previews():
    GAP.update(snapshot=0.01, preview=0.0)
    yield
    GAP.update(snapshot=0.01, preview=0.0)


def test_a_burst_of_snapshots_draws_a_few_previews_each_the_latest(server, store, cheap_previews):
    view = make_view(server, store, {"watched": WATCHED})
    drawn = record_previews(view)
    clouds = sent(server, "PointCloudMessage", "/lab/growing")
    view.press("burst", "Run")
    assert view.session.history[-1].status == "ok"
    span = SNAPSHOTS * GAP["snapshot"]
    assert 2 <= len(drawn) <= 1 + math.ceil(span / PREVIEW_SECONDS)  # not 100
    assert drawn[0][1] == 1  # the first snapshot's preview at once
    for _, iteration, values in drawn:  # each the latest values, not the first of its window
        assert len(values["growing"]) == iteration
    times = [t for t, _, _ in drawn]
    assert all(b - a >= PREVIEW_SECONDS - 1e-9 for a, b in itertools.pairwise(times))
    assert len(clouds) == len(drawn)  # what is sent follows what is drawn
    # the step's result is drawn, the preview is gone
    assert server.scene.get_handle_by_name("/lab/growing") is None
    final = server.scene.get_handle_by_name("/lab/final")
    assert final is not None and len(final.points) == SNAPSHOTS


def test_a_slow_preview_makes_the_next_one_wait(server, store, cheap_previews):
    GAP.update(snapshot=0.1, preview=1.0)  # each draw takes (fake, CPU) 1 s: at most PREVIEW_SHARE
    view = make_view(server, store, {"watched": WATCHED})
    drawn = record_previews(view)
    view.press("burst", "Run")
    times = [t for t, _, _ in drawn]
    assert len(times) >= 2
    assert all(b - a >= GAP["preview"] / PREVIEW_SHARE - 1e-9 for a, b in itertools.pairwise(times))
    spent = len(times) * GAP["preview"]
    assert spent <= PREVIEW_SHARE * (times[-1] - times[0]) + GAP["preview"]


def test_values_left_pending_when_the_step_ends_are_not_drawn_after_it(server, store, cheap_previews):
    view = make_view(server, store, {"watched": WATCHED})
    drawn = record_previews(view)
    view.press("burst", "Run")
    assert drawn[-1][1] < SNAPSHOTS  # the last snapshots came within the wait: only the result shows them
    assert view.progress.state.pending is None
    view.refresh(force=True)
    assert server.scene.get_handle_by_name("/lab/growing") is None


def test_an_unchanged_preview_value_is_sent_once(server, store, cheap_previews):
    view = make_view(server, store, {"watched": WATCHED})
    drawn = record_previews(view)
    clouds = sent(server, "PointCloudMessage", "/lab/fixed")
    view.press("same_preview", "Run")
    assert len(drawn) >= 5  # a fake second apart: many previews drawn ...
    assert len(clouds) == 1  # ... the unchanged cloud sent once
    assert server.scene.get_handle_by_name("/lab/fixed") is None  # a preview, gone with the result


# --- labels while a plan runs -----------------------------------------------------------------------------
LABELS: list[str] = []
SHOWN: list[bool] = []  # whether the shared value is drawn, at each snapshot of adjust
VIEW: list[ClientView] = []


@step_result
class Stage:
    stage: np.ndarray
    shown: PointCloud


@step_result
class Filtered:
    filtered: np.ndarray
    points: np.ndarray


@step_result
class Adjusted:
    adjusted: np.ndarray
    shown: PointCloud


def reconstruct(images: ImageSet) -> Stage:
    """Writes ``stage`` and the shared ``shown``."""
    return Stage(np.zeros(3), PointCloud(np.zeros((2, 3))))


def filter_stage(stage: np.ndarray) -> Filtered:
    """Writes ``filtered`` and ``points``, not ``shown``."""
    return Filtered(stage + 1, np.zeros(2))


def adjust(filtered: np.ndarray) -> Generator[Progress, None, Adjusted]:
    """A long step writing ``shown`` again; its snapshots note the first step's label while it runs."""
    for i in range(3):
        view = VIEW[0]
        LABELS.append(view.rows["reconstruct"].folder.label)
        SHOWN.append(view.scene.get_handle_by_name("/lab/shown") is not None)
        yield Progress(i + 1, 3, 1.0)
    return Adjusted(filtered * 2, PointCloud(np.ones((2, 3))))


SHARED = Pipeline.build(name="shared", title="Shared names", summary="",
                        steps=[reconstruct, filter_stage, adjust], datasets=[blank])


def test_a_done_step_stays_done_while_a_later_step_rewrites_a_name_it_shares(server, store):
    view = make_view(server, store, {"shared": SHARED})
    VIEW[:] = [view]
    LABELS.clear()
    view.run_all()
    done = step_label(0, SHARED.step("reconstruct"), "done")
    assert view.rows["reconstruct"].folder.label == done
    LABELS.clear()
    SHOWN.clear()
    view.press("filter_stage", "Run")  # filter_stage, then adjust (its dependant): adjust's `shown` dropped
    assert LABELS and all(label == done for label in LABELS)  # it read "ready" while adjust ran
    assert SHOWN and all(SHOWN)  # and the value vanished from the scene until adjust wrote it again
    assert view.rows["reconstruct"].folder.label == done
    assert view.session.step_status()["reconstruct"] == "done"
    np.testing.assert_array_equal(view.scene.get_handle_by_name("/lab/shown").points, np.ones((2, 3)))


def test_the_legend_names_the_step_that_wrote_a_shared_value_last(server, store):
    view = make_view(server, store, {"shared": SHARED})
    VIEW[:] = [view]
    view.run("reconstruct")
    assert "(reconstruct)" in view.scene_panel.legend.content
    view.run_all()
    legend = view.scene_panel.legend.content
    assert "(adjust)" in legend and "(reconstruct)" not in legend  # adjust's `shown` is drawn now


def test_once_the_plan_ends_the_label_says_what_the_session_has(server, store):
    view = make_view(server, store, {"shared": SHARED})
    VIEW[:] = [view]
    view.run_all()
    view.tab.auto_rerun.value = False
    view.press("filter_stage", "Run")  # adjust is not re-run: its `shown`, and the first step's, are gone
    assert view.session.step_status()["reconstruct"] == "ready"
    assert view.rows["reconstruct"].folder.label == step_label(0, SHARED.step("reconstruct"), "ready")
    assert view.scene.get_handle_by_name("/lab/shown") is None
