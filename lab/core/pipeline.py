"""Pipelines and sessions: run steps on a state, track history, invalidate what lies downstream.

A :class:`Pipeline` is a module's ordered steps plus the datasets that seed its state and the
evaluation functions that compare values with ground truth. A :class:`Session` is one pipeline's
state, its run history and a lock. Every front end (viewer, REST, CLI, grader) runs steps through
:meth:`Session.run`, so they all behave the same.
"""

from __future__ import annotations

import inspect
import threading
import time
import typing
import uuid
import zlib
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from lab.core.errors import (Cancelled, InvalidControl, InvalidValue, LabError, MissingInput, SessionBusy,
                             StepFailed, UnknownName)
from lab.core.step import (Control, Progress, StepSpec, _control_from, _docstring_params, coerce_controls,
                           describe_step, result_to_values)
from lab.core.values import value_nbytes


@dataclass(frozen=True)
class Loaded:
    """What a dataset loader returns: the initial ``state`` and, separately, its ``truth`` (may be empty)."""

    state: dict[str, Any]
    truth: dict[str, Any] = field(default_factory=dict)
    description: str = ""


@dataclass(frozen=True)
class DatasetSpec:
    """A named way to seed a session. Its keyword-only parameters are options, like step controls.

    A dataset with ``takes_path`` True loads a user's folder or file, given as option ``path``.
    """

    name: str
    loader: Callable[..., Loaded]
    summary: str
    options: tuple[Control, ...]
    takes_path: bool = False

    @classmethod
    def of(cls, loader: Callable[..., Loaded], *, name: str | None = None) -> DatasetSpec:
        signature = inspect.signature(loader)
        hints = typing.get_type_hints(loader, include_extras=True)
        doc = inspect.getdoc(loader) or ""
        described = _docstring_params(doc)
        options = tuple(_control_from(p.name, hints.get(p.name), p.default, described.get(p.name, ""))
                        for p in signature.parameters.values() if p.kind == p.KEYWORD_ONLY)
        return cls(name=name or loader.__name__, loader=loader,
                   summary=doc.split("\n\n", 1)[0].replace("\n", " "), options=options,
                   takes_path=any(o.name == "path" for o in options))

    def coerce_options(self, options: Mapping[str, Any] | None) -> dict[str, Any]:
        """Defaults overridden by ``options``, checked as step controls are (:func:`coerce_controls`).

        Raises :class:`InvalidControl` naming the option as ``options.<name>``.
        """
        try:
            return coerce_controls(self.options, options, owner=f"dataset {self.name!r}", noun="option")
        except InvalidControl as exc:
            raise InvalidControl(f"options.{exc.field}", exc.reason) from None

    def load(self, options: Mapping[str, Any] | None = None) -> Loaded:
        return self.loader(**self.coerce_options(options))

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "summary": self.summary, "takes_path": self.takes_path,
                "options": {"type": "object", "properties": {o.name: o.json_schema() for o in self.options},
                            "additionalProperties": False}}


#: ``evaluate(state, truth) -> metrics``, run after a step: compares its outputs with the truth
#: (``truth`` is empty on real data: return only what can be measured without it, e.g. residuals).
Evaluation = Callable[[dict[str, Any], dict[str, Any]], dict[str, float]]


#: Why a step is in a :class:`Plan`: it is the target; its outputs are missing; it ran with other
#: controls than the ones asked for; it reads what a planned step will rewrite.
PlanReason = Literal["target", "missing", "stale", "dependant"]


@dataclass(frozen=True)
class Plan:
    """The steps a run will execute, in pipeline order, each with the reason it runs.

    Made by :meth:`Pipeline.plan` (the one place that decides what runs) and executed by
    :meth:`Session.run_plan`; the viewer, REST, the CLI and the grader all go through both.
    """

    steps: tuple[str, ...]
    reasons: Mapping[str, PlanReason]
    target: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.steps)

    def to_json(self) -> dict[str, Any]:
        return {"steps": list(self.steps), "reasons": dict(self.reasons), "target": list(self.target)}


