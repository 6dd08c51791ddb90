"""Grade a submission: the student's functions replace the reference steps, on hidden data, checked two ways.

For every check of every task (see :mod:`lab.lessons.format`), the grader:

1. loads the check's data (fresh secret seeds drawn with :mod:`secrets` at every grading, unless
   the lesson gives an instructor's seed or ``--seed`` is passed) and runs the reference pipeline's
   plan for the task's step (:meth:`lab.core.Session.plan`: what the step needs, by data flow);
2. forks that session (:meth:`~lab.core.Session.fork`) and runs the step's plan there with the
   student's function as the override (:meth:`~lab.core.Session.run_plan`), the function running
   in the sandbox and receiving only the step's inputs and controls, never the reference's output
   or the truth; the reference's run of the step with the check's controls is made the same way;
3. checks what came back (type, shape, finite) and compares it with the reference's output
   (stage ``output``), or, on a fork of each, runs the plan that brings the check's ``until`` step
   up to date and compares the resulting value or metric with the reference's (stage ``pipeline``);
4. writes one test per check in Gradescope's ``results.json`` schema, with a message saying which
   check, what was expected, what came back, a hint when a common mistake is recognised, and what
   the code printed.

One sandbox child serves the whole grading run. A function that times out, exceeds the CPU limit
or crashes fails that check; the task's later checks are then not run (they fail, naming the
first failure), and the next task gets a fresh child. The run as a whole stops at the lesson's
``total_timeout_s``: the checks left fail with that reason, so grading always returns in time.

``grade(lesson, reference=True)`` grades the lab's own implementation (in process), which must
score full marks.
"""

from __future__ import annotations

import inspect
import logging
import os
import secrets
import time
import zlib
from dataclasses import dataclass, field
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from lab.core.errors import LabError, StepFailed
from lab.core.pipeline import Pipeline, RunRecord, Session, StepParams, open_session
from lab.core.step import StepSpec
from lab.lessons import checks as checks_module
from lab.lessons import isolation
from lab.lessons import mutants as mutants_module
from lab.lessons.checks import Hint
from lab.lessons import messages
from lab.lessons.format import Check, CheckDataset, Lesson, Limits, Task, parameters_of_spec
from lab.lessons.sandbox import CallResult, Sandbox, SubmissionFailure

log = logging.getLogger("lab.lessons")

#: Longest ``output`` of one test (Gradescope shows it as text).
MAX_TEST_OUTPUT = 6000

#: Failures after which a task's function is not called again in this grading run.
FATAL_KINDS = ("timeout", "cpu", "crashed", "load")


@dataclass
class TestResult:
    """One test of results.json."""

    name: str
    score: float
    max_score: float
    status: str  # "passed" | "failed"
    output: str
    visibility: str = "visible"
    task: str = ""
    hints: tuple[str, ...] = ()  # the names of the hints given, in order

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "score": round(self.score, 6), "max_score": self.max_score,
                "status": self.status, "output": self.output, "visibility": self.visibility,
                "extra_data": {"task": self.task, "hints": list(self.hints)}}


@dataclass
class GradeReport:
    """A grading run: its tests and what to write into results.json."""

    lesson: str
    tests: list[TestResult]
    execution_time: float
    output: str
    seeds: dict[str, list[int]] = field(default_factory=dict)
    reference: bool = False
    practice: bool = False

    @property
    def score(self) -> float:
        return float(sum(t.score for t in self.tests))

    @property
    def max_score(self) -> float:
        return float(sum(t.max_score for t in self.tests))

    def results_json(self) -> dict[str, Any]:
        """Gradescope's results.json (top-level score, execution_time, output, tests; extra_data for
        instructors)."""
        return {"score": round(self.score, 6), "execution_time": round(self.execution_time, 3),
                "output": self.output, "tests": [t.to_json() for t in self.tests],
                "extra_data": {"lesson": self.lesson, "max_score": self.max_score, "seeds": self.seeds,
                               "reference": self.reference, "practice": self.practice}}


# --- seeds ----------------------------------------------------------------------------------------
def derived_seed(seed: int, name: str, attempt: int = 0, variant: int = 0) -> int:
    """The seed of variant ``variant`` of check dataset ``name`` under assignment seed ``seed``: fixed per
    (seed, name, variant, attempt), 31 bits."""
    words = [int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode())]
    if attempt or variant:
        words.append(attempt)
    if variant:
        words.append(variant)
    return int(np.random.SeedSequence(words).generate_state(1)[0] & 0x7FFFFFFF)


def reseeder(lesson: Lesson, name: str, seed: int | None,
             variant: int = 0) -> Callable[[int], int] | None:
    """How to draw another seed when a dataset cannot be made with the first (never for a pinned seed)."""
    if lesson.datasets[name].seed is not None:
        return None  # an instructor's seed is used as given
    if seed is not None:
        return lambda attempt: derived_seed(seed, name, attempt, variant)
    return lambda attempt: secrets.randbits(31)


