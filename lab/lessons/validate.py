"""Mutation testing of a lesson's checks: every check must be failed by some mutant, every mutant caught.

:func:`mutation_report` grades, task by task, every mutant of the task's reference step
(:mod:`lab.lessons.mutants`: the generic ones and the lesson's ``mistakes.py``) on the lesson's
check data, in process (mutants are the lab's own code). It reports

- every **check no mutant fails**: a check that cannot fail grades nothing;
- every **mutant no check catches** (applicable: it ran on some check's data): either the data
  never exercises the mistake (its output equals the reference's everywhere: ties that never
  happen, a mask that masks nothing) or a check is missing; unless the task documents it as
  correct in ``[tasks.correct_mutants]`` (``scaled = "a homography is defined up to scale"``);
- every **hint the reference triggers**: a detector that fires on the reference's own result
  would name a mistake that is not there.

A lesson validates when none of these is left (``vision-lab lesson validate``, exit 2 otherwise).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lab.core.step import StepSpec
from lab.lessons import mutants as mutants_module
from lab.lessons.format import Check, Lesson, Task
from lab.lessons.grader import DataRun, Grader, ReferenceSubmission, StepRun, draw_seeds, takes_parameters_of
from lab.lessons.sandbox import CallResult

#: The assignment seed mutation tests draw the check data from (any fixed seed: the report is reproducible).
VALIDATION_SEED = 20261202


@dataclass(frozen=True)
class MutantResult:
    """What the checks of one task made of one mutant."""

    task: str
    mutant: str
    kind: str
    applied: bool  # it ran on some variant of some check's data
    caught_by: tuple[str, ...]  # the checks it failed
    differs: bool  # its result differed from the reference's on some check's data
    correct_because: str = ""  # the task's [tasks.correct_mutants] reason

    @property
    def survives(self) -> bool:
        return self.applied and not self.caught_by and not self.correct_because

    def describe(self) -> str:
        why = ("its result equals the reference's on every check's data: the data never exercises it"
               if not self.differs else "its result differs from the reference's, but no check fails it")
        return f"{self.task}: mutant {self.mutant} ({self.kind}) survives: {why}"


@dataclass(frozen=True)
class MutationReport:
    """A lesson's mutation test (see the module docstring)."""

    lesson: str
    results: tuple[MutantResult, ...]
    checks_never_failed: tuple[str, ...]
    reference_hints: tuple[str, ...]
    seconds: float
    stale_correct_mutants: tuple[str, ...] = field(default_factory=tuple)

    @property
    def surviving(self) -> tuple[MutantResult, ...]:
        return tuple(r for r in self.results if r.survives)

    @property
    def problems(self) -> list[str]:
        return ([r.describe() for r in self.surviving]
                + [f"{name}: no mutant fails this check" for name in self.checks_never_failed]
                + list(self.reference_hints) + list(self.stale_correct_mutants))

    @property
    def ok(self) -> bool:
        return not self.problems

    def text(self) -> str:
        applied = [r for r in self.results if r.applied]
        caught = [r for r in applied if r.caught_by]
        correct = [r for r in applied if not r.caught_by and r.correct_because]
        lines = [f"{self.lesson}: {len(applied)} mutants applied ({len(self.results) - len(applied)} did not "
                 f"apply), {len(caught)} caught, {len(correct)} documented as correct, "
                 f"{len(self.surviving)} surviving; {len(self.checks_never_failed)} checks no mutant fails "
                 f"({self.seconds:.1f} s)"]
        for result in applied:
            if result.caught_by:
                status = f"caught by {len(result.caught_by)}"
            elif result.correct_because:
                status = f"correct: {result.correct_because}"
            else:
                status = "SURVIVES"
            lines.append(f"  {result.task:<16} {result.mutant:<44} {status}")
        lines += [f"  problem: {p}" for p in self.problems]
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        return {"lesson": self.lesson, "ok": self.ok, "problems": self.problems, "seconds": self.seconds,
                "mutants": [{"task": r.task, "mutant": r.mutant, "kind": r.kind, "applied": r.applied,
                             "caught_by": list(r.caught_by), "differs": r.differs,
                             "correct_because": r.correct_because} for r in self.results]}


class _MutantSubmission(ReferenceSubmission):
    """The reference with one task's step replaced by a mutant (in process: mutants are the lab's code)."""

    def __init__(self, step: str, function: Callable[..., Any]) -> None:
        self.step, self.function = step, function

    def call(self, spec: StepSpec, args: tuple, kwargs: dict[str, Any], deadline: float) -> CallResult:
        if spec.name != self.step:
            return super().call(spec, args, kwargs, deadline)
        started = time.monotonic()
        return CallResult(self.function(*args, **kwargs), seconds=time.monotonic() - started)


def task_mutants(lesson: Lesson, spec: StepSpec) -> list[mutants_module.Mutant]:
    """The generic mutants of the step and the functions of ``mistakes.py`` with its parameters."""
    found = list(mutants_module.generic_mutants(spec.func))
    for name, function in lesson.mistakes.items():
        if takes_parameters_of(function, spec):
            found.append(mutants_module.mistake_mutant(name, function))
    return found


