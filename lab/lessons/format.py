"""The lesson format: one folder per lesson, ``lessons/NN-name/`` (``docs/lessons.md`` is the authors' guide).

``lesson.md``
    The text a student reads. Its first ``# `` heading is the lesson's title unless ``tasks.toml`` names one.
``starter.py``
    The template a student fills in: every task's function, with the step's parameters (and, where it
    gives them, the step's defaults), a docstring and a body that raises ``NotImplementedError``.
``tasks.toml``
    Tables ``[lesson]`` (``module``, optional ``title`` and ``visibility``), ``[limits]`` (:class:`Limits`),
    ``[datasets.NAME]`` (:class:`CheckDataset`, its battery of :class:`DataVariant`), ``[hints.NAME]``
    (:class:`HintRule`: each hint written
    once, named by the checks that try it) and ``[[tasks]]`` (``name``, ``step``, ``title``) with their
    ``[[tasks.checks]]`` (:class:`Check`; ``hints = ["name", ...]``).
``mistakes.py`` (optional)
    Known wrong implementations with a task step's parameters, run by ``same_as_mistake`` hints.

Written once: a task's signature comes from its step (:func:`step_signature`), and the starter's
functions are checked against the step; a task's points are the sum of its checks' points; a hint
is defined once in ``[hints]``, and a check names it (a detector that needs no options, such as
``"transposed"``, can be named directly). Everything is checked when a lesson is loaded
(:func:`load_lesson`): a mistake raises :class:`LessonFormatError` naming the file and the key; a
hint no check names is reported in :attr:`Lesson.warnings`.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import logging
import os
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from collections.abc import Callable
from typing import Annotated, Any, Literal, TypeVar

import numpy as np

from lab.core.errors import InvalidValue, LabError, UnknownName
from lab.core.pipeline import Pipeline
from lab.core.step import StepSpec, type_name
from lab.lessons.checks import COMPARISONS, DETECTORS, check_options, detector_keys, plain_detectors

log = logging.getLogger("lab.lessons")

#: Folder names of lessons: two digits, a dash, a lowercase name.
LESSON_ID = re.compile(r"^\d{2}-[a-z0-9][a-z0-9-]*$")

#: Gradescope's visibilities of a test.
VISIBILITIES = ("visible", "hidden", "after_due_date", "after_published")

STAGES = ("output", "pipeline")

_T = TypeVar("_T")


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
    """A recognisable mistake: detector ``when`` (lab.lessons.checks.DETECTORS), its options and what to say.

    ``name`` is its key in the lesson's ``[hints]`` table (or the detector's name, for a detector named
    directly by a check).
    """

    when: str
    say: str = ""
    options: dict[str, Any] = field(default_factory=dict)
    name: str = ""


@dataclass(frozen=True)
class DataVariant:
    """One variant of a check dataset's battery: options over the dataset's, and how it is described."""

    options: dict[str, Any] = field(default_factory=dict)
    description: str = ""


@dataclass(frozen=True)
class CheckDataset:
    """Data checks run on: a dataset of the module, its options, its battery of variants, step controls.

    ``variants``: the battery (``variants = K`` in tasks.toml: K draws of the same options;
    ``variants = [{option = value, description = "..."}, ...]``: one variant per table, its options
    over ``options``, to build data that exercises a rule). Every check on the dataset runs on every
    variant and passes only if it passes on all. Variant k's seed is derived from the grading run's
    assignment seed, the dataset's name and k (:func:`lab.lessons.grader.draw_seeds`); ``seed``
    pins it instead: an instructor's integer, or ``"env:NAME"`` (read at grading). ``params``:
    controls of the pipeline's steps, by step.
    """

    name: str
    dataset: str
    options: dict[str, Any] = field(default_factory=dict)
    seed: int | str | None = None
    description: str = ""
    params: dict[str, dict[str, Any]] = field(default_factory=dict)
    variants: tuple[DataVariant, ...] = (DataVariant(),)

    def describe(self, variant: int = 0, *, numbered: bool = True) -> str:
        """How the data (of ``variant``) is described to students (``numbered``: with "variant k of K")."""
        with_options = f" with {self.options}" if self.options else ""
        text = self.description or f"dataset {self.dataset!r}" + with_options
        chosen = self.variants[variant]
        if chosen.description:
            text += f"; {chosen.description}"
        elif chosen.options:
            text += f"; with {chosen.options}"
        if numbered and len(self.variants) > 1:
            text += f" (variant {variant + 1} of {len(self.variants)})"
        return text

    def options_of(self, variant: int) -> dict[str, Any]:
        """The dataset's options for ``variant``: its own, with the variant's over them."""
        return {**self.options, **self.variants[variant].options}


@dataclass(frozen=True)
class Check:
    """One graded comparison; becomes one test of results.json.

    Stage ``output`` compares the task step's ``value`` (default: what it writes) with the reference's on
    the same inputs; stage ``pipeline`` runs what ``until`` needs after the student's step and compares
    a ``metric`` or a ``value`` with the reference's. ``compare`` names a comparison of
    :data:`lab.lessons.checks.COMPARISONS`, ``options`` are its options; ``hints`` are tried in order
    when the check fails.
    """

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
    """A step the student implements, with its checks. Its points are its checks' points; its
    ``signature`` is the step's (:func:`step_signature`), filled in when the lesson is loaded."""

    name: str
    step: str
    title: str
    checks: tuple[Check, ...]
    signature: str = ""
    correct_mutants: dict[str, str] = field(default_factory=dict)  # mutant name -> why it is correct

    @property
    def points(self) -> float:
        return float(sum(c.points for c in self.checks))

    @property
    def function(self) -> str:
        """The name of the function the submission defines."""
        return self.step