def draw_seeds(lesson: Lesson, seed: int | None = None, *,
               environ: Mapping[str, str] | None = None) -> dict[str, list[int]]:
    """The seed of every variant of every check dataset.

    A dataset's pinned seed (``seed = 1234`` or ``"env:NAME"`` in tasks.toml) gives its first variant
    that seed and derives the others from it; else every variant's seed is derived from the assignment
    seed ``seed``, so a regrade sees the same data; with no assignment seed (a practice run) each is
    drawn with :mod:`secrets`.
    """
    variables: Mapping[str, str] = os.environ if environ is None else environ
    seeds: dict[str, list[int]] = {}
    for name, data in lesson.datasets.items():
        count = len(data.variants)
        pinned: int | None = None
        if isinstance(data.seed, int):
            pinned = data.seed
        elif isinstance(data.seed, str) and data.seed.startswith("env:"):
            variable = data.seed[4:]
            text = variables.get(variable)
            if text is None or not text.strip().lstrip("-").isdigit():
                why = "not set" if text is None else "not an integer"
                raise LabError(f"datasets.{name}.seed",
                               f"the instructor's seed is read from ${variable}, which is {why}")
            pinned = int(text)
        if pinned is not None:
            seeds[name] = [pinned] + [derived_seed(pinned, name, variant=k) for k in range(1, count)]
        elif seed is not None:
            seeds[name] = [derived_seed(seed, name, variant=k) for k in range(count)]
        else:
            seeds[name] = [secrets.randbits(31) for _ in range(count)]
    return seeds


# --- the code under test ----------------------------------------------------------------------------
class Submission:
    """Where the task functions come from: the student's file in a sandbox, or the reference (in process)."""

    def start(self, deadline: float) -> SubmissionFailure | None:
        return None

    def functions(self) -> dict[str, dict[str, Any]] | None:
        return None

    def call(self, spec: StepSpec, args: tuple, kwargs: dict[str, Any], deadline: float) -> CallResult:
        raise NotImplementedError

    def printed_outside_calls(self) -> str:
        return ""

    def close(self) -> None:
        pass


class ReferenceSubmission(Submission):
    """The lab's own steps (``--reference``): must score full marks."""

    def call(self, spec: StepSpec, args: tuple, kwargs: dict[str, Any], deadline: float) -> CallResult:
        started = time.monotonic()
        return CallResult(spec.func(*args, **kwargs), seconds=time.monotonic() - started)


class SandboxedSubmission(Submission):
    """A student's file, run in one :class:`Sandbox` for the whole grading run."""

    def __init__(self, source: str, limits: Limits) -> None:
        self.limits = limits
        self.sandbox = Sandbox(source, limits=limits)
        self.load_printed = ""

    def start(self, deadline: float) -> SubmissionFailure | None:
        try:
            self.sandbox.start(timeout=min(self.limits.call_timeout_s, max(deadline - time.monotonic(), 0.0)))
        except SubmissionFailure as failure:
            return failure
        self.load_printed = self.sandbox.load_printed
        return None

    def functions(self) -> dict[str, dict[str, Any]] | None:
        return self.sandbox.functions

    def call(self, spec: StepSpec, args: tuple, kwargs: dict[str, Any], deadline: float) -> CallResult:
        timeout = min(self.limits.call_timeout_s, max(deadline - time.monotonic(), 0.0))
        return self.sandbox.call(spec.name, args, kwargs, timeout=timeout)

    def printed_outside_calls(self) -> str:
        return "\n".join(t for t in (self.load_printed, self.sandbox.output()) if t)

    def close(self) -> None:
        self.sandbox.close()


# --- runs of the pipeline -----------------------------------------------------------------------------
@dataclass
class AfterRun:
    """The pipeline brought up to date to a check's ``until`` after the task's step: its session and the
    records of the task's step and of every step run after it (where a check's metric is looked up)."""

    session: Session
    records: list[RunRecord]

    def metric(self, name: str) -> Any:
        """``name`` as the last run step reporting it measured it (None when no step reports it)."""
        for record in reversed(self.records):
            if name in record.metrics:
                return record.metrics[name]
        return None


@dataclass
class StepRun:
    """The task's step run on one state: its outputs and the session holding them, or why it failed."""

    step: str = ""
    session: Session | None = None
    params: StepParams = field(default_factory=dict)
    record: RunRecord | None = None
    outputs: dict[str, Any] = field(default_factory=dict)
    error: str = ""
    failure: SubmissionFailure | None = None
    printed: str = ""
    violations: tuple[str, ...] = ()
    flooded: int = 0
    downstream: dict[str, AfterRun | str] = field(default_factory=dict)  # until -> the run, or the error
    exception: BaseException | None = None  # what the step raised (an in-process alternative or mutant)


