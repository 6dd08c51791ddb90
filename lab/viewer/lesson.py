"""The viewer's lesson mode: a lesson's text beside its pipeline, and the student's code in it.

A :class:`LessonMode` belongs to one tab (:class:`~lab.viewer.view.ClientView`), which it reaches only
through a :class:`LessonContext` (what the tab lends it: its GUI, lock and worker, its session and
step folders; this module imports nothing of the tab's). It adds:

- a **Lesson** folder to the controls: a picker of the catalog's lessons (choosing one opens a
  session on the lesson's module, default dataset), an upload button for the student's ``.py``,
  a button that loads the lesson's own ``starter.py``, and what the loaded file defines;
- the lesson's text (Markdown) in a panel of its own beside the pipeline, docked on the left
  above the images (the panel is there while a lesson is open);
- in the folder of every task step: a **use my code** toggle (Run and Run to here then call the
  student's function, in the sandbox, in place of the reference's), **Compare with reference**
  (both run on the same inputs, the session untouched: :meth:`lab.lessons.live.StudentCode.compare`),
  and the outcome: pass or fail, the comparison's message, both outputs (arrays as a table with
  their difference; drawable values drawn by their renderers in a **Compare** tab of the lesson's
  panel, the student's under ``yours/`` and the reference's under ``reference/``) and what the
  student's code printed.

The page may ask for a lesson with ``?lesson=ID`` (read with the viewer's other query keys); the
viewer keeps ``lesson=ID`` in the address bar while a lesson is open, so a reload comes back to it.

The student's file runs in :class:`~lab.lessons.live.StudentCode`'s sandbox: loading it and every
comparison run in the tab's worker thread (``LessonContext.in_background``), never on viser's
threads. Whatever goes wrong (a file that cannot be loaded, a function that raises, times out or
is refused by the sandbox) is shown in the GUI; the sandbox is closed when the tab closes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lab.core.errors import InvalidValue, LabError, UnknownName
from lab.core.pipeline import Pipeline, Session
from lab.lessons.format import Lesson, LessonCatalog, Task
from lab.lessons.live import SideBySide, StudentCode, StudentCodeFailed
from lab.viewer.gui import MEDIA_PANEL_WIDTH
from lab.viewer.renderers import OVERLAY_TYPES, Canvas, StateDrawer, renderer_for
from lab.viewer.text import cell, error_text, format_number, step_label, value_summary

log = logging.getLogger("lab.viewer.lesson")

#: The picker's entry for "no lesson".
NO_LESSON = "(none)"
#: Name prefixes of the two sides of a comparison, in the Compare tab and the scene.
YOURS, REFERENCE = "yours", "reference"
#: Most rows of an array comparison table, and most characters of printed output shown.
TABLE_ROWS = 12
PRINTED_CHARS = 4000
NO_CODE = "no code of yours is loaded: press \"Upload my .py\" or \"Load starter.py\" in the Lesson folder"


# --- what is shown (pure: no viser) -------------------------------------------------------------
def lesson_summary(lesson: Lesson) -> str:
    """The lesson's title, module and tasks (which step each one replaces), as Markdown."""
    lines = [f"**{lesson.title}** · module: {cell(lesson.module_title)} · "
             f"{format_number(lesson.points)} points", ""]
    for task in lesson.tasks:
        lines.append(f"- {task.title} ({format_number(task.points)} points): step `{task.step}`")
    return "\n".join(lines)


#: What a task step reads when the student's code failed in it (and its outputs are not there).
FAILED = "failed"
#: What the label of a task step whose student code failed adds after :data:`FAILED`.
FAILED_NOTE = "your code failed"


def failure_banner(task: Task, reason: str) -> str:
    """The lesson panel's notice that the student's function failed (shown above the lesson text)."""
    return (f"⚠ **Your code failed** in step `{task.step}` ({cell(task.title)}):\n\n{code_block(reason)}"
            "\n\nUnfold the step for what your code printed; fix the file and load it again.")


