"""The lab in one process: the FastAPI app (landing page, REST API) under uvicorn and the viser
viewer, on two ports, sharing one :class:`~lab.core.SessionStore` (DESIGN.md section 4).

Because both front ends hold the same store, a session made over REST can be opened in the
viewer (``http://HOST:VIEWER_PORT/?session=ID``), and a step run over REST redraws every tab
that shows its session.

    vision-lab serve --host 127.0.0.1 --port 8000 --viewer-port 8080
    # or: from lab.server import serve; serve(port=8000, viewer_port=8080)

At start-up :func:`serve` compiles the modules' fast kernels in one low-priority background thread
(:func:`start_kernel_warmup`, :mod:`lab.core.kernels`), so a user's first RANSAC, SGM or Efros-Leung step
does not pause to compile; ``warmup=False`` or ``VISION_LAB_NO_WARMUP=1`` skips it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from lab.core import kernels
from lab.core.pipeline import Pipeline
from lab.core.store import SessionStore

if TYPE_CHECKING:  # these are imported when the lab starts, not when this module is imported
    import uvicorn

    from lab.api.workers import WorkerIdentity
    from lab.viewer.app import ViewerApp

log = logging.getLogger("lab.server")


@dataclass
class RunningLab:
    """A lab started by :func:`start`: its store, viewer, API server and URLs; :meth:`stop` ends it."""

    store: SessionStore
    viewer: ViewerApp
    api_server: uvicorn.Server | None
    api_thread: threading.Thread | None
    api_url: str
    viewer_url: str

    def stop(self) -> None:
        if self.api_server is not None:
            self.api_server.should_exit = True
        if self.api_thread is not None:
            self.api_thread.join(timeout=10)
        self.viewer.stop()


def _display_host(host: str) -> str:
    return "localhost" if host in ("0.0.0.0", "::", "") else host


def _build(host: str, port: int, viewer_port: int, store: SessionStore | None,
           modules: Mapping[str, Pipeline] | Iterable[Pipeline] | None, log_level: str,
           data_root: str | None, worker: WorkerIdentity | None = None, grading: bool = True,
           trust_forwarded_for: bool = False) -> tuple[SessionStore, ViewerApp, str, uvicorn.Server]:
    import uvicorn

    from lab.api.app import create_app
    from lab.viewer.app import ViewerApp

    if store is None:
        store = SessionStore(data_root=data_root)
    elif data_root is not None:
        raise ValueError("give data_root to the store you pass, not to serve/start")
    if host not in ("127.0.0.1", "localhost", "::1") and store.data_root is None:
        log.warning("serving on %s with no data root: a browser can load any folder this process can read "
                    "as a dataset; pass --data-root FOLDER", host)
    viewer = ViewerApp(store, host=host, port=viewer_port, modules=modules).start()
    try:
        # viser moves to the next free port when the asked one is taken: link the one it got. On a
        # wildcard address the landing page resolves ":PORT" against the host the browser used.
        viewer_url = f":{viewer.port}" if host in ("0.0.0.0", "::", "") else viewer.url
        if modules is None:
            app = create_app(store, viewer_url=viewer_url, worker=worker, grading=grading,
                             trust_forwarded_for=trust_forwarded_for)
        else:
            pipelines = dict(modules) if isinstance(modules, Mapping) else {p.name: p for p in modules}
            app = create_app(store, modules=pipelines.__getitem__, module_names=list(pipelines),
                             viewer_url=viewer_url, worker=worker, grading=grading,
                             trust_forwarded_for=trust_forwarded_for)
        config = uvicorn.Config(app, host=host, port=port, log_level=log_level)
        api_server = uvicorn.Server(config)
    except BaseException:
        viewer.stop()
        raise
    return store, viewer, viewer_url, api_server


#: Set (to anything but "", "0") to skip compiling the kernels at start-up.
NO_WARMUP_ENV = "VISION_LAB_NO_WARMUP"


def _import_modules(names: Iterable[str]) -> None:
    """Import the served module packages (each registers its kernels' warm-up); one that fails to import is
    left to fail when it is opened."""
    from lab.modules import get_pipeline

    for name in names:
        try:
            get_pipeline(name)
        except Exception as exc:
            log.warning("kernel warm-up: module %s did not import: %s", name, exc)


def _served_names(modules: Mapping[str, Pipeline] | Iterable[Pipeline] | None) -> list[str]:
    from lab.modules import MODULES

    if modules is None:
        return list(MODULES)
    return list(modules) if isinstance(modules, Mapping) else [p.name for p in modules]


def _log_warmup(status: Mapping[str, kernels.WarmUpStatus]) -> None:
    """The one start-up line saying the kernels are ready, with the seconds per module."""
    total = sum(s.seconds or 0.0 for s in status.values())
    parts = ", ".join(f"{name} {s.state} {s.seconds or 0.0:.1f} s" for name, s in status.items())
    print(f"Fast kernels ready: compiled in {total:.1f} s ({parts or 'none registered'})", flush=True)


def start_kernel_warmup(names: Iterable[str], *, enabled: bool = True,
                        on_done: Callable[[Mapping[str, kernels.WarmUpStatus]], None] | None = _log_warmup,
                        ) -> threading.Thread | None:
    """Compile the kernels of modules ``names`` in a background daemon thread (not blocking the server);
    None when ``enabled`` is False or :data:`NO_WARMUP_ENV` is set."""
    if not enabled or os.environ.get(NO_WARMUP_ENV, "") not in ("", "0"):
        return None
    chosen = list(names)
    return kernels.warm_up_kernels(prepare=lambda: _import_modules(chosen), on_done=on_done)


def serve(*, host: str = "127.0.0.1", port: int = 8000, viewer_port: int = 8080,
          store: SessionStore | None = None,
          modules: Mapping[str, Pipeline] | Iterable[Pipeline] | None = None, log_level: str = "info",
          data_root: str | None = None, warmup: bool = True, worker: WorkerIdentity | None = None,
          grading: bool = True, trust_forwarded_for: bool = False) -> None:
    """Serve the landing page and REST API on ``port`` and the viewer on ``viewer_port``; blocks
    until interrupted (Ctrl-C / SIGTERM), then stops both.

    ``store`` (default: a new one) is shared by both; ``modules`` restricts what is offered
    (default: every registered module); ``data_root`` limits the folders datasets may read
    (:class:`~lab.core.SessionStore`); ``warmup`` compiles the kernels in the background
    (:func:`start_kernel_warmup`). ``worker`` and ``grading``: this process as one of several on one
    database (:func:`lab.api.app.create_app`; :func:`serve_workers` starts them);
    ``trust_forwarded_for``: behind one trusted proxy, count clients by ``X-Forwarded-For``.
    """
    store, viewer, _viewer_url, api_server = _build(host, port, viewer_port, store, modules, log_level,
                                                    data_root, worker, grading, trust_forwarded_for)
    start_kernel_warmup(_served_names(modules), enabled=warmup)
    name = f" worker {worker.id}" if worker is not None else ""
    print(f"Vision Lab{name}: landing page and REST API on http://{_display_host(host)}:{port} "
          f"(OpenAPI at /docs), 3D viewer on {viewer.url}", flush=True)
    print(f"Grading: {sandbox_status() if grading else 'by another process on the same database'}",
          flush=True)
    try:
        api_server.run()  # uvicorn handles SIGINT / SIGTERM: it shuts down and re-raises the signal
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()


def sandbox_status() -> str:
    """One line on how submissions will be graded (the start-up probe of
    :mod:`lab.lessons.isolation`)."""
    from lab.lessons import isolation

    chosen = isolation.default_isolation()
    if chosen.mode == "unsafe":
        return "--unsafe-sandbox: submissions run with Python's audit hook only (trusted code only)"
    try:
        isolation.check(chosen)
    except isolation.SandboxUnavailable as exc:
        return f"off, submissions are refused (503): {exc.reason}"
    return "each submission in its own bubblewrap sandbox"


def start(*, host: str = "127.0.0.1", port: int = 8000, viewer_port: int = 8080,
          store: SessionStore | None = None,
          modules: Mapping[str, Pipeline] | Iterable[Pipeline] | None = None, log_level: str = "warning",
          timeout: float = 30.0, data_root: str | None = None) -> RunningLab:
    """Start the lab in background threads and return once both servers accept connections
    (for notebooks and tests); call ``.stop()`` on the result."""
    store, viewer, _viewer_url, api_server = _build(host, port, viewer_port, store, modules, log_level,
                                                    data_root)
    thread = threading.Thread(target=api_server.run, name="lab-api", daemon=True)
    thread.start()
    deadline = time.monotonic() + timeout
    while not api_server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            viewer.stop()
            api_server.should_exit = True
            raise RuntimeError(f"the REST API did not start on {host}:{port}")
        time.sleep(0.05)
    return RunningLab(store, viewer, api_server, thread, f"http://{_display_host(host)}:{port}", viewer.url)


# --- several worker processes on one database (issue 20 item 3; lab.api.workers) -----------------------
#: Times one worker may exit unasked within :data:`RESTART_WINDOW_S` and be started again; one more and
#: :func:`serve_workers` stops them all (a port taken, a broken install: restarting will not help).
MAX_RESTARTS = 3
RESTART_WINDOW_S = 60.0


@dataclass(frozen=True)
class WorkerPlan:
    """One worker process of :func:`serve_workers`: its id, ports and command line."""

    id: str
    port: int
    viewer_port: int
    command: tuple[str, ...]


def plan_workers(workers: int, *, host: str = "127.0.0.1", port: int = 8000, viewer_port: int = 8080,
                 extra_args: Iterable[str] = ()) -> list[WorkerPlan]:
    """The command lines of ``workers`` processes ``w0`` .. ``wN-1``: worker ``wI`` serves its API on
    ``port + I`` and its viewer on ``viewer_port + I``, knows the others' addresses (``--peers``), and only
    ``w0`` grades (the others get ``--no-grading``). ``extra_args`` go to every one."""
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    last_api, last_viewer = port + workers - 1, viewer_port + workers - 1
    if max(last_api, last_viewer) > 65535:
        raise ValueError(f"{workers} workers need ports up to {max(last_api, last_viewer)}, above 65535")
    if port <= last_viewer and viewer_port <= last_api:
        raise ValueError(f"the API ports {port}-{last_api} and the viewer ports {viewer_port}-{last_viewer} "
                         "overlap; choose --port and --viewer-port further apart")
    peers = ",".join(f"w{i}=http://{_display_host(host)}:{port + i}" for i in range(workers))
    extra = tuple(extra_args)
    return [WorkerPlan(f"w{i}", port + i, viewer_port + i, (
        sys.executable, "-m", "lab", "serve", "--host", host, "--port", str(port + i),
        "--viewer-port", str(viewer_port + i), "--worker-id", f"w{i}", "--peers", peers,
        *(("--no-grading",) if i else ()), *extra)) for i in range(workers)]


def _end_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """A worker gets SIGTERM when its supervisor dies, even by SIGKILL (Linux ``PR_SET_PDEATHSIG``)."""
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)


def serve_workers(plans: list[WorkerPlan], *, stop: threading.Event | None = None,
                  poll_s: float = 0.5) -> int:
    """Run the worker processes of ``plans`` until ``stop`` is set, SIGTERM or Ctrl-C; returns the exit code.

    A worker that exits unasked is started again (so a killed ``w0`` comes back and requeues the gradings
    it was running: none is lost), at most :data:`MAX_RESTARTS` times in :data:`RESTART_WINDOW_S`;
    beyond that every worker is stopped and the code is 1. Stopping sends SIGTERM to each (uvicorn shuts
    down cleanly), then SIGKILL to any still alive after 15 s.
    """
    _check_ports_free(plans)
    stop = stop or threading.Event()
    preexec = _end_with_parent if sys.platform.startswith("linux") else None
    children: dict[str, subprocess.Popen[bytes]] = {}
    exits: dict[str, list[float]] = {plan.id: [] for plan in plans}
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set()) \
        if threading.current_thread() is threading.main_thread() else None
    print(f"Vision Lab: {len(plans)} worker processes on one database, behind your proxy: "
          + ", ".join(f"{p.id} API :{p.port} viewer :{p.viewer_port}" for p in plans)
          + f" ({plans[0].id} grades; README 'Behind a proxy')", flush=True)
    code = 0
    try:
        for plan in plans:
            children[plan.id] = subprocess.Popen(plan.command, preexec_fn=preexec)
        while not stop.wait(poll_s):
            for plan in plans:
                returned = children[plan.id].poll()
                if returned is None:
                    continue
                now = time.monotonic()
                exits[plan.id] = [t for t in exits[plan.id] if now - t < RESTART_WINDOW_S] + [now]
                if len(exits[plan.id]) > MAX_RESTARTS:
                    log.error("worker %s exited %d times within %.0f s (last code %s): stopping every worker",
                              plan.id, len(exits[plan.id]), RESTART_WINDOW_S, returned)
                    code = 1
                    stop.set()
                    break
                log.warning("worker %s exited (code %s): starting it again", plan.id, returned)
                children[plan.id] = subprocess.Popen(plan.command, preexec_fn=preexec)
    except KeyboardInterrupt:
        pass
    finally:
        _stop_children(list(children.values()))
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return code


def _check_ports_free(plans: list[WorkerPlan]) -> None:
    """OSError (address in use) naming the first worker whose API port is taken, before anything starts
    (each worker would otherwise fail at start-up and be restarted in vain)."""
    import socket

    for plan in plans:
        host = plan.command[plan.command.index("--host") + 1]
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
            try:
                probe.bind((host, plan.port))
            except OSError as exc:
                raise OSError(exc.errno, f"worker {plan.id}'s port {plan.port} on {host}: {exc.strerror}; "
                                         "choose another --port") from None


def _stop_children(children: list[subprocess.Popen[bytes]], timeout: float = 15.0) -> None:
    for child in children:
        if child.poll() is None:
            child.terminate()
    deadline = time.monotonic() + timeout
    for child in children:
        try:
            child.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait(timeout=5)


__all__ = ["MAX_RESTARTS", "NO_WARMUP_ENV", "RunningLab", "WorkerPlan", "plan_workers", "serve",
           "serve_workers", "start", "start_kernel_warmup"]