class DataRun:
    """One check dataset: a session holding the reference pipeline's run, which every run of a task forks.

    A generator may fail for some seeds (a board that cannot be placed in the image): with a
    fresh or ``--seed`` seed, up to :attr:`ATTEMPTS` seeds are tried (``reseed(attempt)``).
    """

    ATTEMPTS = 5

    def __init__(self, pipeline: Pipeline, data: CheckDataset, seed: int,
                 reseed: Callable[[int], int] | None = None, *, variant: int = 0) -> None:
        self.pipeline = pipeline
        self.data = data
        self.variant = variant
        self.seed = seed
        self.reseed = reseed
        self.error = ""
        self._session: Session | None = None
        self._ready: set[str] = set()

    def params(self, step: str) -> dict[str, Any]:
        return dict(self.data.params.get(step, {}))

    def controls(self, step: str | None = None, params: Mapping[str, Any] | None = None) -> StepParams:
        """The controls of every step as the dataset gives them, with ``params`` for ``step``."""
        controls = {name: dict(values) for name, values in self.data.params.items()}
        if step is not None:
            controls[step] = dict(params if params is not None else self.params(step))
        return controls

    def reference(self, step: str) -> Session:
        """The session after the reference pipeline ran ``step``'s plan (what it needs, and the step) with
        the dataset's controls; every run of the step forks it."""
        if self.error:
            raise LabError("dataset", self.error)
        if self._session is None:
            self._session = self._open()
        session = self._session
        if step not in self._ready:
            plan = session.plan(step, self.controls())
            ran: list[RunRecord] = []
            try:
                session.run_plan(plan, self.controls(), on_step=ran.append)
            except LabError as exc:
                self.error = (f"the reference pipeline failed on the check data at step "
                              f"{plan.steps[len(ran)]!r} ({exc}); this is a problem of the lesson, not yours")
                raise LabError("dataset", self.error) from None
            self._ready.add(step)
        return session

    def _open(self) -> Session:
        spec = self.pipeline.dataset(self.data.dataset)
        takes_seed = any(o.name == "seed" for o in spec.options)
        attempts = self.ATTEMPTS if self.reseed is not None and takes_seed else 1
        for attempt in range(attempts):
            if attempt:
                self.seed = self.reseed(attempt)  # type: ignore[misc]
            options = dict(self.data.options_of(self.variant), **({"seed": self.seed} if takes_seed else {}))
            try:
                return open_session(self.pipeline, self.data.dataset, options, seed=self.seed)
            except LabError as exc:
                problem = exc
        self.error = (f"the check data could not be made ({problem}); this is a problem of the lesson, "
                      "not yours")
        raise LabError("dataset", self.error)