def code_status(lesson: Lesson, name: str, problems: Mapping[str, str]) -> str:
    """Which task functions the loaded file defines (``problems``: :meth:`StudentCode.tasks`)."""
    lines = [f"Loaded **`{name}`**:", "", "| task | your file |", "|---|---|"]
    for task in lesson.tasks:
        problem = problems.get(task.step, "")
        verdict = f"✓ defines `{task.step}`" if not problem else f"✗ {cell(problem)}"
        lines.append(f"| {cell(task.title)} | {verdict} |")
    return "\n".join(lines)


def code_block(text: str) -> str:
    """``text`` as a fenced code block (fences inside it are defused)."""
    return "```\n" + text.replace("```", "'''").rstrip() + "\n```"


def printed_markdown(printed: str) -> str:
    if not printed.strip():
        return "*Your code printed nothing.*"
    if len(printed) > PRINTED_CHARS:
        printed = printed[:PRINTED_CHARS] + f"\n... ({len(printed) - PRINTED_CHARS} more characters)"
    return "**Your code printed:**\n\n" + code_block(printed)


def _index_label(index: tuple[int, ...]) -> str:
    return "[" + ", ".join(str(i) for i in index) + "]" if index else "value"


def array_comparison(name: str, yours: Any, reference: Any, *, rows: int = TABLE_ROWS) -> str:
    """Two numeric arrays as Markdown: shapes, the largest difference, and a table of entries.

    The table has the columns entry, yours, reference and yours − reference; it lists every entry
    of small arrays (at most ``rows``), else the item (along the first axis) that differs most
    when it is small enough (one homography of a stack), else the ``rows`` entries that differ most.
    """
    mine, theirs = np.asarray(yours), np.asarray(reference)
    head = (f"**`{name}`** · yours: array {tuple(mine.shape)} {mine.dtype} · reference: array "
            f"{tuple(theirs.shape)} {theirs.dtype}")
    if mine.shape != theirs.shape:
        return head + "\n\nThe shapes differ: your array must have the reference's shape."
    if mine.dtype.kind not in "biuf" or theirs.dtype.kind not in "biuf":
        return head
    if mine.size == 0:
        return head + "\n\nBoth are empty."
    mine64, theirs64 = mine.astype(np.float64), theirs.astype(np.float64)
    difference = mine64 - theirs64
    size = np.where(np.isnan(difference), np.inf, np.abs(difference))  # NaN: as far off as it gets
    worst = tuple(int(i) for i in np.unravel_index(int(np.argmax(size)), size.shape))
    lines = [head, "", f"largest \\|yours − reference\\| = {format_number(float(np.abs(difference[worst])))} "
                       f"at {_index_label(worst)}"]
    if mine.size <= rows:
        entries = list(np.ndindex(mine.shape))
    elif mine.ndim >= 2 and int(np.prod(mine.shape[1:])) <= rows:
        entries = [(worst[0], *rest) for rest in np.ndindex(mine.shape[1:])]
        lines.append(f"\nItem {worst[0]} of {mine.shape[0]}, the one that differs most:")
    else:
        flat = np.argsort(-size, axis=None, kind="stable")[:rows]
        entries = sorted(tuple(int(i) for i in np.unravel_index(int(k), size.shape)) for k in flat)
        lines.append(f"\nThe {rows} entries that differ most:")
    lines += ["", "| entry | yours | reference | yours − reference |", "|---|---|---|---|"]
    for index in entries:
        lines.append(f"| {_index_label(index)} | {format_number(float(mine64[index]))} | "
                     f"{format_number(float(theirs64[index]))} | {format_number(float(difference[index]))} |")
    return "\n".join(lines)


def _is_array(value: Any) -> bool:
    return isinstance(value, (np.ndarray, np.generic, int, float)) and not isinstance(value, bool)


def _drawn(value: Any) -> bool:
    return renderer_for(value) is not None or isinstance(value, OVERLAY_TYPES)


