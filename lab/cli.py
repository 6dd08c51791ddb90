"""The ``vision-lab`` command: serve the lab, list modules, run a pipeline headless, export values.

    vision-lab serve [--host 127.0.0.1] [--port 8000] [--viewer-port 8080] [--no-warmup] [--workers N]
    vision-lab modules [--json]
    vision-lab run MODULE [--dataset NAME|PATH] [--option KEY=VALUE]... [--set STEP.CONTROL=VALUE]...
                          [--until STEP] [--seed N] [--json]
    vision-lab export MODULE --what VALUE --format json|npy|png|ply --out PATH [run options]
    vision-lab export MODULE --format FORMAT --out PATH [run options]   (a module's own format:
                          opencv-yaml of calibration, colmap and transforms-json of sfm; see 'modules')

The CLI is one more front end on :mod:`lab.core` (docs/design.md): it opens a session with
:func:`lab.open_session`'s dataset rules, runs the core's plan (:meth:`lab.core.Session.plan`,
:meth:`lab.core.Session.run_plan`; controls from ``--set``, checked by the step's own schema before
anything runs) and writes values with :mod:`lab.data.exports` or the pipeline's own exports. A
problem with what the user asked for (:class:`lab.core.errors.LabError`, a bad ``--set``, an
unknown name, a missing folder, a step that fails on this input) prints one line
``error: <field>: <reason>`` on stderr and exits with code 2, never a traceback.
"""

import contextlib
import json
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from typer.core import TyperGroup

from lab.core.errors import InvalidControl, InvalidValue, LabError

if TYPE_CHECKING:  # the CLI imports the core lazily: `vision-lab --help` stays fast
    from rich.progress import Progress as ProgressBar
    from rich.progress import ProgressColumn, TaskID
    # typer (>= 0.26) vendors click in a private package: its exception classes are named here for
    # the type checker only; at run time they are found through the public typer.BadParameter.
    from typer._click.exceptions import ClickException, UsageError

    from lab.api.workers import WorkerIdentity
    from lab.core.pipeline import Pipeline, Plan, RunRecord, Session
    from lab.core.step import Control, Progress

#: Exit code for every problem with what the user asked for (as click uses for usage errors).
EXIT_USAGE = 2

#: Formats ``export`` writes any state value in (the codecs'); a module adds its own
#: (``Pipeline.exports``).
EXPORT_FORMATS = ("json", "npy", "png", "ply")


def _click_class(name: str) -> type:
    """Click's exception class ``name``, a base of typer.BadParameter, whether typer vendors click
    (>= 0.26) or uses the package."""
    return next(c for c in typer.BadParameter.__mro__ if c.__name__ == name)


_CLICK_EXCEPTION: "type[ClickException]" = _click_class("ClickException")
_USAGE_ERROR: "type[UsageError]" = _click_class("UsageError")


# --- the pipeline registry (tests inject their own pipelines here) ------------------------------
def module_names() -> tuple[str, ...]:
    """Names of the registered modules, in the order they are listed."""
    from lab.modules import MODULES

    return tuple(MODULES)


def lookup_pipeline(name: str) -> "Pipeline":
    """The pipeline of module ``name``; raises :class:`UnknownName` (field ``module``)."""
    from lab.modules import get_pipeline

    return get_pipeline(name)


# --- one-line errors ------------------------------------------------------------------------
class LabGroup(TyperGroup):
    """The command group: turns click's usage errors into the same one-line form as LabError."""

    def main(self, args: Sequence[str] | None = None, prog_name: str | None = None,
             complete_var: str | None = None, standalone_mode: bool = True,
             windows_expand_args: bool = True, **extra: Any) -> Any:
        """Click's ``main``; standalone, every usage error becomes one line and its exit code."""
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False,
                                windows_expand_args=windows_expand_args, **extra)
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False,
                                windows_expand_args=windows_expand_args, **extra)
        except _CLICK_EXCEPTION as exc:
            if type(exc).__name__ == "NoArgsIsHelpError":
                exc.show()  # the help text
            else:
                _print_error(*_click_error_parts(exc))
            sys.exit(exc.exit_code)
        except typer.Abort:
            typer.echo("aborted", err=True)
            sys.exit(1)
        sys.exit(code if isinstance(code, int) else 0)