# --- the grader -----------------------------------------------------------------------------------------
class Grader:
    """One grading run of one submission (see the module docstring)."""

    def __init__(self, lesson: Lesson, submission: Submission, *, seeds: dict[str, list[int]], limits: Limits,
                 reference: bool = False, seed: int | None = None,
                 variant_order: Callable[[int], list[int]] | None = None) -> None:
        self.lesson = lesson
        self.pipeline = lesson.pipeline
        self.submission = submission
        self.limits = limits
        self.reference = reference
        self.practice = seed is None
        self.data = {name: [DataRun(self.pipeline, data, variant_seed, reseeder(lesson, name, seed, k),
                                    variant=k) for k, variant_seed in enumerate(seeds[name])]
                     for name, data in lesson.datasets.items()}
        # the order the variants of a dataset are graded in (tests: the grade must not depend on it)
        self.variant_order = variant_order or (lambda count: list(range(count)))
        self.reference_runs: dict[tuple, StepRun] = {}
        self.student_runs: dict[tuple, StepRun] = {}
        self.broken: dict[str, str] = {}  # task -> why its function is not called again
        self.started = time.monotonic()
        self.deadline = self.started + limits.total_timeout_s
        self.load_failure: SubmissionFailure | None = None

    # --- entry point --------------------------------------------------------------------------------
    def run(self) -> GradeReport:
        self.load_failure = self.submission.start(self.deadline)
        tests: list[TestResult] = []
        try:
            for task in self.lesson.tasks:
                problem = self._signature_problem(task)
                for check in task.checks:
                    tests.append(self._grade_check(task, check, problem))
        finally:
            self.submission.close()
        elapsed = time.monotonic() - self.started
        return GradeReport(lesson=self.lesson.id, tests=tests, execution_time=elapsed,
                           output=self._summary(tests, elapsed), seeds=self.seeds, reference=self.reference,
                           practice=self.practice)

    @property
    def seeds(self) -> dict[str, list[int]]:
        """The seed each variant of each dataset was made with (after any retries)."""
        return {name: [run.seed for run in runs] for name, runs in self.data.items()}

    def _summary(self, tests: list[TestResult], elapsed: float) -> str:
        score, top = sum(t.score for t in tests), sum(t.max_score for t in tests)
        passed = sum(t.status == "passed" for t in tests)
        lines = [f"{self.lesson.title}: {score:g} / {top:g} points ({passed} of {len(tests)} checks passed) "
                 f"in {elapsed:.1f} s."]
        if self.reference:
            lines.append("Graded the lab's own reference implementation.")
        if self.practice:
            lines.append("Practice run: fresh data, not the assignment's (a grade uses the assignment's "
                         "seed).")
        if self.load_failure is not None:
            lines.append(messages.failure_text(self.load_failure, "your file", self.limits))
        printed = self.submission.printed_outside_calls()
        if printed:
            lines += ["What your file printed when loaded (or outside Python's print):",
                      messages.truncate(printed, 2000)]
        return "\n".join(lines)

    # --- one check ------------------------------------------------------------------------------------
    def _grade_check(self, task: Task, check: Check, problem: str | None) -> TestResult:
        """One test: the check run on every variant of its dataset (in :attr:`variant_order`), passed only
        if it passes on all; the message lists the variants that failed, in their order."""
        test = TestResult(name=f"{task.title}: {check.name}", score=0.0, max_score=check.points,
                          status="failed", output="", visibility=check.visibility, task=task.name)
        data = self.lesson.datasets[check.dataset]
        count = len(data.variants)
        bodies: dict[int, tuple[str, bool]] = {}
        for variant in self.variant_order(count):
            bodies[variant] = self._variant_body(task, check, problem, variant)
        passed = all(ok for _, ok in bodies.values())
        header = f"Check: {check.name}"
        if count == 1:
            header += f"\nData: {data.describe(0)}"
        if check.params:
            header += f"\nControls of {task.step}: {messages.format_params(check.params)}"
        if passed:
            test.score, test.status = check.points, "passed"
        test.output = messages.truncate(f"{header}\n{messages.variants_text(data, bodies)}", MAX_TEST_OUTPUT)
        test.hints = tuple(dict.fromkeys(name for body, _ in bodies.values()
                                         for name in messages.hint_names(body)))
        return test

    def _variant_body(self, task: Task, check: Check, problem: str | None, variant: int) -> tuple[str, bool]:
        try:
            return self._check_body(task, check, problem, variant)
        except LabError as exc:  # the lesson's own data or reference failed: say so, never crash
            return f"Not graded: {exc.reason}", False
        except Exception as exc:  # a bug in the lab: the other checks still run, the student is told
            log.exception("grading check %r of %s failed", check.name, self.lesson.id)
            return (f"Not graded: the grader itself failed on this check ({type(exc).__name__}: {exc}); "
                    "this is a bug in the lab, not in your code: tell your instructor"), False

    def _check_body(self, task: Task, check: Check, problem: str | None, variant: int) -> tuple[str, bool]:
        if self.load_failure is not None:
            return messages.failure_text(self.load_failure, "your file", self.limits), False
        if problem:
            return problem, False
        if task.name in self.broken:
            return f"Not run: {self.broken[task.name]}", False
        if time.monotonic() >= self.deadline:
            return (f"Not run: grading stopped after its time limit of {self.limits.total_timeout_s:g} s "
                    "(earlier calls of your code took that long)"), False
        params = {**self.data[check.dataset][variant].params(task.step), **check.params}
        where = (check.dataset, variant)
        reference = self._step_run(task, where, params, student=False)
        if reference.error:
            raise LabError("reference", f"the reference {task.step} failed on the check data "
                                        f"({reference.error}); this is a problem of the lesson")
        student = self._step_run(task, where, params, student=True)
        shown = messages.truncate(student.printed, 2000)
        printed = (f"\nWhat your code printed:\n{shown}" if student.printed.strip()
                   else "")
        if student.failure is not None or student.error:
            text = (messages.failure_text(student.failure, f"{task.step}()", self.limits) if student.failure
                    else student.error)
            return text + printed, False
        if student.flooded:
            return (f"{task.step}() printed {student.flooded} characters more than the "
                    f"{self.limits.output_kb:g} KB a call may print: remove your debugging "
                    f"prints.{printed}"), False
        check_stage = self._output_body if check.stage == "output" else self._pipeline_body
        body, passed = check_stage(task, check, student, reference, params, where)
        return body + printed, passed

    def _output_body(self, task: Task, check: Check, student: StepRun, reference: StepRun,
                     params: dict[str, Any], where: tuple[str, int]) -> tuple[str, bool]:
        """Stage ``output``: the step's value against the reference's on the same inputs."""
        value_name = check.value or self.pipeline.step(task.step).writes[0]
        got, expected = self._values(student, reference, value_name, "your")
        if isinstance(got, str):
            return got, False
        problem = checks_module.structure_problem(got, expected, what=f"{task.step}'s {value_name}")
        if problem:
            return (f"Your function returned a value of the wrong form: {problem}."
                    + self._form_hints(task, where, params, got, expected)), False
        outcome = self._compare(check, got, expected)
        hints = [] if outcome.passed else self._hints(task, check, student, reference, params, got, expected,
                                                      where)
        return messages.outcome_text(outcome, f"{value_name}", hints), outcome.passed

    def _pipeline_body(self, task: Task, check: Check, student: StepRun, reference: StepRun,
                       params: dict[str, Any], where: tuple[str, int]) -> tuple[str, bool]:
        """Stage ``pipeline``: what ``until`` needs run on the student's output; a metric or value
        compared."""
        first = self.pipeline.step(task.step).writes[0]
        got_out, expected_out = student.outputs.get(first), reference.outputs.get(first)
        problem = checks_module.structure_problem(got_out, expected_out, what=f"{task.step}'s {first}")
        if problem:
            return ("The rest of the pipeline was not run: your function returned a value of the wrong "
                    f"form: {problem}." + self._form_hints(task, where, params, got_out, expected_out)), False
        until = check.until or self.pipeline.steps[-1].name
        student_after = self._downstream(student, until)
        if isinstance(student_after, str):
            hints = self._hints(task, check, student, reference, params, got_out, expected_out, where)
            return (f"The rest of the pipeline failed on your output: {student_after}"
                    + messages.hints_text(hints)), False
        reference_after = self._downstream(reference, until)
        if isinstance(reference_after, str):
            raise LabError("reference", f"the reference pipeline failed after {task.step}: {reference_after}")
        if check.metric is not None:
            got, expected = student_after.metric(check.metric), reference_after.metric(check.metric)
            if expected is None:
                raise LabError("metric", f"no step up to {until!r} reports metric {check.metric!r}")
            if got is None:  # measured on the reference's output, not on the student's: say what in theirs
                hints = self._hints(task, check, student, reference, params, got_out, expected_out, where)
                warned = [w for record in student_after.records for w in record.warnings]
                why = f": {'; '.join(dict.fromkeys(warned))}" if warned else ""
                return (f"Failed: the lab's steps up to {until} could not measure {check.metric} on your "
                        f"{first}{why}" + messages.hints_text(hints)), False
            what = f"metric {check.metric} after running the pipeline to {until} on your {first}"
        else:
            got, expected = self._values(_as_run(student_after.session), _as_run(reference_after.session),
                                         check.value or "", "the")
            if isinstance(got, str):
                return got, False
            problem = checks_module.structure_problem(got, expected, what=check.value or "")
            if problem:
                return f"After the pipeline ran on your output: {problem}.", False
            what = f"{check.value} after running the pipeline to {until} on your {first}"
        outcome = self._compare(check, got, expected)
        hints = ([] if outcome.passed
                 else self._hints(task, check, student, reference, params, got_out, expected_out, where))
        return messages.outcome_text(outcome, what, hints), outcome.passed

    def _compare(self, check: Check, got: Any, expected: Any) -> checks_module.Outcome:
        compare = checks_module.COMPARISONS[check.compare]
        try:
            return compare(checks_module.as_compared(got), checks_module.as_compared(expected),
                           **check.options)
        except (TypeError, ValueError) as exc:
            return checks_module.Outcome(False, f"could not be compared with the expected value ({exc})")

    def _values(self, student: StepRun, reference: StepRun, path: str, whose: str) -> tuple[Any, Any]:
        root, *rest = path.split(".")
        if root not in reference.outputs:
            raise LabError("value", f"the reference wrote no {root!r}")
        expected = reference.outputs[root]
        got = student.outputs.get(root)
        try:
            expected = checks_module.select(expected, rest, what=root)
        except KeyError as exc:
            raise LabError("value", str(exc)) from None
        try:
            got = checks_module.select(got, rest, what=f"{whose} {root}")
        except KeyError as exc:
            return f"{exc.args[0]}", None
        return got, expected

    # --- running steps ----------------------------------------------------------------------------------
    def _step_run(self, task: Task, where: tuple[str, int], params: dict[str, Any], *, student: bool,
                  mistake: str | None = None) -> StepRun:
        """Run the task's step on variant ``where = (dataset, k)``: the student's code, the reference, or
        (``mistake``) a function of the lesson's ``mistakes.py``, on a fork of the variant's reference run."""
        key = (task.step, where, _freeze(params), mistake)
        cache = self.student_runs if student else self.reference_runs
        if key in cache:
            return cache[key]
        data = self.data[where[0]][where[1]]
        session = data.reference(task.step).fork()
        spec = self.pipeline.step(task.step)
        run = StepRun(step=task.step, session=session, params=data.controls(task.step, params))
        proxy = _Proxy(self, task, spec) if student else None
        override = proxy or (self._alternative_function(spec, mistake) if mistake else None)
        try:
            records = session.run_plan(session.plan(task.step, run.params), run.params,
                                       overrides={task.step: override} if override else None)
            run.record = records[-1]
            run.outputs = {name: session.state[name] for name in spec.writes if name in session.state}
        except StepFailed as exc:
            cause = exc.__cause__
            run.exception = cause
            if isinstance(cause, SubmissionFailure):
                run.failure = cause
                if cause.kind in FATAL_KINDS:
                    self.broken[task.name] = (f"{task.step}() failed on an earlier check: "
                                              f"{messages.failure_kind_text(cause)}")
            else:
                run.error = f"{task.step}() failed: {exc.reason}" if student else exc.reason
        except LabError as exc:  # the runner refused the returned value (type, NaN)
            run.error = (f"Your function returned a value of the wrong form: {exc.reason}"
                         + messages.nan_hint(exc.reason)) if student else str(exc)
        if proxy is not None:
            run.printed, run.violations, run.flooded = proxy.printed, proxy.violations, proxy.flooded
        cache[key] = run
        return run

    def _alternative_function(self, spec: StepSpec, name: str) -> Callable[..., Any]:
        """A function of the lesson's ``mistakes.py`` or a generic mutant of the step, by its name."""
        if name in self.lesson.mistakes:
            return self.lesson.mistakes[name]
        for mutant in mutants_module.generic_mutants(spec.func):
            if mutant.name == name:
                return mutant(spec.func)
        raise LabError("hint", f"no mistake or mutant {name!r}")

    def _downstream(self, run: StepRun, until: str) -> AfterRun | str:
        """A fork of ``run``'s session brought up to date to ``until`` (the plan of what ``until`` needs,
        which re-runs what reads the step's output), or why a step of that plan failed."""
        if until in run.downstream:
            return run.downstream[until]
        assert run.session is not None and run.record is not None
        session = run.session.fork()
        plan = session.plan(until, run.params)
        records = [run.record]
        result: AfterRun | str
        try:
            session.run_plan(plan, run.params, on_step=records.append)
            result = AfterRun(session, records)
        except LabError as exc:
            result = f"step {plan.steps[len(records) - 1]}: {exc.reason}"
        run.downstream[until] = result
        return result

    # --- hints ------------------------------------------------------------------------------------------
    def _hints(self, task: Task, check: Check, student: StepRun, reference: StepRun, params: dict[str, Any],
               got: Any, expected: Any, where: tuple[str, int]) -> list[Hint]:
        """What a failed check says about the cause, tried in tiers: the check's own hints (every one that
        fires), else the lesson's ``mistakes.py`` for the step, else the generic detectors and mutants
        (:func:`_generic_hints`; the first that fires). An alternative computation names the mistake only
        when the student's value matches it and the reference's does not."""
        first = self.pipeline.step(task.step).writes[0]
        if check.stage != "output":
            got, expected = student.outputs.get(first), reference.outputs.get(first)
        try:
            got_array, expected_array = checks_module.as_compared(got), checks_module.as_compared(expected)
        except (TypeError, ValueError):
            return []
        if got_array.shape != expected_array.shape:
            return []
        matches = self._matcher(check, got_array, expected_array)
        found = self._named_hints(task, check, params, where, got_array, expected_array, matches)
        if found:
            return found
        named = {rule.options.get("mistake") for rule in check.hints if rule.when == "same_as_mistake"}
        for name in self.lesson.mistakes:
            if name in named or not takes_parameters_of(self.lesson.mistakes[name],
                                                         self.pipeline.step(task.step)):
                continue
            alternative = self._alternative_value(task, where, params, name)
            if alternative is not None and matches(alternative):
                found.append(checks_module.Hint(name, self._mistake_text(name)))
        if found:
            return found
        return self._generic_hints(task, where, params, got, expected, got_array, expected_array, matches)

    def _matcher(self, check: Check, got: np.ndarray, expected: np.ndarray) -> Callable[[Any], bool]:
        """``matches(alternative)``: the student's value equals the alternative (by the check's comparison at
        stage output, else closely) and the reference's does not."""
        if check.stage == "output":
            compare, options = checks_module.COMPARISONS[check.compare], dict(check.options)
        else:
            scale = float(np.abs(expected).max()) if expected.size else 1.0
            compare, options = checks_module.allclose, {"rtol": 1e-6, "atol": 1e-9 * max(scale, 1e-300)}

        def same(a: np.ndarray, b: np.ndarray) -> bool:
            try:
                return a.shape == b.shape and compare(a, b, **options).passed
            except (TypeError, ValueError, np.linalg.LinAlgError):
                return False

        def matches(alternative: Any) -> bool:
            try:
                alt = checks_module.as_compared(alternative)
            except (TypeError, ValueError):
                return False
            return same(got, alt) and not same(expected, alt)
        return matches

    def _named_hints(self, task: Task, check: Check, params: dict[str, Any], where: tuple[str, int],
                     got_array: np.ndarray, expected_array: np.ndarray,
                     matches: Callable[[Any], bool]) -> list[Hint]:
        found: list[Hint] = []
        for rule in check.hints:
            options = dict(rule.options)
            if rule.when in ("same_as_reference_with", "same_as_mistake"):
                alternative = self._step_run(task, where, {**params, **options.get("params", {})},
                                             student=False, mistake=options.get("mistake"))
                first = self.pipeline.step(task.step).writes[0]
                if alternative.error or first not in alternative.outputs:
                    continue
                # the hint's own comparison, else the check's (stage output), else equality up to scale
                if "compare" in options:
                    compare, compare_options = (checks_module.COMPARISONS[options["compare"]],
                                                options.get("compare_options", {}))
                elif check.stage == "output":
                    compare, compare_options = checks_module.COMPARISONS[check.compare], check.options
                else:
                    compare, compare_options = checks_module.equal_up_to_scale, {}
                try:
                    alt = checks_module.as_compared(alternative.outputs[first])
                    outcome = compare(got_array, alt, **compare_options)
                    if outcome.passed and compare(expected_array, alt, **compare_options).passed:
                        continue  # the reference matches it too: it names nothing
                except (TypeError, ValueError):
                    continue
                which = ({"mistake": options["mistake"]} if rule.when == "same_as_mistake"
                         else {"params": options.get("params", {})})
                options = {"outcome": outcome, **which}
            message = checks_module.detect(rule.when, got_array, expected_array, options)
            if message:
                found.append(checks_module.Hint(rule.name, rule.say or message))
        return found

    def _mistake_text(self, name: str) -> str:
        """A mistake's hint: the ``say`` of a lesson hint that names it, else its docstring's first line."""
        for rule in self.lesson.hints.values():
            if rule.when == "same_as_mistake" and rule.options.get("mistake") == name and rule.say:
                return rule.say
        doc = inspect.getdoc(self.lesson.mistakes[name]) or ""
        return (doc.split("\n\n")[0].replace("\n", " ")
                or f"your result is what the known mistake {name!r} computes")

    def _generic_hints(self, task: Task, where: tuple[str, int], params: dict[str, Any], got: Any,
                       expected: Any, got_array: np.ndarray, expected_array: np.ndarray,
                       matches: Callable[[Any], bool]) -> list[Hint]:
        """The first generic detector that fires: a float32 or integer result, a reflection, then the output
        transforms and changed inputs of :mod:`lab.lessons.mutants` (NumPy-patching mutants are left to
        ``vision-lab lesson validate``: they would touch other gradings running in this process)."""
        raw_got, raw_expected = _primary_or_self(got), _primary_or_self(expected)
        message = checks_module.dtype_difference(raw_got, raw_expected)
        if message:
            name = "float32" if np.asarray(raw_got).dtype == np.float32 else "dtype"
            return [checks_module.Hint(name, message)]
        for name in ("reflection", "transposed", "inverse", "negated", "scaled", "permuted"):
            message = checks_module.detect(name, got_array, expected_array, {})
            if message:
                return [checks_module.Hint(name, message)]
        spec = self.pipeline.step(task.step)
        partial: list[tuple[mutants_module.Mutant, Any]] = []
        for mutant in mutants_module.generic_mutants(spec.func):
            if mutant.kind == "patch" or mutant.name in _DETECTED_DIRECTLY:
                continue
            if mutant.kind == "output":
                try:
                    array, _ = mutants_module.primary_array(expected)
                    alternative: Any = mutants_module.transform(mutant.name, array)
                except mutants_module.NotApplicable:
                    continue
            else:
                alternative = self._alternative_value(task, where, params, mutant.name)
            if alternative is not None and matches(alternative):
                return [checks_module.Hint(mutant.name, mutant.hint)]
            if alternative is not None:
                partial.append((mutant, alternative))
        return messages.partial_match(partial, got_array, expected_array)

    def _form_hints(self, task: Task, where: tuple[str, int], params: dict[str, Any], got: Any,
                    expected: Any) -> str:
        """Hint lines for a value of the wrong form: a function of mistakes.py that returns the same shape and
        values (one disparity short, one row too many), else what the shape or the NaN suggests."""
        finite = isinstance(got, np.ndarray) and got.dtype.kind in "biuf" and bool(np.all(np.isfinite(got)))
        if finite and got.shape != np.shape(_primary_or_self(expected)):
            for name in self.lesson.mistakes:
                if not takes_parameters_of(self.lesson.mistakes[name], self.pipeline.step(task.step)):
                    continue
                alternative = _primary_or_self(self._alternative_value(task, where, params, name))
                if not isinstance(alternative, np.ndarray) or alternative.shape != got.shape:
                    continue
                scale = float(np.abs(alternative).max()) if alternative.size else 1.0
                if np.allclose(got, alternative, rtol=1e-4, atol=1e-6 * scale):  # a shape the reference lacks
                    return messages.hints_text([Hint(name, self._mistake_text(name))])
        return messages.structure_hint(got, expected)

    def _alternative_value(self, task: Task, where: tuple[str, int], params: dict[str, Any],
                           name: str) -> Any:
        """The task step's first output computed by alternative ``name`` (a function of mistakes.py or a
        generic mutant) on the check's inputs, or None where it does not apply or fails."""
        run = self._step_run(task, where, params, student=False, mistake=name)
        first = self.pipeline.step(task.step).writes[0]
        return None if run.error or first not in run.outputs else run.outputs[first]

    def _signature_problem(self, task: Task) -> str | None:
        functions = self.submission.functions()
        if functions is None or self.load_failure is not None:
            return None
        expected = parameters_of_spec(self.pipeline.step(task.step))
        got = functions.get(task.step)
        if got is None:
            others = sorted(functions)
            return (f"Your file defines no function {task.step!r}"
                    + (f" (it defines {others}); keep the name from starter.py" if others else "")
                    + f". Expected: def {task.signature}")
        if got.get("varargs"):
            return None
        if len(got["positional"]) != len(expected.positional) or set(got["keyword"]) != set(expected.keyword):
            keyword = ["*", *got["keyword"]] if got["keyword"] else []
            shown = "(" + ", ".join([*got["positional"], *keyword]) + ")"
            return (f"Your {task.step}{shown} does not match the signature the pipeline calls: "
                    f"def {task.signature} (keep the parameters of starter.py, including the keyword-only "
                    f"ones)")
        return None