@dataclass(frozen=True)
class Export:
    """A file format a pipeline can write from a session's state (``vision-lab export``, REST).

    ``reads`` are the state names it needs (a run plans their producers); ``write(state, metrics,
    out)`` writes the file at ``out`` and returns the path written. ``metrics`` maps step names to
    the metrics of their last run.
    """

    format: str
    summary: str
    reads: tuple[str, ...]
    write: Callable[[Mapping[str, Any], Mapping[str, Mapping[str, Any]], Path], Path]


@dataclass(frozen=True)
class Pipeline:
    """A teaching module: ordered steps, datasets (the first is the default) and evaluations.

    ``exports`` maps a format name to the :class:`Export` that writes it; ``views`` are the state
    names the viewer's interactions may read by name (checked by a contract test against what the
    steps and datasets provide, so a rename fails a test instead of a browser).
    """

    name: str
    title: str
    summary: str
    steps: tuple[StepSpec, ...]
    datasets: tuple[DatasetSpec, ...]
    evaluations: dict[str, Evaluation] = field(default_factory=dict)
    exports: Mapping[str, Export] = field(default_factory=dict)
    views: frozenset[str] = frozenset()

    @classmethod
    def build(cls, *, name: str, title: str, summary: str, steps: Iterable[Callable[..., Any]],
              datasets: Iterable[Callable[..., Loaded]], evaluations: dict[str, Evaluation] | None = None,
              exports: Iterable[Export] = (), views: Iterable[str] = ()) -> Pipeline:
        specs = tuple(describe_step(f) for f in steps)
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise TypeError(f"pipeline {name}: duplicate step names {names}")
        by_format = {e.format: e for e in exports}
        return cls(name=name, title=title, summary=summary, steps=specs,
                   datasets=tuple(DatasetSpec.of(d) for d in datasets), evaluations=dict(evaluations or {}),
                   exports=by_format, views=frozenset(views))

    def export(self, fmt: str) -> Export:
        """The :class:`Export` of format ``fmt``; :class:`UnknownName` lists the formats there are."""
        if fmt not in self.exports:
            raise UnknownName("format", f"module {self.name!r} exports no {fmt!r}; "
                                        f"its formats are {sorted(self.exports)}")
        return self.exports[fmt]

    def step(self, name: str) -> StepSpec:
        for spec in self.steps:
            if spec.name == name:
                return spec
        raise UnknownName("step", f"module {self.name!r} has no step {name!r}; "
                                  f"steps are {[s.name for s in self.steps]}")

    def dataset(self, name: str | None) -> DatasetSpec:
        if name is None:
            return self.datasets[0]
        for spec in self.datasets:
            if spec.name == name:
                return spec
        raise UnknownName("dataset", f"module {self.name!r} has no dataset {name!r}; "
                                     f"datasets are {[d.name for d in self.datasets]}")

    def producer(self, value_name: str, *, before: str | None = None) -> StepSpec | None:
        """The step that writes ``value_name``: the first in the pipeline, or with ``before`` the last
        one ahead of that step (the one whose output that step reads). None for a dataset value."""
        if before is None:
            return next((spec for spec in self.steps if value_name in spec.writes), None)
        found = None
        for spec in self.steps:
            if spec.name == before:
                return found
            if value_name in spec.writes:
                found = spec
        raise UnknownName("step", f"module {self.name!r} has no step {before!r}")

    def plan(self, target: str | Iterable[str] | None, available: Collection[str], *,
             stale: Collection[str] = (), dependants: bool = False,
             ran: Collection[str] | None = None) -> Plan:
        """The steps to run, in pipeline order, to bring ``target`` up to date from data flow.

        ``available`` are the state names present; ``stale`` the steps whose outputs are out of date
        (they ran with other controls; the steps downstream of them are out of date too); ``ran`` the
        steps whose outputs are present, when known (a session knows; else a step has run when all it
        writes is present, which a second writer of the same name can fake).

        With a target (a step name or several) the plan holds the targets and, recursively, the producer
        of every input that is missing, stale or rewritten by a planned step — nothing else: ``quilt``,
        which reads only ``sample``, plans only itself. With ``target`` None ("Run all") it holds every
        step whose outputs are missing or stale and every step that reads what those rewrite.
        ``dependants`` adds the steps downstream of the plan whose outputs exist (what the run would
        otherwise drop), so a changed step re-runs what depends on it.

        The producer of an input is the last step ahead of the reader that writes it
        (:meth:`producer` with ``before``); an input no step writes is the dataset's.
        """
        have = set(available)
        stale_set = {self.step(name).name for name in stale}
        if ran is None:
            ran_set = {s.name for s in self.steps if s.writes and have.issuperset(s.writes)}
        else:
            ran_set = set(ran)
        stale_writes = [w for name in stale_set for w in self.step(name).writes]
        stale_set |= {s.name for s in self.downstream(stale_writes)} & ran_set
        reasons: dict[str, PlanReason] = {}

        def out_of_date(spec: StepSpec) -> PlanReason | None:
            if spec.name in stale_set:
                return "stale"
            if not spec.writes or not have.issuperset(spec.writes):
                return "missing"
            return None

        if target is None:
            targets: tuple[str, ...] = ()
            for spec in self.steps:
                reason = out_of_date(spec)
                if reason is None and self._reads_rewritten(spec, reasons):
                    reason = "dependant"
                if reason is not None:
                    reasons[spec.name] = reason
        else:
            targets = (target,) if isinstance(target, str) else tuple(target)
            for name in targets:
                reasons[self.step(name).name] = "target"
            changed = True
            while changed:  # grow the plan backwards along data flow until nothing more is needed
                changed = False
                for spec in [s for s in self.steps if s.name in reasons]:
                    for value in spec.reads:
                        producer = self.producer(value, before=spec.name)
                        if producer is None or producer.name in reasons:
                            continue
                        reason = out_of_date(producer) if value in have else "missing"
                        if reason is None and self._reads_rewritten(producer, reasons):
                            reason = "dependant"
                        if reason is not None:
                            reasons[producer.name] = reason
                            changed = True
        if dependants:
            for spec in self.steps:
                if spec.name not in reasons and spec.name in ran_set and self._reads_rewritten(spec, reasons):
                    reasons[spec.name] = "dependant"
        order = tuple(s.name for s in self.steps if s.name in reasons)
        return Plan(steps=order, reasons={name: reasons[name] for name in order}, target=targets)

    def upstream(self, target: str) -> tuple[str, ...]:
        """Every step ``target`` can need, in order, itself included: its plan on an empty state."""
        return self.plan(target, available=()).steps

    def _reads_rewritten(self, spec: StepSpec, planned: Mapping[str, Any]) -> bool:
        """Whether ``spec`` reads a value that a planned step ahead of it writes."""
        for value in spec.reads:
            producer = self.producer(value, before=spec.name)
            if producer is not None and producer.name in planned:
                return True
        return False

    def input_annotation(self, value_name: str) -> Any:
        """The type a state value must have: from a step that reads it, else one that writes it."""
        for spec in self.steps:
            for inp in spec.inputs:
                if inp.name == value_name:
                    return inp.annotation
        for spec in self.steps:
            for out in spec.outputs:
                if out.name == value_name and not out.is_metric:
                    return out.annotation
        return inspect.Parameter.empty

    def downstream(self, names: Iterable[str]) -> list[StepSpec]:
        """Steps that read any of ``names``, directly or through other steps, in pipeline order."""
        dirty = set(names)
        found: list[StepSpec] = []
        for spec in self.steps:
            if dirty.intersection(spec.reads):
                found.append(spec)
                dirty.update(spec.writes)
        return found

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "title": self.title, "summary": self.summary,
                "steps": [s.describe() for s in self.steps],
                "datasets": [d.describe() for d in self.datasets],
                "exports": [{"format": e.format, "summary": e.summary, "reads": list(e.reads)}
                            for e in self.exports.values()]}