def comparison_markdown(side: SideBySide) -> str:
    """The outcome of a comparison: the verdict and its message, both outputs, what the student printed."""
    if side.passed is True:
        verdict = "✓ **Your output matches the reference's.**"
    elif side.passed is False:
        verdict = "✗ **Your output differs from the reference's.**"
    else:
        verdict = "⚠ **Your step failed**, so there is nothing to compare."
    parts = [verdict]
    if side.message:
        parts.append(code_block(side.message) if "\n" in side.message else cell(side.message))
    for name, reference in side.reference.items():
        if name not in side.student:
            continue
        yours = side.student[name]
        if _is_array(yours) and _is_array(reference):
            parts.append(array_comparison(name, yours, reference))
        elif _drawn(yours) or _drawn(reference):
            parts.append(f"**`{name}`**: drawn in the **Compare** tab as `{YOURS}/{name}` and "
                         f"`{REFERENCE}/{name}`.")
        else:
            parts.append(f"{value_summary(f'{YOURS}/{name}', yours)}  "
                         f"\n{value_summary(f'{REFERENCE}/{name}', reference)}")
    parts.append(printed_markdown(side.printed))
    return "\n\n".join(parts)


def side_by_side_state(side: SideBySide, state: Mapping[str, Any]) -> dict[str, Any]:
    """The drawable outputs of both sides, named ``yours/NAME`` and ``reference/NAME``.

    2D points and segments are overlays: each side gets its own copy of the image (set) they are
    drawn on (``yours/images`` ...), taken from the side's outputs or else from ``state``.
    """
    drawn: dict[str, Any] = {}
    for prefix, values in ((YOURS, side.student), (REFERENCE, side.reference)):
        for name, value in values.items():
            if isinstance(value, OVERLAY_TYPES):
                base = values.get(value.image, state.get(value.image))
                if base is None or renderer_for(base) is None:
                    continue  # nothing to draw it on
                drawn[f"{prefix}/{value.image}"] = base
                drawn[f"{prefix}/{name}"] = dataclasses.replace(value, image=f"{prefix}/{value.image}")
            elif renderer_for(value) is not None:
                drawn[f"{prefix}/{name}"] = value
    return drawn


def upload_text(name: str, content: bytes) -> str:
    """The uploaded file as Python source, checked as the REST API checks a submission
    (``lab.lessons.submission.check_upload``: a ``.py`` name, at most the default submission size, UTF-8
    text without NUL bytes, parsable)."""
    from lab.lessons.submission import check_upload
    from lab.lessons.service import DEFAULT_MAX_SUBMISSION_BYTES

    if not name:
        raise InvalidValue("file", "no file was uploaded")
    return check_upload(content, name, limit=DEFAULT_MAX_SUBMISSION_BYTES)


# --- what the tab lends the lesson mode ---------------------------------------------------------------
@dataclass(frozen=True)
class LessonContext:
    """What a :class:`LessonMode` may use of the tab it lives in (the tab makes it; nothing else is reached).

    ``gui`` and ``scene`` are the tab's viser GUI and scene, ``media_panel`` its panel of images (the
    lesson's text is docked above it), ``lock`` the tab's lock. ``session()`` is the session shown (None
    before one opens); ``open_session(pipeline)`` shows a new session on a pipeline's default dataset;
    ``step_folder(step)`` is the GUI folder of a step of the session shown (None when it has no such
    step) and ``step_params(step)`` the controls its widgets show. ``guard(action)`` runs a GUI callback
    showing what it raises; ``in_background(job, name)`` runs a job in the tab's worker thread;
    ``show_error`` / ``clear_error`` use the tab's error box; ``set_query(**params)`` writes the tab's
    address bar (``lesson=ID``; a no-op off a browser).
    """

    gui: Any
    scene: Any
    media_panel: Any
    lock: threading.RLock
    session: Callable[[], Session | None]
    open_session: Callable[[Pipeline], None]
    step_folder: Callable[[str], Any]
    step_params: Callable[[str], dict[str, Any]]
    guard: Callable[[Callable[[], Any]], None]
    in_background: Callable[[Callable[[], Any], str], None]
    show_error: Callable[[BaseException], None]
    clear_error: Callable[[], None]
    set_query: Callable[..., None]

    def require_session(self) -> Session:
        """The session shown; :class:`LabError` when there is none."""
        session = self.session()
        if session is None:
            raise LabError("session", "no session is open: press New session")
        return session


# --- the GUI of one tab --------------------------------------------------------------------------
@dataclass
class TaskRow:
    """The lesson widgets in the folder of one task step."""

    task: Task
    folder: Any  # the step's folder, which holds them
    use_mine: Any
    compare: Any
    result: Any
    handles: list[Any] = field(default_factory=list)