@dataclass(frozen=True)
class Lesson:
    """A loaded, validated lesson folder. ``warnings``: what the loader reports without refusing (unused
    hints)."""

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
    hints: dict[str, HintRule] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    @cached_property
    def pipeline(self) -> Pipeline:
        return resolve_pipeline(self.module)

    @cached_property
    def mistakes(self) -> dict[str, Any]:
        """The functions of ``mistakes.py`` by name (executed once, on first use)."""
        if not self.mistakes_source:
            return {}
        namespace: dict[str, Any] = {"__name__": f"lab_lesson_mistakes_{self.id.replace('-', '_')}"}
        exec(compile(self.mistakes_source, str(self.path / "mistakes.py"), "exec"), namespace)  # the author's
        return {name: value for name, value in namespace.items()  # its own functions, not the imported ones
                if inspect.isfunction(value) and value.__module__ == namespace["__name__"]}

    @property
    def points(self) -> float:
        return float(sum(t.points for t in self.tasks))

    def task(self, name: str) -> Task:
        for task in self.tasks:
            if name in (task.name, task.step):
                return task
        raise UnknownName("task", f"lesson {self.id!r} has no task {name!r}; tasks are "
                                  f"{[t.name for t in self.tasks]}")

    @property
    def module_title(self) -> str:
        """The module as a person reads it: its pipeline's title (``lab.modules.sfm_basics:PIPELINE`` ->
        "Structure from motion: the building blocks"); the ``module`` entry when it does not load."""
        try:
            return self.pipeline.title or self.module
        except LabError:
            return self.module

    def summary(self) -> dict[str, Any]:
        """The lesson as listed by ``GET /api/lessons`` (``module`` is the entry of tasks.toml,
        ``module_title`` the module's human name)."""
        return {"id": self.id, "title": self.title, "module": self.module, "module_title": self.module_title,
                "points": self.points,
                "tasks": [{"name": t.name, "title": t.title, "step": t.step, "points": t.points}
                          for t in self.tasks]}

    def describe(self) -> dict[str, Any]:
        """Everything a student sees (``GET /api/lessons/{id}``): text, tasks, starter; no seeds, no
        secrets."""
        tasks = []
        for task in self.tasks:
            checks = [{"name": c.name if c.visibility != "hidden" else "hidden check", "points": c.points,
                       "stage": c.stage, "visibility": c.visibility} for c in task.checks]
            tasks.append({"name": task.name, "title": task.title, "step": task.step,
                          "signature": task.signature, "points": task.points, "checks": checks})
        return {**self.summary(), "text": self.text, "starter": self.starter, "tasks": tasks,
                "limits": {k: v for k, v in self.limits.to_json().items()
                           if k in ("cpu_seconds", "memory_mb", "call_timeout_s", "total_timeout_s")}}


# --- finding lessons ------------------------------------------------------------------------------
def lessons_root() -> Path:
    """Where lessons live: ``$VISION_LAB_LESSONS_DIR``, else the ``lessons/`` folder beside the ``lab``
    package."""
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
_TOP_KEYS = {"lesson", "limits", "datasets", "hints", "tasks"}
_TASK_KEYS = {"name", "step", "title", "checks", "correct_mutants"}
_CHECK_KEYS = {"name", "points", "dataset", "compare", "stage", "value", "metric", "until", "params", "hints",
               "visibility"}