#: How a run ended: its outputs were written, it raised, or the user stopped it.
RunStatus = Literal["ok", "failed", "cancelled"]

#: What :meth:`Session.step_status` says of a step: its outputs exist and match the controls asked
#: for; they exist but other controls were asked for (or it reads a stale step's outputs); its
#: inputs exist; some input is missing.
StepStatus = Literal["done", "stale", "ready", "blocked"]


@dataclass(frozen=True)
class RunRecord:
    """One entry of a session's history: what ran, with which controls, how long, and its metrics."""

    step: str
    params: dict[str, Any]
    seed: int
    seconds: float
    metrics: dict[str, Any]
    status: RunStatus
    error: str = ""
    warnings: tuple[str, ...] = ()
    replaced: bool = False
    started: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {"step": self.step, "params": _jsonable(self.params), "seed": self.seed,
                "seconds": round(self.seconds, 6), "metrics": _jsonable(self.metrics), "status": self.status,
                "error": self.error, "warnings": list(self.warnings), "replaced": self.replaced,
                "started": self.started}


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


ProgressCallback = Callable[[str, Progress], None]
#: Called after each step of a plan with the step's record (the viewer redraws, REST updates a run).
StepCallback = Callable[[RunRecord], None]
#: Params of several steps: ``{step name: {control: value}}``.
StepParams = Mapping[str, Mapping[str, Any]]


