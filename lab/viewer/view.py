"""One browser tab of the viewer: a session shown, its steps run from the GUI, its values drawn.

A :class:`ClientView` ties the tab's pieces together, each in a module of its own: the widgets
(:mod:`lab.viewer.gui`, :mod:`lab.viewer.widgets`), what its buttons run and the worker thread
(:mod:`lab.viewer.runner`), the progress of long steps (:mod:`lab.viewer.progress`), the drawing
(:mod:`lab.viewer.renderers`), the camera (:mod:`lab.viewer.camera`), the module's interactions
(:mod:`lab.viewer.interactions`) and, with a lesson catalog, the lesson mode
(:mod:`lab.viewer.lesson`, which reaches the tab only through a :class:`LessonContext`).

The step list follows the session: each step's widgets show the controls its outputs were computed
with (``Session.ran_with``; a step run over REST shows the script's), and changing a widget marks
the step, and every step downstream of it, **stale** at once (``Session.step_status`` with the
controls shown). Run re-runs the step and, with "Re-run dependants automatically" on, what depends
on it; Run to here and Run all run the core's plan (:mod:`lab.viewer.runner`).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import traceback
from collections.abc import Callable, Mapping, Sequence, Set
from typing import TYPE_CHECKING, Any

import numpy as np

from lab.core.errors import LabError, UnknownName
from lab.core.pipeline import DatasetSpec, Plan, RunRecord, Session, StepParams, StepStatus
from lab.core.store import SessionStore
from lab.viewer.camera import CameraFramer, framing
from lab.viewer.legend import ScenePanel, add_how_to
from lab.viewer.catalog import ModuleCatalog
from lab.viewer.gui import StepRow, build_step_rows, build_tab_gui
from lab.viewer.interactions import Interaction, InteractionContext, interactions_for
from lab.viewer.page import set_page_query
from lab.viewer.progress import ProgressPanel
from lab.viewer.renderers import Canvas, StateDrawer, renderer_for, scene_extent
from lab.viewer.runner import Runner, step_plan
from lab.viewer.text import (error_text, history_markdown, metrics_markdown, stale_note, step_label,
                             value_summary)
from lab.viewer.widgets import add_control_widget, same_as_default, show_value, widget_value

if TYPE_CHECKING:
    from lab.viewer.lesson import LessonContext, LessonMode

log = logging.getLogger("lab.viewer")

#: The controls :meth:`ClientView.restart` runs with: ``{step: controls}``, or a function of the new session.
ParamsSource = StepParams | Callable[[Session], StepParams] | None


class ClientView:
    """The viewer of one browser tab (or, in tests, of a viser server's shared GUI).

    ``target`` is a viser ``ClientHandle`` (or a ``ViserServer``): anything with ``.gui`` and
    ``.scene``. The view owns every GUI element (``tab``: :class:`~lab.viewer.gui.TabGui`) and
    scene node it adds. ``background`` False runs steps inline (tests). With ``lessons`` (a
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
        self.lock = threading.RLock()
        self.session: Session | None = None
        self.rows: dict[str, StepRow] = {}
        self.errors: list[str] = []
        self.closed = False
        self._seen: tuple[int, int] | None = None
        self._drawn: dict[str, Any] = {}  # the values the last refresh drew (held_during_plan)
        self._synced: dict[str, dict[str, Any]] = {}  # per step, the ran_with its widgets were set to
        self._syncing = False  # the code is setting widgets (their callbacks must not mark anything stale)
        self._marked: str | None = None  # the step labelled "running"
        self._marked_status = "running"  # its label (the runner's: "running", or the compiling notice)
        self._failed: set[str] = set()  # steps whose last run failed (labelled so until they run or reset)
        self._history_read = 0  # how many of the session's history records _note_runs has read
        self._step_handles: list[Any] = []
        self._dataset_option_handles: dict[str, Any] = {}
        #: The module's special interactions for the session shown (:mod:`lab.viewer.interactions`).
        self.interactions: list[Interaction] = []
        self._interaction_handles: list[Any] = []
        self._carry: Any = None  # handed to the interactions of a restarted session (ctx.carried)
        self.tab = build_tab_gui(self.gui, catalog.names())
        self.drawer = StateDrawer(Canvas(scene=self.scene, gui=self.gui, images=self.tab.images_tab,
                                         plots=self.tab.plots_tab, on_view_selected=self._view_selected,
                                         on_pixel_clicked=self._pixel_clicked))
        self.progress = ProgressPanel(self.tab, self.lock, self._preview)
        self.runner = Runner(background=background, show_error=self.show_error,
                             refresh=lambda: self.refresh(force=True), mark=self._mark)
        self.camera = CameraFramer(target, is_client=is_client)
        self.how_to = add_how_to(self.gui)
        self.scene_panel = ScenePanel(self.gui, on_fit=lambda: self.guard(self.fit_view))
        self._wire()
        self._module_changed()
        self.lesson_mode: LessonMode | None = None
        if lessons is not None:
            from lab.viewer.lesson import LessonMode

            self.lesson_mode = LessonMode(self._lesson_context(), lessons)

    # --- the fixed GUI ------------------------------------------------------------------------------
    def _wire(self) -> None:
        tab = self.tab
        tab.module_dropdown.on_update(lambda _: self.guard(self._module_changed))
        tab.dataset_dropdown.on_update(lambda _: self.guard(self._dataset_changed))
        tab.new_button.on_click(lambda _: self.guard(self.new_session_from_gui))
        tab.open_button.on_click(lambda _: self.guard(
            lambda: self.open_session_id(tab.session_id_text.value)))
        tab.cancel_button.on_click(lambda _: self.guard(self.cancel))
        tab.run_all_button.on_click(lambda _: self.guard(self.run_all))

    def guard(self, action: Callable[[], Any]) -> None:
        """Run a GUI callback: a LabError (or a bug) is shown, never raised into viser."""
        try:
            action()
        except Exception as exc:
            if not isinstance(exc, LabError):
                log.error("viewer callback failed:\n%s", traceback.format_exc())
            self.show_error(exc)

    def _module_changed(self) -> None:
        name = self.tab.module_dropdown.value
        try:
            pipeline = self.catalog.get(name)
        except LabError:
            if self.session is not None and self.session.pipeline.name == name:
                pipeline = self.session.pipeline
            else:
                return
        names = [d.name for d in pipeline.datasets] or ["(none)"]
        self.tab.dataset_dropdown.options = names
        self.tab.dataset_dropdown.value = names[0]
        self._dataset_changed()

    def _dataset_changed(self) -> None:
        for handle in self._dataset_option_handles.values():
            handle.remove()
        self._dataset_option_handles = {}
        spec = self._selected_dataset()
        if spec is None:
            return
        with self.tab.dataset_options:
            for option in spec.options:
                self._dataset_option_handles[option.name] = add_control_widget(self.gui, option)

    def _selected_dataset(self) -> DatasetSpec | None:
        try:
            pipeline = self.catalog.get(self.tab.module_dropdown.value)
        except LabError:
            if self.session is None:
                return None
            pipeline = self.session.pipeline
        return next((d for d in pipeline.datasets if d.name == self.tab.dataset_dropdown.value), None)

    # --- sessions -----------------------------------------------------------------------------------
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
                self._open_first(query)
            except LabError as exc:
                problems.append(exc)
        for problem in problems:
            self.show_error(problem)

    def _open_first(self, query: Mapping[str, str]) -> None:
        if self.lesson_mode is not None and self.lesson_mode.lesson is not None:
            self.lesson_mode.new_session()
            return
        names = self.catalog.names()
        module = query.get("module") or (names[0] if names else None)
        if module is None:
            raise UnknownName("module", "this server offers no module")
        self.open_session(self.store.create(self.catalog.get(module), query.get("dataset") or None))

    def new_session_from_gui(self) -> None:
        """A new session on the module, dataset and dataset options the pickers show."""
        pipeline = self.catalog.get(self.tab.module_dropdown.value)
        spec = self._selected_dataset()
        options = {}
        for option in spec.options if spec is not None else ():
            handle = self._dataset_option_handles.get(option.name)
            if handle is None:
                continue
            value = widget_value(option, handle)
            if option.required and value in ("", None):
                continue  # reported by the loader as a missing option
            if not option.required and same_as_default(option, value):
                continue
            options[option.name] = value
        self.open_session(self.store.create(pipeline, spec.name if spec else None, options))

    def open_session_id(self, session_id: str) -> None:
        """Show the session with this id (one made over REST)."""
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
            session.listeners.append(self.progress.on_progress)
            self.clear_error()
            # what is drawn stays for the refresh below: a value of the same name changes in place, the others
            # go (a GUI element removed right after its last update logs an error in the browser: renderers)
            self.drawer.canvas.views.clear()
            self.camera.reset()
            self._seen, self._drawn = None, {}
            self._failed, self._history_read = set(), 0
            self.tab.session_id_text.value = session.id
            dropdown = self.tab.module_dropdown
            if session.pipeline.name not in dropdown.options:  # opened by id, not offered here
                dropdown.options = [*self.catalog.names(), session.pipeline.name]
            if dropdown.value != session.pipeline.name:
                dropdown.value = session.pipeline.name
                self._module_changed()
            self._build_steps()
            if self.lesson_mode is not None:
                self.lesson_mode.attach()  # the task steps get "use my code" and "Compare with reference"
            self._build_interactions()
            self.refresh(force=True)
        self._set_query(session_id=session.id)

    def _detach(self) -> None:
        if self.session is not None:
            with contextlib.suppress(ValueError):
                self.session.listeners.remove(self.progress.on_progress)

    def close(self) -> None:
        """The tab went away: stop listening (the session stays in the store for REST / a reload)."""
        self.closed = True
        self.progress.closed = True
        with self.lock:
            self._detach()
            self._close_interactions()
        if self.lesson_mode is not None:
            self.lesson_mode.close()  # ends the student's sandbox

    def require_session(self) -> Session:
        """The session shown; :class:`LabError` when there is none."""
        if self.session is None:
            raise LabError("session", "no session is open: press New session")
        return self.session

    def _set_query(self, **params: str | None) -> None:
        if self.is_client:
            set_page_query(self.target, **params)

    def _lesson_context(self) -> LessonContext:
        from lab.viewer.lesson import LessonContext

        def step_folder(step: str) -> Any:
            row = self.rows.get(step)
            return None if row is None else row.folder

        return LessonContext(
            gui=self.gui, scene=self.scene, media_panel=self.tab.media_panel, lock=self.lock,
            session=lambda: self.session,
            open_session=lambda pipeline: self.open_session(self.store.create(pipeline)),
            step_folder=step_folder, step_params=self.step_params, guard=self.guard,
            in_background=self.runner.in_background, show_error=self.show_error, clear_error=self.clear_error,
            set_query=self._set_query)

    # --- the module's special interactions ------------------------------------------------------------
    def _build_interactions(self) -> None:
        """Replace the interactions with those of the session's module, each in a folder of its own."""
        self._close_interactions()
        session = self.require_session()
        for index, cls in enumerate(interactions_for(session.pipeline.name)):
            folder = self.gui.add_folder(cls.title, order=3.5 + index / 100, expand_by_default=True)
            self._interaction_handles.append(folder)
            ctx = InteractionContext(
                scene=self.scene, gui=self.gui, folder=folder, images=self.tab.images_tab,
                plots=self.tab.plots_tab, session=session, is_client=self.is_client,
                show_error=self.show_error,
                run=lambda step, params: self.guard(lambda: self.run_with(step, params)),
                restart=self._restart_for_interaction, carried=self._carry,
                extent=lambda: scene_extent(dict(session.state).values()),
                camera=getattr(self.target, "camera", None) if self.is_client else None)
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
            with contextlib.suppress(Exception):
                handle.remove()
        self._interaction_handles = []

    def _update_interactions(self, state: Mapping[str, Any]) -> None:
        for interaction in self.interactions:
            try:
                interaction.update(state)
            except Exception as exc:
                if not isinstance(exc, LabError):
                    log.error("interaction update failed:\n%s", traceback.format_exc())
                self.show_error(exc)

    def restart(self, options: Mapping[str, Any], *, run_to: str | None = None, params: ParamsSource = None,
                carry: Any = None) -> None:
        """Open a new session of the shown module and dataset with ``options`` changed, then run what
        step ``run_to`` needs (the core's plan, as Run to here) with ``params`` (``{step: controls}``, or a
        function of the new session giving them; controls not given come from the step widgets, which
        keep what they showed). ``carry`` reaches the new session's interactions as ``ctx.carried``."""
        session = self.require_session()
        if self.runner.busy():
            raise LabError("session", "a step is still running; wait or press Cancel")
        if run_to is not None:
            session.pipeline.step(run_to)  # an unknown step: UnknownName before anything changes
        shown = self.gui_params()
        fresh = self.store.create(session.pipeline, session.dataset, {**session.options, **options})
        self._carry = carry
        try:
            self.open_session(fresh)
        finally:
            self._carry = None
        given = params(fresh) if callable(params) else (params or {})
        merged = {name: {**shown.get(name, {}), **dict(given.get(name, {}))} for name in self.rows}
        self._show_params(merged)
        if run_to is not None:
            self._run(fresh, fresh.plan(run_to), merged)

    def _restart_for_interaction(self, options: Mapping[str, Any], **kwargs: Any) -> bool:
        """:meth:`restart` for an interaction: True when the new session opened, else the error is shown."""
        before = self.session
        self.guard(lambda: self.restart(options, **kwargs))
        return self.session is not before

    # --- steps: widgets and status ----------------------------------------------------------------
    def _build_steps(self) -> None:
        for handle in self._step_handles:
            handle.remove()
        session = self.require_session()
        ran_with = {step: dict(controls) for step, controls in session.ran_with.items()}
        self.rows = build_step_rows(self.gui, self.tab.steps_folder, session.pipeline, session.step_status(),
                                    ran_with)
        self._step_handles = [row.folder for row in self.rows.values()]
        self._synced = ran_with
        for name, row in self.rows.items():
            row.buttons.on_click(lambda event, name=name: self.guard(
                lambda: self.press(name, event.target.value)))
            for handle in row.controls.values():
                handle.on_update(lambda _: None if self._syncing else self.guard(self.refresh_status))

    def step_params(self, step: str) -> dict[str, Any]:
        """The values of a step's control widgets (checked by the step's schema when it runs)."""
        row = self.rows[step]
        return {c.name: widget_value(c, row.controls[c.name]) for c in row.spec.controls}

    def gui_params(self) -> dict[str, dict[str, Any]]:
        """The controls every step's widgets show, raw: ``{step: {control: value}}``."""
        return {name: self.step_params(name) for name in self.rows}

    def shown_params(self) -> dict[str, dict[str, Any]]:
        """The checked controls of the steps whose widgets hold valid ones (what stale marking compares with
        the controls each step ran with; an invalid widget is reported when its step runs)."""
        session = self.require_session()
        checked = {}
        for name, params in self.gui_params().items():
            with contextlib.suppress(LabError):
                checked[name] = session.pipeline.step(name).coerce_controls(params)
        return checked

    def _show_params(self, params: StepParams) -> None:
        """Put controls into the step widgets without marking anything stale (a restart keeps what was
        shown)."""
        self._syncing = True
        try:
            for name, controls in params.items():
                row = self.rows.get(name)
                if row is None:
                    continue
                for control in row.spec.controls:
                    if control.name in controls:
                        with contextlib.suppress(Exception):  # a value the widget cannot show stays as it is
                            show_value(control, row.controls[control.name], controls[control.name])
        finally:
            self._syncing = False

    def _sync_widgets(self, session: Session) -> None:
        """Show in each step's widgets the controls its outputs came from, when they changed since the last
        look (a step run over REST, or by an interaction, with other controls than the widgets showed)."""
        ran_with = {step: dict(controls) for step, controls in session.ran_with.items()}
        changed = {step: controls for step, controls in ran_with.items()
                   if self._synced.get(step) != controls}
        self._synced = ran_with
        self._show_params(changed)

    def refresh_status(self) -> dict[str, str]:
        """Label every step with its status now: a done step whose controls (or an upstream step's)
        differ from those its outputs came from is marked stale, with a note saying what changed. While
        a plan runs, a step outside it keeps its label (:func:`status_during_plan`)."""
        with self.lock:
            session = self.session
            if session is None or self.closed:
                return {}
            shown = self.shown_params()
            planned = self.runner.planned
            status = status_during_plan(session, session.step_status(shown), planned,
                                        stale=session.stale(shown) if planned else set())
            for index, spec in enumerate(session.pipeline.steps):
                row = self.rows.get(spec.name)
                if row is None:
                    continue
                label = self._marked_status if spec.name == self._marked else status[spec.name]
                if spec.name in self._failed and label in ("ready", "blocked"):
                    label = "failed"  # its last run failed: the error box (top of the panel) says why
                why = "see the error at the top" if label == "failed" else ""
                if self.lesson_mode is not None:  # a student's failed step stays failed until it works
                    label = self.lesson_mode.status_of(spec.name, label)
                    why = self.lesson_mode.failure_note(spec.name) or why
                row.folder.label = step_label(index, spec, label, why=why)
                stale = status[spec.name] == "stale"
                row.note.content = stale_note(spec, session.ran_with.get(spec.name), shown.get(spec.name)) \
                    if stale else ""
                row.note.visible = stale
            self.progress.forget_changed()  # a reset or stale step's old progress goes at once
            return status

    def _mark(self, step: str, status: str) -> None:
        """Label ``step`` with ``status`` (the runner's "running") until the next refresh."""
        with self.lock:
            row, session = self.rows.get(step), self.session
            if row is None or session is None:
                return
            self._marked, self._marked_status = step, status
            index = [s.name for s in session.pipeline.steps].index(step)
            row.folder.label = step_label(index, row.spec, status)

    # --- running ------------------------------------------------------------------------------------
    @property
    def rerun_dependants(self) -> bool:
        """Whether Run re-runs the steps that depend on the step (the "Re-run dependants" checkbox)."""
        return bool(self.tab.auto_rerun.value)

    def press(self, step: str, button: str) -> None:
        """A step's button: ``Run``, ``Run to here`` or ``Reset``."""
        if button == "Reset":
            self.reset(step)
        elif button == "Run to here":
            self.run_to(step)
        else:
            self.run(step)

    def run(self, step: str, *, until: bool = False) -> None:
        """The Run button of ``step`` (:func:`~lab.viewer.runner.step_plan`: the step, and what depends on it
        when dependants are re-run); ``until`` True is Run to here (:meth:`run_to`)."""
        if until:
            self.run_to(step)
            return
        session = self.require_session()
        self._run(session, step_plan(session, step, dependants=self.rerun_dependants), self.gui_params())

    def run_to(self, step: str) -> None:
        """Run to here: what ``step`` needs by data flow, then the step (``Session.plan(step, params)``)."""
        session = self.require_session()
        self._run(session, session.plan(step, self.shown_params()), self.gui_params())

    def run_all(self) -> None:
        """Run all: every missing or stale step and what reads their outputs
        (``Session.plan(None, params)``)."""
        session = self.require_session()
        self._run(session, session.plan(None, self.shown_params()), self.gui_params())

    def run_with(self, step: str, params: Mapping[str, Any]) -> None:
        """Run ``step`` with these controls (an interaction's request), as its Run button would."""
        session = self.require_session()
        given = {**self.gui_params(), step: dict(params)}
        self._run(session, step_plan(session, step, dependants=self.rerun_dependants), given)

    def _run(self, session: Session, plan: Plan, params: StepParams) -> None:
        self.clear_error()
        self.runner.run_plan(session, plan, params, self.override)

    def override(self, step: str) -> Callable[..., Any] | None:
        """The function run in place of ``step``: the student's, in lesson mode with "use my code" on."""
        return self.lesson_mode.override(step) if self.lesson_mode is not None else None

    def reset(self, step: str) -> None:
        """Forget the outputs of ``step`` and of every step downstream."""
        session = self.require_session()
        self.clear_error()
        session.reset(step)
        spec = session.pipeline.step(step)
        self._failed -= {step, *(s.name for s in session.pipeline.downstream(spec.writes))}
        self.refresh(force=True)

    def cancel(self) -> None:
        """Stop the running long step (at its next snapshot) and this tab's plan (before its next step)."""
        if not self.runner.cancel(self.require_session()):
            self.show_error(LabError("cancel", "no step is running"))

    def in_background(self, job: Callable[[], Any], name: str) -> None:
        """Run ``job`` in the tab's worker thread (:meth:`Runner.in_background`)."""
        self.runner.in_background(job, name)

    @property
    def worker(self) -> threading.Thread | None:
        """The tab's worker thread (None before the first background job)."""
        return self.runner.worker

    def wait(self, timeout: float = 30.0) -> None:
        """Wait for the background run (tests)."""
        self.runner.wait(timeout)

    # --- refresh ------------------------------------------------------------------------------------
    def poll(self) -> None:
        """Redraw when the session changed behind this tab's back (REST, another tab)."""
        session = self.session
        if session is None or self.closed:
            return
        if session.id not in self.store:
            if self._seen != (-1, -1):
                self._seen = (-1, -1)
                gone = self.store.why_gone(session.id)
                self.show_error(UnknownName("session", f"{gone}; press New session"))
            return
        if self.runner.busy() or session.running is not None:
            return
        if (session.version, len(session.history)) != self._seen:
            self.refresh()

    def refresh(self, *, force: bool = False) -> None:
        """Bring every status, widget, metric and drawing up to date with the session (while a plan runs,
        what it dropped and will write again stays drawn: :func:`held_during_plan`)."""
        with self.lock:
            session = self.session
            if session is None or self.closed:
                return
            seen = (session.version, len(session.history))
            if not force and seen == self._seen:
                return
            self._seen = seen
            self._marked = None
            # Copies: a step running in another thread (REST) may change these meanwhile; dict()
            # and list() copy in one go under the GIL, iterating the originals would not.
            state, metrics, history = dict(session.state), dict(session.metrics), list(session.history)
            self._note_runs(history)
            self._sync_widgets(session)
            self.refresh_status()
            self._show_metrics(session, metrics, history)
            self._show_session(session, state, history)
            if session.running is None:
                self.progress.idle(history)
            drawn = {**held_during_plan(session, self._drawn, state, self.runner.planned), **state}
            self._drawn = drawn
            self.drawer.sync(drawn, order=self._order(drawn))
            self._update_interactions(state)
            if self.drawer.errors:
                problems = "; ".join(f"{k}: {v}" for k, v in self.drawer.errors.items())
                self.show_error(LabError("drawing", problems))
            self.tab.media_panel.visible = any(not r.in_scene for r in map(renderer_for, state.values())
                                               if r is not None)
            self.camera.frame(state, self.interactions)
            self.scene_panel.show(drawn, _producers(session, drawn), self.interactions)

    def _note_runs(self, history: Sequence[RunRecord]) -> None:
        """Read the history records added since the last look: a step whose run failed is labelled failed
        (:meth:`refresh_status`) until a run of it ends otherwise or it is reset."""
        for record in history[self._history_read:]:
            if record.status == "failed":
                self._failed.add(record.step)
            else:
                self._failed.discard(record.step)
        self._history_read = len(history)

    def _pixel_clicked(self, image_name: str, view: int, pixel: np.ndarray) -> bool:
        """A click on a frustum's picture: the first interaction that takes the pixel gets it."""
        for interaction in list(self.interactions):
            try:
                if interaction.pixel_clicked(image_name, view, pixel):
                    return True
            except Exception as exc:  # an interaction's bug must not take the click handler down
                self.show_error(exc)
                return True
        return False

    def fit_view(self) -> None:
        """The "Fit view" button: the camera pointed at everything drawn in 3D."""
        with self.lock:
            if self.session is not None:
                self.camera.fit(dict(self.session.state), self.interactions)

    def _show_metrics(self, session: Session, metrics: Mapping[str, Mapping[str, Any]],
                      history: list[RunRecord]) -> None:
        last = {r.step: r for r in history}
        for spec in session.pipeline.steps:
            row = self.rows.get(spec.name)
            if row is None:
                continue
            record = last.get(spec.name)
            parts = []
            if spec.name in metrics:
                ran = next((r for r in reversed(history) if r.step == spec.name and r.status == "ok"), None)
                if ran is not None:
                    parts.append(f"Ran in {ran.seconds:.3f} s.")
                warnings = ran.warnings if ran is not None else ()
                parts.append(metrics_markdown(spec, metrics[spec.name], warnings))
            if record is not None and record.status != "ok":
                parts.append(f"Last run {record.status}: {record.error}")
            row.metrics.content = "\n\n".join(p for p in parts if p)

    def _show_session(self, session: Session, state: Mapping[str, Any], history: list[RunRecord]) -> None:
        title = session.pipeline.title or session.pipeline.name
        self.tab.header.content = (f"**Vision Lab · {title}**  \nsession `{session.id}` · dataset "
                                   f"`{session.dataset}`" + (" · has ground truth" if session.truth else ""))
        self.tab.history_md.content = history_markdown(history)
        self.tab.values_md.content = "  \n".join(value_summary(n, v) for n, v in sorted(state.items()))

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

    def _preview(self, values: Mapping[str, Any]) -> None:
        """Draw a long step's preview values (a progress snapshot's) over the session's state, and over what
        the plan dropped and will write again (:func:`held_during_plan`, as :meth:`refresh` draws it: a value
        that vanished for a preview would be removed and drawn anew at the next refresh)."""
        session = self.session
        if session is not None:
            state = dict(session.state)
            held = held_during_plan(session, self._drawn, state, self.runner.planned)
            preview = {**held, **state, **values}
            self.drawer.sync(preview, order=self._order(preview))

    def framing(self, state: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
        """``(eye, look_at)`` for the tab's camera (:func:`lab.viewer.camera.framing` with the
        interactions)."""
        return framing(state, self.interactions)

    def _view_selected(self, image_name: str, view: int) -> None:
        with self.lock:
            self.drawer.show_view(image_name, view)

    # --- errors -------------------------------------------------------------------------------------
    def show_error(self, exc: BaseException) -> None:
        """Show ``exc`` in the error box (and as a notification in a browser tab)."""
        text = error_text(exc)
        self.errors.append(text)
        with contextlib.suppress(Exception):  # the tab is gone
            self.tab.error_box.content = f"**Error** — {text}"
            self.tab.error_box.visible = True
            if self.is_client and hasattr(self.target, "add_notification"):
                self.target.add_notification("Error", text, color="red", auto_close_seconds=8.0)

    def clear_error(self) -> None:
        """Hide the error box (a new action starts)."""
        self.tab.error_box.visible = False
        self.tab.error_box.content = ""


__all__ = ["ClientView", "ParamsSource", "held_during_plan", "status_during_plan"]


def status_during_plan(session: Session, status: Mapping[str, StepStatus], planned: Sequence[str], *,
                       stale: Set[str] = frozenset()) -> dict[str, str]:
    """The steps' labels while the steps ``planned`` are still to finish (:attr:`Runner.planned`).

    Steps share output names (SfM's ``cameras``, ``points3d``, ``observations`` are written by four
    steps, each stage's own), so while a plan runs a done step outside it can miss a value a step of the
    plan has dropped and will write again: ``filter_points`` drops bundle adjustment's outputs, its
    ``cameras`` with them, and until ``bundle_adjust_all`` has run ``reconstruct_incrementally`` read
    "ready" (issue 16: SfM's labels flickered between done and ready while a later step ran). A step that
    ran (``Session.ran_with``), is not in ``planned`` and misses only names ``planned`` will write keeps
    the label it had: done, or stale when it is in ``stale`` (``Session.stale`` of the controls shown).
    """
    labels: dict[str, str] = dict(status)
    if not planned:
        return labels
    pipeline, state = session.pipeline, dict(session.state)
    coming = {name for step in planned for name in pipeline.step(step).writes}
    for spec in pipeline.steps:
        if status[spec.name] not in ("ready", "blocked") or spec.name in planned or \
                spec.name not in session.ran_with:
            continue
        if all(name in state or name in coming for name in spec.writes):
            labels[spec.name] = "stale" if spec.name in stale else "done"
    return labels


def held_during_plan(session: Session, drawn: Mapping[str, Any], state: Mapping[str, Any],
                     planned: Sequence[str]) -> dict[str, Any]:
    """The values drawn before (``drawn``) that the steps ``planned`` dropped and will write again: they
    stay on screen until those steps write them (SfM's cameras would vanish while bundle adjustment runs,
    :func:`status_during_plan`); none once the plan ended."""
    if not planned:
        return {}
    coming = {name for step in planned for name in session.pipeline.step(step).writes}
    return {name: value for name, value in drawn.items() if name in coming and name not in state}


def _producers(session: Session, state: Mapping[str, Any]) -> dict[str, str]:
    """The step whose run wrote each state value (the legend names it), "dataset" for the dataset's: of the
    steps that write the name, the last that ran (``Session.ran_with``: a later stage rewrites an earlier
    one's SfM ``cameras``, and a re-run upstream drops the later runs), else the first that writes it."""
    found = {}
    for name in state:
        writers = [spec.name for spec in session.pipeline.steps if name in spec.writes]
        ran = [step for step in writers if step in session.ran_with]
        found[name] = ran[-1] if ran else writers[0] if writers else "dataset"
    return found
