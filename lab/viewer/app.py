"""The viewer: a viser GUI generated from any pipeline, one session per browser tab.

Every browser tab (a viser client) gets a :class:`ClientView`: a module and dataset picker, the
pipeline's steps in order (each in its own folder with its status, its docstring summary, its
controls generated from :attr:`lab.core.StepSpec.controls`, Run / Run to here / Reset, and its
metrics and warnings after a run), a progress bar, a live loss plot and Cancel for long
(generator) steps, the run history, and every value of the state drawn by its renderer
(:mod:`lab.viewer.renderers`). Steps run through :meth:`lab.core.Session.run` in a background
thread, so the GUI stays responsive; a :class:`~lab.core.LabError` is shown in the GUI and
never ends the client's connection.

Sessions live in the :class:`~lab.core.SessionStore` the REST API shares (``lab.server``), so a
script can drive what a browser shows: open the viewer at ``?session=ID`` (or type the id in
the "Session id" field and press Open), and every change made over REST (``Session.version``
increases) redraws the tab within about half a second.

How ``?session=ID`` reaches the server: viser's client does not send the page's query string
(its websocket URL drops it). On connect, the viewer sends the tab one line of JavaScript
(viser's ``RunJavascriptMessage``, the message viser itself uses to load plotly) that copies
``window.location.search`` into the tab's localStorage under a one-off key, then reads that key
back with viser's public ``client.local_storage.get_item``. Messages to a client are handled in
order, so the value is there when the read arrives; the key is random per connection, so two
tabs never see each other's query. When a session is opened, the viewer writes ``?session=ID``
into the tab's address bar (``history.replaceState``), so reloading the tab reopens it.

Lesson mode (:mod:`lab.viewer.lesson`, on when the view is given a lesson catalog): a lesson
picker and ``?lesson=ID``, the lesson's text in a panel beside the pipeline, and the student's
own code (uploaded, or the starter) run in a sandbox in place of a task's step, or compared with
the reference's on the same inputs.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import traceback
import uuid
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from lab.core.errors import LabError, UnknownName
from lab.core.pipeline import Pipeline, Session
from lab.core.step import Control, Progress, StepSpec
from lab.core.store import SessionStore
from lab.core.values import VALUE_TYPES, PointCloud
from lab.viewer.interactions import Interaction, InteractionContext, interactions_for
from lab.viewer.renderers import OVERLAY_TYPES, Canvas, StateDrawer, renderer_for, scene_extent, viewpoint

log = logging.getLogger("lab.viewer")

#: How often the viewer looks for changes made to its sessions by someone else (REST, another tab).
POLL_SECONDS = 0.5
#: Minimum time between two GUI updates from progress snapshots (and between two preview draws).
PROGRESS_SECONDS = 0.1
PREVIEW_SECONDS = 0.5
#: Width in pixels of the panel of images and plots, docked on the left.
MEDIA_PANEL_WIDTH = 440
#: Query parameters the viewer understands.
QUERY_KEYS = ("session", "module", "dataset", "lesson")

STATUS_MARK = {"done": "✓", "ready": "›", "blocked": "·", "running": "…"}


# --- pipelines the viewer offers ----------------------------------------------------------------
class ModuleCatalog:
    """The modules a viewer offers: ``lab.modules`` by default, or an explicit set (tests)."""

    def __init__(self, modules: Mapping[str, Pipeline] | Iterable[Pipeline] | None = None) -> None:
        if modules is None:
            self._explicit: dict[str, Pipeline] | None = None
        elif isinstance(modules, Mapping):
            self._explicit = dict(modules)
        else:
            self._explicit = {p.name: p for p in modules}

    def names(self) -> list[str]:
        if self._explicit is not None:
            return list(self._explicit)
        from lab.modules import MODULES

        return list(MODULES)

    def get(self, name: str) -> Pipeline:
        if self._explicit is not None:
            if name not in self._explicit:
                raise UnknownName("module", f"no module {name!r}; modules are {list(self._explicit)}")
            return self._explicit[name]
        from lab.modules import get_pipeline

        return get_pipeline(name)


# --- controls -> widgets --------------------------------------------------------------------------
def nice_step(span: float, *values: float) -> float:
    """A round slider step giving about 100 positions over ``span`` (0.01 for [0, 1]), made finer
    until every one of ``values`` (the minimum, the default) lies on a step."""
    step = 0.01 if not np.isfinite(span) or span <= 0 else float(10.0 ** math.floor(math.log10(span / 100.0)))
    for _ in range(6):
        if all(abs(v / step - round(v / step)) < 1e-6 for v in values if v is not None):
            break
        step /= 10.0
    return step


def control_hint(control: Control) -> str:
    parts = [control.description] if control.description else []
    if control.minimum is not None or control.maximum is not None:
        lo = "-inf" if control.minimum is None else f"{control.minimum:g}"
        hi = "inf" if control.maximum is None else f"{control.maximum:g}"
        parts.append(f"range [{lo}, {hi}]")
    if not control.required:
        parts.append(f"default {control.default!r}")
    return "; ".join(parts)


def widget_kind(control: Control) -> str:
    """Which viser widget shows a control: slider, number, checkbox, dropdown, text, vector2/3."""
    if control.kind == "bool":
        return "checkbox"
    if control.kind == "choice":
        return "dropdown"
    if control.kind == "str":
        return "text"
    if control.kind == "tuple":
        numeric = all(k in ("int", "float") for k in control.item_kinds)
        if numeric and len(control.item_kinds) in (2, 3):
            return f"vector{len(control.item_kinds)}"
        return "text"
    bounded = control.minimum is not None and control.maximum is not None
    if control.kind == "int":
        return "slider" if bounded and control.maximum - control.minimum <= 1000 else "number"
    return "slider" if bounded else "number"


def add_control_widget(gui: Any, control: Control, value: Any = None) -> Any:
    """Add the widget of ``control`` (showing ``value``, else its default) and return its handle."""
    kind = widget_kind(control)
    value = control.default if value is None else value
    hint = control_hint(control) or None
    label = control.name
    if kind == "checkbox":
        return gui.add_checkbox(label, bool(value), hint=hint)
    if kind == "dropdown":
        options = [str(c) for c in control.choices]
        initial = str(value) if value is not None and str(value) in options else options[0]
        return gui.add_dropdown(label, options, initial_value=initial, hint=hint)
    if kind == "text":
        if control.kind == "tuple":
            value = ", ".join(str(v) for v in value) if value is not None else ""
        return gui.add_text(label, "" if value is None else str(value), hint=hint)
    if kind in ("vector2", "vector3"):
        n = len(control.item_kinds)
        initial = tuple(float(v) for v in value) if value is not None else (0.0,) * n
        lo = None if control.minimum is None else (float(control.minimum),) * n
        hi = None if control.maximum is None else (float(control.maximum),) * n
        step = 1.0 if all(k == "int" for k in control.item_kinds) else None
        add = gui.add_vector2 if n == 2 else gui.add_vector3
        return add(label, initial, min=lo, max=hi, step=step, hint=hint)
    is_int = control.kind == "int"
    cast = int if is_int else float
    if value is None:  # a required number: start at its lower bound (or 0)
        value = control.minimum if control.minimum is not None else 0
    value = cast(value)
    if kind == "slider":
        lo, hi = cast(control.minimum), cast(control.maximum)
        step = 1 if is_int else nice_step(hi - lo, lo, value)
        return gui.add_slider(label, min=lo, max=hi, step=step, initial_value=value, hint=hint)
    lo = None if control.minimum is None else cast(control.minimum)
    hi = None if control.maximum is None else cast(control.maximum)
    return gui.add_number(label, value, min=lo, max=hi, step=1 if is_int else None, hint=hint)


def widget_value(control: Control, handle: Any) -> Any:
    """The raw value a widget holds (checked later by :meth:`Control.coerce`)."""
    value = handle.value
    if isinstance(value, tuple):
        return list(value)
    if control.kind == "tuple" and isinstance(value, str) and "str" in control.item_kinds:
        # text items: split on commas only (the core's parser also splits "640x480" on the x)
        return [item.strip() for item in value.strip().strip("()[]").split(",")]
    return value


# --- formatting -------------------------------------------------------------------------------
def format_number(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if value == 0 or 1e-3 <= abs(value) < 1e5:
            return f"{value:.4g}"
        return f"{value:.3e}"
    if isinstance(value, (list, tuple)):
        if not value:
            return "[]"
        numbers = [v for v in value if isinstance(v, (int, float))]
        if len(value) <= 4:
            return "[" + ", ".join(format_number(v) for v in value) + "]"
        if numbers:
            return f"{len(value)} values, max {format_number(max(numbers))}"
        return f"{len(value)} values"
    return str(value)


def metrics_markdown(spec: StepSpec, metrics: Mapping[str, Any], warnings: Iterable[str] = ()) -> str:
    """A step's metrics as a markdown table (units from its ``metric()`` fields); warnings below."""
    described = {o.name: o for o in spec.outputs if o.is_metric}
    lines = []
    if metrics:
        lines += ["| metric | value |", "|---|---|"]
        for name, value in metrics.items():
            out = described.get(name)
            unit = f" {out.unit}" if out is not None and out.unit else ""
            label = name if out is not None else f"{name} (evaluation)"
            lines.append(f"| {label} | {_cell(format_number(value))}{unit} |")
    for warning in warnings:
        lines.append(f"\n⚠ {warning}")
    return "\n".join(lines)