#: Keys a task no longer takes, and why (each was a copy of something written elsewhere).
_DERIVED_TASK_KEYS = {
    "signature": "a task's signature comes from its step (students see the step's own): remove this key",
    "points": "a task's points are the sum of its checks' points: remove this key",
}


def load_lesson(folder: Path | str, *, validate: bool = True) -> Lesson:
    """Read and check a lesson folder; raises :class:`LessonFormatError` naming the file and key."""
    folder = Path(folder).resolve()
    lesson_id = folder.name
    if not LESSON_ID.match(lesson_id):
        raise LessonFormatError("lesson", f"a lesson folder is named NN-name (e.g. 01-calibration), got "
                                          f"{lesson_id!r}")
    files = {}
    for name in ("lesson.md", "tasks.toml", "starter.py"):
        path = folder / name
        if not path.is_file():
            raise LessonFormatError(f"{lesson_id}/{name}",
                                    "is missing: a lesson has lesson.md, tasks.toml and starter.py")
        files[name] = path.read_text(encoding="utf-8")
    where = f"{lesson_id}/tasks.toml"
    try:
        data = tomllib.loads(files["tasks.toml"])
    except tomllib.TOMLDecodeError as exc:
        raise LessonFormatError(where, f"is not valid TOML: {exc}") from None
    _only(data, _TOP_KEYS, where)
    head = _table(data.get("lesson", {}), f"{where}: lesson")
    _only(head, {"module", "title", "visibility"}, f"{where}: lesson")
    module = _string(head.get("module"), f"{where}: lesson.module")
    visibility = _visibility(head.get("visibility", "visible"), f"{where}: lesson.visibility")
    title = head.get("title") or _first_heading(files["lesson.md"]) or lesson_id
    limits = _limits(data.get("limits", {}), where)
    datasets = {name: _dataset(name, table, f"{where}: datasets.{name}")
                for name, table in _table(data.get("datasets", {}), f"{where}: datasets").items()}
    hints = _hint_table(data.get("hints", {}), f"{where}: hints")
    raw_tasks = data.get("tasks", [])
    if not isinstance(raw_tasks, list) or not raw_tasks:
        raise LessonFormatError(f"{where}: tasks", "a lesson needs at least one [[tasks]] table")
    tasks = tuple(_task(t, f"{where}: tasks[{i}]", datasets, hints, visibility)
                  for i, t in enumerate(raw_tasks))
    names = [t.name for t in tasks]
    if len(set(names)) != len(names) or len({t.step for t in tasks}) != len(tasks):
        raise LessonFormatError(f"{where}: tasks", f"task names and steps must be unique, got {names}")
    used = {rule.name for task in tasks for check in task.checks for rule in check.hints}
    warnings = tuple(f"{where}: hints.{name} is named by no check" for name in hints if name not in used)
    for warning in warnings:
        log.warning("lesson %s: %s", lesson_id, warning)
    mistakes = folder / "mistakes.py"
    lesson = Lesson(id=lesson_id, path=folder, title=str(title), module=module, text=files["lesson.md"],
                    starter=files["starter.py"], tasks=tasks, datasets=datasets, limits=limits,
                    visibility=visibility,
                    mistakes_source=mistakes.read_text(encoding="utf-8") if mistakes.is_file() else "",
                    hints=hints, warnings=warnings)
    lesson = _with_signatures(lesson)
    if validate:
        validate_lesson(lesson)
    return lesson


def _limits(table: Any, where: str) -> Limits:
    table = _table(table, f"{where}: limits")
    _only(table, {f.name for f in dataclasses.fields(Limits)}, f"{where}: limits")
    try:
        return Limits(**table)
    except LessonFormatError as exc:
        raise LessonFormatError(f"{where}: {exc.field}", exc.reason) from None


def _with_signatures(lesson: Lesson) -> Lesson:
    """The lesson with every task's signature taken from its step (left empty where the step is unknown:
    :func:`validate_lesson` says why)."""
    try:
        pipeline = lesson.pipeline
    except LabError:
        return lesson
    tasks = []
    for task in lesson.tasks:
        try:
            spec = pipeline.step(task.step)
        except UnknownName:
            tasks.append(task)
            continue
        tasks.append(dataclasses.replace(task, signature=step_signature(spec)))
    return dataclasses.replace(lesson, tasks=tuple(tasks))


