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

import logging
import os
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from lab.core import kernels
from lab.core.pipeline import Pipeline
from lab.core.store import SessionStore

if TYPE_CHECKING:  # both are imported when the lab starts, not when this module is imported
    import uvicorn

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
           data_root: str | None) -> tuple[SessionStore, ViewerApp, str, uvicorn.Server]:
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
            app = create_app(store, viewer_url=viewer_url)
        else:
            pipelines = dict(modules) if isinstance(modules, Mapping) else {p.name: p for p in modules}
            app = create_app(store, modules=pipelines.__getitem__, module_names=list(pipelines),
                             viewer_url=viewer_url)
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
          data_root: str | None = None, warmup: bool = True) -> None:
    """Serve the landing page and REST API on ``port`` and the viewer on ``viewer_port``; blocks
    until interrupted (Ctrl-C / SIGTERM), then stops both.

    ``store`` (default: a new one) is shared by both; ``modules`` restricts what is offered
    (default: every registered module); ``data_root`` limits the folders datasets may read
    (:class:`~lab.core.SessionStore`); ``warmup`` compiles the kernels in the background
    (:func:`start_kernel_warmup`).
    """
    store, viewer, _viewer_url, api_server = _build(host, port, viewer_port, store, modules, log_level,
                                                    data_root)
    start_kernel_warmup(_served_names(modules), enabled=warmup)
    print(f"Vision Lab: landing page and REST API on http://{_display_host(host)}:{port} "
          f"(OpenAPI at /docs), 3D viewer on {viewer.url}", flush=True)
    print(f"Grading: {sandbox_status()}", flush=True)
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
    import time

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


__all__ = ["NO_WARMUP_ENV", "RunningLab", "serve", "start", "start_kernel_warmup"]