def value_summary(name: str, value: Any) -> str:
    type_name = type(value).__name__
    if isinstance(value, np.ndarray):
        text = f"`{name}`: array {tuple(value.shape)} {value.dtype}"
        if value.size <= 16 and value.dtype.kind in "fiub":
            text += "  \n`" + np.array2string(value, precision=4, suppress_small=True, max_line_width=60) \
                .replace("\n", " ") + "`"
        return text
    if isinstance(value, (int, float, str, bool, np.generic)):
        return f"`{name}`: {format_number(value) if not isinstance(value, str) else value}"
    if isinstance(value, OVERLAY_TYPES):
        return f"`{name}`: {type_name} ({len(value)}), drawn on `{value.image}`"
    if type(value) in VALUE_TYPES.values():
        size = f" ({len(value)})" if hasattr(value, "__len__") else ""
        return f"`{name}`: {type_name}{size}"
    return f"`{name}`: {type_name}"


def history_markdown(history: list, limit: int = 12) -> str:
    """The last runs of a session's history, newest first, as a markdown table."""
    records = history[-limit:]
    if not records:
        return "No step has run yet."
    start = len(history) - len(records)
    rows = []
    for i, record in enumerate(records):
        status = record.status if not record.error else f"{record.status}: {record.error[:60]}"
        rows.append(f"| {start + i + 1} | {record.step} | {_cell(status)} | {record.seconds:.3f} |")
    return "\n".join(["| # | step | status | seconds |", "|---|---|---|---|"] + rows[::-1])