def _click_error_parts(exc: "ClickException") -> tuple[str, str]:
    """(field, reason) of a click usage error: the option at fault when click names one."""
    param = getattr(exc, "param", None)  # BadParameter and its kin
    option_name = getattr(exc, "option_name", None)  # NoSuchOption, BadOptionUsage
    message = exc.format_message()
    if param is not None and type(exc).__name__ == "BadParameter":
        opts = getattr(param, "opts", None) or [param.human_readable_name]
        message = exc.message
        field = opts[0]
    elif option_name:
        field = option_name
    else:
        field = "usage"
    ctx = getattr(exc, "ctx", None)
    if isinstance(exc, _USAGE_ERROR) and ctx is not None:
        message = f"{message} (see '{ctx.command_path} --help')"
    return field, message


def _print_error(field: str, reason: str) -> None:
    line = f"error: {field}: {reason}".replace("\r", " ").replace("\n", " ")
    typer.echo(line, err=True)


@contextlib.contextmanager
def _user_errors() -> Iterator[None]:
    """Print a LabError (or a file that cannot be written) as one line and exit 2."""
    try:
        yield
    except LabError as exc:
        _print_error(exc.field, exc.reason)
        raise typer.Exit(EXIT_USAGE) from None
    except OSError as exc:  # writing --out, binding a port
        where = getattr(exc, "filename", None)
        _print_error("file" if where else "os", f"{exc.strerror or exc}{f': {where}' if where else ''}")
        raise typer.Exit(EXIT_USAGE) from None


# --- argument parsing -------------------------------------------------------------------------
def parse_options(items: list[str] | None) -> dict[str, str]:
    """``--option KEY=VALUE`` items as a dict (the dataset checks the names and types)."""
    options: dict[str, str] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise InvalidValue("--option", f"expected KEY=VALUE, got {item!r}")
        options[key.strip()] = value
    return options


def parse_settings(pipeline: "Pipeline", items: list[str] | None) -> dict[str, dict[str, Any]]:
    """``--set STEP.CONTROL=VALUE`` items as ``{step: {control: value}}``, each checked and converted.

    Raises :class:`InvalidControl` for bad syntax (field ``--set``) or a value the control
    refuses (field ``STEP.CONTROL``), :class:`UnknownName` for an unknown step.
    """
    params: dict[str, dict[str, Any]] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        step, dot, control = key.strip().partition(".")
        if not sep or not dot or not step or not control:
            raise InvalidControl("--set", f"expected STEP.CONTROL=VALUE, got {item!r}")
        spec = pipeline.step(step)
        try:
            params.setdefault(step, {})[control] = spec.control(control).coerce(value)
        except InvalidControl as exc:
            raise InvalidControl(f"{step}.{exc.field}", exc.reason) from None
    return params


def _plan(session: "Session", targets: list[str] | None, params: dict[str, dict[str, Any]]) -> "Plan":
    """The core's plan of ``targets`` (every step when None) on a fresh session, with ``--set``
    controls."""
    return session.plan(targets, params)


# --- running ----------------------------------------------------------------------------------
def _stderr_is_terminal() -> bool:
    isatty = getattr(sys.stderr, "isatty", None)
    return bool(isatty and isatty())


class _ProgressDisplay:
    """A transient progress line per step on a terminal (bar for long steps), and each step's warnings.

    Its methods are the callbacks of :meth:`Session.run_plan`: ``start`` a step, show its
    ``progress``, ``finished`` with its record; ``close`` ends a line a failure left open.
    """

    def __init__(self, pipeline: "Pipeline", *, enabled: bool) -> None:
        self.pipeline = pipeline
        self.enabled = enabled
        self._bar: ProgressBar | None = None
        self._task: TaskID | None = None

    def start(self, step: str) -> None:
        self.close()
        if not self.enabled:
            return
        from rich.console import Console
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn,
                                   TimeElapsedColumn)

        columns: list[ProgressColumn] = [SpinnerColumn(), TextColumn("{task.description}")]
        if self.pipeline.step(step).is_generator:
            columns += [BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[note]}")]
        columns.append(TimeElapsedColumn())
        self._bar = Progress(*columns, console=Console(file=sys.stderr, force_terminal=True),
                             transient=True)
        self._bar.start()
        self._task = self._bar.add_task(step, total=None, note="")

    def progress(self, step: str, snapshot: "Progress") -> None:
        if self._bar is not None and self._task is not None:  # a bar has its task
            note = f"loss {snapshot.loss:.4g}" if snapshot.loss is not None else snapshot.message
            self._bar.update(self._task, completed=snapshot.iteration, total=snapshot.total, note=note)

    def finished(self, record: "RunRecord") -> None:
        self.close()
        for warning in record.warnings:
            _print_warning(record.step, warning)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