class _Proxy:
    """The override handed to :meth:`Session.run_plan`: proxies the call to the sandboxed (or reference)
    function."""

    def __init__(self, grader: Grader, task: Task, spec: StepSpec) -> None:
        self.grader, self.task, self.spec = grader, task, spec
        self.printed = ""
        self.violations: tuple[str, ...] = ()
        self.flooded = 0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        try:
            result = self.grader.submission.call(self.spec, args, kwargs, self.grader.deadline)
        except SubmissionFailure as failure:
            self.printed, self.violations = failure.printed, failure.violations
            raise
        self.printed, self.violations, self.flooded = result.printed, result.violations, result.flooded
        return result.value


#: Output mutants the generic hints recognise with a detector of their own (any scale, any order).
_DETECTED_DIRECTLY = ("transposed", "inverse", "negated", "scaled", "reversed", "float32")


def _primary_or_self(value: Any) -> Any:
    """A typed value's first array (what the checks compare), else the value."""
    try:
        return mutants_module.primary_array(value)[0]
    except mutants_module.NotApplicable:
        return value


def takes_parameters_of(function: Callable[..., Any], spec: StepSpec) -> bool:
    """Whether a function of mistakes.py has the step's parameters (it is a mistake of that task)."""
    try:
        parameters = list(inspect.signature(function).parameters)
    except (TypeError, ValueError):
        return False
    return parameters == list(inspect.signature(spec.func).parameters)