def _cell(text: str) -> str:
    """Text safe inside a markdown table cell."""
    return str(text).replace("|", "\\|").replace("\n", " ")


def error_text(exc: BaseException) -> str:
    if isinstance(exc, LabError):
        return f"{exc.kind}: {exc.field}: {exc.reason}"
    return f"{type(exc).__name__}: {exc}"


# --- reading the page's query ---------------------------------------------------------------------
def read_query(client: Any, *, timeout: float = 5.0) -> dict[str, str]:
    """The query parameters of the page a viser client was opened at (``?session=ID`` ...).

    See the module docstring: one line of JavaScript copies ``window.location.search`` into the
    tab's localStorage under a random key, read back with ``client.local_storage.get_item``.
    Returns {} when the client cannot answer (no localStorage, timeout).
    """
    from urllib.parse import parse_qsl

    from viser import _messages

    key = f"lab-query-{uuid.uuid4().hex}"
    script = f'try {{ window.localStorage.setItem("viser-user:{key}", window.location.search); }} catch (e) {{}}'
    try:
        client._websock_connection.queue_message(_messages.RunJavascriptMessage(source=script))
        client.flush()
        search = client.local_storage.get_item(key, timeout=timeout)
        client.local_storage.remove_item(key)
    except Exception as exc:  # an old client, blocked storage, a tab closed meanwhile
        log.info("could not read the page query of client %s: %s", getattr(client, "client_id", "?"), exc)
        return {}
    return {k: v for k, v in parse_qsl((search or "").lstrip("?")) if k in QUERY_KEYS}


def set_page_query(client: Any, session_id: str | None = None, **params: str | None) -> None:
    """Write ``?session=ID`` into the tab's address bar (keeping viser's own parameters, dropping
    ``module`` and ``dataset``, which the session replaces); ``params`` set others (None: remove)."""
    from viser import _messages

    changes = dict(params)
    if session_id is not None:
        changes.update(session=session_id, module=None, dataset=None)
    safe = {key: None if value is None else "".join(c for c in value if c.isalnum() or c in "-_")
            for key, value in changes.items()}
    edits = " ".join(f'p.delete("{key}");' if value is None else f'p.set("{key}", "{value}");'
                     for key, value in safe.items())
    script = ("try { const p = new URLSearchParams(window.location.search); " + edits +
              ' window.history.replaceState(null, "", "?" + p.toString()); } catch (e) {}')
    try:
        client._websock_connection.queue_message(_messages.RunJavascriptMessage(source=script))
    except Exception as exc:
        log.info("could not update the page address: %s", exc)


# --- one tab ---------------------------------------------------------------------------------------
@dataclass
class StepRow:
    """The GUI of one step: its folder (label = number, title, status), control widgets by name,
    the Run / Run to here / Reset button group and the markdown of its metrics."""

    spec: StepSpec
    folder: Any
    controls: dict[str, Any]
    buttons: Any
    metrics: Any