def _dataset(name: str, table: Any, where: str) -> CheckDataset:
    table = _table(table, where)
    _only(table, {"dataset", "options", "seed", "description", "params", "variants"}, where)
    seed = table.get("seed")
    from_env = isinstance(seed, str) and seed.startswith("env:") and len(seed) > 4
    if seed == "fresh":
        raise LessonFormatError(f"{where}.seed", 'seed = "fresh" is gone: check data is drawn from the '
                                                 "assignment's secret seed (fresh data is a practice run); "
                                                 "remove the key, or pin an integer")
    if seed is not None and (isinstance(seed, bool) or not (isinstance(seed, int) or from_env)):
        raise LessonFormatError(f"{where}.seed", f'must be an integer or "env:NAME", got {seed!r}')
    params = _table(table.get("params", {}), f"{where}.params")
    for step, controls in params.items():
        _table(controls, f"{where}.params.{step}")
    return CheckDataset(name=name, dataset=_string(table.get("dataset"), f"{where}.dataset"),
                        options=dict(_table(table.get("options", {}), f"{where}.options")), seed=seed,
                        description=str(table.get("description", "")),
                        params={k: dict(v) for k, v in params.items()},
                        variants=_variants(table.get("variants", 1), f"{where}.variants"))


#: Most variants a check dataset may have (each check runs on every one).
MAX_VARIANTS = 32


def _variants(value: Any, where: str) -> tuple[DataVariant, ...]:
    """``variants = K`` (K draws of the dataset's options) or a list of tables (options over the dataset's,
    and an optional ``description``)."""
    if isinstance(value, int) and not isinstance(value, bool):
        if not 1 <= value <= MAX_VARIANTS:
            raise LessonFormatError(where, f"must be from 1 to {MAX_VARIANTS}, got {value}")
        return (DataVariant(),) * value
    if not isinstance(value, list) or not value or len(value) > MAX_VARIANTS:
        raise LessonFormatError(where, f"must be a number of variants or a list of 1 to {MAX_VARIANTS} "
                                       f"tables of options, got {value!r}")
    variants = []
    for i, entry in enumerate(value):
        entry = dict(_table(entry, f"{where}[{i}]"))
        description = entry.pop("description", "")
        if not isinstance(description, str):
            raise LessonFormatError(f"{where}[{i}].description", f"must be a string, got {description!r}")
        variants.append(DataVariant(options=entry, description=description))
    return tuple(variants)


def _hint_table(table: Any, where: str) -> dict[str, HintRule]:
    """``[hints.NAME]`` tables: ``when`` (a detector), ``say`` (what to tell the student), the detector's
    keys."""
    rules = {}
    for name, entry in _table(table, where).items():
        at = f"{where}.{name}"
        if name in DETECTORS:
            raise LessonFormatError(at, f"{name!r} is a detector's name: name the hint after the mistake it "
                                        "recognises (a check names a detector without options directly)")
        entry = _table(entry, at)
        when = _string(entry.get("when"), f"{at}.when")
        if when not in DETECTORS:
            raise LessonFormatError(f"{at}.when", f"unknown detector {when!r}; detectors are "
                                                  f"{sorted(DETECTORS)}")
        say = entry.get("say", "")
        if not isinstance(say, str):
            raise LessonFormatError(f"{at}.say", f"must be a string, got {say!r}")
        options = {k: v for k, v in entry.items() if k not in ("when", "say")}
        rule = HintRule(when=when, say=say, options=options, name=name)
        _hint_options(rule, at)
        rules[name] = rule
    return rules


def _hint_options(hint: HintRule, where: str) -> None:
    """A hint's keys are its detector's options; ``compare`` names a comparison, ``compare_options`` its
    options."""
    allowed, required = detector_keys(hint.when)
    for key in hint.options:
        if key not in allowed:
            raise LessonFormatError(f"{where}.{key}", f"detector {hint.when!r} takes no option {key!r}; "
                                                     f"its options are {sorted(allowed)}")
    for key in sorted(required - set(hint.options)):
        raise LessonFormatError(f"{where}.{key}", f"detector {hint.when!r} needs option {key!r}")
    if "compare_options" in hint.options and "compare" not in hint.options:
        raise LessonFormatError(f"{where}.compare_options",
                                "give the comparison they are for (compare = ...)")
    if "compare" in hint.options:
        compare = hint.options["compare"]
        if compare not in COMPARISONS:
            raise LessonFormatError(f"{where}.compare", f"unknown comparison {compare!r}; comparisons are "
                                                        f"{sorted(COMPARISONS)}")
        problem = check_options(compare, dict(_table(hint.options.get("compare_options", {}),
                                                     f"{where}.compare_options")))
        if problem:
            raise LessonFormatError(f"{where}.compare_options.{problem[0]}", problem[1])