def _open(module: str, dataset: str | None, options: list[str] | None, settings: list[str] | None,
          seed: int) -> tuple["Pipeline", "Session", dict[str, dict[str, Any]]]:
    """Check every argument, then load the dataset: (pipeline, session, params by step)."""
    import lab
    from lab.core.pipeline import open_session

    pipeline = lookup_pipeline(module)
    params = parse_settings(pipeline, settings)
    name, resolved = lab.resolve_dataset(pipeline, dataset, parse_options(options))
    spec = pipeline.dataset(name)
    try:
        session = open_session(pipeline, spec.name, resolved, seed=seed)
    except (InvalidControl, InvalidValue) as exc:  # an option's name or value: as the user wrote it
        field = exc.field
        if field.startswith("options."):
            field = f"--option {field.removeprefix('options.')}"
        raise type(exc)(field, exc.reason) from None
    except LabError:
        raise
    except Exception as exc:  # a loader failing on the user's files
        raise InvalidValue("dataset", f"{spec.name!r} could not be loaded: "
                                      f"{type(exc).__name__}: {exc}") from None
    return pipeline, session, params


def _run_plan(session: "Session", plan: "Plan", params: dict[str, dict[str, Any]],
              display: _ProgressDisplay) -> list["RunRecord"]:
    try:
        return session.run_plan(plan, params, on_start=display.start, on_step=display.finished,
                                on_progress=display.progress)
    finally:
        display.close()


def _print_warning(step: str, text: str) -> None:
    typer.echo(f"warning: {step}: {text}".replace("\n", " "), err=True)


def summary(module: str, dataset: str, records: list["RunRecord"]) -> dict[str, Any]:
    """The JSON summary of a run: each step's seconds, metrics and warnings, and all metrics merged."""
    from lab.core.codecs import to_json

    merged: dict[str, Any] = {}
    steps = []
    for record in records:
        metrics = to_json(record.metrics)
        merged.update(metrics)
        steps.append({"name": record.step, "seconds": round(record.seconds, 6), "metrics": metrics,
                      "warnings": list(record.warnings)})
    return {"module": module, "dataset": dataset, "steps": steps, "metrics": merged}


def _format_number(value: object) -> str:
    if isinstance(value, bool) or value is None:
        return "-" if value is None else str(value).lower()
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        shown = ", ".join(_format_number(v) for v in value[:4])
        return f"[{shown}]" if len(value) <= 4 else f"[{shown}, ...] ({len(value)} values)"
    return str(value)


def _print_table(result: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"{result['module']} on {result['dataset']}", title_justify="left")
    table.add_column("step")
    table.add_column("seconds", justify="right")
    table.add_column("metrics")
    table.add_column("warnings", justify="right")
    for step in result["steps"]:
        metrics = "\n".join(f"{k} = {_format_number(v)}" for k, v in step["metrics"].items()) or "-"
        table.add_row(step["name"], f"{step['seconds']:.3f}", metrics, str(len(step["warnings"])))
    Console(file=sys.stdout, highlight=False, soft_wrap=False).print(table)