class Session:
    """One pipeline's state, its history and a lock. Thread-safe: one step runs at a time.

    ``overrides`` maps step names to functions with the same signature (a student's code, for the
    grader and the viewer's lesson mode); they run in place of the reference step.
    """

    def __init__(self, pipeline: Pipeline, loaded: Loaded, *, dataset: str,
                 options: Mapping[str, Any] | None = None, seed: int = 0,
                 session_id: str | None = None) -> None:
        self.id = session_id or uuid.uuid4().hex[:12]
        self.pipeline = pipeline
        self.dataset = dataset
        self.options = dict(options or {})
        self.seed = int(seed)
        self.state: dict[str, Any] = dict(loaded.state)
        self.truth: dict[str, Any] = dict(loaded.truth)
        self.description = loaded.description
        self.history: list[RunRecord] = []
        self.metrics: dict[str, dict[str, Any]] = {}
        self.lock = threading.RLock()
        self.running: str | None = None
        self.cancel_event = threading.Event()
        self.created = time.time()
        self.last_used = time.time()
        self.listeners: list[ProgressCallback] = []
        self.version = 0  # bumped on every change of state, for viewers to notice
        #: The controls each step's outputs in ``state`` were computed with (dropped with them).
        self.ran_with: dict[str, dict[str, Any]] = {}

    # --- reading -------------------------------------------------------------------------------
    def get(self, name: str) -> Any:
        if name not in self.state:
            producer = self.pipeline.producer(name)
            hint = f"; run step {producer.name!r} first" if producer else ""
            raise UnknownName("value", f"session has no value {name!r}{hint}; "
                                       f"values are {sorted(self.state)}")
        return self.state[name]

    def nbytes(self) -> int:
        return value_nbytes(self.state)

    def step_status(self, params: StepParams | None = None) -> dict[str, StepStatus]:
        """:data:`StepStatus` of every step; ``params`` are the controls a front end shows (stale when
        a done step ran with others, and so is every done step downstream of it)."""
        stale = self.stale(params) if params else set()
        status: dict[str, StepStatus] = {}
        for spec in self.pipeline.steps:
            if spec.writes and all(w in self.state for w in spec.writes):
                status[spec.name] = "stale" if spec.name in stale else "done"
            elif all(i.optional or i.name in self.state for i in spec.inputs):
                status[spec.name] = "ready"
            else:
                status[spec.name] = "blocked"
        return status

    def stale(self, params: StepParams | None) -> set[str]:
        """Steps whose outputs exist but were computed with other controls than ``params`` asks for,
        and the steps downstream of them that have outputs. A step ``params`` does not name is not
        compared (it keeps what it ran with); invalid controls raise :class:`InvalidControl`."""
        changed: list[str] = []
        for name, controls in (params or {}).items():
            spec = self.pipeline.step(name)
            if name in self.ran_with and spec.coerce_controls(controls) != self.ran_with[name]:
                changed.append(name)
        stale = set(changed)
        for spec in self.pipeline.downstream(w for name in changed for w in self.pipeline.step(name).writes):
            if spec.name in self.ran_with:
                stale.add(spec.name)
        return stale

    def plan(self, target: str | Iterable[str] | None = None, params: StepParams | None = None, *,
             dependants: bool = False) -> Plan:
        """:meth:`Pipeline.plan` on this session's state, with the steps ``params`` makes stale."""
        return self.pipeline.plan(target, self.state.keys(), stale=self.stale(params), dependants=dependants,
                                  ran=self.ran_with.keys())

    def summary(self) -> dict[str, Any]:
        return {"id": self.id, "module": self.pipeline.name, "dataset": self.dataset,
                "options": _jsonable(self.options), "seed": self.seed, "running": self.running,
                "values": {name: type(v).__name__ for name, v in sorted(self.state.items())},
                "steps": self.step_status(), "history": [r.to_json() for r in self.history],
                "metrics": _jsonable(self.metrics), "has_truth": bool(self.truth), "version": self.version}

    # --- writing -------------------------------------------------------------------------------
    def put(self, name: str, value: Any) -> list[str]:
        """Set an input value (an upload) and drop everything computed from the old one.

        Replacing a dataset value that no step produces (the photos, the board) also drops the
        dataset's ground truth, which no longer describes the data.
        """
        with self._exclusive():
            self._invalidate([name])
            if self.pipeline.producer(name) is None:
                self.truth = {}
            self.state[name] = value
            self.version += 1
            return [s.name for s in self.pipeline.downstream([name])]

    def reset(self, step: str | None = None) -> None:
        """Forget the outputs of ``step`` and everything downstream (all steps when None)."""
        with self._exclusive():
            specs = self.pipeline.steps if step is None else [self.pipeline.step(step)]
            for spec in specs:
                for name in spec.writes:
                    self.state.pop(name, None)
                self.metrics.pop(spec.name, None)
                self.ran_with.pop(spec.name, None)
                self._invalidate(spec.writes)
            self.version += 1

    def _invalidate(self, names: Iterable[str], state: dict[str, Any] | None = None) -> None:
        state = self.state if state is None else state
        for spec in self.pipeline.downstream(names):
            for out in spec.writes:
                state.pop(out, None)
            self.metrics.pop(spec.name, None)
            self.ran_with.pop(spec.name, None)

    def fork(self, *, session_id: str | None = None) -> Session:
        """A new session with a copy of this one's state, truth, history and metrics (values are
        shared, not copied: steps never mutate their inputs). The grader forks the reference run
        before a student's step; the viewer forks to try a change without losing the original."""
        with self._exclusive():
            twin = Session(self.pipeline, Loaded(dict(self.state), dict(self.truth), self.description),
                           dataset=self.dataset, options=self.options, seed=self.seed, session_id=session_id)
            twin.history = list(self.history)
            twin.metrics = {step: dict(values) for step, values in self.metrics.items()}
            twin.ran_with = {step: dict(values) for step, values in self.ran_with.items()}
            return twin

    def _exclusive(self):
        if not self.lock.acquire(blocking=False):
            raise SessionBusy("session", f"step {self.running!r} is running in this session; "
                                         "wait or cancel it")
        session = self

        class _Release:
            def __enter__(self):
                return session

            def __exit__(self, *exc):
                session.lock.release()
                session.last_used = time.time()
                return False

        return _Release()

    def cancel(self) -> bool:
        """Ask the running long step to stop at its next progress snapshot."""
        if self.running is None:
            return False
        self.cancel_event.set()
        return True

    def step_seed(self, step: str) -> int:
        """The seed a step's ``rng`` gets: fixed per (session seed, step), recorded in history."""
        return int(np.random.SeedSequence([self.seed, zlib.crc32(step.encode())]).generate_state(1)[0])

    def run(self, step: str, params: Mapping[str, Any] | None = None, *,
            override: Callable[..., Any] | None = None, on_progress: ProgressCallback | None = None,
            device: str | None = None) -> RunRecord:
        """Run one step on the current state and write its outputs back.

        Controls are checked before anything runs; inputs must exist. On failure the state is
        left exactly as it was and the failure is recorded in history (and raised).
        """
        spec = self.pipeline.step(step)
        controls = spec.coerce_controls(params)
        with self._exclusive():
            args = []
            for inp in spec.inputs:
                if inp.name in self.state:
                    args.append(self.state[inp.name])
                elif inp.optional:
                    args.append(None)
                else:
                    producer = self.pipeline.producer(inp.name)
                    how = (f"run step {producer.name!r} first" if producer
                           else "upload it or pick a dataset that has it")
                    raise MissingInput(inp.name, f"step {step!r} reads {inp.name!r}, "
                                                 f"which does not exist yet: {how}")
            kwargs = dict(controls)
            seed = self.step_seed(step)
            if "rng" in spec.runner_args:
                kwargs["rng"] = np.random.default_rng(seed)
            if "device" in spec.runner_args:
                kwargs["device"] = device or default_device()
            func = override or spec.func
            self.running = step
            self.cancel_event.clear()
            try:
                return self._execute(spec, func, args, kwargs, controls, seed, on_progress,
                                     replaced=override is not None)
            finally:
                self.running = None  # only after the new state (or the failure) is recorded
                self.version += 1

    def _execute(self, spec: StepSpec, func: Callable[..., Any], args: list[Any], kwargs: dict[str, Any],
                 controls: dict[str, Any], seed: int, on_progress: ProgressCallback | None, *,
                 replaced: bool) -> RunRecord:
        step = spec.name
        started = time.time()
        t0 = time.perf_counter()
        try:
            result = func(*args, **kwargs)
            if inspect.isgenerator(result):
                result = self._drive(step, result, on_progress)
            outcome = result_to_values(spec, result)
            values, metrics, warnings = outcome.values, outcome.metrics, outcome.warnings
            for name, value in values.items():
                _check_output(spec, name, value)
        except LabError as exc:
            self.history.append(RunRecord(step, controls, seed, time.perf_counter() - t0, {},
                                          "cancelled" if isinstance(exc, Cancelled) else "failed",
                                          error=str(exc), replaced=replaced, started=started))
            raise
        except Exception as exc:  # a step (or a student's function) failed on this input
            self.history.append(RunRecord(step, controls, seed, time.perf_counter() - t0, {}, "failed",
                                          error=f"{type(exc).__name__}: {exc}", replaced=replaced,
                                          started=started))
            raise StepFailed(step, f"{type(exc).__name__}: {exc}") from exc
        seconds = time.perf_counter() - t0
        state = dict(self.state)  # readers (the viewer's thread) always see a whole state
        self._invalidate(spec.writes, state)
        state.update(values)
        evaluate = self.pipeline.evaluations.get(step)
        if evaluate is not None:  # runs without truth too (real data): it returns what it can
            try:
                metrics.update({k: _jsonable(v) for k, v in evaluate(state, self.truth).items()})
            except Exception as exc:  # an evaluation must never lose a finished result
                warnings += (f"evaluation against the truth failed: {type(exc).__name__}: {exc}",)
        record = RunRecord(step, controls, seed, seconds, metrics, "ok", warnings=warnings,
                           replaced=replaced, started=started)
        self.state = state
        self.metrics[step] = metrics
        self.ran_with[step] = dict(controls)
        self.history.append(record)
        return record

    def _drive(self, step: str, generator, on_progress: ProgressCallback | None) -> Any:
        """Iterate a generator step, forwarding progress; on cancel, :meth:`_stop` it."""
        try:
            while True:
                try:
                    progress = next(generator)
                except StopIteration as stop:
                    return stop.value
                if self.cancel_event.is_set():
                    return self._stop(step, generator)
                if isinstance(progress, Progress):
                    for listener in [on_progress, *self.listeners]:
                        if listener is not None:
                            listener(step, progress)
        finally:
            generator.close()

    @staticmethod
    def _stop(step: str, generator) -> Any:
        """Cancel a generator step: :class:`Cancelled` is thrown in where it yielded. A step that catches it
        and returns (a training loop whose model so far is the result) has that result written as usual,
        its warnings saying it stopped early; one that does not is cancelled and writes nothing."""
        try:
            generator.throw(Cancelled(step, "cancelled by the user"))
        except StopIteration as stop:
            return stop.value
        raise Cancelled(step, "cancelled by the user (the step went on after it was asked to stop)")

    def run_plan(self, plan: Plan, params: StepParams | None = None, *,
                 overrides: Mapping[str, Callable[..., Any]] | None = None,
                 on_start: Callable[[str], None] | None = None, on_step: StepCallback | None = None,
                 should_stop: Callable[[], bool] | None = None, on_progress: ProgressCallback | None = None,
                 device: str | None = None) -> list[RunRecord]:
        """Run the steps of ``plan`` in order, each with its controls from ``params`` (defaults else).

        Every step's controls are checked before the first runs. ``overrides`` replace steps by name
        (a student's function). ``on_start`` gets each step's name before it runs, ``on_step`` its
        record after it ran (failed steps raise instead); ``should_stop`` is asked
        between steps and ends the run early (:class:`Cancelled`). A failing step raises and the
        steps after it do not run; the records of those that ran are in :attr:`history`.
        """
        params = params or {}
        for name in plan.steps:
            self.pipeline.step(name).coerce_controls(params.get(name))
        records: list[RunRecord] = []
        for name in plan.steps:
            if should_stop is not None and should_stop():
                raise Cancelled(name, "cancelled by the user before this step")
            if on_start is not None:
                on_start(name)
            record = self.run(name, params.get(name), override=(overrides or {}).get(name),
                              on_progress=on_progress, device=device)
            records.append(record)
            if on_step is not None:
                on_step(record)
        return records

    def run_until(self, step: str | None, params: StepParams | None = None, **kwargs: Any) -> list[RunRecord]:
        """Plan ``step`` (every step when None) on this state and run the plan (:meth:`run_plan`)."""
        return self.run_plan(self.plan(step, params), params, **kwargs)