def _freeze(value: Any) -> Any:
    if isinstance(value, dict):
        return tuple(sorted((k, _freeze(v)) for k, v in value.items()))
    if isinstance(value, (list, tuple)):
        return tuple(_freeze(v) for v in value)
    return value


def _as_run(session: Session) -> StepRun:
    return StepRun(session=session, outputs=dict(session.state))  # every value, for pipeline-stage checks


# --- entry points -------------------------------------------------------------------------------------------
def grade(lesson: Lesson, source: str | None = None, *, reference: bool = False, seed: int | None = None,
          practice: bool = False, limits: Limits | None = None,
          variant_order: Callable[[int], list[int]] | None = None) -> GradeReport:
    """Grade ``source`` (a student's file) or, with ``reference``, the lab's own steps.

    ``seed`` is the assignment's secret seed: the check data (every variant of every dataset) is
    derived from it, so a regrade gives the same score and messages. Without one the run is a
    practice run (``practice=True`` says so explicitly): fresh data, labelled as such in the report.
    ``variant_order`` (tests) changes the order the variants are graded in, which must not matter.
    """
    if not reference and source is None:
        raise LabError("submission", "give the submission's source, or grade the reference")
    if practice and seed is not None:
        raise LabError("seed", "a practice run draws fresh data: give no assignment seed")
    if not reference:
        isolation.check(isolation.default_isolation())  # SandboxUnavailable (HTTP 503, CLI exit 2), not a 0
    limits = limits or lesson.limits
    seeds = draw_seeds(lesson, seed)
    submission: Submission = ReferenceSubmission() if reference else SandboxedSubmission(source or "", limits)
    return Grader(lesson, submission, seeds=seeds, limits=limits, reference=reference, seed=seed,
                  variant_order=variant_order).run()


__all__ = [
    "DataRun",
    "GradeReport",
    "Grader",
    "ReferenceSubmission",
    "SandboxedSubmission",
    "Submission",
    "TestResult",
    "draw_seeds",
    "grade",
]
