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

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "score": round(self.score, 6), "max_score": self.max_score,
                "status": self.status, "output": self.output, "visibility": self.visibility}


@dataclass
class GradeReport:
    """A grading run: its tests and what to write into results.json."""

    lesson: str
    tests: list[TestResult]
    execution_time: float
    output: str
    seeds: dict[str, int] = field(default_factory=dict)
    reference: bool = False

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
                               "reference": self.reference}}


# --- seeds ----------------------------------------------------------------------------------------
def derived_seed(seed: int, name: str, attempt: int = 0) -> int:
    """The seed of check dataset ``name`` under ``--seed``: fixed per (seed, name, attempt), 31 bits."""
    words = [int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode())] + ([attempt] if attempt else [])
    return int(np.random.SeedSequence(words).generate_state(1)[0] & 0x7FFFFFFF)


def reseeder(lesson: Lesson, name: str, seed: int | None) -> Callable[[int], int] | None:
    """How to draw another seed when a dataset cannot be made with the first (fresh or --seed only)."""
    if seed is not None:
        return lambda attempt: derived_seed(seed, name, attempt)
    if lesson.datasets[name].seed == "fresh":
        return lambda attempt: secrets.randbits(31)
    return None  # an instructor's seed is used as given


def draw_seeds(lesson: Lesson, seed: int | None = None, *,
               environ: Mapping[str, str] | None = None) -> dict[str, int]:
    """One seed per check dataset: from ``--seed`` (derived per dataset), the lesson, the environment or
    :mod:`secrets`."""
    variables: Mapping[str, str] = os.environ if environ is None else environ
    seeds = {}
    for name, data in lesson.datasets.items():
        if seed is not None:
            seeds[name] = derived_seed(seed, name)
        elif isinstance(data.seed, int):
            seeds[name] = data.seed
        elif isinstance(data.seed, str) and data.seed.startswith("env:"):
            variable = data.seed[4:]
            text = variables.get(variable)
            if text is None or not text.strip().lstrip("-").isdigit():
                why = "not set" if text is None else "not an integer"
                raise LabError(f"datasets.{name}.seed",
                               f"the instructor's seed is read from ${variable}, which is {why}")
            seeds[name] = int(text)
        else:
            seeds[name] = secrets.randbits(31)
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