def _task(table: Any, where: str, datasets: dict[str, CheckDataset], hints: dict[str, HintRule],
          visibility: str) -> Task:
    table = _table(table, where)
    for key, why in _DERIVED_TASK_KEYS.items():
        if key in table:
            raise LessonFormatError(f"{where}.{key}", why)
    _only(table, _TASK_KEYS, where)
    step = _string(table.get("step"), f"{where}.step")
    raw_checks = table.get("checks", [])
    if not isinstance(raw_checks, list) or not raw_checks:
        raise LessonFormatError(f"{where}.checks", "a task needs at least one [[tasks.checks]] table")
    checks = tuple(_check(c, f"{where}.checks[{i}]", datasets, hints, visibility)
                   for i, c in enumerate(raw_checks))
    check_names = [c.name for c in checks]
    if len(set(check_names)) != len(check_names):
        raise LessonFormatError(f"{where}.checks", f"check names must be unique within a task, got "
                                                   f"{check_names}")
    return Task(name=str(table.get("name", step)), step=step,
                title=str(table.get("title", step.replace("_", " ").capitalize())), checks=checks,
                correct_mutants=_correct_mutants(table.get("correct_mutants", {}),
                                                 f"{where}.correct_mutants"))


def _correct_mutants(table: Any, where: str) -> dict[str, str]:
    """``[tasks.correct_mutants]``: mutant name -> why it is correct (the mutation report accepts it)."""
    reasons = {}
    for name, why in _table(table, where).items():
        if not isinstance(why, str) or len(why.strip()) < 10:
            raise LessonFormatError(f"{where}.{name}", "say why this mutant is correct (a sentence)")
        reasons[name] = why.strip()
    return reasons


def _check(table: Any, where: str, datasets: dict[str, CheckDataset], hints: dict[str, HintRule],
           visibility: str) -> Check:
    table = _table(table, where)
    dataset = _string(table.get("dataset"), f"{where}.dataset")
    if dataset not in datasets:
        raise LessonFormatError(f"{where}.dataset", f"no [datasets.{dataset}] table; datasets are "
                                                    f"{sorted(datasets)}")
    stage = table.get("stage", "output")
    if stage not in STAGES:
        raise LessonFormatError(f"{where}.stage", f"must be one of {list(STAGES)}, got {stage!r}")
    metric, value = table.get("metric"), table.get("value")
    if metric is not None and value is not None:
        raise LessonFormatError(where, "give either value or metric, not both")
    if metric is not None and stage != "pipeline":
        raise LessonFormatError(f"{where}.metric", 'metrics are checked at stage = "pipeline"')
    return Check(name=_string(table.get("name"), f"{where}.name"),
                 points=_number(table.get("points"), f"{where}.points"),
                 dataset=dataset, compare=_string(table.get("compare"), f"{where}.compare"), stage=stage,
                 value=value, metric=metric, until=table.get("until"),
                 params=dict(_table(table.get("params", {}), f"{where}.params")),
                 options={k: v for k, v in table.items() if k not in _CHECK_KEYS},
                 hints=_named_hints(table.get("hints", []), hints, f"{where}.hints"),
                 visibility=_visibility(table.get("visibility", visibility), f"{where}.visibility"))


def _named_hints(names: Any, hints: dict[str, HintRule], where: str) -> tuple[HintRule, ...]:
    """A check's ``hints``: names of ``[hints]`` entries, or of detectors that need no options."""
    if not isinstance(names, list):
        raise LessonFormatError(where, f"must be a list of hint names, got {names!r}")
    rules = []
    for i, name in enumerate(names):
        if isinstance(name, dict):
            raise LessonFormatError(f"{where}[{i}]", "hints are defined once, in the lesson's [hints] table, "
                                                     'and named by the checks: hints = ["name", ...]')
        if not isinstance(name, str) or not name:
            raise LessonFormatError(f"{where}[{i}]", f"must be the name of a hint, got {name!r}")
        if name in hints:
            rules.append(hints[name])
        elif name in plain_detectors():
            rules.append(HintRule(when=name, name=name))
        else:
            raise LessonFormatError(f"{where}[{i}]", f"unknown hint {name!r}; the [hints] table defines "
                                                     f"{sorted(hints)}, and the detectors a check may name "
                                                     f"directly are {sorted(plain_detectors())}")
    if len({r.name for r in rules}) != len(rules):
        raise LessonFormatError(where, f"names a hint twice: {names}")
    return tuple(rules)


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