class LessonMode:
    """Lesson mode of one tab, reached through ``ctx`` (see the module docstring)."""

    def __init__(self, ctx: LessonContext, catalog: LessonCatalog) -> None:
        self.ctx = ctx
        self.catalog = catalog
        self.lesson: Lesson | None = None
        self.code: StudentCode | None = None
        self.code_name = ""
        self.rows: dict[str, TaskRow] = {}
        #: "use my code" of each task step, kept across sessions of the same lesson.
        self.use_mine: dict[str, bool] = {}
        #: The last comparison of each task step (what the GUI shows).
        self.compared: dict[str, SideBySide] = {}
        #: Task steps whose student code failed on its last run, and why (cleared by a run that works).
        self.failed: dict[str, str] = {}
        self.closed = False
        self._syncing = False  # the picker is being set by the code, not by the user
        #: The lesson's panel (its text, and the Compare tab): there while a lesson is open.
        self.panel: Any = None
        self.text: Any = None
        self.banner: Any = None
        self._compare_tab: Any = None
        self._compare_drawer: StateDrawer | None = None
        self._build()

    # --- static GUI ------------------------------------------------------------------------------
    def _build(self) -> None:
        gui = self.ctx.gui
        self.folder = gui.add_folder("Lesson", order=2.5)
        with self.folder:
            self.picker = gui.add_dropdown("lesson", [NO_LESSON, *self._ids()], initial_value=NO_LESSON,
                                           hint="a lesson: its text opens beside the pipeline, in a new "
                                                "session")
            self.summary = gui.add_markdown("Pick a lesson above.")
            self.upload_button = gui.add_upload_button(
                "Upload my .py", mime_type=".py,text/x-python", disabled=True,
                hint="your filled-in starter.py: its functions can replace the lesson's steps")
            self.starter_button = gui.add_button("Load starter.py", disabled=True,
                                                 hint="load the lesson's starter file (every task "
                                                      "unimplemented)")
            self.code_md = gui.add_markdown("")
        guard = self.ctx.guard
        self.picker.on_update(lambda _: None if self._syncing else guard(self._picked))
        self.upload_button.on_upload(lambda event: guard(lambda: self.load_upload(event.target.value)))
        self.starter_button.on_click(lambda _: guard(self.load_starter))

    def _ids(self) -> list[str]:
        try:
            return self.catalog.ids()
        except OSError as exc:  # an unreadable lessons folder: no lessons, but the viewer works
            log.error("cannot list the lessons: %s", exc)
            return []

    def _set_picker(self, value: str) -> None:
        self._syncing = True
        try:
            if value not in self.picker.options:
                self.picker.options = [*self.picker.options, value]
            self.picker.value = value
        finally:
            self._syncing = False

    def _picked(self) -> None:
        if self.picker.value == NO_LESSON:
            self.leave()
            return
        try:
            self.select(self.picker.value)
        except LabError:  # a lesson that does not load: the picker goes back to what is shown
            self._set_picker(self.lesson.id if self.lesson is not None else NO_LESSON)
            raise
        self.new_session()

    # --- choosing a lesson -----------------------------------------------------------------------
    def select(self, name: str) -> Lesson:
        """Show lesson ``name`` (an id or a short name): its text, tasks and picker entry.

        The open session keeps running; the task widgets appear when it is one of the lesson's
        module (see :meth:`new_session`). Raises UnknownName / LessonFormatError.
        """
        lesson = self.catalog.get(name)
        with self.ctx.lock:
            if self.lesson is None or self.lesson.id != lesson.id:
                self._drop_code()
                self.use_mine.clear()
            self.lesson = lesson
            self._set_picker(lesson.id)
            self._show_panel(lesson)
            self.summary.content = lesson_summary(lesson)
            self.upload_button.disabled = self.starter_button.disabled = False
            self.attach()
        self.ctx.set_query(lesson=lesson.id)
        return lesson

    def new_session(self) -> None:
        """Open a fresh session on the lesson's module (its default dataset)."""
        lesson = self._require_lesson()
        self.ctx.open_session(lesson.pipeline)

    def leave(self) -> None:
        """No lesson: close the student's code, take the lesson's widgets away (the session stays)."""
        with self.ctx.lock:
            self._drop_code()
            self._remove_rows()
            self._clear_compare()
            self._hide_panel()
            self.lesson = None
            self._set_picker(NO_LESSON)
            self.summary.content = "Pick a lesson above."
            self.upload_button.disabled = self.starter_button.disabled = True
        self.ctx.set_query(lesson=None)

    def _show_panel(self, lesson: Lesson) -> None:
        """The lesson's text in its panel, docked on the left with the images below it."""
        if self.panel is None:
            gui = self.ctx.gui
            self.panel = gui.add_panel()
            with self.panel.add_tab("Lesson"):
                self.banner = gui.add_markdown("", visible=False)
                self.text = gui.add_markdown("")
            try:  # one column: the text above, the images below
                media = self.ctx.media_panel
                if media.visible:  # docked on the left: split its column (keeps its width)
                    self.panel.dock_above(media)
                else:  # a hidden panel is no anchor: dock the text, put the images under it
                    self.panel.dock_left()
                    media.dock_below(self.panel)
                self.panel.set_width(MEDIA_PANEL_WIDTH)
            except Exception as exc:  # placement is cosmetic
                log.info("could not dock the lesson panel: %s", exc)
        self.text.content = lesson.text

    def _hide_panel(self) -> None:
        if self.panel is None:
            return
        self._compare_drawer, self._compare_tab = None, None  # went with the panel
        self.panel.remove()
        self.panel = self.text = self.banner = None
        try:
            self.ctx.media_panel.dock_left()
            self.ctx.media_panel.set_width(MEDIA_PANEL_WIDTH)
        except Exception as exc:  # placement is cosmetic
            log.info("could not dock the image panel: %s", exc)

    def attach(self) -> None:
        """Add the task widgets to the open session's step folders (after the view rebuilt them)."""
        with self.ctx.lock:
            self._clear_failures()
            self._remove_rows()
            self._clear_compare()
            lesson, session = self.lesson, self.ctx.session()
            if lesson is None or session is None:
                return
            if session.pipeline.name != lesson.pipeline.name:
                self.code_md.content = (f"This session runs module `{session.pipeline.name}`; the lesson is "
                                        f"about `{lesson.pipeline.name}`. Pick the lesson again to open a "
                                        "session on it.")
                return
            gui = self.ctx.gui
            for task in lesson.tasks:
                folder = self.ctx.step_folder(task.step)
                if folder is None:
                    continue
                with folder:
                    note = gui.add_markdown(f"**Your task: {task.title}** ({format_number(task.points)} "
                                            f"points)  \n`def {task.signature}`")
                    use_mine = gui.add_checkbox("use my code", self.use_mine.get(task.step, False),
                                                hint="Run calls your function (in a sandbox) in place of the "
                                                     "reference's")
                    compare = gui.add_button("Compare with reference",
                                             hint="run the reference's step and yours on the same inputs and "
                                                  "show both outputs (the session is left as it is)")
                    result = gui.add_markdown("")
                use_mine.on_update(lambda event, step=task.step:
                                   self.use_mine.__setitem__(step, event.target.value))
                compare.on_click(lambda _, step=task.step: self.ctx.guard(lambda: self.compare(step)))
                self.rows[task.step] = TaskRow(task, folder, use_mine, compare, result,
                                               [note, use_mine, compare, result])
            self._show_code()

    def _remove_rows(self) -> None:
        for step, row in self.rows.items():
            if self.ctx.step_folder(step) is not row.folder:
                continue  # the tab rebuilt its step folders: these went with the old ones
            for handle in row.handles:
                with contextlib.suppress(Exception):  # gone with its step folder already
                    handle.remove()
        self.rows = {}

    # --- the student's code ----------------------------------------------------------------------
    def load_upload(self, uploaded: Any) -> None:
        """The upload button's file (viser's ``UploadedFile``: ``name``, ``content``)."""
        self._require_lesson()
        try:
            source = upload_text(uploaded.name, uploaded.content)
        except LabError as exc:
            self._show_load_failure(uploaded.name, exc.reason)
            raise
        self.load_source(uploaded.name, source)

    def load_starter(self) -> None:
        lesson = self._require_lesson()
        self.load_source("starter.py", lesson.starter)

    def load_source(self, name: str, source: str) -> None:
        """Start ``source`` in a sandbox (in the tab's worker) and use it for the lesson's tasks."""
        lesson = self._require_lesson()
        self.ctx.clear_error()
        self.code_md.content = f"Loading `{name}` ..."

        def job() -> None:
            try:
                code = StudentCode(lesson, source)
            except StudentCodeFailed as exc:
                self._show_load_failure(name, exc.reason)
                raise
            with self.ctx.lock:
                if self.closed or self.lesson is not lesson:  # the tab closed or the lesson changed meanwhile
                    code.close()
                    return
                old, self.code, self.code_name = self.code, code, name
                problems = code.tasks()
                for step, problem in problems.items():
                    self.use_mine[step] = not problem
                    row = self.rows.get(step)
                    if row is not None:
                        row.use_mine.value = not problem
                        row.result.content = ""
                self._show_code()
            if old is not None:
                old.close()

        self.ctx.in_background(job, "load-code")

    def _show_code(self) -> None:
        lesson, code = self.lesson, self.code
        if lesson is None:
            self.code_md.content = ""
        elif code is None:
            self.code_md.content = "No code of yours is loaded yet."
        else:
            self.code_md.content = code_status(lesson, self.code_name, code.tasks())

    def _show_load_failure(self, name: str, reason: str) -> None:
        still = f"\n\nStill using `{self.code_name}`." if self.code is not None else ""
        self.code_md.content = f"**Could not load `{cell(name)}`:**\n\n{code_block(reason)}{still}"

    def _drop_code(self) -> None:
        code, self.code, self.code_name = self.code, None, ""
        if code is not None:
            code.close()
        for step in self.use_mine:
            self.use_mine[step] = False
        for row in self.rows.values():
            row.use_mine.value = False
        self._show_code()

    def override(self, step: str) -> Callable[..., Any] | None:
        """The student's function for ``step`` when its "use my code" is on, else None (the reference).

        Called by the view when it runs a step (in its worker). What the student's code printed,
        or why it failed, is shown under the step.
        """
        row = self.rows.get(step)
        if row is None or not row.use_mine.value:
            return None
        code = self.code
        if code is None:
            raise StudentCodeFailed(step, NO_CODE)
        student = code.override(step)

        def run_mine(*args: Any, **kwargs: Any) -> Any:
            try:
                value = student(*args, **kwargs)
            except StudentCodeFailed as exc:
                row.result.content = (f"⚠ **Your code failed:**\n\n{code_block(exc.reason)}\n\n"
                                      f"{printed_markdown(code.printed)}")
                self._failed(row.task, exc.reason)
                raise
            row.result.content = f"Ran **your** `{step}`.\n\n{printed_markdown(code.printed)}"
            self._worked(step)
            return value

        run_mine.__name__ = step
        return run_mine

    def status_of(self, step: str, status: str) -> str:
        """``status`` of ``step`` as the lesson sees it: :data:`FAILED` for a task step whose student code
        failed on its last run and whose outputs are not there (for a view that labels its steps)."""
        return FAILED if step in self.failed and status not in ("done", "stale", "running") else status

    def failure_note(self, step: str) -> str:
        """What a failed label of ``step`` adds: "your code failed" for a task step whose student code failed
        on its last run, else nothing."""
        return FAILED_NOTE if step in self.failed else ""

    def _failed(self, task: Task, reason: str) -> None:
        """The student's code failed in ``task``'s step: say so where it is seen with the step folded."""
        with self.ctx.lock:
            self.failed[task.step] = reason
            if self.banner is not None:
                self.banner.content = failure_banner(task, reason)
                self.banner.visible = True
        self._relabel_after_run(task.step)

    def _worked(self, step: str) -> None:
        with self.ctx.lock:
            self.failed.pop(step, None)
            if self.banner is not None and not self.failed:
                self.banner.visible = False

    def _relabel_after_run(self, step: str) -> None:
        """Label the failed step once the tab's worker has ended (its last act is a refresh that labels
        every step by the session's status, which knows nothing of the lesson: ``ready``)."""
        worker = threading.current_thread()
        if worker is threading.main_thread() or not worker.name.startswith("lab-viewer-"):
            self._show_failed_label(step)  # run inline (tests): no worker to wait for
            return

        def relabel() -> None:
            worker.join(timeout=120)
            self._show_failed_label(step)

        threading.Thread(target=relabel, name=f"lab-lesson-relabel-{step}", daemon=True).start()

    def _show_failed_label(self, step: str) -> None:
        with self.ctx.lock:
            session = self.ctx.session()
            folder = self.ctx.step_folder(step)
            if self.closed or session is None or folder is None or step not in self.failed:
                return
            if self.status_of(step, session.step_status().get(step, "ready")) != FAILED:
                return
            names = [spec.name for spec in session.pipeline.steps]
            folder.label = step_label(names.index(step), session.pipeline.step(step), FAILED,
                                      why=self.failure_note(step))

    # --- comparing -------------------------------------------------------------------------------
    def compare(self, step: str) -> None:
        """Run ``step`` by the reference and by the student on the session's inputs (in the tab's
        worker) and show both outputs; the session is left as it is."""
        self._require_lesson()
        session = self.ctx.require_session()
        row = self.rows.get(step)
        if row is None:
            raise UnknownName("step", f"step {step!r} is not a task of this lesson in this session")
        code = self.code
        if code is None:
            raise StudentCodeFailed(step, NO_CODE)
        params = self.ctx.step_params(step)
        self.ctx.clear_error()
        row.result.content = "Comparing ..."

        def job() -> None:
            try:
                side = code.compare(session, step, params)
            except LabError as exc:
                row.result.content = f"**Could not compare:** {cell(error_text(exc))}"
                raise
            with self.ctx.lock:
                if self.closed:
                    return
                self.compared[step] = side
                row.result.content = comparison_markdown(side)
                self._draw_compared(session.state)
            if side.passed is None:
                self.ctx.show_error(StudentCodeFailed(step, side.message))

        self.ctx.in_background(job, f"compare-{step}")

    def _draw_compared(self, state: Mapping[str, Any]) -> None:
        """Draw the drawable outputs of every comparison in the Compare tab (and the scene)."""
        drawn: dict[str, Any] = {}
        for side in self.compared.values():
            drawn.update(side_by_side_state(side, state))
        if not drawn and self._compare_drawer is None:
            return
        if self.panel is None:
            return
        if self._compare_drawer is None:
            self._compare_tab = self.panel.add_tab("Compare")
            with self._compare_tab:
                self.ctx.gui.add_markdown(f"Your outputs (`{YOURS}/...`) and the reference's "
                                          f"(`{REFERENCE}/...`) on the same inputs, from **Compare with "
                                          "reference**.", order=-1.0)
            self._compare_drawer = StateDrawer(Canvas(scene=self.ctx.scene, gui=self.ctx.gui,
                                                      images=self._compare_tab, plots=self._compare_tab))
        names = sorted({name.split("/", 1)[1] for name in drawn})
        order = {f"{prefix}/{name}": 2.0 * i + j for i, name in enumerate(names)
                 for j, prefix in enumerate((YOURS, REFERENCE))}
        self._compare_drawer.sync(drawn, order=order)
        if self._compare_drawer.errors:
            problems = "; ".join(f"{k}: {v}" for k, v in self._compare_drawer.errors.items())
            self.ctx.show_error(LabError("drawing", problems))

    def _clear_failures(self) -> None:
        self.failed.clear()
        if self.banner is not None:
            self.banner.visible = False

    def _clear_compare(self) -> None:
        self.compared.clear()
        if self._compare_drawer is not None:
            self._compare_drawer.clear()

    # --- lifetime --------------------------------------------------------------------------------
    def _require_lesson(self) -> Lesson:
        if self.lesson is None:
            raise UnknownName("lesson", "no lesson is open: pick one in the Lesson folder")
        return self.lesson

    def close(self) -> None:
        """The tab closed: end the student's sandbox (a load still running closes its own)."""
        with self.ctx.lock:
            self.closed = True
            code, self.code = self.code, None
        if code is not None:
            code.close()


__all__ = ["FAILED", "NO_LESSON", "LessonMode", "TaskRow", "array_comparison", "code_status",
           "comparison_markdown", "failure_banner", "lesson_summary", "side_by_side_state",
           "upload_text"]