class DataRun:
    """One check dataset: a session holding the reference pipeline's run, which every run of a task forks.

    A generator may fail for some seeds (a board that cannot be placed in the image): with a
    fresh or ``--seed`` seed, up to :attr:`ATTEMPTS` seeds are tried (``reseed(attempt)``).
    """

    ATTEMPTS = 5

    def __init__(self, pipeline: Pipeline, data: CheckDataset, seed: int,
                 reseed: Callable[[int], int] | None = None) -> None:
        self.pipeline = pipeline
        self.data = data
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
            options = dict(self.data.options, **({"seed": self.seed} if takes_seed else {}))
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

    def __init__(self, lesson: Lesson, submission: Submission, *, seeds: dict[str, int], limits: Limits,
                 reference: bool = False, seed: int | None = None) -> None:
        self.lesson = lesson
        self.pipeline = lesson.pipeline
        self.submission = submission
        self.limits = limits
        self.reference = reference
        self.data = {name: DataRun(self.pipeline, data, seeds[name], reseeder(lesson, name, seed))
                     for name, data in lesson.datasets.items()}
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
                           output=self._summary(tests, elapsed), seeds=self.seeds, reference=self.reference)

    @property
    def seeds(self) -> dict[str, int]:
        """The seed each dataset was made with (after any retries)."""
        return {name: run.seed for name, run in self.data.items()}

    def _summary(self, tests: list[TestResult], elapsed: float) -> str:
        score, top = sum(t.score for t in tests), sum(t.max_score for t in tests)
        passed = sum(t.status == "passed" for t in tests)
        lines = [f"{self.lesson.title}: {score:g} / {top:g} points ({passed} of {len(tests)} checks passed) "
                 f"in {elapsed:.1f} s."]
        if self.reference:
            lines.append("Graded the lab's own reference implementation.")
        if self.load_failure is not None:
            lines.append(_failure_text(self.load_failure, "your file", self.limits))
        printed = self.submission.printed_outside_calls()
        if printed:
            lines += ["What your file printed when loaded (or outside Python's print):",
                      _truncate(printed, 2000)]
        return "\n".join(lines)

    # --- one check ------------------------------------------------------------------------------------
    def _grade_check(self, task: Task, check: Check, problem: str | None) -> TestResult:
        test = TestResult(name=f"{task.title}: {check.name}", score=0.0, max_score=check.points,
                          status="failed", output="", visibility=check.visibility, task=task.name)
        header = f"Check: {check.name}\nData: {self.lesson.datasets[check.dataset].describe()}"
        if check.params:
            header += f"\nControls of {task.step}: {_format_params(check.params)}"
        try:
            body, passed = self._check_body(task, check, problem)
        except LabError as exc:  # the lesson's own data or reference failed: say so, never crash
            body, passed = f"Not graded: {exc.reason}", False
        except Exception as exc:  # a bug in the lab: the other checks still run, the student is told
            log.exception("grading check %r of %s failed", check.name, self.lesson.id)
            body = (f"Not graded: the grader itself failed on this check ({type(exc).__name__}: {exc}); "
                    "this is a bug in the lab, not in your code: tell your instructor")
            passed = False
        if passed:
            test.score, test.status = check.points, "passed"
        test.output = _truncate(f"{header}\n{body}", MAX_TEST_OUTPUT)
        return test

    def _check_body(self, task: Task, check: Check, problem: str | None) -> tuple[str, bool]:
        if self.load_failure is not None:
            return _failure_text(self.load_failure, "your file", self.limits), False
        if problem:
            return problem, False
        if task.name in self.broken:
            return f"Not run: {self.broken[task.name]}", False
        if time.monotonic() >= self.deadline:
            return (f"Not run: grading stopped after its time limit of {self.limits.total_timeout_s:g} s "
                    "(earlier calls of your code took that long)"), False
        params = {**self.data[check.dataset].params(task.step), **check.params}
        reference = self._step_run(task, check.dataset, params, student=False)
        if reference.error:
            raise LabError("reference", f"the reference {task.step} failed on the check data "
                                        f"({reference.error}); this is a problem of the lesson")
        student = self._step_run(task, check.dataset, params, student=True)
        printed = (f"\nWhat your code printed:\n{_truncate(student.printed, 2000)}" if student.printed.strip()
                   else "")
        if student.failure is not None or student.error:
            text = (_failure_text(student.failure, f"{task.step}()", self.limits) if student.failure
                    else student.error)
            return text + printed, False
        if student.flooded:
            return (f"{task.step}() printed {student.flooded} characters more than the "
                    f"{self.limits.output_kb:g} KB a call may print: remove your debugging "
                    f"prints.{printed}"), False
        check_stage = self._output_body if check.stage == "output" else self._pipeline_body
        body, passed = check_stage(task, check, student, reference, params)
        return body + printed, passed

    def _output_body(self, task: Task, check: Check, student: StepRun, reference: StepRun,
                     params: dict[str, Any]) -> tuple[str, bool]:
        """Stage ``output``: the step's value against the reference's on the same inputs."""
        value_name = check.value or self.pipeline.step(task.step).writes[0]
        got, expected = self._values(student, reference, value_name, "your")
        if isinstance(got, str):
            return got, False
        problem = checks_module.structure_problem(got, expected, what=f"{task.step}'s {value_name}")
        if problem:
            return f"Your function returned a value of the wrong form: {problem}.", False
        outcome = self._compare(check, got, expected)
        hints = [] if outcome.passed else self._hints(task, check, student, reference, params, got, expected)
        return _outcome_text(outcome, f"{value_name}", hints), outcome.passed

    def _pipeline_body(self, task: Task, check: Check, student: StepRun, reference: StepRun,
                       params: dict[str, Any]) -> tuple[str, bool]:
        """Stage ``pipeline``: what ``until`` needs run on the student's output; a metric or value
        compared."""
        first = self.pipeline.step(task.step).writes[0]
        got_out, expected_out = student.outputs.get(first), reference.outputs.get(first)
        problem = checks_module.structure_problem(got_out, expected_out, what=f"{task.step}'s {first}")
        if problem:
            return ("The rest of the pipeline was not run: your function returned a value of the wrong "
                    f"form: {problem}."), False
        until = check.until or self.pipeline.steps[-1].name
        student_after = self._downstream(student, until)
        if isinstance(student_after, str):
            hints = self._hints(task, check, student, reference, params, got_out, expected_out)
            return (f"The rest of the pipeline failed on your output: {student_after}"
                    + "".join(f"\nHint: {h}" for h in hints)), False
        reference_after = self._downstream(reference, until)
        if isinstance(reference_after, str):
            raise LabError("reference", f"the reference pipeline failed after {task.step}: {reference_after}")
        if check.metric is not None:
            got, expected = student_after.metric(check.metric), reference_after.metric(check.metric)
            if got is None or expected is None:
                raise LabError("metric", f"no step up to {until!r} reports metric {check.metric!r}")
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
                 else self._hints(task, check, student, reference, params, got_out, expected_out))
        return _outcome_text(outcome, what, hints), outcome.passed

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
    def _step_run(self, task: Task, dataset: str, params: dict[str, Any], *, student: bool,
                  mistake: str | None = None) -> StepRun:
        """Run the task's step on ``dataset``: the student's code, the reference, or (``mistake``) a function
        of the lesson's ``mistakes.py``, on a fork of the dataset's reference run."""
        key = (task.step, dataset, _freeze(params), mistake)
        cache = self.student_runs if student else self.reference_runs
        if key in cache:
            return cache[key]
        data = self.data[dataset]
        session = data.reference(task.step).fork()
        spec = self.pipeline.step(task.step)
        run = StepRun(step=task.step, session=session, params=data.controls(task.step, params))
        proxy = _Proxy(self, task, spec) if student else None
        override = proxy or (self.lesson.mistakes[mistake] if mistake else None)
        try:
            records = session.run_plan(session.plan(task.step, run.params), run.params,
                                       overrides={task.step: override} if override else None)
            run.record = records[-1]
            run.outputs = {name: session.state[name] for name in spec.writes if name in session.state}
        except StepFailed as exc:
            cause = exc.__cause__
            if isinstance(cause, SubmissionFailure):
                run.failure = cause
                if cause.kind in FATAL_KINDS:
                    self.broken[task.name] = (f"{task.step}() failed on an earlier check: "
                                              f"{_failure_kind_text(cause)}")
            else:
                run.error = f"{task.step}() failed: {exc.reason}" if student else exc.reason
        except LabError as exc:  # the runner refused the returned value (type, NaN)
            run.error = (f"Your function returned a value of the wrong form: {exc.reason}"
                         + _nan_hint(exc.reason)) if student else str(exc)
        if proxy is not None:
            run.printed, run.violations, run.flooded = proxy.printed, proxy.violations, proxy.flooded
        cache[key] = run
        return run

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

    # --- hints --------------------------------------------------------------------------------------------
    def _hints(self, task: Task, check: Check, student: StepRun, reference: StepRun, params: dict[str, Any],
               got: Any, expected: Any) -> list[str]:
        found: list[str] = []
        if check.stage != "output":
            first = self.pipeline.step(task.step).writes[0]
            got, expected = student.outputs.get(first), reference.outputs.get(first)
        try:
            got_array, expected_array = checks_module.as_compared(got), checks_module.as_compared(expected)
        except (TypeError, ValueError):
            return found
        if got_array.shape != expected_array.shape:
            return found
        for rule in check.hints:
            options = dict(rule.options)
            if rule.when in ("same_as_reference_with", "same_as_mistake"):
                alternative = self._step_run(task, check.dataset, {**params, **options.get("params", {})},
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
                    outcome = compare(got_array, checks_module.as_compared(alternative.outputs[first]),
                                      **compare_options)
                except (TypeError, ValueError):
                    continue
                which = ({"mistake": options["mistake"]} if rule.when == "same_as_mistake"
                         else {"params": options.get("params", {})})
                options = {"outcome": outcome, **which}
            message = checks_module.detect(rule.when, got_array, expected_array, options)
            if message:
                found.append(rule.say or message)
        return found

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


# --- messages ---------------------------------------------------------------------------------------------
def _failure_kind_text(failure: SubmissionFailure) -> str:
    return {"timeout": "it did not return in time", "cpu": "it used up its CPU time",
            "crashed": "the process running it died", "load": "the file could not be loaded"}.get(
        failure.kind, failure.kind)


def _failure_text(failure: SubmissionFailure | None, what: str, limits: Limits) -> str:
    if failure is None:
        return ""
    if failure.kind == "raised":
        if failure.type_name == "NotImplementedError":
            text = (f"{what} is not implemented yet: it raised NotImplementedError. Replace the "
                    f"`raise NotImplementedError` in starter.py with your code.")
        else:
            text = f"{what} raised {failure.type_name}: {failure.message}"
            hint = _exception_hint(failure)
            if hint:
                text += f"\nHint: {hint}"
        if failure.traceback and failure.type_name != "NotImplementedError":
            text += f"\n{failure.traceback}"
        return text
    if failure.kind == "blocked":
        tried = f" (it tried: {'; '.join(failure.violations)})" if failure.violations else ""
        return (f"{what} tried something submissions may not do{tried}: {failure.message}\n"
                f"Submissions may use numpy, scipy and cv2 and the files in their own directory only.")
    if failure.kind == "memory":
        detail = f": {failure.message}" if failure.message else ""
        return (f"{what} ran out of memory{detail}. A submission may allocate {limits.memory_mb:g} MB; keep "
                f"arrays the size of the inputs.\n{failure.traceback}")
    if failure.kind == "load" and failure.traceback:
        return f"{failure.message}\n{failure.traceback}"
    return failure.message


def _exception_hint(failure: SubmissionFailure) -> str:
    message = failure.message
    if failure.type_name == "LinAlgError" and "SVD did not converge" in message:
        return "the matrix you decompose contains NaN or infinite entries (a division by zero earlier?)"
    if failure.type_name == "ValueError" and ("could not broadcast" in message or "shapes" in message):
        return "array shapes do not match: print the shapes of the arrays on the failing line"
    if failure.type_name == "IndexError":
        return "an index is out of range: check the shapes of the inputs (they are in the docstring)"
    if failure.type_name == "TypeError" and "argument" in message:
        return "the pipeline calls your function with the parameters of starter.py: keep them unchanged"
    return ""


def _nan_hint(reason: str) -> str:
    if "NaN" in reason:
        return " (a division by zero, or the square root of a negative number?)"
    return ""


def _outcome_text(outcome: checks_module.Outcome, what: str, hints: list[str]) -> str:
    text = f"{'Passed' if outcome.passed else 'Failed'}: {what}: {outcome.message()}"
    for hint in dict.fromkeys(hints):
        text += f"\nHint: {hint}"
    return text


def _format_params(params: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v!r}" for k, v in params.items())


def _truncate(text: str, limit: int) -> str:
    if len(text) <= limit:
        return text
    return text[:limit] + f"\n... ({len(text) - limit} more characters not shown)"


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
          limits: Limits | None = None) -> GradeReport:
    """Grade ``source`` (a student's file) or, with ``reference``, the lab's own steps."""
    if not reference and source is None:
        raise LabError("submission", "give the submission's source, or grade the reference")
    if not reference:
        isolation.check(isolation.default_isolation())  # SandboxUnavailable (HTTP 503, CLI exit 2), not a 0
    limits = limits or lesson.limits
    seeds = draw_seeds(lesson, seed)
    submission: Submission = ReferenceSubmission() if reference else SandboxedSubmission(source or "", limits)
    return Grader(lesson, submission, seeds=seeds, limits=limits, reference=reference, seed=seed).run()


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
