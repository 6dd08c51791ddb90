"""The lesson format: one folder per lesson, ``lessons/NN-name/``, with three files.

``lesson.md``
    The text a student reads (shown in the viewer beside the pipeline and by the REST API). Its
    first ``# `` heading is the lesson's title unless ``tasks.toml`` names one.
``starter.py``
    The template a student fills in: for every task, the step's signature with a docstring and
    a body that raises ``NotImplementedError``.
``tasks.toml``
    What is graded and how::

        [lesson]
        module = "calibration"        # a module of lab.modules, or "package.module:ATTRIBUTE" (a Pipeline)
        title = "..."                 # optional; default: the first heading of lesson.md
        visibility = "visible"        # default visibility of every test (Gradescope's values)

        [limits]                      # the sandbox's limits; every key optional (see Limits)
        cpu_seconds = 60
        memory_mb = 1024
        call_timeout_s = 20
        total_timeout_s = 120

        [datasets.noisy]              # data the checks run on, by a name the checks use
        dataset = "synthetic"         # one of the module's datasets
        options = { noise_px = 1.0 }  # its options; option ``seed`` is drawn (below)
        seed = "fresh"                # "fresh": a new secret seed at every grading (default);
                                      # an integer: an instructor's seed; "env:NAME": read at grading
        description = "..."           # how the data is described to students in messages
        params = { detect_corners = { window = 5 } }   # controls of the pipeline's steps

        [[tasks]]
        name = "homography"           # a short id
        step = "estimate_homographies"
        title = "..."
        signature = "estimate_homographies(corners: Points2D, board_points: np.ndarray, *, normalize: bool = True) -> np.ndarray"
        points = 10                   # the sum of its checks' points

        [[tasks.checks]]
        name = "noisy data: the same homographies as the reference, up to scale"
        points = 3
        dataset = "noisy"
        stage = "output"              # "output": the step's return value against the reference's on the
                                      # same inputs; "pipeline": the rest of the pipeline is run on it
        params = { normalize = true } # controls of the task's step for this check
        value = "homographies"        # a state value, or a field of a typed one ("cloud.xyz")
        until = "refine_calibration"  # pipeline stage: the last step to run (default: the last one)
        metric = "rms_px"             # pipeline stage: a metric instead of a value
        compare = "equal_up_to_scale" # a comparison of lab.lessons.checks.COMPARISONS ...
        rtol = 1e-6                   # ... and its options
        hints = [{ when = "transposed" }, { when = "same_as_reference_with", params = { normalize = false }, say = "..." }]

``mistakes.py`` (optional)
    Recognisable wrong implementations, written by the lesson's author so that a check can say
    what went wrong when the mistake leaves no trace in the output alone ("you took the argmax").
    Each is a function with the parameters of a task's step; a hint
    ``{ when = "same_as_mistake", mistake = "winner_take_all_argmax", say = "..." }`` runs it on
    the check's inputs and controls (in the grader's process, like the reference: it is trusted
    code) and fires when the student's result matches it. A hint that runs an alternative
    (``same_as_mistake``, ``same_as_reference_with``) compares with the check's comparison (stage
    output) or up to scale (stage pipeline), unless it names its own: ``compare = "allclose"``,
    ``compare_options = { rtol = 1e-6 }``.

Everything is checked when a lesson is loaded (:func:`load_lesson`): names of steps, controls,
datasets, values and comparisons, the signatures against the module's own steps, the points, and
that ``starter.py`` defines every task's function with the same parameters and a body that
raises ``NotImplementedError``. A mistake raises :class:`LessonFormatError` naming the file and
the key.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import os
import re
import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

from lab.core.errors import InvalidValue, LabError, UnknownName
from lab.core.pipeline import Pipeline
from lab.core.step import StepSpec

#: Folder names of lessons: two digits, a dash, a lowercase name.
LESSON_ID = re.compile(r"^\d{2}-[a-z0-9][a-z0-9-]*$")

#: Gradescope's visibilities of a test.
VISIBILITIES = ("visible", "hidden", "after_due_date", "after_published")

STAGES = ("output", "pipeline")


class LessonFormatError(InvalidValue):
    """A lesson folder breaks the format (the field names the file and the key)."""


@dataclass(frozen=True)
class Limits:
    """What a submission may use. The sandbox enforces them; the grader stops at ``total_timeout_s``.

    ``cpu_seconds``: CPU time of the child process over all calls (RLIMIT_CPU). ``memory_mb``:
    address space the submission may add to the interpreter and libraries (RLIMIT_AS).
    ``call_timeout_s``: wall clock per call of a student function. ``total_timeout_s``: wall
    clock of a whole grading run. ``file_size_mb``: largest file the code may write in its
    directory (RLIMIT_FSIZE). ``open_files``: RLIMIT_NOFILE. ``processes``: RLIMIT_NPROC (the
    child runs as an unprivileged user, so this stops fork bombs). ``output_kb``: how much of
    what the code prints is kept. ``result_mb``: the largest return value accepted.
    """

    cpu_seconds: float = 60.0
    memory_mb: float = 1024.0
    call_timeout_s: float = 20.0
    total_timeout_s: float = 120.0
    file_size_mb: float = 4.0
    open_files: int = 64
    processes: int = 1
    output_kb: float = 32.0
    result_mb: float = 64.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise LessonFormatError(f"limits.{f.name}", f"must be a positive number, got {value!r}")

    def replace(self, **changes: Any) -> Limits:
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict[str, float]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class HintRule:
    """A recognisable mistake: detector ``when`` (see lab.lessons.checks.DETECTORS) and what to say."""

    when: str
    say: str = ""
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CheckDataset:
    """Data checks run on: a dataset of the module, its options, how its seed is drawn, step controls."""

    name: str
    dataset: str
    options: dict[str, Any] = field(default_factory=dict)
    seed: int | str = "fresh"
    description: str = ""
    params: dict[str, dict[str, Any]] = field(default_factory=dict)

    def describe(self) -> str:
        return self.description or f"dataset {self.dataset!r}" + (f" with {self.options}" if self.options else "")


@dataclass(frozen=True)
class Check:
    """One graded comparison; becomes one test of results.json."""

    name: str
    points: float
    dataset: str
    compare: str
    stage: str = "output"
    value: str | None = None
    metric: str | None = None
    until: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)
    hints: tuple[HintRule, ...] = ()
    visibility: str = "visible"


@dataclass(frozen=True)
class Task:
    """A step the student implements, with its checks."""

    name: str
    step: str
    title: str
    signature: str
    points: float
    checks: tuple[Check, ...]

    @property
    def function(self) -> str:
        """The name of the function the submission defines."""
        return self.step


@dataclass(frozen=True)
class Lesson:
    """A loaded, validated lesson folder."""

    id: str
    path: Path
    title: str
    module: str
    text: str
    starter: str
    tasks: tuple[Task, ...]
    datasets: dict[str, CheckDataset]
    limits: Limits
    visibility: str = "visible"
    mistakes_source: str = ""

    @cached_property
    def pipeline(self) -> Pipeline:
        return resolve_pipeline(self.module)

    @cached_property
    def mistakes(self) -> dict[str, Any]:
        """The functions of ``mistakes.py`` by name (executed once, on first use)."""
        if not self.mistakes_source:
            return {}
        namespace: dict[str, Any] = {"__name__": f"lab_lesson_mistakes_{self.id.replace('-', '_')}"}
        exec(compile(self.mistakes_source, str(self.path / "mistakes.py"), "exec"), namespace)  # noqa: S102 - the author's file
        return {name: value for name, value in namespace.items()
                if inspect.isfunction(value) and value.__module__ == namespace["__name__"]}  # not the imported ones

    @property
    def points(self) -> float:
        return float(sum(t.points for t in self.tasks))

    def task(self, name: str) -> Task:
        for task in self.tasks:
            if name in (task.name, task.step):
                return task
        raise UnknownName("task", f"lesson {self.id!r} has no task {name!r}; tasks are {[t.name for t in self.tasks]}")

    def summary(self) -> dict[str, Any]:
        """The lesson as listed by ``GET /api/lessons``."""
        return {"id": self.id, "title": self.title, "module": self.module, "points": self.points,
                "tasks": [{"name": t.name, "title": t.title, "step": t.step, "points": t.points} for t in self.tasks]}

    def describe(self) -> dict[str, Any]:
        """Everything a student sees (``GET /api/lessons/{id}``): text, tasks, starter; no seeds, no secrets."""
        tasks = []
        for task in self.tasks:
            checks = [{"name": c.name if c.visibility != "hidden" else "hidden check", "points": c.points,
                       "stage": c.stage, "visibility": c.visibility} for c in task.checks]
            tasks.append({"name": task.name, "title": task.title, "step": task.step, "signature": task.signature,
                          "points": task.points, "checks": checks})
        return {**self.summary(), "text": self.text, "starter": self.starter, "tasks": tasks,
                "limits": {k: v for k, v in self.limits.to_json().items()
                           if k in ("cpu_seconds", "memory_mb", "call_timeout_s", "total_timeout_s")}}


# --- finding lessons ------------------------------------------------------------------------------
def lessons_root() -> Path:
    """Where lessons live: ``$VISION_LAB_LESSONS_DIR``, else the ``lessons/`` folder beside the ``lab`` package."""
    configured = os.environ.get("VISION_LAB_LESSONS_DIR")
    if configured:
        return Path(configured).expanduser().resolve()
    import lab

    beside = Path(lab.__file__).resolve().parent.parent / "lessons"
    return beside if beside.is_dir() else Path.cwd() / "lessons"


class LessonCatalog:
    """The lessons of one folder, loaded (and validated) on first use and cached."""

    def __init__(self, root: Path | str | None = None) -> None:
        self.root = Path(root).resolve() if root is not None else lessons_root()
        self._cache: dict[str, Lesson] = {}

    def ids(self) -> list[str]:
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir()
                      if p.is_dir() and LESSON_ID.match(p.name) and (p / "tasks.toml").is_file())

    def resolve_id(self, name: str) -> str:
        """A lesson id from its id (``01-calibration``) or its name without the number (``calibration``)."""
        ids = self.ids()
        if name in ids:
            return name
        matches = [i for i in ids if i.split("-", 1)[1] == name]
        if len(matches) == 1:
            return matches[0]
        raise UnknownName("lesson", f"no lesson {name!r}; lessons are {ids}")

    def get(self, name: str) -> Lesson:
        lesson_id = self.resolve_id(name)
        if lesson_id not in self._cache:
            self._cache[lesson_id] = load_lesson(self.root / lesson_id)
        return self._cache[lesson_id]

    def all(self) -> list[Lesson]:
        return [self.get(i) for i in self.ids()]


def find_lesson(name: str | os.PathLike[str], catalog: LessonCatalog | None = None) -> Lesson:
    """A lesson by id, by short name, or by the path of its folder (the CLI's LESSON argument)."""
    text = os.fspath(name)
    path = Path(text).expanduser()
    if (path / "tasks.toml").is_file():
        return load_lesson(path)
    if path.is_file() and path.name == "tasks.toml":
        return load_lesson(path.parent)
    return (catalog or LessonCatalog()).get(text)


def resolve_pipeline(module: str) -> Pipeline:
    """``"calibration"`` -> the registered module's pipeline; ``"pkg.mod:ATTR"`` -> that Pipeline object."""
    if ":" in module:
        import_path, _, attribute = module.partition(":")
        try:
            pipeline = getattr(importlib.import_module(import_path), attribute)
        except (ImportError, AttributeError) as exc:
            raise UnknownName("module", f"cannot import pipeline {module!r}: {exc}") from None
        if not isinstance(pipeline, Pipeline):
            raise InvalidValue("module", f"{module!r} is a {type(pipeline).__name__}, not a Pipeline")
        return pipeline
    from lab.modules import get_pipeline

    return get_pipeline(module)


# --- loading ------------------------------------------------------------------------------------
_CHECK_KEYS = {"name", "points", "dataset", "compare", "stage", "value", "metric", "until", "params", "hints",
               "visibility"}


def load_lesson(folder: Path | str, *, validate: bool = True) -> Lesson:
    """Read and check a lesson folder; raises :class:`LessonFormatError` naming the file and key."""
    folder = Path(folder).resolve()
    lesson_id = folder.name
    if not LESSON_ID.match(lesson_id):
        raise LessonFormatError("lesson", f"a lesson folder is named NN-name (e.g. 01-calibration), got {lesson_id!r}")
    files = {}
    for name in ("lesson.md", "tasks.toml", "starter.py"):
        path = folder / name
        if not path.is_file():
            raise LessonFormatError(f"{lesson_id}/{name}", "is missing: a lesson has lesson.md, tasks.toml and starter.py")
        files[name] = path.read_text(encoding="utf-8")
    where = f"{lesson_id}/tasks.toml"
    try:
        data = tomllib.loads(files["tasks.toml"])
    except tomllib.TOMLDecodeError as exc:
        raise LessonFormatError(where, f"is not valid TOML: {exc}") from None
    _only(data, {"lesson", "limits", "datasets", "tasks"}, where)
    head = _table(data.get("lesson", {}), f"{where}: lesson")
    _only(head, {"module", "title", "visibility"}, f"{where}: lesson")
    module = _string(head.get("module"), f"{where}: lesson.module")
    visibility = _visibility(head.get("visibility", "visible"), f"{where}: lesson.visibility")
    title = head.get("title") or _first_heading(files["lesson.md"]) or lesson_id
    limits_table = _table(data.get("limits", {}), f"{where}: limits")
    _only(limits_table, {f.name for f in dataclasses.fields(Limits)}, f"{where}: limits")
    try:
        limits = Limits(**limits_table)
    except LessonFormatError as exc:
        raise LessonFormatError(f"{where}: {exc.field}", exc.reason) from None
    datasets = {name: _dataset(name, table, f"{where}: datasets.{name}")
                for name, table in _table(data.get("datasets", {}), f"{where}: datasets").items()}
    raw_tasks = data.get("tasks", [])
    if not isinstance(raw_tasks, list) or not raw_tasks:
        raise LessonFormatError(f"{where}: tasks", "a lesson needs at least one [[tasks]] table")
    tasks = tuple(_task(t, f"{where}: tasks[{i}]", datasets, visibility) for i, t in enumerate(raw_tasks))
    names = [t.name for t in tasks]
    if len(set(names)) != len(names) or len({t.step for t in tasks}) != len(tasks):
        raise LessonFormatError(f"{where}: tasks", f"task names and steps must be unique, got {names}")
    mistakes = folder / "mistakes.py"
    lesson = Lesson(id=lesson_id, path=folder, title=str(title), module=module, text=files["lesson.md"],
                    starter=files["starter.py"], tasks=tasks, datasets=datasets, limits=limits, visibility=visibility,
                    mistakes_source=mistakes.read_text(encoding="utf-8") if mistakes.is_file() else "")
    if validate:
        validate_lesson(lesson)
    return lesson


def _dataset(name: str, table: Any, where: str) -> CheckDataset:
    table = _table(table, where)
    _only(table, {"dataset", "options", "seed", "description", "params"}, where)
    seed = table.get("seed", "fresh")
    if isinstance(seed, bool) or not (isinstance(seed, int) or seed == "fresh"
                                      or (isinstance(seed, str) and seed.startswith("env:") and len(seed) > 4)):
        raise LessonFormatError(f"{where}.seed", f'must be "fresh", an integer or "env:NAME", got {seed!r}')
    params = _table(table.get("params", {}), f"{where}.params")
    for step, controls in params.items():
        _table(controls, f"{where}.params.{step}")
    return CheckDataset(name=name, dataset=_string(table.get("dataset"), f"{where}.dataset"),
                        options=dict(_table(table.get("options", {}), f"{where}.options")), seed=seed,
                        description=str(table.get("description", "")), params={k: dict(v) for k, v in params.items()})


def _task(table: Any, where: str, datasets: dict[str, CheckDataset], visibility: str) -> Task:
    table = _table(table, where)
    _only(table, {"name", "step", "title", "signature", "points", "checks"}, where)
    step = _string(table.get("step"), f"{where}.step")
    name = str(table.get("name", step))
    raw_checks = table.get("checks", [])
    if not isinstance(raw_checks, list) or not raw_checks:
        raise LessonFormatError(f"{where}.checks", "a task needs at least one [[tasks.checks]] table")
    checks = tuple(_check(c, f"{where}.checks[{i}]", datasets, visibility) for i, c in enumerate(raw_checks))
    points = _number(table.get("points", sum(c.points for c in checks)), f"{where}.points")
    if abs(points - sum(c.points for c in checks)) > 1e-9:
        raise LessonFormatError(f"{where}.points", f"is {points} but its checks add up to {sum(c.points for c in checks)}")
    check_names = [c.name for c in checks]
    if len(set(check_names)) != len(check_names):
        raise LessonFormatError(f"{where}.checks", f"check names must be unique within a task, got {check_names}")
    return Task(name=name, step=step, title=str(table.get("title", step.replace("_", " ").capitalize())),
                signature=_string(table.get("signature"), f"{where}.signature"), points=points, checks=checks)


def _check(table: Any, where: str, datasets: dict[str, CheckDataset], visibility: str) -> Check:
    table = _table(table, where)
    dataset = _string(table.get("dataset"), f"{where}.dataset")
    if dataset not in datasets:
        raise LessonFormatError(f"{where}.dataset", f"no [datasets.{dataset}] table; datasets are {sorted(datasets)}")
    stage = table.get("stage", "output")
    if stage not in STAGES:
        raise LessonFormatError(f"{where}.stage", f"must be one of {list(STAGES)}, got {stage!r}")
    hints = []
    for i, hint in enumerate(table.get("hints", [])):
        hint = _table(hint, f"{where}.hints[{i}]")
        when = _string(hint.get("when"), f"{where}.hints[{i}].when")
        hints.append(HintRule(when=when, say=str(hint.get("say", "")),
                              options={k: v for k, v in hint.items() if k not in ("when", "say")}))
    metric, value = table.get("metric"), table.get("value")
    if metric is not None and value is not None:
        raise LessonFormatError(where, "give either value or metric, not both")
    if metric is not None and stage != "pipeline":
        raise LessonFormatError(f"{where}.metric", 'metrics are checked at stage = "pipeline"')
    return Check(name=_string(table.get("name"), f"{where}.name"), points=_number(table.get("points"), f"{where}.points"),
                 dataset=dataset, compare=_string(table.get("compare"), f"{where}.compare"), stage=stage,
                 value=value, metric=metric, until=table.get("until"),
                 params=dict(_table(table.get("params", {}), f"{where}.params")),
                 options={k: v for k, v in table.items() if k not in _CHECK_KEYS}, hints=tuple(hints),
                 visibility=_visibility(table.get("visibility", visibility), f"{where}.visibility"))


def _table(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise LessonFormatError(where, f"must be a table, got {type(value).__name__}")
    return value


def _only(table: dict[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise LessonFormatError(f"{where}.{unknown[0]}", f"unknown key; keys are {sorted(allowed)}")


def _string(value: Any, where: str) -> str:
    if not isinstance(value, str) or not value:
        raise LessonFormatError(where, f"must be a non-empty string, got {value!r}")
    return value


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
        raise LessonFormatError(where, f"must be a number of at least 0, got {value!r}")
    return float(value)


def _visibility(value: Any, where: str) -> str:
    if value not in VISIBILITIES:
        raise LessonFormatError(where, f"must be one of {list(VISIBILITIES)}, got {value!r}")
    return value


def _first_heading(text: str) -> str | None:
    for line in text.splitlines():
        if line.startswith("# "):
            return line[2:].strip()
    return None


# --- validation against the module --------------------------------------------------------------
@dataclass(frozen=True)
class Parameters:
    """A function's parameters as the grader compares them: positional names, keyword-only names and defaults."""

    positional: tuple[str, ...]
    keyword: tuple[str, ...]
    defaults: dict[str, Any] = field(default_factory=dict)

    def text(self) -> str:
        parts = list(self.positional)
        if self.keyword:
            parts.append("*")
            parts.extend(f"{k}={self.defaults[k]!r}" if k in self.defaults else k for k in self.keyword)
        return "(" + ", ".join(parts) + ")"


def parameters_of_spec(spec: StepSpec) -> Parameters:
    signature = inspect.signature(spec.func)
    positional = tuple(p.name for p in signature.parameters.values() if p.kind != p.KEYWORD_ONLY)
    keyword = tuple(p.name for p in signature.parameters.values() if p.kind == p.KEYWORD_ONLY)
    defaults = {p.name: p.default for p in signature.parameters.values()
                if p.kind == p.KEYWORD_ONLY and p.default is not p.empty}
    return Parameters(positional, keyword, defaults)


def parameters_of_def(node: ast.FunctionDef) -> Parameters:
    args = node.args
    defaults: dict[str, Any] = {}
    for arg, default in zip(args.kwonlyargs, args.kw_defaults):
        if default is not None:
            try:
                defaults[arg.arg] = ast.literal_eval(default)
            except ValueError:
                defaults[arg.arg] = ast.unparse(default)
    return Parameters(tuple(a.arg for a in [*args.posonlyargs, *args.args]), tuple(a.arg for a in args.kwonlyargs),
                      defaults)


def parse_signature(text: str, where: str) -> tuple[str, Parameters]:
    """``"name(a: T, *, k: int = 1) -> R"`` -> (name, its parameters)."""
    try:
        tree = ast.parse(f"def {text.strip()}:\n    ...\n")
    except SyntaxError as exc:
        raise LessonFormatError(where, f"is not a Python signature ({exc.msg})") from None
    node = tree.body[0]
    assert isinstance(node, ast.FunctionDef)
    if node.args.vararg or node.args.kwarg:
        raise LessonFormatError(where, "steps take no *args or **kwargs")
    return node.name, parameters_of_def(node)


def validate_lesson(lesson: Lesson) -> None:
    """Check a lesson against its module: steps, controls, datasets, values, comparisons, signatures, starter."""
    from lab.lessons.checks import COMPARISONS, DETECTORS, check_options

    where = f"{lesson.id}/tasks.toml"
    try:
        pipeline = lesson.pipeline
    except (UnknownName, InvalidValue) as exc:
        raise LessonFormatError(f"{where}: lesson.module", exc.reason) from None
    step_names = [s.name for s in pipeline.steps]
    for name, data in lesson.datasets.items():
        spec = _known(lambda: pipeline.dataset(data.dataset), f"{where}: datasets.{name}.dataset")
        option_names = {o.name for o in spec.options}
        for key in data.options:
            if key not in option_names:
                raise LessonFormatError(f"{where}: datasets.{name}.options.{key}",
                                        f"dataset {data.dataset!r} has no such option; options are {sorted(option_names)}")
        if "seed" in data.options:
            raise LessonFormatError(f"{where}: datasets.{name}.options.seed", "give the seed as datasets.NAME.seed")
        for step, controls in data.params.items():
            step_spec = _known(lambda: pipeline.step(step), f"{where}: datasets.{name}.params.{step}")
            _controls(step_spec, controls, f"{where}: datasets.{name}.params.{step}")
    starter = _functions(lesson.starter, f"{lesson.id}/starter.py")
    mistakes = _functions(lesson.mistakes_source, f"{lesson.id}/mistakes.py")
    if mistakes:
        try:
            lesson.mistakes  # noqa: B018 - run it once now: an import error is the author's to see, not a grading's
        except Exception as exc:  # noqa: BLE001 - any error of the author's file
            raise LessonFormatError(f"{lesson.id}/mistakes.py", f"fails to run: {type(exc).__name__}: {exc}") from None
    for ti, task in enumerate(lesson.tasks):
        at = f"{where}: tasks[{ti}]"
        spec = _known(lambda: pipeline.step(task.step), f"{at}.step")
        one_value = len(spec.outputs) == 1 and spec.outputs[0].annotation is spec.result_type
        if not one_value or spec.is_generator:
            raise LessonFormatError(f"{at}.step", f"step {task.step!r} cannot be a task: a task's step returns one "
                                                  f"value (-> Annotated[T, 'name']), which the student's code returns")
        expected = parameters_of_spec(spec)
        name, declared = parse_signature(task.signature, f"{at}.signature")
        if name != task.step or declared.positional != expected.positional or declared.keyword != expected.keyword:
            raise LessonFormatError(f"{at}.signature", f"{task.signature!r} differs from the module's step "
                                                       f"{task.step}{expected.text()}")
        node = starter.get(task.step)
        if node is None:
            raise LessonFormatError(f"{lesson.id}/starter.py", f"defines no function {task.step!r}")
        got = parameters_of_def(node)
        if got.positional != expected.positional or got.keyword != expected.keyword:
            raise LessonFormatError(f"{lesson.id}/starter.py", f"{task.step}{got.text()} differs from the module's "
                                                               f"step {task.step}{expected.text()}")
        if not _raises_not_implemented(node):
            raise LessonFormatError(f"{lesson.id}/starter.py", f"{task.step} must raise NotImplementedError")
        for ci, check in enumerate(task.checks):
            cat = f"{at}.checks[{ci}]"
            _controls(spec, check.params, f"{cat}.params")
            if check.compare not in COMPARISONS:
                raise LessonFormatError(f"{cat}.compare", f"unknown comparison {check.compare!r}; "
                                                          f"comparisons are {sorted(COMPARISONS)}")
            problem = check_options(check.compare, check.options)
            if problem:
                raise LessonFormatError(f"{cat}.{problem[0]}", problem[1])
            for hi, hint in enumerate(check.hints):
                if hint.when not in DETECTORS:
                    raise LessonFormatError(f"{cat}.hints[{hi}].when", f"unknown detector {hint.when!r}; "
                                                                      f"detectors are {sorted(DETECTORS)}")
                _hint_options(hint, f"{cat}.hints[{hi}]")
                if hint.when == "same_as_reference_with":
                    _controls(spec, hint.options.get("params", {}), f"{cat}.hints[{hi}].params")
                if hint.when == "same_as_mistake":
                    _mistake(mistakes, hint.options.get("mistake"), expected, f"{cat}.hints[{hi}].mistake",
                             f"{lesson.id}/mistakes.py")
            index = step_names.index(task.step)
            if check.stage == "output":
                root = (check.value or (spec.writes[0] if spec.writes else "")).split(".")[0]
                if root not in spec.writes:
                    raise LessonFormatError(f"{cat}.value", f"step {task.step!r} writes {list(spec.writes)}, "
                                                            f"not {root!r}")
            else:
                until = check.until or step_names[-1]
                if until not in step_names or step_names.index(until) <= index:
                    raise LessonFormatError(f"{cat}.until", f"must be a step after {task.step!r}: one of "
                                                            f"{step_names[index + 1:]}")
                ran = pipeline.steps[index:step_names.index(until) + 1]
                if check.metric is None and check.value is None:
                    raise LessonFormatError(cat, 'a check at stage = "pipeline" names a metric or a value')
                if check.value is not None:
                    root = check.value.split(".")[0]
                    written = {w for s in ran for w in s.writes}
                    if root not in written:
                        raise LessonFormatError(f"{cat}.value", f"no step from {task.step!r} to {until!r} writes "
                                                                f"{root!r}; they write {sorted(written)}")


def _known(get, where: str):
    try:
        return get()
    except UnknownName as exc:
        raise LessonFormatError(where, exc.reason) from None


def _controls(spec: StepSpec, params: dict[str, Any], where: str) -> None:
    try:
        spec.coerce_controls(params)
    except LabError as exc:
        raise LessonFormatError(f"{where}.{exc.field}", exc.reason) from None


def _functions(source: str, where: str) -> dict[str, ast.FunctionDef]:
    """The top-level functions of a lesson's Python file (``starter.py``, ``mistakes.py``), by name."""
    try:
        tree = ast.parse(source, filename=where)
    except SyntaxError as exc:
        raise LessonFormatError(where, f"line {exc.lineno}: {exc.msg}") from None
    return {node.name: node for node in tree.body if isinstance(node, ast.FunctionDef)}


#: Keys of a hint that runs an alternative (the reference with other controls, or a mistake) and compares.
_ALTERNATIVE_HINT_KEYS = {"same_as_reference_with": {"params", "compare", "compare_options"},
                          "same_as_mistake": {"mistake", "compare", "compare_options"}}


def _hint_options(hint: HintRule, where: str) -> None:
    """A hint's keys are its detector's options; ``compare`` names a comparison and its ``compare_options``."""
    from lab.lessons.checks import COMPARISONS, DETECTORS, check_options

    if hint.when in _ALTERNATIVE_HINT_KEYS:
        allowed = _ALTERNATIVE_HINT_KEYS[hint.when]
    else:
        parameters = inspect.signature(DETECTORS[hint.when]).parameters.values()
        allowed = {p.name for p in parameters if p.kind == p.KEYWORD_ONLY}
    for key in hint.options:
        if key not in allowed:
            raise LessonFormatError(f"{where}.{key}", f"detector {hint.when!r} takes no option {key!r}; "
                                                     f"its options are {sorted(allowed)}")
    if "compare_options" in hint.options and "compare" not in hint.options:
        raise LessonFormatError(f"{where}.compare_options", "give the comparison they are for (compare = ...)")
    if "compare" in hint.options:
        compare = hint.options["compare"]
        if compare not in COMPARISONS:
            raise LessonFormatError(f"{where}.compare", f"unknown comparison {compare!r}; comparisons are "
                                                        f"{sorted(COMPARISONS)}")
        problem = check_options(compare, dict(_table(hint.options.get("compare_options", {}),
                                                     f"{where}.compare_options")))
        if problem:
            raise LessonFormatError(f"{where}.compare_options.{problem[0]}", problem[1])


def _mistake(mistakes: dict[str, ast.FunctionDef], name: Any, expected: Parameters, where: str, file: str) -> None:
    """A ``same_as_mistake`` hint names a function of ``mistakes.py`` with the step's parameters."""
    if not isinstance(name, str) or not name:
        raise LessonFormatError(where, "a same_as_mistake hint names a function of mistakes.py (mistake = \"...\")")
    if name not in mistakes:
        raise LessonFormatError(where, f"{file} defines no function {name!r}"
                                       + (f"; it defines {sorted(mistakes)}" if mistakes else " (is the file missing?)"))
    got = parameters_of_def(mistakes[name])
    if got.positional != expected.positional or got.keyword != expected.keyword:
        raise LessonFormatError(where, f"{name}{got.text()} in {file} differs from the step's parameters "
                                       f"{expected.text()}")


def _raises_not_implemented(node: ast.FunctionDef) -> bool:
    for child in ast.walk(node):
        if isinstance(child, ast.Raise) and child.exc is not None:
            target = child.exc.func if isinstance(child.exc, ast.Call) else child.exc
            if isinstance(target, ast.Name) and target.id == "NotImplementedError":
                return True
    return False