def _check_output(spec: StepSpec, name: str, value: Any) -> None:
    """A replaced step (a student's code) must return values of the declared types."""
    for out in spec.outputs:
        if out.name == name and isinstance(out.annotation, type) and out.annotation is not float:
            if not isinstance(value, out.annotation):
                raise InvalidValue(name, f"step {spec.name!r} must return {out.annotation.__name__} "
                                         f"for {name!r}, got {type(value).__name__}")
            if isinstance(value, np.ndarray) and value.dtype.kind == "f" and not np.all(np.isfinite(value)):
                raise InvalidValue(name, f"step {spec.name!r} returned NaN or infinite values in {name!r}")


def default_device() -> str:
    """``cuda`` when PyTorch sees a GPU, else ``cpu`` (imports torch only when asked)."""
    try:
        import torch
    except ImportError:  # pragma: no cover - torch is a dependency
        return "cpu"
    return "cuda" if torch.cuda.is_available() else "cpu"


def open_session(pipeline: Pipeline, dataset: str | None = None, options: dict[str, Any] | None = None, *,
                 seed: int = 0, session_id: str | None = None) -> Session:
    """Load a dataset and make a session on it (the notebook / script entry point)."""
    spec = pipeline.dataset(dataset)
    loaded = spec.load(options)
    return Session(pipeline, loaded, dataset=spec.name, options=options, seed=seed, session_id=session_id)


__all__ = ["DatasetSpec", "Export", "Loaded", "Pipeline", "Plan", "PlanReason", "RunRecord", "RunStatus",
           "Session", "StepParams", "StepStatus", "default_device", "open_session"]