# --- signatures -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Parameters:
    """A function's parameters as the grader compares them: positional names, keyword-only names,
    defaults."""

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
    defaults = {p.name: p.default for p in signature.parameters.values() if p.default is not p.empty}
    return Parameters(positional, keyword, defaults)


def parameters_of_def(node: ast.FunctionDef) -> Parameters:
    """The parameters of a ``def`` in a lesson's file; a default that is no literal is kept as its
    source text."""
    args = node.args
    positional = [*args.posonlyargs, *args.args]
    pairs = [*zip(positional[len(positional) - len(args.defaults):], args.defaults, strict=True),
             *((a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults, strict=True) if d is not None)]
    defaults: dict[str, Any] = {}
    for arg, default in pairs:
        try:
            defaults[arg.arg] = ast.literal_eval(default)
        except ValueError:
            defaults[arg.arg] = _Source(ast.unparse(default))
    return Parameters(tuple(a.arg for a in positional), tuple(a.arg for a in args.kwonlyargs), defaults)


class _Source(str):
    """A default written as an expression (``np.inf``), not a literal: shown, never compared."""

    def __repr__(self) -> str:
        return str(self)


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


def step_signature(spec: StepSpec) -> str:
    """The signature a student implements, read from the step: ``name(a: T, *, k: int = 1) -> R``.

    Annotations are shown as a reader writes them, without ``Annotated`` metadata (ranges, the
    output's state name): ``np.ndarray``, ``Points2D``, ``Literal['ssd', 'ncc']``, ``np.ndarray | None``.
    """
    signature = inspect.signature(spec.func)
    hints = typing.get_type_hints(spec.func, include_extras=True)
    parts: list[str] = []
    for param in signature.parameters.values():
        if param.kind == param.KEYWORD_ONLY and "*" not in parts:
            parts.append("*")
        text = param.name
        if param.name in hints:
            text += f": {annotation_text(hints[param.name])}"
        if param.default is not param.empty:
            text += f" = {param.default!r}"
        parts.append(text)
    returns = f" -> {annotation_text(hints['return'])}" if "return" in hints else ""
    return f"{spec.name}({', '.join(parts)}){returns}"


