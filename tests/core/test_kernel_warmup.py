"""The kernels' warm-up (lab.core.kernels): it compiles every registered module's kernels, the first RANSAC,
SGM and Efros-Leung steps of a fresh session then compile nothing new (no numba signature is added, so no
compile pause), ``vision-lab serve`` starts it in a background thread, and the viewer labels a step that is
about to compile."""

from __future__ import annotations

import os
import threading
import types
from typing import Any

import numba
import numpy as np
import pytest
from numba.core import event

from lab import server
from lab.core import kernels
from lab.core.pipeline import Session
from lab.modules import get_pipeline
from lab.viewer.runner import COMPILING, running_label

KERNEL_MODULES = ("epipolar", "stereo", "texture")


def _signatures() -> dict[str, set[Any]]:
    return {f"{name}.{k.py_func.__name__}": set(k.signatures)
            for name, entry in kernels.warm_ups().items() for k in entry.kernels}


@pytest.fixture(scope="module")
def warmed() -> dict[str, kernels.WarmUpStatus]:
    done: list[dict[str, kernels.WarmUpStatus]] = []
    thread = kernels.warm_up_kernels(prepare=lambda: [get_pipeline(name) for name in KERNEL_MODULES],
                                     on_done=done.append)
    assert thread.daemon and thread.name == "lab-kernel-warmup"
    thread.join(600)
    assert not thread.is_alive() and len(done) == 1
    return done[0]


def test_the_warm_up_compiles_every_registered_kernel(warmed: dict[str, kernels.WarmUpStatus]) -> None:
    assert set(KERNEL_MODULES) <= set(kernels.warm_ups())
    for name in KERNEL_MODULES:
        status = kernels.kernel_warmup_status()[name]
        assert status.state == "done", status.error
        assert status.seconds is not None and status == warmed[name]
        assert all(kernel.endswith("_kernel") and seconds > 0 for kernel, seconds in status.kernel_seconds)
        entry = kernels.warm_ups()[name]
        assert entry.kernels and entry.steps
        assert [k.py_func.__name__ for k in entry.kernels if not k.signatures] == []
        assert not any(kernels.needs_compiling(name, step) for step in entry.steps)


@pytest.mark.parametrize(("module", "dataset", "options", "step", "params"), [
    ("epipolar", "rendered", {}, "estimate_fundamental_ransac", {}),
    ("stereo", "motorcycle", {"downsample": 4}, "refine_subpixel", {}),
    ("texture", "brick", {}, "synthesize_efros_leung", {}),
    ("texture", "procedural", {"colour": True}, "synthesize_efros_leung", {}),
])
def test_a_first_step_after_the_warm_up_compiles_nothing(warmed: dict[str, kernels.WarmUpStatus], module: str,
                                                         dataset: str, options: dict[str, Any], step: str,
                                                         params: dict[str, dict[str, Any]]) -> None:
    pipeline = get_pipeline(module)
    session = Session(pipeline, pipeline.dataset(dataset).load(options), dataset=dataset, options=options)
    plan = session.plan(step, params)
    assert step in plan.steps
    before = _signatures()
    with event.install_recorder("numba:compile") as recording:
        session.run_plan(plan, params)
    assert step in session.ran_with
    added = {name: sigs - before[name] for name, sigs in _signatures().items() if sigs - before[name]}
    assert added == {}
    assert kernels.compile_seconds(recording.buffer) == {}  # and numba compiled nothing at all


def _fresh_dispatcher() -> Any:
    def _double_kernel(x: np.ndarray) -> np.ndarray:
        return x * 2

    return numba.njit(_double_kernel)  # not cached: compiled only when first called


