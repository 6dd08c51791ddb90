"""The viewer's lesson mode, lesson side: a student's file in a sandbox, as overrides of a live session.

The viewer shows a lesson's text beside its pipeline; a student loads their ``starter.py`` (filled
in) into the session and sees their step's output next to the reference's::

    code = StudentCode(lesson, source)            # starts the sandbox, loads the file
    code.tasks()                                  # {step: problem or ""} for the lesson's tasks
    record = session.run(step, params, override=code.override(step))   # the student's step in place
    side = code.compare(session, step, params)    # reference and student outputs on the same inputs
    side.reference["homographies"], side.student["homographies"], side.message
    code.close()

:meth:`StudentCode.override` returns a callable with the step's signature that proxies each call
to the sandboxed child (inputs pickled through a pipe, never the reference's output or the
truth); a failure there (an exception, a timeout, something the sandbox refuses) is raised as
:class:`StudentCodeFailed`, a :class:`~lab.core.errors.StepFailed` whose reason is the message a
student needs, so :meth:`Session.run` records it and leaves the state as it was.
:meth:`StudentCode.compare` runs both on forks of the session (:meth:`Session.fork`) and never touches it.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Any

from lab.core.errors import LabError, StepFailed, UnknownName
from lab.core.pipeline import Session
from lab.lessons import checks as checks_module
from lab.lessons.format import Lesson, Limits, parameters_of_spec
from lab.lessons.sandbox import Sandbox, SubmissionFailure


class StudentCodeFailed(StepFailed):
    """The student's function failed (raised, timed out, was refused by the sandbox) or could not be
    loaded."""


@dataclass
class SideBySide:
    """One step run by the reference and by the student on the same inputs."""

    step: str
    reference: dict[str, Any]
    student: dict[str, Any] = field(default_factory=dict)
    passed: bool | None = None  # None: the student's step failed, see message
    message: str = ""
    printed: str = ""


class StudentCode:
    """A student's file loaded in a sandbox for a live session (one child process, reused for every call)."""

    def __init__(self, lesson: Lesson, source: str, *, limits: Limits | None = None) -> None:
        self.lesson = lesson
        self.limits = limits or lesson.limits
        self.sandbox = Sandbox(source, limits=self.limits)
        self._lock = threading.Lock()
        self.printed = ""
        try:
            self.sandbox.start()
        except SubmissionFailure as failure:
            self.sandbox.close()
            raise StudentCodeFailed("submission", _failure_message(failure)) from None

    def __enter__(self) -> StudentCode:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        with self._lock:
            self.sandbox.close()

    def tasks(self) -> dict[str, str]:
        """For each task step: "" when the file defines it with the right parameters, else the problem."""
        found: dict[str, str] = {}
        for task in self.lesson.tasks:
            expected = parameters_of_spec(self.lesson.pipeline.step(task.step))
            got = self.sandbox.functions.get(task.step)
            if got is None:
                found[task.step] = f"your file defines no function {task.step!r}"
            elif not got.get("varargs") and (len(got["positional"]) != len(expected.positional)
                                              or set(got["keyword"]) != set(expected.keyword)):
                found[task.step] = f"{task.step} must have the parameters of starter.py: def {task.signature}"
            else:
                found[task.step] = ""
        return found

    def override(self, step: str) -> Callable[..., Any]:
        """A function with ``step``'s signature that runs the student's version in the sandbox."""
        if step not in {t.step for t in self.lesson.tasks}:
            raise UnknownName("step", f"lesson {self.lesson.id!r} does not ask for {step!r}; its tasks are "
                                      f"{[t.step for t in self.lesson.tasks]}")
        problem = self.tasks()[step]
        if problem:
            raise StudentCodeFailed(step, problem)

        def student_step(*args: Any, **kwargs: Any) -> Any:
            with self._lock:
                try:
                    result = self.sandbox.call(step, args, kwargs)
                except SubmissionFailure as failure:
                    self.printed = failure.printed
                    raise StudentCodeFailed(step, _failure_message(failure)) from None
            self.printed = result.printed
            return result.value

        student_step.__name__ = step
        return student_step

    def compare(self, session: Session, step: str, params: dict[str, Any] | None = None) -> SideBySide:
        """Run ``step`` by the reference and by the student on forks of ``session`` (left untouched), each on
        the inputs the session holds now."""
        spec = session.pipeline.step(step)
        with session.lock:  # wait for a step running there, then fork one state twice
            reference_session, student_session = session.fork(), session.fork()
        reference_session.run(step, params)
        reference = {name: reference_session.state[name] for name in spec.writes}
        side = SideBySide(step=step, reference=reference)
        try:
            student_session.run(step, params, override=self.override(step))
        except LabError as exc:
            side.message, side.printed = exc.reason, self.printed
            return side
        side.student = {name: student_session.state[name] for name in spec.writes}
        side.printed = self.printed
        first = spec.writes[0]
        problem = checks_module.structure_problem(side.student[first], reference[first], what=first)
        if problem:
            side.passed, side.message = False, problem
            return side
        check = next((c for t in self.lesson.tasks if t.step == step
                      for c in t.checks if c.stage == "output"), None)
        compare = checks_module.COMPARISONS[check.compare] if check else checks_module.allclose
        outcome = compare(checks_module.as_compared(side.student[first]),
                          checks_module.as_compared(reference[first]),
                          **(check.options if check else {}))
        side.passed, side.message = outcome.passed, outcome.message()
        return side


def _failure_message(failure: SubmissionFailure) -> str:
    text = failure.message
    if failure.kind == "raised" and failure.type_name:
        text = f"{failure.type_name}: {failure.message}"
        if failure.type_name == "NotImplementedError":
            text = "not implemented yet (it raised NotImplementedError)"
    if failure.traceback and failure.type_name != "NotImplementedError":
        text += "\n" + failure.traceback
    return text


__all__ = ["SideBySide", "StudentCode", "StudentCodeFailed"]
