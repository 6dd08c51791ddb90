"""What the viewer's buttons run, and what its step list says, without a browser.

Changing a control marks the step (when it has run) and every step downstream of it stale at once,
with a note naming the control; Run re-runs the step and what depends on it (or, with "Re-run
dependants automatically" off, only the step, the later ones then needing a run); Run to here runs
what the step needs by data flow and nothing else; Run all runs every missing or stale step. The
widgets follow the controls a step's outputs came from (a step run over REST shows the script's).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pytest

from lab.core import Image, Loaded, Pipeline, Range
from lab.viewer.app import ClientView, ModuleCatalog
from lab.viewer.runner import step_plan
from toy_pipeline import TOY


def make_view(server, store, modules=None) -> ClientView:
    view = ClientView(server, store, ModuleCatalog(modules or {"toy": TOY}), is_client=False,
                      background=False)
    view.start({})
    return view


@pytest.fixture
def view(server, store):
    return make_view(server, store)


def labels(view) -> dict[str, str]:
    """Each step's status word, as its folder label ends."""
    return {name: row.folder.label.rsplit(" ", 1)[1] for name, row in view.rows.items()}


def ran(view, since: int) -> list[str]:
    return [record.step for record in view.session.history[since:]]


def test_changing_a_control_marks_the_step_and_its_dependants_stale_at_once(view):
    view.press("lift", "Run to here")
    assert labels(view) == {"add_noise": "done", "mean_intensity": "done", "lift": "done"}
    assert not any(row.note.visible for row in view.rows.values())

    view.rows["add_noise"].controls["sigma"].value = 0.3  # what a student's drag does: no refresh, no run
    assert labels(view) == {"add_noise": "stale", "mean_intensity": "stale", "lift": "stale"}
    assert view.rows["add_noise"].folder.label == "1. Add noise ↻ stale"
    note = view.rows["add_noise"].note
    assert note.visible and "`sigma` 0.1 → 0.3" in note.content
    assert "reads the output of a step that is stale" in view.rows["lift"].note.content
    assert view.session.state["cloud"] is not None  # nothing was thrown away

    view.rows["add_noise"].controls["sigma"].value = 0.1  # back to what it ran with: done again
    assert labels(view) == {"add_noise": "done", "mean_intensity": "done", "lift": "done"}
    assert not view.rows["add_noise"].note.visible

    view.rows["mean_intensity"].controls["scale"].value = 3  # downstream only
    assert labels(view) == {"add_noise": "done", "mean_intensity": "stale", "lift": "stale"}


def test_a_control_of_a_step_that_never_ran_marks_nothing(view):
    view.rows["lift"].controls["iterations"].value = 9
    assert labels(view) == {"add_noise": "ready", "mean_intensity": "blocked", "lift": "blocked"}


def test_run_on_a_changed_step_reruns_it_and_then_its_dependants(view):
    view.press("lift", "Run to here")
    before = len(view.session.history)
    cloud = view.session.state["cloud"]
    view.rows["add_noise"].controls["sigma"].value = 0.4
    view.press("add_noise", "Run")
    assert ran(view, before) == ["add_noise", "mean_intensity", "lift"]
    assert view.session.history[before].params["sigma"] == pytest.approx(0.4)
    assert labels(view) == {"add_noise": "done", "mean_intensity": "done", "lift": "done"}
    assert view.session.state["cloud"] is not cloud
    assert view.drawer.drawn["cloud"].fingerprint[0] == id(view.session.state["cloud"])  # the new one drawn


def test_run_with_rerun_dependants_off_runs_only_the_step(view):
    view.press("lift", "Run to here")
    before = len(view.session.history)
    view.tab.auto_rerun.value = False
    view.rows["add_noise"].controls["sigma"].value = 0.4
    view.press("add_noise", "Run")
    assert ran(view, before) == ["add_noise"]
    # what depended on the old output is gone: the later steps need a run
    assert labels(view) == {"add_noise": "done", "mean_intensity": "ready", "lift": "blocked"}
    assert "cloud" not in view.session.state


def test_run_never_runs_upstream_a_missing_input_is_reported(view):
    view.press("mean_intensity", "Run")
    assert "missing_input" in view.tab.error_box.content and view.session.history == []
    assert step_plan(view.session, "mean_intensity", dependants=True).steps == ("mean_intensity",)