def test_needs_compiling_follows_the_dispatchers_and_the_viewer_says_so(
        monkeypatch: pytest.MonkeyPatch) -> None:
    dispatcher = _fresh_dispatcher()
    monkeypatch.setattr(kernels, "_WARM_UPS", {})
    monkeypatch.setattr(kernels, "_STATUS", {})
    kernels.register_warm_up("fake", ["slow_step"], [dispatcher], lambda: None)
    session = types.SimpleNamespace(pipeline=types.SimpleNamespace(name="fake"))
    assert kernels.kernel_warmup_status()["fake"].state == "pending"
    assert kernels.needs_compiling("fake", "slow_step")
    assert not kernels.needs_compiling("fake", "other_step")
    assert not kernels.needs_compiling("other", "slow_step")
    assert running_label(session, "slow_step") == COMPILING  # type: ignore[arg-type]
    assert running_label(session, "other_step") == "running"  # type: ignore[arg-type]
    dispatcher(np.ones(3))
    assert not kernels.needs_compiling("fake", "slow_step")
    assert running_label(session, "slow_step") == "running"  # type: ignore[arg-type]


def test_a_failing_warm_up_is_reported_not_raised(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kernels, "_WARM_UPS", {})
    monkeypatch.setattr(kernels, "_STATUS", {})

    def broken() -> None:
        raise ValueError("no data")

    kernels.register_warm_up("fake", ["step"], [_fresh_dispatcher()], broken)
    kernels.warm_up_kernels().join(60)
    status = kernels.kernel_warmup_status()
    assert status["fake"].state == "failed" and "no data" in (status["fake"].error or "")


def test_the_server_start_up_launches_the_warm_up_thread(monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(kernels, "_WARM_UPS", {})
    monkeypatch.setattr(kernels, "_STATUS", {})
    monkeypatch.delenv(server.NO_WARMUP_ENV, raising=False)
    dispatcher = _fresh_dispatcher()
    ran: list[str] = []
    niceness: list[int] = []

    def run() -> None:
        ran.append(threading.current_thread().name)
        assert kernels.in_parallel(lambda: threading.current_thread().name, [(), ()]) == ran * 2  # inline
        niceness.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))
        dispatcher(np.ones(2))

    kernels.register_warm_up("fake", ["step"], [dispatcher], run)
    thread = server.start_kernel_warmup([])
    assert thread is not None and thread.daemon
    thread.join(60)
    assert ran == ["lab-kernel-warmup"] and niceness[0] >= 10  # low priority: the server's threads go first
    assert kernels.kernel_warmup_status()["fake"].state == "done"
    assert "Fast kernels ready: compiled in" in capsys.readouterr().out
    assert server.start_kernel_warmup([], enabled=False) is None
    monkeypatch.setenv(server.NO_WARMUP_ENV, "1")
    assert server.start_kernel_warmup([]) is None


def test_serve_starts_the_warm_up_for_the_modules_it_serves(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[list[str], bool]] = []
    stopped: list[bool] = []
    viewer = types.SimpleNamespace(url="http://localhost:8080", stop=lambda: stopped.append(True))
    api = types.SimpleNamespace(run=lambda: None)
    monkeypatch.setattr(server, "_build", lambda *args: (None, viewer, viewer.url, api))
    monkeypatch.setattr(server, "sandbox_status", lambda: "test")
    monkeypatch.setattr(server, "start_kernel_warmup",
                        lambda names, *, enabled=True: calls.append((list(names), enabled)))
    server.serve()
    server.serve(modules={"stereo": get_pipeline("stereo")}, warmup=False)
    assert calls[0][0][:3] == ["calibration", "epipolar", "stereo"] and calls[0][1]
    assert calls[1] == (["stereo"], False) and stopped == [True, True]


def test_the_viewer_labels_a_step_that_compiles_while_it_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    from lab.viewer.runner import Runner

    pipeline = get_pipeline("texture")  # imported first: importing registers the real warm-up
    monkeypatch.setattr(kernels, "_WARM_UPS", {})
    monkeypatch.setattr(kernels, "_STATUS", {})
    kernels.register_warm_up("texture", ["window_distances"], [_fresh_dispatcher()], lambda: None)
    session = Session(pipeline, pipeline.dataset("brick").load({}), dataset="brick")
    marks: list[tuple[str, str]] = []
    errors: list[BaseException] = []
    runner = Runner(background=False, show_error=errors.append, refresh=lambda: None,
                    mark=lambda step, status: marks.append((step, status)))
    runner.run_plan(session, session.plan("window_distances"), {})
    assert errors == []
    assert marks == [("pick_query_window", "running"), ("window_distances", COMPILING)]