# --- commands -------------------------------------------------------------------------------
app = typer.Typer(
    name="vision-lab",
    cls=LabGroup,
    help="Vision Lab: step through 3D computer-vision algorithms in a live viewer, or run them headless.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

DatasetOpt = Annotated[str | None, typer.Option(
    "--dataset", "-d", help="A dataset name (default: the module's first) or a folder/file of your own.")]
OptionOpt = Annotated[list[str] | None, typer.Option(
    "--option", "-o", metavar="KEY=VALUE", help="A dataset option, e.g. num_views=10 (repeatable).")]
SetOpt = Annotated[list[str] | None, typer.Option(
    "--set", "-s", metavar="STEP.CONTROL=VALUE",
    help="A step control, e.g. detect_corners.window=7 (repeatable).")]
UntilOpt = Annotated[str | None, typer.Option("--until", "-u", metavar="STEP",
                                                 help="Stop after this step (default: run every step).")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed of every step's random generator.")]


@app.command()
def serve(
    host: Annotated[str, typer.Option(
        help="Address to bind (0.0.0.0 to serve other machines).")] = "127.0.0.1",
    port: Annotated[int, typer.Option(
        min=1, max=65535, help="Port of the landing page and REST API.")] = 8000,
    viewer_port: Annotated[int, typer.Option(min=1, max=65535, help="Port of the 3D viewer.")] = 8080,
    data_root: Annotated[Path | None, typer.Option(
        help="Only folders under this one may be loaded as datasets (set it when serving beyond "
             "127.0.0.1).")] = None,
    unsafe_sandbox: Annotated[bool, typer.Option(
        "--unsafe-sandbox", help="Grade submissions without the bubblewrap sandbox, with Python's audit hook "
                                 "only. For trusted code only, never for a class.")] = False,
    no_warmup: Annotated[bool, typer.Option(
        "--no-warmup", help="Do not compile the fast kernels in the background at start-up (also: "
                            "VISION_LAB_NO_WARMUP=1); a module's first RANSAC, SGM or Efros-Leung step then "
                            "compiles them, about 20 s on a fresh install.")] = False,
    workers: Annotated[int, typer.Option(
        min=1, max=64, help="Start this many worker processes on one database, on consecutive ports (the API "
                            "on PORT, PORT+1, ..., the viewers on VIEWER_PORT, VIEWER_PORT+1, ...), for a "
                            "proxy in front (README 'Behind a proxy'); a worker that dies is restarted."
                            )] = 1,
    worker_id: Annotated[str | None, typer.Option(
        help="This process's id among several behind a proxy (like w1): its sessions' ids start with it "
             "and a request for another worker's session is answered 421 (set by --workers).")] = None,
    peers: Annotated[str | None, typer.Option(
        help="The other workers' addresses, WORKER=URL,... (named in a 421 answer; set by --workers)."
        )] = None,
    no_grading: Annotated[bool, typer.Option(
        "--no-grading", help="Store submissions and read them back, but leave grading to the one process on "
                             "the same database that grades (with --workers: every worker but w0).")] = False,
    trust_forwarded_for: Annotated[bool, typer.Option(
        "--trust-forwarded-for", help="Behind one trusted proxy: count each client's sessions by the last "
                                      "X-Forwarded-For entry, not the proxy's address.")] = False,
) -> None:
    """Start the landing page, the REST API and the 3D viewer (Ctrl-C stops them).

    Submissions are graded in the bubblewrap sandbox (docs/sandbox.md). Where it cannot run, the
    lab still serves every module but refuses submissions (HTTP 503 naming the fix) unless
    ``--unsafe-sandbox`` is given.
    """
    with _user_errors():
        if data_root is not None and not data_root.is_dir():
            raise InvalidValue("--data-root", f"{str(data_root)!r} is not a folder")
        if workers > 1:
            _serve_workers(workers, host=host, port=port, viewer_port=viewer_port, data_root=data_root,
                           unsafe_sandbox=unsafe_sandbox, no_warmup=no_warmup,
                           trust_forwarded_for=trust_forwarded_for,
                           given=worker_id is not None or peers is not None or no_grading)
            return
        if unsafe_sandbox:
            from lab.lessons.isolation import allow_unsafe

            allow_unsafe(True)
        from lab.server import serve as start_server

        start_server(host=host, port=port, viewer_port=viewer_port,
                     data_root=str(data_root) if data_root is not None else None, warmup=not no_warmup,
                     worker=_worker_identity(worker_id, peers), grading=not no_grading,
                     trust_forwarded_for=trust_forwarded_for)


def _worker_identity(worker_id: str | None, peers: str | None) -> "WorkerIdentity | None":
    from lab.api.workers import WorkerIdentity, check_worker_id, parse_peers

    if worker_id is None:
        if peers is not None:
            raise InvalidValue("--peers", "give --worker-id too: the peers are named for this worker")
        return None
    try:
        return WorkerIdentity(check_worker_id(worker_id), parse_peers(peers or ""))
    except ValueError as exc:
        raise InvalidValue("--peers" if peers and "peers" in str(exc) else "--worker-id", str(exc)) from None


def _serve_workers(workers: int, *, host: str, port: int, viewer_port: int, data_root: Path | None,
                   unsafe_sandbox: bool, no_warmup: bool, trust_forwarded_for: bool, given: bool) -> None:
    """``serve --workers N``: start and watch the N worker processes (:func:`lab.server.serve_workers`)."""
    from lab.server import plan_workers, serve_workers

    if given:
        raise InvalidValue("--workers", "--worker-id, --peers and --no-grading are set per worker by "
                                        "--workers; give them only to a single worker")
    extra = [*(["--data-root", str(data_root)] if data_root is not None else []),
             *(["--unsafe-sandbox"] if unsafe_sandbox else []), *(["--no-warmup"] if no_warmup else []),
             *(["--trust-forwarded-for"] if trust_forwarded_for else [])]
    try:
        plans = plan_workers(workers, host=host, port=port, viewer_port=viewer_port, extra_args=extra)
    except ValueError as exc:
        raise InvalidValue("--workers", str(exc)) from None
    code = serve_workers(plans)
    if code:
        raise typer.Exit(code)


@app.command()
def modules(as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False) -> None:
    """List the modules, their datasets and steps with every control."""
    with _user_errors():
        pipelines = [lookup_pipeline(name) for name in module_names()]
        if as_json:
            from lab.core.codecs import to_json

            typer.echo(json.dumps({"modules": to_json([p.describe() for p in pipelines])}))
            return
        for pipeline in pipelines:
            typer.echo(f"{pipeline.name}: {pipeline.title}. {pipeline.summary}".rstrip())
            typer.echo("  datasets:")
            for i, dataset in enumerate(pipeline.datasets):
                tags = " (default)" if i == 0 else ""
                tags += " (reads a folder or file: --dataset PATH)" if dataset.takes_path else ""
                typer.echo(f"    {dataset.name}{tags}: {dataset.summary}")
                for option in dataset.options:
                    typer.echo(f"      --option {_describe_control(option)}")
            if pipeline.exports:
                typer.echo("  exports (vision-lab export MODULE --format FORMAT):")
                for export in pipeline.exports.values():
                    typer.echo(f"    {export.format}: {export.summary} (reads {', '.join(export.reads)})")
            typer.echo("  steps:")
            for n, step in enumerate(pipeline.steps, 1):
                long = " (long)" if step.is_generator else ""
                typer.echo(f"    {n}. {step.name}{long}: {step.summary}")
                reads, writes = ", ".join(step.reads) or "-", ", ".join(step.writes) or "-"
                typer.echo(f"       reads {reads}; writes {writes}")
                for control in step.controls:
                    typer.echo(f"       --set {step.name}.{_describe_control(control)}")
            typer.echo("")


def _describe_control(control: "Control") -> str:
    """``name=default  (kind, range)  description`` for the listing."""
    if control.required:
        text = f"{control.name}=..."
    else:
        default = control.default
        shown = ",".join(str(v) for v in default) if isinstance(default, tuple) else default
        text = f"{control.name}={str(shown).lower() if isinstance(shown, bool) else shown}"
    kind: str = control.kind
    if control.kind == "choice":
        kind = "one of " + "|".join(str(c) for c in control.choices)
    elif control.minimum is not None and control.maximum is not None:
        kind = f"{kind} in [{_format_number(control.minimum)}, {_format_number(control.maximum)}]"
    elif control.minimum is not None:
        kind = f"{kind} >= {_format_number(control.minimum)}"
    elif control.maximum is not None:
        kind = f"{kind} <= {_format_number(control.maximum)}"
    text += f"  ({kind}{', required' if control.required else ''})"
    return f"{text}  {control.description}".rstrip()


@app.command()
def run(
    module: Annotated[str, typer.Argument(help="The module, e.g. calibration (see 'vision-lab modules').")],
    dataset: DatasetOpt = None,
    option: OptionOpt = None,
    set_: SetOpt = None,
    until: UntilOpt = None,
    seed: SeedOpt = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print only one JSON object on stdout.")] = False,
) -> None:
    """Run a module's pipeline headless and print each step's time and metrics."""
    with _user_errors():
        pipeline, session, params = _open(module, dataset, option, set_, seed)
        plan = _plan(session, None if until is None else [until], params)
        display = _ProgressDisplay(pipeline, enabled=not as_json and _stderr_is_terminal())
        # With --json stdout carries exactly one JSON object: anything a step prints goes to stderr.
        redirect = contextlib.redirect_stdout(sys.stderr) if as_json else contextlib.nullcontext()
        with redirect:
            records = _run_plan(session, plan, params, display)
        result = summary(pipeline.name, session.dataset, records)
    if as_json:
        typer.echo(json.dumps(result))
    else:
        _print_table(result)


@app.command()
def export(
    module: Annotated[str, typer.Argument(help="The module, e.g. calibration.")],
    fmt: Annotated[str, typer.Option(
        "--format", "-f", help=f"One of {', '.join(EXPORT_FORMATS)}, or a format of the module's own "
                               "(listed by 'vision-lab modules').")],
    out: Annotated[Path, typer.Option("--out", help="The file to write (folders are created).")],
    what: Annotated[str | None, typer.Option(
        "--what", "-w", help="The state value to write, e.g. K, corners, cloud (a module's format writes "
                             "what it needs: leave it out).")] = None,
    index: Annotated[int | None, typer.Option(help="One view of an image set (png, npy).")] = None,
    dataset: DatasetOpt = None,
    option: OptionOpt = None,
    set_: SetOpt = None,
    until: UntilOpt = None,
    seed: SeedOpt = 0,
) -> None:
    """Run the pipeline up to the steps that produce a value, and write that value to a file."""
    with _user_errors():
        pipeline = lookup_pipeline(module)
        needed = _values_to_export(pipeline, what, fmt)
        targets = _export_targets(pipeline, needed, until)
        _, session, params = _open(module, dataset, option, set_, seed)
        display = _ProgressDisplay(pipeline, enabled=_stderr_is_terminal())
        _run_plan(session, _plan(session, targets, params), params, display)
        if fmt in pipeline.exports:
            written = pipeline.export(fmt).write(session.state, session.metrics, out)
        else:
            from lab.data.exports import write_value

            written = write_value(out, session.get(needed[0]), fmt, name=needed[0], index=index)
    what_was_written = pipeline.export(fmt).summary if fmt in pipeline.exports else " and ".join(needed)
    typer.echo(f"wrote {what_was_written} ({fmt}) to {written}")


def _values_to_export(pipeline: "Pipeline", what: str | None, fmt: str) -> list[str]:
    """The state names ``export`` writes: ``--what`` for a value format, what a module's format reads."""
    if fmt in pipeline.exports:
        reads = list(pipeline.export(fmt).reads)
        if what is not None and what not in reads:
            raise InvalidValue("--what", f"{fmt} writes {' and '.join(reads)} together; leave --what out")
        return reads
    if fmt not in EXPORT_FORMATS:
        raise InvalidValue("--format", f"unknown format {fmt!r}; formats are {list(EXPORT_FORMATS)} and "
                                       f"module {pipeline.name!r}'s own {sorted(pipeline.exports)}")
    if not what:
        written = sorted({name for spec in pipeline.steps for name in spec.writes})
        raise InvalidValue("--what", f"name the value to write; the steps of {pipeline.name!r} write "
                                     f"{written}")
    return [what]


def _export_targets(pipeline: "Pipeline", needed: list[str], until: str | None) -> list[str]:
    """The steps to plan for: the last step that writes each of ``needed`` (its final value; none for a
    dataset value), or ``until`` when it is given and leads to them."""
    last_writer = {n: [s.name for s in pipeline.steps if n in s.writes][-1:] for n in needed}
    if until is None:
        return [step for writers in last_writer.values() for step in writers]
    pipeline.step(until)
    upstream = set(pipeline.upstream(until))
    for name, writers in last_writer.items():
        if writers and writers[0] not in upstream:
            raise InvalidValue("--until", f"{name!r} is written by step {writers[0]!r}, which {until!r} does "
                                          f"not lead to (it comes after it or on another branch)")
    return [until]


# Lessons and grading (`vision-lab grade ...`, `vision-lab lesson ...`) live with the grader.
from lab.lessons.cli import register as _register_lessons  # noqa: E402

_register_lessons(app)

__all__ = [
    "EXIT_USAGE",
    "EXPORT_FORMATS",
    "app",
    "lookup_pipeline",
    "module_names",
    "parse_options",
    "parse_settings",
    "summary",
]
