"""What watching costs: SfM's incremental step with and without a browser viewing the session (issue 16).

One process holds the lab's viewer (``ViewerApp``, viser on 127.0.0.1, a free port) and the session
store; SfM's default dataset is run up to ``refine_initial_points`` once, then
``reconstruct_incrementally`` runs on copies of that session (``Session.fork``):

* **no viewer**: the step run as a REST call runs it (``Session.run``), no tab open;
* **viewer**: headless Debian chromium (a process of its own, started by this script through
  Playwright, flags as in ``tests/e2e/test_browser.py``) shows the copy at ``?session=ID`` and the
  step is run by the tab's Run button (``ClientView.run``): its progress snapshots reach the tab's
  progress widgets and its previews (cameras and points as they register) the 3D scene.

The figure is the server process' own CPU time (``time.process_time``: every thread of this process:
the step, the tab's drawing, viser's serialising and sending; not chromium's software rendering,
which runs in other processes) from the step's start until it ended and its last redraw was sent
(plus :data:`SETTLE_S` for viser to flush, counted in both cases). Wall times are printed too; they
are noisy on a shared machine. BLAS runs in one thread (its busy-waiting threads would count CPU time the
machine's load decides). The viewer run also counts the tab's progress snapshots, preview
draws and scene values (re)drawn.

    python benchmarks/bench_viewer_watch.py [--rounds 1]

The last line is ``RESULT {json}``: sfm_incremental_cpu_s_no_viewer, sfm_incremental_cpu_s_viewer,
ratio (viewer / no viewer), the wall seconds of both, snapshots, previews_drawn, values_redrawn,
rounds.

Measured 2026-12-02 on the 2-core shared machine (load average 8-10 from other work), ``--rounds 2``
unless said: before the throttle (60ea3ad, one round) 3.05 s without a viewer, 5.37 s with one (x1.76;
10 previews drawn, 1.6 s of CPU in the tab's listener); with the throttle 3.23 s and 4.09 s (x1.27; 3
previews, 0.5 s in the listener, each draw re-making every frustum's picture); with the camera frustums
also sent as deltas (``CamerasRenderer.update``, proposed for renderers.py) 2.80 s and 3.19 s (x1.14;
every preview drawn, 0.1-0.2 s in the listener). Wall times on the same 2 cores as chromium's software
rendering: 7.6 s and 11.7 s.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

# BLAS in one thread (before numpy loads): its idle threads busy-wait, and on a loaded machine that counts
# CPU time the load decides, not the step or the viewer.
for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

from lab.core import kernels  # noqa: E402
from lab.core.pipeline import Session  # noqa: E402
from lab.core.store import SessionStore  # noqa: E402
from lab.modules import get_pipeline  # noqa: E402
from lab.viewer.app import ViewerApp  # noqa: E402
from lab.viewer.view import ClientView  # noqa: E402

MODULE, STEP = "sfm", "reconstruct_incrementally"
#: Seconds after a run ends that still count (viser sends what was queued).
SETTLE_S = 1.0
CHROMIUM = "/usr/bin/chromium"
#: The e2e tests' chromium flags (tests/e2e/test_browser.py, CHROMIUM_ARGS).
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--disable-gpu",
                 "--no-first-run", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]
OPEN_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class Measured:
    """One run of the step: the process' CPU seconds and wall seconds; the viewer's counts (0 without)."""

    cpu_s: float
    wall_s: float
    snapshots: int = 0
    previews: int = 0
    redrawn: int = 0
    listener_s: float = 0.0
    #: CPU seconds per thread name (the threads that used at least 0.05 s).
    threads: dict[str, float] = field(default_factory=dict)


def thread_cpu() -> dict[str, float]:
    """CPU seconds (user + system) of each thread of this process so far, by thread name (Linux /proc)."""
    names = {t.native_id: t.name for t in threading.enumerate()}
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        comm = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        name = names.get(int(tid), comm)
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick
    return out


def cpu_since(before: dict[str, float]) -> dict[str, float]:
    """Each thread's CPU seconds since ``before`` (:func:`thread_cpu`), those over 0.05 s."""
    now = thread_cpu()
    return {name: round(s - before.get(name, 0.0), 2) for name, s in sorted(now.items())
            if s - before.get(name, 0.0) >= 0.05}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def browse(url: str) -> None:
    """The browser process: chromium at ``url`` until this process' stdin closes."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        page.goto(url)
        print("opened", flush=True)
        sys.stdin.read()
        browser.close()


def prepared_session() -> Session:
    """SfM's default dataset, run up to the step before :data:`STEP`."""
    session = SessionStore().create(get_pipeline(MODULE))
    for step in session.plan(STEP, {}).steps[:-1]:
        session.run(step)
    return session


def without_viewer(base: Session) -> Measured:
    """The step run as a REST call runs it, no tab open."""
    session = base.fork()
    threads, cpu, wall = thread_cpu(), time.process_time(), time.perf_counter()
    session.run(STEP)
    time.sleep(SETTLE_S)
    return Measured(time.process_time() - cpu, time.perf_counter() - wall, threads=cpu_since(threads))


