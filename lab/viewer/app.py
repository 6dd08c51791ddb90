"""The viewer: a viser GUI generated from any pipeline, one session per browser tab.

Every browser tab (a viser client) gets a :class:`~lab.viewer.view.ClientView`: a module and dataset
picker, the pipeline's steps in order (each in its own folder with its status, its docstring summary,
its controls generated from :attr:`lab.core.StepSpec.controls`, Run / Run to here / Reset, and its
metrics and warnings after a run), Run all, a progress bar, a live loss plot and Cancel for long
(generator) steps, the run history, and every value of the state drawn by its renderer
(:mod:`lab.viewer.renderers`). Changing a control marks the step and what depends on it stale at
once; what each button runs is the core's plan (:mod:`lab.viewer.runner`). Steps run in a
background thread, so the GUI stays responsive; a :class:`~lab.core.LabError` is shown in the GUI
and never ends the client's connection.

Sessions live in the :class:`~lab.core.SessionStore` the REST API shares (``lab.server``), so a
script can drive what a browser shows: open the viewer at ``?session=ID`` (or type the id in
the "Session id" field and press Open; :mod:`lab.viewer.page` says how the query reaches the
server), and every change made over REST (``Session.version`` increases) redraws the tab within
about half a second.

Lesson mode (:mod:`lab.viewer.lesson`, on when the view is given a lesson catalog): a lesson
picker and ``?lesson=ID``, the lesson's text in a panel beside the pipeline, and the student's
own code (uploaded, or the starter) run in a sandbox in place of a task's step, or compared with
the reference's on the same inputs.

This module is the server (:class:`ViewerApp`); the tab's pieces are in :mod:`lab.viewer.view`,
:mod:`lab.viewer.gui`, :mod:`lab.viewer.widgets`, :mod:`lab.viewer.runner`,
:mod:`lab.viewer.progress`, :mod:`lab.viewer.camera` and :mod:`lab.viewer.text`; their public
names are importable from here too.
"""

from __future__ import annotations

import logging
import threading
import traceback
from collections.abc import Iterable, Mapping
from typing import Any

from lab.core.pipeline import Pipeline
from lab.core.store import SessionStore
from lab.viewer.catalog import ModuleCatalog
from lab.viewer.gui import MEDIA_PANEL_WIDTH, StepRow
from lab.viewer.page import QUERY_KEYS, read_query, set_page_query
from lab.viewer.text import error_text, format_number, history_markdown, metrics_markdown, value_summary
from lab.viewer.view import ClientView
from lab.viewer.widgets import add_control_widget, control_hint, nice_step, widget_kind, widget_value

log = logging.getLogger("lab.viewer")

#: How often the viewer looks for changes made to its sessions by someone else (REST, another tab).
POLL_SECONDS = 0.5


class ViewerApp:
    """The viser server of the lab: one :class:`ClientView` per browser tab, sharing ``store``.

    ``modules`` (default: every registered module) is what the module picker offers; sessions
    of other modules can still be opened by id. ``lessons`` is the lesson picker's
    :class:`~lab.lessons.format.LessonCatalog` (True: the lessons folder, ``lessons_root()``;
    False: no lesson mode). Call :meth:`start`, then :meth:`stop`.
    """

    def __init__(self, store: SessionStore | None = None, *, host: str = "127.0.0.1", port: int = 8080,
                 modules: Mapping[str, Pipeline] | Iterable[Pipeline] | None = None,
                 label: str = "Vision Lab",
                 poll_seconds: float = POLL_SECONDS, lessons: Any = True) -> None:
        self.store = store if store is not None else SessionStore()
        self.catalog = ModuleCatalog(modules)
        if lessons is True:
            from lab.lessons.format import LessonCatalog

            lessons = LessonCatalog()
        self.lessons = None if lessons is False else lessons
        self.host = host
        self.requested_port = port
        self.label = label
        self.poll_seconds = poll_seconds
        self.server: Any = None
        self.views: dict[int, ClientView] = {}
        self._views_lock = threading.Lock()
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        host = "localhost" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.port}"

    def start(self) -> ViewerApp:
        import viser

        self.server = viser.ViserServer(host=self.host, port=self.requested_port, label=self.label,
                                        verbose=False)
        self.server.scene.set_up_direction("-y")
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._poller = threading.Thread(target=self._poll_loop, name="lab-viewer-poll", daemon=True)
        self._poller.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._poller is not None:
            self._poller.join(timeout=5)
        with self._views_lock:
            views = list(self.views.values())
            self.views.clear()
        for view in views:
            view.close()
        if self.server is not None:
            self.server.stop()

    def _connect(self, client: Any) -> None:
        try:
            query = read_query(client)
            client.scene.set_up_direction("-y")
            view = ClientView(client, self.store, self.catalog, lessons=self.lessons)
            with self._views_lock:
                self.views[client.client_id] = view
            view.start(query)
        except Exception:  # never let one tab's failure reach viser's thread pool silently
            log.error("viewer client %s failed to start:\n%s", client.client_id, traceback.format_exc())

    def _disconnect(self, client: Any) -> None:
        with self._views_lock:
            view = self.views.pop(client.client_id, None)
        if view is not None:
            view.close()

    def _poll_loop(self) -> None:
        while not self._stop.wait(self.poll_seconds):
            with self._views_lock:
                views = list(self.views.values())
            for view in views:
                try:
                    view.poll()
                except Exception:
                    log.error("viewer poll failed:\n%s", traceback.format_exc())


__all__ = ["MEDIA_PANEL_WIDTH", "POLL_SECONDS", "QUERY_KEYS", "ClientView", "ModuleCatalog", "StepRow",
           "ViewerApp", "add_control_widget", "control_hint", "error_text", "format_number",
           "history_markdown", "metrics_markdown", "nice_step", "read_query", "set_page_query",
           "value_summary", "widget_kind", "widget_value"]