class ClientView:
    """The viewer of one browser tab (or, in tests, of a viser server's shared GUI).

    ``target`` is a viser ``ClientHandle`` (or a ``ViserServer``): anything with ``.gui`` and
    ``.scene``. The view owns every GUI element and scene node it adds. With ``lessons`` (a
    :class:`~lab.lessons.format.LessonCatalog`) the view has a lesson mode (:mod:`lab.viewer.lesson`).
    """

    def __init__(self, target: Any, store: SessionStore, catalog: ModuleCatalog, *, is_client: bool = True,
                 background: bool = True, lessons: Any = None) -> None:
        self.target = target
        self.gui = target.gui
        self.scene = target.scene
        self.store = store
        self.catalog = catalog
        self.is_client = is_client
        #: Run steps in a background thread (the viewer); False runs them inline (tests).
        self.background = background
        self.lock = threading.RLock()
        self.session: Session | None = None
        self.rows: dict[str, StepRow] = {}
        self.errors: list[str] = []
        self.worker: threading.Thread | None = None
        self.closed = False
        self._seen: tuple[int, int] | None = None
        self._framed = False
        self._progress_state: dict[str, Any] = {"step": None, "iteration": -1, "x": [], "y": [], "shown": 0.0,
                                                "preview": 0.0}
        self._step_handles: list[Any] = []
        self._dataset_option_handles: dict[str, Any] = {}
        self.lesson_mode: Any = None  # a LessonMode when ``lessons`` is given
        #: The module's special interactions for the session shown (:mod:`lab.viewer.interactions`).
        self.interactions: list[Interaction] = []
        self._interaction_handles: list[Any] = []
        self._carry: Any = None  # handed to the interactions of a restarted session (ctx.carried)
        self._build_static()
        self.drawer = StateDrawer(Canvas(scene=self.scene, gui=self.gui, images=self.images_tab,
                                         plots=self.plots_tab, on_view_selected=self._view_selected))
        if lessons is not None:
            from lab.viewer.lesson import LessonMode  # imports this module

            self.lesson_mode = LessonMode(self, lessons)

    # --- static GUI ------------------------------------------------------------------------------
    def _build_static(self) -> None:
        gui = self.gui
        try:
            gui.configure_theme(control_width="large", show_share_button=False)
        except Exception:  # an older viser without this option: the default width is fine
            pass
        self.header = gui.add_markdown("**Vision Lab**", order=0)
        self.error_box = gui.add_markdown("", order=1, visible=False)
        self.session_folder = gui.add_folder("Module · dataset · session", order=2, expand_by_default=False)
        names = self.catalog.names()
        with self.session_folder:
            offered = names or ["(none)"]
            self.module_dropdown = gui.add_dropdown("module", offered, initial_value=offered[0],
                                                    hint="the teaching module")
            self.dataset_dropdown = gui.add_dropdown("dataset", ["(none)"], hint="the data the session starts from")
            self.dataset_options = gui.add_folder("dataset options", expand_by_default=False)
            self.new_button = gui.add_button("New session", hint="load the dataset into a fresh session")
            self.session_id_text = gui.add_text("session id", "", hint="a session made over REST: paste its id")
            self.open_button = gui.add_button("Open session", hint="show the session whose id is above")
        self.steps_folder = gui.add_folder("Steps", order=3)
        self.progress_folder = gui.add_folder("Progress", order=4, visible=False)
        with self.progress_folder:
            self.progress_text = gui.add_markdown("")
            self.progress_bar = gui.add_progress_bar(0.0, animated=False)
            self.loss_plot = gui.add_uplot((np.zeros(1), np.zeros(1)), ({"label": "iteration"}, {
                "label": "loss", "stroke": "#d62728", "width": 2}), title="loss", aspect=1.6,
                scales={"x": {"time": False}})
            self.cancel_button = gui.add_button("Cancel", color="red", hint="stop the running step")
        self.history_folder = gui.add_folder("History", order=5, expand_by_default=False)
        with self.history_folder:
            self.history_md = gui.add_markdown("No step has run yet.")
        self.values_folder = gui.add_folder("Values", order=6, expand_by_default=False)
        with self.values_folder:
            self.values_md = gui.add_markdown("")
        # images and plots: a panel of their own, docked on the left
        self.media_panel = gui.add_panel(visible=False)
        self.images_tab = self.media_panel.add_tab("Images")
        self.plots_tab = self.media_panel.add_tab("Plots")
        try:
            self.media_panel.dock_left()
            self.media_panel.set_width(MEDIA_PANEL_WIDTH)
            gui.main_panel.dock_right()
            gui.main_panel.set_width(400)
        except Exception as exc:  # placement is cosmetic
            log.info("could not dock the image panel: %s", exc)

        self.module_dropdown.on_update(lambda _: self._guard(self._module_changed))
        self.dataset_dropdown.on_update(lambda _: self._guard(self._dataset_changed))
        self.new_button.on_click(lambda _: self._guard(self.new_session_from_gui))
        self.open_button.on_click(lambda _: self._guard(lambda: self.open_session_id(self.session_id_text.value)))
        self.cancel_button.on_click(lambda _: self._guard(self.cancel))
        self._module_changed()

    def _guard(self, action: Callable[[], Any]) -> None:
        """Run a GUI callback: a LabError (or a bug) is shown, never raised into viser."""
        try:
            action()
        except Exception as exc:
            if not isinstance(exc, LabError):
                log.error("viewer callback failed:\n%s", traceback.format_exc())
            self.show_error(exc)

    def _module_changed(self) -> None:
        name = self.module_dropdown.value
        try:
            pipeline = self.catalog.get(name)
        except LabError:
            if self.session is not None and self.session.pipeline.name == name:
                pipeline = self.session.pipeline
            else:
                return
        names = [d.name for d in pipeline.datasets] or ["(none)"]
        self.dataset_dropdown.options = names
        self.dataset_dropdown.value = names[0]
        self._dataset_changed()

    def _dataset_changed(self) -> None:
        for handle in self._dataset_option_handles.values():
            handle.remove()
        self._dataset_option_handles = {}
        spec = self._selected_dataset()
        if spec is None:
            return
        with self.dataset_options:
            for option in spec.options:
                self._dataset_option_handles[option.name] = add_control_widget(self.gui, option)

    def _selected_dataset(self):
        try:
            pipeline = self.catalog.get(self.module_dropdown.value)
        except LabError:
            if self.session is None:
                return None
            pipeline = self.session.pipeline
        for spec in pipeline.datasets:
            if spec.name == self.dataset_dropdown.value:
                return spec
        return None

    # --- sessions ---------------------------------------------------------------------------------
    def start(self, query: Mapping[str, str] | None = None) -> None:
        """Open what the page asked for (``?session=ID``, ``?module=..&dataset=..``, ``?lesson=ID``),
        else a new session on the first module's default dataset (the lesson's module with a lesson)."""
        query = dict(query or {})
        problems: list[LabError] = []  # shown once a session is open (opening one clears the error box)
        if query.get("lesson") and self.lesson_mode is not None:
            try:
                self.lesson_mode.select(query["lesson"])
            except LabError as exc:
                problems.append(exc)
        if query.get("session"):
            try:
                self.open_session(self.store.get(query["session"]))
            except LabError as exc:
                problems.append(exc)
        if self.session is None:
            try:
                if self.lesson_mode is not None and self.lesson_mode.lesson is not None:
                    self.lesson_mode.new_session()
                else:
                    module = query.get("module") or (self.catalog.names() or [None])[0]
                    if module is None:
                        raise UnknownName("module", "this server offers no module")
                    pipeline = self.catalog.get(module)
                    self.open_session(self.store.create(pipeline, query.get("dataset") or None))
            except LabError as exc:
                problems.append(exc)
        for problem in problems:
            self.show_error(problem)

    def new_session_from_gui(self) -> None:
        pipeline = self.catalog.get(self.module_dropdown.value)
        spec = self._selected_dataset()
        options = {}
        if spec is not None:
            for option in spec.options:
                handle = self._dataset_option_handles.get(option.name)
                if handle is None:
                    continue
                value = widget_value(option, handle)
                if option.required and value in ("", None):
                    continue  # reported by the loader as a missing option
                if not option.required and _same(option, value):
                    continue
                options[option.name] = value
        self.open_session(self.store.create(pipeline, spec.name if spec else None, options))

    def open_session_id(self, session_id: str) -> None:
        session_id = (session_id or "").strip()
        if not session_id:
            raise UnknownName("session", "type a session id first")
        self.open_session(self.store.get(session_id))

    def open_session(self, session: Session) -> None:
        """Show ``session`` in this tab (replacing the one shown)."""
        with self.lock:
            if self.session is not None:
                self._detach()
            self.session = session
            session.listeners.append(self._on_progress)
            self.clear_error()
            self.drawer.clear()
            self._framed = False
            self._seen = None
            self.session_id_text.value = session.id
            if session.pipeline.name not in self.module_dropdown.options:  # opened by id, not offered here
                self.module_dropdown.options = [*self.catalog.names(), session.pipeline.name]
            if self.module_dropdown.value != session.pipeline.name:
                self.module_dropdown.value = session.pipeline.name
                self._module_changed()
            self._build_steps()
            if self.lesson_mode is not None:
                self.lesson_mode.attach()  # the task steps get "use my code" and "Compare with reference"
            self._build_interactions()
            self.refresh(force=True)
        if self.is_client:
            set_page_query(self.target, session.id)

    def _detach(self) -> None:
        session = self.session
        if session is not None:
            try:
                session.listeners.remove(self._on_progress)
            except ValueError:
                pass

    def close(self) -> None:
        """The tab went away: stop listening (the session stays in the store for REST / a reload)."""
        self.closed = True
        with self.lock:
            self._detach()
            self._close_interactions()
        if self.lesson_mode is not None:
            self.lesson_mode.close()  # ends the student's sandbox

    # --- the module's special interactions ---------------------------------------------------------
    def _build_interactions(self) -> None:
        """Replace the interactions with those of the session's module, each in a folder of its own."""
        self._close_interactions()
        session = self.session
        assert session is not None
        for index, cls in enumerate(interactions_for(session.pipeline.name)):
            folder = self.gui.add_folder(cls.title, order=3.5 + index / 100, expand_by_default=True)
            self._interaction_handles.append(folder)
            ctx = InteractionContext(
                scene=self.scene, gui=self.gui, folder=folder, images=self.images_tab, plots=self.plots_tab,
                session=session, is_client=self.is_client, show_error=self.show_error,
                run=lambda step, params: self._guard(lambda: self.run_with(step, params)),
                restart=self._restart_for_interaction, carried=self._carry,
                extent=lambda: scene_extent(dict(session.state).values()))
            try:
                with folder:
                    self.interactions.append(cls(ctx))
            except Exception as exc:  # a broken interaction never takes the tab down
                log.error("interaction %s failed to start:\n%s", cls.__name__, traceback.format_exc())
                self.show_error(exc)

    def _close_interactions(self) -> None:
        for interaction in self.interactions:
            try:
                interaction.close()
            except Exception:
                log.error("interaction close failed:\n%s", traceback.format_exc())
        self.interactions = []
        for handle in self._interaction_handles:
            try:
                handle.remove()
            except Exception:
                pass
        self._interaction_handles = []

    def _update_interactions(self, state: Mapping[str, Any]) -> None:
        for interaction in self.interactions:
            try:
                interaction.update(state)
            except Exception as exc:
                if not isinstance(exc, LabError):
                    log.error("interaction update failed:\n%s", traceback.format_exc())
                self.show_error(exc)

    def run_with(self, step: str, params: Mapping[str, Any]) -> None:
        """Run ``step`` with these controls (an interaction's request), like its Run button."""
        session = self._require_session()
        self.clear_error()
        values = dict(params)
        self._set_label(step, "running")
        self.in_background(lambda: session.run(step, values, override=self.override(step)), step)

    def restart(self, options: Mapping[str, Any], *, run_until: str | None = None,
                params: Mapping[str, Mapping[str, Any]] | Callable[[Session], Mapping[str, Mapping[str, Any]]] | None = None,
                carry: Any = None) -> None:
        """Open a new session of the shown module and dataset with ``options`` changed; then run
        every step through ``run_until`` with ``params`` (``{step: controls}``, or a function of the
        new session giving them; controls not given come from the step widgets). ``carry`` reaches
        the new session's interactions as ``ctx.carried``."""
        session = self._require_session()
        if self.worker is not None and self.worker.is_alive():
            raise LabError("session", "a step is still running; wait or press Cancel")
        if run_until is not None:
            session.pipeline.step(run_until)  # an unknown step: UnknownName before anything changes
        fresh = self.store.create(session.pipeline, session.dataset, {**session.options, **options})
        self._carry = carry
        try:
            self.open_session(fresh)
        finally:
            self._carry = None
        if run_until is not None:
            given = params(fresh) if callable(params) else (params or {})
            names = [s.name for s in fresh.pipeline.steps]
            merged = {name: {**self.step_params(name), **dict(given.get(name, {}))}
                      for name in names[:names.index(run_until) + 1]}
            self.in_background(lambda: self._run_until(fresh, run_until, merged), run_until)

    def _restart_for_interaction(self, options: Mapping[str, Any], **kwargs: Any) -> bool:
        """:meth:`restart` for an interaction: True when the new session opened, else the error is shown."""
        before = self.session
        self._guard(lambda: self.restart(options, **kwargs))
        return self.session is not before

    # --- steps ------------------------------------------------------------------------------------
    def _build_steps(self) -> None:
        for handle in self._step_handles:
            handle.remove()
        self._step_handles = []
        self.rows = {}
        session = self.session
        assert session is not None
        status = session.step_status()
        current = next((s.name for s in session.pipeline.steps if status[s.name] != "done"), None)
        gui = self.gui
        with self.steps_folder:
            for index, spec in enumerate(session.pipeline.steps):
                folder = gui.add_folder(self._step_label(index, spec, status[spec.name]),
                                        expand_by_default=spec.name == current)
                self._step_handles.append(folder)
                with folder:
                    reads = ", ".join(spec.reads) or "nothing"
                    writes = ", ".join(spec.writes) or "metrics only"
                    long = " Long step: shows progress, can be cancelled." if spec.is_generator else ""
                    gui.add_markdown(f"{spec.summary}\n\n*reads* {reads} → *writes* {writes}.{long}")
                    controls = {c.name: add_control_widget(gui, c) for c in spec.controls}
                    buttons = gui.add_button_group("step", ("Run", "Run to here", "Reset"))
                    metrics = gui.add_markdown("")
                row = StepRow(spec, folder, controls, buttons, metrics)
                buttons.on_click(lambda event, name=spec.name: self._guard(
                    lambda: self.press(name, event.target.value)))
                self.rows[spec.name] = row

    @staticmethod
    def _step_label(index: int, spec: StepSpec, status: str) -> str:
        return f"{index + 1}. {spec.title} {STATUS_MARK.get(status, '')} {status}"

    def press(self, step: str, button: str) -> None:
        """A step's button: ``Run``, ``Run to here`` or ``Reset``."""
        if button == "Reset":
            self.reset(step)
        elif button == "Run to here":
            self.run(step, until=True)
        else:
            self.run(step)

    def step_params(self, step: str) -> dict[str, Any]:
        """The values of a step's control widgets (checked by the step's schema when it runs)."""
        row = self.rows[step]
        return {c.name: widget_value(c, row.controls[c.name]) for c in row.spec.controls}

    def run(self, step: str, *, until: bool = False) -> None:
        """Run ``step`` (or every step not done up to it) in a background thread."""
        session = self._require_session()
        if self.worker is not None and self.worker.is_alive():
            raise LabError("step", f"step {session.running or '...'} is still running; wait or press Cancel")
        self.clear_error()
        if until:
            names = [s.name for s in session.pipeline.steps]
            params = {name: self.step_params(name) for name in names[:names.index(step) + 1]}
            job = lambda: self._run_until(session, step, params)  # noqa: E731
        else:
            params = self.step_params(step)
            job = lambda: session.run(step, params, override=self.override(step))  # noqa: E731
        if not until:
            self._set_label(step, "running")
        self.in_background(job, step)

    def in_background(self, job: Callable[[], Any], name: str) -> None:
        """Run ``job`` in the tab's worker thread (inline when ``background`` is False), off viser's
        threads; what it raises is shown in the GUI, and the view is refreshed after it."""
        if self.worker is not None and self.worker.is_alive():
            raise LabError(name, "the tab is still busy with the last step or comparison; wait or press Cancel")
        if self.background:
            self.worker = threading.Thread(target=self._work, args=(job,), name=f"lab-viewer-{name}", daemon=True)
            self.worker.start()
        else:
            self._work(job)

    def override(self, step: str) -> Callable[..., Any] | None:
        """The function run in place of ``step``: the student's, in lesson mode with "use my code" on."""
        return self.lesson_mode.override(step) if self.lesson_mode is not None else None

    def _run_until(self, session: Session, step: str, params: dict[str, dict[str, Any]]) -> None:
        """:meth:`Session.run_until`, one step at a time, redrawing after each."""
        for spec in session.pipeline.steps:
            if spec.name == step or session.step_status()[spec.name] != "done":
                self._set_label(spec.name, "running")
                session.run(spec.name, params.get(spec.name), override=self.override(spec.name))
                if spec.name != step:
                    self.refresh(force=True)
            if spec.name == step:
                break

    def _work(self, job: Callable[[], Any]) -> None:
        try:
            job()
        except LabError as exc:
            self.show_error(exc)
        except Exception as exc:  # a bug somewhere: show it, keep the tab alive
            log.error("step failed in the viewer:\n%s", traceback.format_exc())
            self.show_error(exc)
        finally:
            try:
                self.refresh(force=True)
            except Exception as exc:
                log.error("refresh failed:\n%s", traceback.format_exc())
                self.show_error(exc)

    def reset(self, step: str) -> None:
        session = self._require_session()
        self.clear_error()
        session.reset(step)
        self.refresh(force=True)

    def cancel(self) -> None:
        session = self._require_session()
        if not session.cancel():
            self.show_error(LabError("cancel", "no step is running"))

    def wait(self, timeout: float = 30.0) -> None:
        """Wait for the background run (tests)."""
        worker = self.worker
        if worker is not None:
            worker.join(timeout)

    def _require_session(self) -> Session:
        if self.session is None:
            raise LabError("session", "no session is open: press New session")
        return self.session

    def _set_label(self, step: str, status: str) -> None:
        row = self.rows.get(step)
        if row is None or self.session is None:
            return
        index = [s.name for s in self.session.pipeline.steps].index(step)
        row.folder.label = self._step_label(index, row.spec, status)

    # --- progress of long steps -------------------------------------------------------------------
    def _on_progress(self, step: str, progress: Progress) -> None:
        """Session listener: called from the thread running a long step (ours or a REST call's)."""
        if self.closed:
            return
        state = self._progress_state
        now = time.monotonic()
        new_run = step != state["step"] or progress.iteration <= state["iteration"]
        if new_run:
            state.update(step=step, x=[], y=[], shown=0.0, preview=0.0, finished=False, log=False)
        state["iteration"] = progress.iteration
        if progress.loss is not None and np.isfinite(progress.loss):
            state["x"].append(float(progress.iteration))
            state["y"].append(float(progress.loss))
        total = progress.total
        state["fraction"] = min(1.0, progress.iteration / total) if total else 0.0
        state["animated"] = not total
        loss = "" if progress.loss is None else f", loss {format_number(progress.loss)}"
        note = f" — {progress.message}" if progress.message else ""
        state["message"] = f"**{step}**: iteration {progress.iteration}{f'/{total}' if total else ''}{loss}{note}"
        last = total is not None and progress.iteration >= total
        if not new_run and not last and now - state["shown"] < PROGRESS_SECONDS:
            return  # shown at the next snapshot, or when the step ends
        state["shown"] = now
        with self.lock:
            self._show_progress(reset_scale=new_run)
            if progress.values and now - state["preview"] >= PREVIEW_SECONDS and self.session is not None:
                state["preview"] = now
                preview = {**self.session.state, **progress.values}
                self.drawer.sync(preview, order=self._order(preview))

    def _show_progress(self, *, reset_scale: bool = False) -> None:
        """Put the latest progress snapshot on screen (bar, text, loss plot, log scale when it spans decades)."""
        state = self._progress_state
        self.progress_folder.visible = True
        self.cancel_button.disabled = False
        self.progress_bar.animated = state["animated"]
        self.progress_bar.value = 100.0 * state["fraction"]
        self.progress_text.content = state["message"]
        if state["x"]:
            xs, ys = np.asarray(state["x"]), np.asarray(state["y"])
            self.loss_plot.data = (xs, ys)
            log_scale = bool(ys.min() > 0 and ys.max() / ys.min() > 100)
            if reset_scale or log_scale != state["log"]:
                state["log"] = log_scale
                self.loss_plot.scales = {"x": {"time": False}, **({"y": {"distr": 3, "log": 10}} if log_scale else {})}

    def _finish_progress(self, history: list) -> None:
        """After a long step: show its last snapshot and how it ended (it may stop early, converged)."""
        state = self._progress_state
        if state["step"] is None or state.get("finished"):
            return
        record = next((r for r in reversed(history) if r.step == state["step"]), None)
        if record is None:
            return
        state["finished"] = True
        self._show_progress()
        self.cancel_button.disabled = True
        self.progress_bar.animated = False
        if record.status == "ok":
            self.progress_bar.value = 100.0
        self.progress_text.content = f"{state['message']} — **{record.status}**"

    # --- refresh ----------------------------------------------------------------------------------
    def poll(self) -> None:
        """Redraw when the session changed behind this tab's back (REST, another tab)."""
        session = self.session
        if session is None or self.closed:
            return
        if session.id not in self.store:
            if self._seen != (-1, -1):
                self._seen = (-1, -1)
                self.show_error(UnknownName("session", f"{self.store.why_gone(session.id)}; press New session"))
            return
        if (self.worker is not None and self.worker.is_alive()) or session.running is not None:
            return
        if (session.version, len(session.history)) != self._seen:
            self.refresh()

    def refresh(self, *, force: bool = False) -> None:
        """Bring every status, metric and drawing up to date with the session."""
        with self.lock:
            session = self.session
            if session is None or self.closed:
                return
            seen = (session.version, len(session.history))
            if not force and seen == self._seen:
                return
            self._seen = seen
            # Copies: a step running in another thread (REST) may change these meanwhile; dict()
            # and list() copy in one go under the GIL, iterating the originals would not.
            state, metrics, history = dict(session.state), dict(session.metrics), list(session.history)
            status = session.step_status()
            last = {r.step: r for r in history}
            for index, spec in enumerate(session.pipeline.steps):
                row = self.rows.get(spec.name)
                if row is None:
                    continue
                row.folder.label = self._step_label(index, spec, status[spec.name])
                record = last.get(spec.name)
                parts = []
                if spec.name in metrics:
                    ran = next((r for r in reversed(history) if r.step == spec.name and r.status == "ok"), None)
                    if ran is not None:
                        parts.append(f"Ran in {ran.seconds:.3f} s.")
                    parts.append(metrics_markdown(spec, metrics[spec.name], ran.warnings if ran is not None else ()))
                if record is not None and record.status != "ok":
                    parts.append(f"Last run {record.status}: {record.error}")
                row.metrics.content = "\n\n".join(p for p in parts if p)
            title = session.pipeline.title or session.pipeline.name
            self.header.content = (f"**Vision Lab · {title}**  \nsession `{session.id}` · dataset "
                                   f"`{session.dataset}`" + (" · has ground truth" if session.truth else ""))
            self.history_md.content = history_markdown(history)
            self.values_md.content = "  \n".join(value_summary(n, v) for n, v in sorted(state.items()))
            if session.running is None:
                self.progress_bar.animated = False
                self.cancel_button.disabled = True
                self._finish_progress(history)
            self.drawer.sync(state, order=self._order(state))
            self._update_interactions(state)
            if self.drawer.errors:
                self.show_error(LabError("drawing", "; ".join(f"{k}: {v}" for k, v in self.drawer.errors.items())))
            self.media_panel.visible = any(not renderer_for(v).in_scene for v in state.values()
                                           if renderer_for(v) is not None)
            self._frame_camera(state)

    def _order(self, state: Mapping[str, Any]) -> dict[str, float]:
        """Draw values in the order the pipeline makes them (dataset values first)."""
        session = self.session
        if session is None:
            return {}
        order: dict[str, float] = {}
        for index, spec in enumerate(session.pipeline.steps):
            for name in spec.writes:
                order.setdefault(name, index + 1.0)
        return {name: order.get(name, 0.0) for name in state}

    def _frame_camera(self, state: Mapping[str, Any]) -> None:
        """Point the tab's camera at the 3D content the first time there is some."""
        if self._framed or not self.is_client:
            return
        view = self.framing(state)
        if view is None:
            return
        self._framed = True
        position, look_at = view
        try:
            camera = self.target.camera
            camera.up_direction = (0.0, -1.0, 0.0)
            camera.position = tuple(position)
            camera.look_at = tuple(look_at)  # after the position, which drags look_at along
        except Exception as exc:  # cosmetic
            log.info("could not frame the camera: %s", exc)

    def framing(self, state: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
        """``(eye, look_at)`` for the tab's camera: the state's 3D values, else what the module's
        interactions draw (e.g. the two cameras of an epipolar pair before anything is triangulated)."""
        view = viewpoint(state.values())
        if view is None:
            boxes = [b for b in (i.bounds() for i in self.interactions) if b is not None]
            view = viewpoint([PointCloud(np.concatenate(boxes))]) if boxes else None
        return view

    def _view_selected(self, image_name: str, view: int) -> None:
        with self.lock:
            self.drawer.show_view(image_name, view)

    # --- errors ------------------------------------------------------------------------------------
    def show_error(self, exc: BaseException) -> None:
        text = error_text(exc)
        self.errors.append(text)
        try:
            self.error_box.content = f"**Error** — {text}"
            self.error_box.visible = True
            if self.is_client and hasattr(self.target, "add_notification"):
                self.target.add_notification("Error", text, color="red", auto_close_seconds=8.0)
        except Exception:  # the tab is gone
            pass

    def clear_error(self) -> None:
        self.error_box.visible = False
        self.error_box.content = ""


def _same(control: Control, value: Any) -> bool:
    try:
        return control.coerce(value) == control.default
    except LabError:
        return False


# --- the viewer server -----------------------------------------------------------------------------
class ViewerApp:
    """The viser server of the lab: one :class:`ClientView` per browser tab, sharing ``store``.

    ``modules`` (default: every registered module) is what the module picker offers; sessions
    of other modules can still be opened by id. ``lessons`` is the lesson picker's
    :class:`~lab.lessons.format.LessonCatalog` (True: the lessons folder, ``lessons_root()``;
    False: no lesson mode). Call :meth:`start`, then :meth:`stop`.
    """

    def __init__(self, store: SessionStore | None = None, *, host: str = "127.0.0.1", port: int = 8080,
                 modules: Mapping[str, Pipeline] | Iterable[Pipeline] | None = None, label: str = "Vision Lab",
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

        self.server = viser.ViserServer(host=self.host, port=self.requested_port, label=self.label, verbose=False)
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


__all__ = ["ViewerApp", "ClientView", "ModuleCatalog", "add_control_widget", "widget_kind", "widget_value",
           "read_query", "set_page_query", "metrics_markdown", "format_number", "nice_step"]