def view_of(app: ViewerApp, session_id: str) -> ClientView:
    """The tab showing ``session_id`` once it has drawn it."""
    deadline = time.monotonic() + OPEN_TIMEOUT_S
    while time.monotonic() < deadline:
        for view in list(app.views.values()):
            if view.session is not None and view.session.id == session_id and view.rows:
                return view
        time.sleep(0.2)
    raise RuntimeError(f"no tab opened session {session_id} within {OPEN_TIMEOUT_S:.0f} s")


def with_viewer(app: ViewerApp, base: Session) -> Measured:
    """The step run by the Run button of a chromium tab showing a copy of ``base``."""
    session = app.store.add(base.fork())
    browser = subprocess.Popen([sys.executable, __file__, "--browse", f"{app.url}/?session={session.id}"],
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert browser.stdout is not None and browser.stdin is not None
        if browser.stdout.readline().strip() != "opened":
            raise RuntimeError("the browser did not open the viewer")
        view = view_of(app, session.id)
        time.sleep(3.0)  # the tab's first drawing of the prepared state is not the step's cost
        counts = count_drawing(view)
        threads, cpu, wall = thread_cpu(), time.process_time(), time.perf_counter()
        view.run(STEP)
        view.wait(timeout=600)
        time.sleep(SETTLE_S)
        measured = Measured(time.process_time() - cpu, time.perf_counter() - wall, int(counts["snapshots"]),
                            int(counts["previews"]), int(counts["redrawn"]), round(counts["listener_s"], 3),
                            cpu_since(threads))
        if session.history[-1].step != STEP or session.history[-1].status != "ok":
            raise RuntimeError(f"the step did not run: {session.history[-1]}")
        return measured
    finally:
        if browser.stdin is not None:
            browser.stdin.close()
        try:
            browser.wait(timeout=30)
        except subprocess.TimeoutExpired:
            browser.kill()


def count_drawing(view: ClientView) -> dict[str, float]:
    """Counters of the tab's progress snapshots, preview draws and values (re)drawn, updated as they happen,
    and ``listener_s``: the CPU seconds the step's thread spent in the tab's progress listener."""
    counts: dict[str, float] = {"snapshots": 0, "previews": 0, "redrawn": 0, "listener_s": 0.0}
    lock = threading.Lock()
    on_progress, preview, sync = view.progress.on_progress, view.progress.preview, view.drawer.sync

    def counted_progress(step: str, progress: Any) -> None:
        started = time.thread_time()
        on_progress(step, progress)
        with lock:
            counts["snapshots"] += 1
            counts["listener_s"] += time.thread_time() - started

    def counted_preview(values: Any) -> None:
        with lock:
            counts["previews"] += 1
        preview(values)

    def counted_sync(state: Any, **kwargs: Any) -> list[str]:
        changed = sync(state, **kwargs)
        with lock:
            counts["redrawn"] += len(changed)
        return changed

    session = view.require_session()
    session.listeners[session.listeners.index(on_progress)] = counted_progress
    view.progress.on_progress = counted_progress  # type: ignore[method-assign]
    view.progress.preview = counted_preview
    view.drawer.sync = counted_sync  # type: ignore[method-assign]
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=1, help="runs of each kind (alternating)")
    parser.add_argument("--browse", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.browse:
        browse(args.browse)
        return
    base = prepared_session()
    print(f"prepared {MODULE} up to {STEP}", flush=True)
    if kernels.needs_compiling(MODULE, STEP):
        without_viewer(base)  # compiles the step's kernels; not counted
    app = ViewerApp(SessionStore(), port=free_port(), modules=[get_pipeline(MODULE)], lessons=False).start()
    plain: list[Measured] = []
    watched: list[Measured] = []
    try:
        for _ in range(args.rounds):
            plain.append(without_viewer(base))
            print(f"no viewer: {plain[-1]}", flush=True)
            watched.append(with_viewer(app, base))
            print(f"viewer:    {watched[-1]}", flush=True)
    finally:
        app.stop()
    cpu_plain = statistics.mean(m.cpu_s for m in plain)
    cpu_watched = statistics.mean(m.cpu_s for m in watched)
    result = {
        "sfm_incremental_cpu_s_no_viewer": round(cpu_plain, 3),
        "sfm_incremental_cpu_s_viewer": round(cpu_watched, 3),
        "ratio": round(cpu_watched / cpu_plain, 3),
        "sfm_incremental_wall_s_no_viewer": round(statistics.mean(m.wall_s for m in plain), 3),
        "sfm_incremental_wall_s_viewer": round(statistics.mean(m.wall_s for m in watched), 3),
        "snapshots": watched[-1].snapshots, "previews_drawn": watched[-1].previews,
        "values_redrawn": watched[-1].redrawn, "rounds": args.rounds,
    }
    print(f"server CPU: {cpu_plain:.2f} s without a viewer, {cpu_watched:.2f} s with one "
          f"(x{result['ratio']})")
    print("RESULT " + json.dumps(result))


if __name__ == "__main__":
    main()