def test_run_on_a_step_below_a_stale_one_leaves_it_stale_run_to_here_brings_it_up_to_date(view):
    view.press("lift", "Run to here")
    view.rows["add_noise"].controls["sigma"].value = 0.2
    before = len(view.session.history)
    view.press("mean_intensity", "Run")  # this step and what depends on it, on the inputs there are
    assert ran(view, before) == ["mean_intensity", "lift"]
    assert labels(view) == {"add_noise": "stale", "mean_intensity": "stale", "lift": "stale"}
    before = len(view.session.history)
    view.press("mean_intensity", "Run to here")  # the stale producer first, then the step
    assert ran(view, before) == ["add_noise", "mean_intensity"]
    assert labels(view)["mean_intensity"] == "done" and labels(view)["lift"] == "ready"


def test_run_all_runs_every_missing_or_stale_step_and_nothing_else(view):
    assert view.tab.run_all_button.label == "Run all"
    view.run_all()
    assert ran(view, 0) == ["add_noise", "mean_intensity", "lift"]
    assert set(labels(view).values()) == {"done"}
    view.run_all()  # everything is up to date: nothing runs
    assert len(view.session.history) == 3
    view.rows["lift"].controls["iterations"].value = 7
    view.tab.run_all_button.value = True  # the button's click callback
    assert ran(view, 3) == ["lift"] and view.session.history[-1].params == {"iterations": 7}
    assert set(labels(view).values()) == {"done"}


def sample_images(*, size: Annotated[int, Range(4, 32)] = 8) -> Loaded:
    return Loaded({"sample": Image(np.linspace(0, 1, size * size, dtype=np.float32).reshape(size, size))})


def pick_window(sample: Image, *, window: Annotated[int, Range(1, 8)] = 3) -> Annotated[np.ndarray, "query"]:
    """A micro-step of the lesson."""
    return sample.pixels[:window, :window].copy()


def match_window(sample: Image, query: np.ndarray) -> Annotated[np.ndarray, "match"]:
    """Another micro-step: reads the previous one's output."""
    return np.array([float(query.mean())])


def quilt(sample: Image, *, block: Annotated[int, Range(1, 8)] = 2) -> Annotated[Image, "quilting"]:
    """Reads only the sample."""
    return Image(np.tile(sample.pixels[:block, :block], (2, 2)))


BRANCHES = Pipeline.build(name="branches", title="Branches", summary="",
                          steps=[pick_window, match_window, quilt],
                          datasets=[sample_images])


def test_run_to_here_runs_only_what_the_step_reads(server, store):
    view = make_view(server, store, {"branches": BRANCHES})
    view.press("quilt", "Run to here")  # the micro-steps listed before it are not needed
    assert ran(view, 0) == ["quilt"]
    assert labels(view) == {"pick_window": "ready", "match_window": "blocked", "quilt": "done"}
    view.press("match_window", "Run to here")
    assert ran(view, 1) == ["pick_window", "match_window"]


def test_widgets_show_the_controls_a_step_ran_with(view, store):
    session = view.session
    session.run("add_noise", {"sigma": 0.5, "mode": "uniform"})  # a script, behind the tab's back
    view.poll()
    assert view.rows["add_noise"].controls["sigma"].value == pytest.approx(0.5)
    assert view.rows["add_noise"].controls["mode"].value == "uniform"
    assert labels(view)["add_noise"] == "done"  # what the script ran with is not stale
    other = make_view(view.target, store)  # a tab opened on it later shows the same
    other.open_session(session)
    assert other.rows["add_noise"].controls["sigma"].value == pytest.approx(0.5)
    assert labels(other)["add_noise"] == "done"


def test_an_invalid_control_is_reported_when_its_step_runs_and_marks_nothing(view):
    view.press("lift", "Run to here")
    view.rows["add_noise"].controls["mode"].value = "bogus"
    assert labels(view)["add_noise"] == "done"
    view.press("add_noise", "Run")
    assert "invalid_control" in view.tab.error_box.content and len(view.session.history) == 3
    view.run_all()  # nothing is stale: nothing runs, nothing complains
    assert len(view.session.history) == 3


def test_an_interactions_run_reruns_the_dependants_too(view):
    view.press("lift", "Run to here")
    before = len(view.session.history)
    view.run_with("mean_intensity", {"scale": 2})
    assert ran(view, before) == ["mean_intensity", "lift"]
    assert view.rows["mean_intensity"].controls["scale"].value == 2  # the widgets follow the run
    assert set(labels(view).values()) == {"done"}