def annotation_text(annotation: Any) -> str:
    """An annotation as source text: ``Annotated[T, ...]`` -> ``T``, numpy's types with ``np.``."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is Annotated:
        return annotation_text(args[0])
    if origin is Literal:
        return f"Literal[{', '.join(repr(a) for a in args)}]"
    if origin in (typing.Union, types.UnionType):
        return " | ".join(annotation_text(a) for a in args)
    if annotation is type(None) or annotation is None:
        return "None"
    if annotation is Ellipsis:
        return "..."
    if origin is not None:
        return f"{annotation_text(origin)}[{', '.join(annotation_text(a) for a in args)}]"
    if isinstance(annotation, type):
        return _class_text(annotation)
    return type_name(annotation)


def _class_text(cls: type) -> str:
    if cls.__module__.split(".")[0] == "numpy":
        for prefix, namespace in (("np.", np), ("np.random.", np.random)):
            if getattr(namespace, cls.__name__, None) is cls:
                return prefix + cls.__name__
    return cls.__qualname__


# --- validation against the module --------------------------------------------------------------
def validate_lesson(lesson: Lesson) -> None:
    """Check a lesson against its module: steps, controls, datasets, values, comparisons, hints, starter."""
    where = f"{lesson.id}/tasks.toml"
    try:
        pipeline = lesson.pipeline
    except (UnknownName, InvalidValue) as exc:
        raise LessonFormatError(f"{where}: lesson.module", exc.reason) from None
    _validate_datasets(lesson, pipeline, where)
    starter = _functions(lesson.starter, f"{lesson.id}/starter.py")
    mistakes = _functions(lesson.mistakes_source, f"{lesson.id}/mistakes.py")
    if mistakes:
        try:
            lesson.mistakes  # noqa: B018 - run it now: its import errors are the author's, not a grading's
        except Exception as exc:
            raise LessonFormatError(f"{lesson.id}/mistakes.py",
                                    f"fails to run: {type(exc).__name__}: {exc}") from None
    for ti, task in enumerate(lesson.tasks):
        at = f"{where}: tasks[{ti}]"
        spec = _task_step(pipeline, task, at)
        _validate_starter(lesson.id, task, spec, starter)
        for ci, check in enumerate(task.checks):
            _validate_check(pipeline, task, spec, check, f"{at}.checks[{ci}]")
            for rule in check.hints:
                _validate_hint_use(lesson, spec, rule, mistakes, f"{at}.checks[{ci}]")


def _validate_datasets(lesson: Lesson, pipeline: Pipeline, where: str) -> None:
    for name, data in lesson.datasets.items():
        spec = _known(pipeline.dataset, data.dataset, f"{where}: datasets.{name}.dataset")
        option_names = {o.name for o in spec.options}
        keys = [(f"options.{key}", key) for key in data.options]
        keys += [(f"variants[{i}].{key}", key) for i, v in enumerate(data.variants) for key in v.options]
        for at, key in keys:
            if key == "seed":
                raise LessonFormatError(f"{where}: datasets.{name}.{at}",
                                        "a variant's seed is derived from the assignment seed: pin one as "
                                        "datasets.NAME.seed")
            if key not in option_names:
                raise LessonFormatError(f"{where}: datasets.{name}.{at}",
                                        f"dataset {data.dataset!r} has no such option; options are "
                                        f"{sorted(option_names)}")
        for step, controls in data.params.items():
            at = f"{where}: datasets.{name}.params.{step}"
            step_spec = _known(pipeline.step, step, at)
            _controls(step_spec, controls, at)


def _task_step(pipeline: Pipeline, task: Task, at: str) -> StepSpec:
    """The task's step, which must return one value (what the student's function returns)."""
    spec = _known(pipeline.step, task.step, f"{at}.step")
    one_value = len(spec.outputs) == 1 and spec.outputs[0].annotation is spec.result_type
    if not one_value or spec.is_generator:
        raise LessonFormatError(f"{at}.step", f"step {task.step!r} cannot be a task: a task's step returns "
                                              "one value (-> Annotated[T, 'name']), which the student's "
                                              "code returns")
    name, shown = parse_signature(task.signature, f"{at}.step")
    expected = parameters_of_spec(spec)
    if name != task.step or (shown.positional, shown.keyword) != (expected.positional, expected.keyword):
        raise LessonFormatError(f"{at}.step", f"the signature shown for step {task.step!r}, "
                                              f"{task.signature!r}, does not read back as its parameters "
                                              f"{expected.text()}")
    return spec


def _validate_starter(lesson_id: str, task: Task, spec: StepSpec,
                      starter: dict[str, ast.FunctionDef]) -> None:
    """``starter.py`` defines the task's function with the step's parameters (and defaults, where it gives
    any)."""
    where = f"{lesson_id}/starter.py"
    expected = parameters_of_spec(spec)
    node = starter.get(task.step)
    if node is None:
        raise LessonFormatError(where, f"defines no function {task.step!r}")
    got = parameters_of_def(node)
    if got.positional != expected.positional or got.keyword != expected.keyword:
        raise LessonFormatError(where, f"{task.step}{got.text()} differs from the module's step "
                                       f"{task.step}{expected.text()}")
    for name, default in got.defaults.items():
        if isinstance(default, _Source):
            continue
        if name not in expected.defaults:
            raise LessonFormatError(where, f"{task.step}: {name}={default!r} has a default the step's {name} "
                                           f"does not have: {task.signature}")
        wanted = expected.defaults[name]
        if default != wanted or isinstance(default, bool) != isinstance(wanted, bool):
            raise LessonFormatError(where, f"{task.step}: {name}={default!r} differs from the step's default "
                                           f"{name}={wanted!r}: give the step's default or none")
    if not _raises_not_implemented(node):
        raise LessonFormatError(where, f"{task.step} must raise NotImplementedError")


def _validate_check(pipeline: Pipeline, task: Task, spec: StepSpec, check: Check, cat: str) -> None:
    _controls(spec, check.params, f"{cat}.params")
    if check.compare not in COMPARISONS:
        raise LessonFormatError(f"{cat}.compare", f"unknown comparison {check.compare!r}; "
                                                  f"comparisons are {sorted(COMPARISONS)}")
    problem = check_options(check.compare, check.options)
    if problem:
        raise LessonFormatError(f"{cat}.{problem[0]}", problem[1])
    if check.stage == "output":
        root = (check.value or (spec.writes[0] if spec.writes else "")).split(".")[0]
        if root not in spec.writes:
            raise LessonFormatError(f"{cat}.value", f"step {task.step!r} writes {list(spec.writes)}, "
                                                    f"not {root!r}")
        return
    dependants = [s.name for s in pipeline.downstream(spec.writes)]
    until = check.until or pipeline.steps[-1].name
    if until not in dependants:
        raise LessonFormatError(f"{cat}.until", f"must be a step after {task.step!r} that reads its output "
                                                f"(directly or through other steps): one of {dependants}")
    if check.metric is None and check.value is None:
        raise LessonFormatError(cat, 'a check at stage = "pipeline" names a metric or a value')
    if check.value is not None:
        root = check.value.split(".")[0]
        after = steps_after(pipeline, task.step, until)
        written = {*spec.writes, *(w for name in after for w in pipeline.step(name).writes)}
        if root not in written:
            raise LessonFormatError(f"{cat}.value", f"neither {task.step!r} nor a step run after it to bring "
                                                    f"{until!r} up to date writes {root!r}; they write "
                                                    f"{sorted(written)}")


def steps_after(pipeline: Pipeline, step: str, until: str) -> tuple[str, ...]:
    """The steps a pipeline check runs after a student's ``step`` to bring ``until`` up to date: the
    planner's plan for ``until`` once ``step`` has run again, when what reads its outputs is gone."""
    gone = {w for s in pipeline.downstream(pipeline.step(step).writes) for w in s.writes}
    available = {w for s in pipeline.steps for w in s.writes} - gone
    return pipeline.plan(until, available).steps