def mutation_report(lesson: Lesson, *, seed: int = VALIDATION_SEED,
                    on_mutant: Callable[[str, str], None] | None = None) -> MutationReport:
    """Grade every mutant of every task of ``lesson`` (see the module docstring)."""
    started = time.monotonic()
    seeds = draw_seeds(lesson, seed)
    shared = _SharedData(lesson, seeds, seed)
    results: list[MutantResult] = []
    failed_checks: set[str] = set()
    reference_hints: list[str] = []
    stale: list[str] = []
    for task in lesson.tasks:
        spec = lesson.pipeline.step(task.step)
        reference_hints += _reference_hints(shared, task)
        names = set()
        for mutant in task_mutants(lesson, spec):
            names.add(mutant.name)
            if on_mutant is not None:
                on_mutant(task.name, mutant.name)
            result = _grade_mutant(shared, task, spec, mutant)
            failed_checks.update(result.caught_by)
            results.append(result)
        stale += [f"{task.name}: [tasks.correct_mutants] names {name!r}, which is no mutant of {task.step}; "
                  f"mutants are {sorted(names)}" for name in task.correct_mutants if name not in names]
    never = tuple(f"{task.title}: {check.name}" for task in lesson.tasks for check in task.checks
                  if f"{task.title}: {check.name}" not in failed_checks)
    return MutationReport(lesson.id, tuple(results), never, tuple(reference_hints),
                          time.monotonic() - started, tuple(stale))


class _SharedData:
    """The check data and the reference's runs, made once and shared by the graders of every mutant."""

    def __init__(self, lesson: Lesson, seeds: dict[str, list[int]], seed: int) -> None:
        self.lesson, self.seeds, self.seed = lesson, seeds, seed
        probe = Grader(lesson, ReferenceSubmission(), seeds=seeds, limits=lesson.limits, reference=True,
                       seed=seed)
        self.data: dict[str, list[DataRun]] = probe.data
        self.reference_runs: dict[tuple, StepRun] = probe.reference_runs

    def grader(self, submission: ReferenceSubmission) -> Grader:
        limits = self.lesson.limits.replace(total_timeout_s=1e9, call_timeout_s=1e9)
        grader = Grader(self.lesson, submission, seeds=self.seeds, limits=limits, reference=True,
                        seed=self.seed)
        grader.data, grader.reference_runs = self.data, self.reference_runs
        return grader


def _grade_mutant(shared: _SharedData, task: Task, spec: StepSpec,
                  mutant: mutants_module.Mutant) -> MutantResult:
    grader = shared.grader(_MutantSubmission(task.step, mutant(spec.func)))
    caught: list[str] = []
    applied = differs = False
    for check in task.checks:
        for variant in range(len(shared.lesson.datasets[check.dataset].variants)):
            _, passed = grader._variant_body(task, check, None, variant)
            params = {**shared.data[check.dataset][variant].params(task.step), **check.params}
            run = grader._step_run(task, (check.dataset, variant), params, student=True)  # cached
            if isinstance(run.exception, mutants_module.NotApplicable):
                continue
            applied = True
            differs = differs or _differs(grader, shared, task, check, variant)
            if not passed:
                caught.append(f"{task.title}: {check.name}")
                break
    return MutantResult(task.name, mutant.name, mutant.kind, applied, tuple(caught), differs,
                        task.correct_mutants.get(mutant.name, ""))


def _differs(grader: Grader, shared: _SharedData, task: Task, check: Check, variant: int) -> bool:
    """Whether the mutant's output (the step's first value) differs from the reference's on this data."""
    first = shared.lesson.pipeline.step(task.step).writes[0]
    params = {**shared.data[check.dataset][variant].params(task.step), **check.params}
    where = (check.dataset, variant)
    mine = grader._step_run(task, where, params, student=True)
    theirs = grader._step_run(task, where, params, student=False)
    if first not in mine.outputs or first not in theirs.outputs:
        return True
    try:
        a = mutants_module.primary_array(mine.outputs[first])[0]
        b = mutants_module.primary_array(theirs.outputs[first])[0]
    except mutants_module.NotApplicable:
        return mine.outputs[first] != theirs.outputs[first]
    return a.shape != b.shape or a.dtype != b.dtype or not np.array_equal(a, b, equal_nan=True)


def _reference_hints(shared: _SharedData, task: Task) -> list[str]:
    """Hints the generic detectors and the lesson's give when the student's result is the reference's own:
    each would name a mistake that is not there."""
    found = []
    grader = shared.grader(ReferenceSubmission())
    for check in task.checks:
        for variant in range(len(shared.lesson.datasets[check.dataset].variants)):
            params = {**shared.data[check.dataset][variant].params(task.step), **check.params}
            where = (check.dataset, variant)
            reference = grader._step_run(task, where, params, student=False)
            if reference.error:
                continue
            first = shared.lesson.pipeline.step(task.step).writes[0]
            value = reference.outputs.get(first)
            hints = grader._hints(task, check, reference, reference, params, value, value, where)
            found += [f"{task.title}: {check.name}: the reference's own result triggers hint {h.name!r}"
                      for h in hints]
    return found


__all__ = ["MutantResult", "MutationReport", "mutation_report", "task_mutants"]