def _validate_hint_use(lesson: Lesson, spec: StepSpec, rule: HintRule, mistakes: dict[str, ast.FunctionDef],
                       cat: str) -> None:
    """A hint fits the step of each check that names it: its controls, or its mistake's parameters."""
    if rule.when == "same_as_reference_with":
        _controls(spec, rule.options.get("params", {}), f"{lesson.id}/tasks.toml: hints.{rule.name}.params",
                  used_by=cat)
    if rule.when == "same_as_mistake":
        _mistake(mistakes, rule.options.get("mistake"), parameters_of_spec(spec),
                 f"{lesson.id}/tasks.toml: hints.{rule.name}.mistake", f"{lesson.id}/mistakes.py")


def _known(get: Callable[[str], _T], name: str, where: str) -> _T:
    """``get(name)``, an unknown name raised as a :class:`LessonFormatError` at ``where``."""
    try:
        return get(name)
    except UnknownName as exc:
        raise LessonFormatError(where, exc.reason) from None


def _controls(spec: StepSpec, params: dict[str, Any], where: str, *, used_by: str = "") -> None:
    try:
        spec.coerce_controls(params)
    except LabError as exc:
        named = f" (the hint is named by {used_by.split(': ', 1)[-1]})" if used_by else ""
        raise LessonFormatError(f"{where}.{exc.field}", exc.reason + named) from None


def _functions(source: str, where: str) -> dict[str, ast.FunctionDef]:
    """The top-level functions of a lesson's Python file (``starter.py``, ``mistakes.py``), by name."""
    try:
        tree = ast.parse(source, filename=where)
    except SyntaxError as exc:
        raise LessonFormatError(where, f"line {exc.lineno}: {exc.msg}") from None
    return {node.name: node for node in tree.body if isinstance(node, ast.FunctionDef)}


def _mistake(mistakes: dict[str, ast.FunctionDef], name: Any, expected: Parameters, where: str,
             file: str) -> None:
    """A ``same_as_mistake`` hint names a function of ``mistakes.py`` with the step's parameters."""
    if not isinstance(name, str) or not name:
        raise LessonFormatError(where, "a same_as_mistake hint names a function of mistakes.py "
                                       '(mistake = "...")')
    if name not in mistakes:
        defined = f"; it defines {sorted(mistakes)}" if mistakes else " (is the file missing?)"
        raise LessonFormatError(where, f"{file} defines no function {name!r}{defined}")
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
