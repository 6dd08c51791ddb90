"""The one way a module compiles and parallelizes its fast kernels (Numba, no GIL, a shared thread pool).

Every module keeps its fast kernels in a private ``_kernels.py`` and a slow readable version of each
in its public ``reference.py``, the oracle the tests compare with (gsplat's ``_torch_impl`` pattern).
The names pair up the same way everywhere:

    ``_box_mean_kernel``   the compiled loop (``@kernel``), in ``_kernels.py``: arrays in, arrays out
    ``box_mean``           the public fast function that calls it (checks, banding, threads)
    ``box_mean_reference`` the readable NumPy/Python version, in ``reference.py``

:func:`kernel` is ``numba.njit(cache=True, nogil=True)`` with a fallback to compiling once per
process where the package folder is read-only (a system install, the grading sandbox).
:func:`in_parallel` runs one job per band of rows on a process-wide thread pool (the kernels release
the GIL), sized to the CPUs this process may use, as OpenCV sizes its own pool.

Warm-up: compiling a module's kernels takes seconds on a cold cache (epipolar's RANSAC about 20 s), a pause
a first-time user takes for a hang. Each module with kernels registers a :class:`WarmUp` (its
``_kernels.py``: the steps that compile, the dispatchers, and a function that calls them once on tiny
inputs of the steps' own dtypes and ranks, so numba compiles, and caches on disk, the signatures the steps
use). :func:`warm_up_kernels` runs them all in one low-priority background thread (``vision-lab serve``
starts it); :func:`kernel_warmup_status` says how far it got, and :func:`needs_compiling` tells the viewer
when a step is about to compile (its first-run notice).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal, TypeVar, cast

import numba
import numpy as np

_F = TypeVar("_F", bound=Callable[..., Any])


def kernel(func: _F) -> _F:
    """``numba.njit(nogil=True)``, cached on disk where the package folder is writable (else compiled once
    per process). The returned dispatcher is called like ``func``; ``func.py_func`` is the Python original."""
    compiled: Any
    try:
        compiled = numba.njit(cache=True, nogil=True)(func)
    except RuntimeError:  # no writable cache location (a read-only install, a sandbox)
        compiled = numba.njit(nogil=True)(func)
    return cast(_F, compiled)  # a Dispatcher is called as func is


def workers() -> int:
    """Threads the kernels use: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


_POOL: ThreadPoolExecutor | None = None
#: ``_INLINE.active`` in a thread: its :func:`in_parallel` jobs run in that thread (the warm-up's, so that it
#: compiles in its one low-priority thread, not on the pool's threads at normal priority).
_INLINE = threading.local()
_POOL_LOCK = threading.Lock()


def _forget_pool() -> None:
    """A forked child has none of its parent's threads: it builds its own pool when it needs one."""
    global _POOL
    _POOL = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=workers(), thread_name_prefix="lab-kernels")
        return _POOL


def in_parallel(function: Callable[..., Any], jobs: Sequence[tuple[Any, ...]]) -> list[Any]:
    """``[function(*job) for job in jobs]``, on the shared thread pool when there is more than one job.

    The jobs must write disjoint parts of their outputs (one band each) and release the GIL
    (:func:`kernel` does) to run at the same time. Exceptions propagate from the first failing job.
    """
    if len(jobs) <= 1 or getattr(_INLINE, "active", False):
        return [function(*job) for job in jobs]
    futures = [_pool().submit(function, *job) for job in jobs]
    return [future.result() for future in futures]


def bands(count: int, *, parts: int | None = None) -> list[tuple[int, int]]:
    """Split ``range(count)`` into contiguous ``(start, stop)`` bands, one per worker by default."""
    parts = max(1, min(workers() if parts is None else parts, count))
    edges = np.linspace(0, count, parts + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in itertools.pairwise(edges) if b > a]


# ----------------------------------------------------------------------------------------------------
# Warm-up: compile every module's kernels ahead, in the background
# ----------------------------------------------------------------------------------------------------
log = logging.getLogger("lab.kernels")

WarmUpState = Literal["pending", "running", "done", "failed"]


@dataclass(frozen=True)
class WarmUp:
    """One module's warm-up: ``run()`` calls its ``kernels`` (its entry numba dispatchers,
    :func:`dispatchers_in`) once on tiny inputs; the ``steps`` of pipeline ``module`` are those whose first
    run compiles them."""

    module: str
    steps: frozenset[str]
    kernels: tuple[Any, ...]
    run: Callable[[], None]


@dataclass(frozen=True)
class WarmUpStatus:
    """How far one module's warm-up got: ``state``, the seconds it took once done (or failed), and per
    kernel the seconds numba spent compiling it (inclusive of the kernels it calls; none when its on-disk
    cache served it)."""

    state: WarmUpState
    seconds: float | None = None
    error: str | None = None
    kernel_seconds: tuple[tuple[str, float], ...] = ()


_WARM_UPS: dict[str, WarmUp] = {}
_STATUS: dict[str, WarmUpStatus] = {}
_WARM_LOCK = threading.Lock()


def register_warm_up(module: str, steps: Sequence[str], kernels: Sequence[Any],
                     run: Callable[[], None]) -> None:
    """Register (or replace) the warm-up of ``module``'s kernels; see :class:`WarmUp`."""
    with _WARM_LOCK:
        _WARM_UPS[module] = WarmUp(module, frozenset(steps), tuple(kernels), run)
        _STATUS[module] = WarmUpStatus("done" if all_compiled(kernels) else "pending")


def warm_ups() -> dict[str, WarmUp]:
    """The registered warm-ups, by module name (those of the module packages imported so far)."""
    with _WARM_LOCK:
        return dict(_WARM_UPS)


def all_compiled(kernels: Sequence[Any]) -> bool:
    """Whether every dispatcher has at least one compiled signature in this process."""
    return all(len(getattr(k, "signatures", ())) > 0 for k in kernels)


def kernel_warmup_status() -> dict[str, WarmUpStatus]:
    """Each registered module's warm-up: pending, running, done (with its seconds) or failed."""
    with _WARM_LOCK:
        return dict(_STATUS)


def needs_compiling(module: str, step: str) -> bool:
    """Whether running ``step`` of pipeline ``module`` now would compile kernels first (its module's
    kernels are not all compiled in this process yet): the viewer shows its first-run notice then."""
    entry = warm_ups().get(module)
    return entry is not None and step in entry.steps and not all_compiled(entry.kernels)


def _lower_priority() -> None:
    """Make the calling thread nice (Linux threads have their own nice value), best effort."""
    with contextlib.suppress(AttributeError, OSError):  # not Linux, or not allowed
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)


def compile_seconds(events: Sequence[tuple[float, Any]]) -> dict[str, float]:
    """Seconds of compilation per kernel (its Python name) from a numba ``numba:compile`` event recording."""
    started: dict[int, list[float]] = {}
    seconds: dict[str, float] = {}
    for stamp, event in events:
        dispatcher = (event.data or {}).get("dispatcher")
        if dispatcher is None:
            continue
        if event.is_start:
            started.setdefault(id(dispatcher), []).append(stamp)
        elif started.get(id(dispatcher)):
            name = getattr(dispatcher.py_func, "__name__", str(dispatcher))
            seconds[name] = seconds.get(name, 0.0) + stamp - started[id(dispatcher)].pop()
    return seconds


def _warm_one(entry: WarmUp) -> WarmUpStatus:
    from numba.core import event

    with _WARM_LOCK:
        _STATUS[entry.module] = WarmUpStatus("running")
    start = time.perf_counter()
    with event.install_recorder("numba:compile") as recording:
        try:
            entry.run()
        except Exception as exc:  # a warm-up must never take the server down: the step compiles when run
            log.warning("warming up %s's kernels failed: %s", entry.module, exc)
            failure: str | None = f"{type(exc).__name__}: {exc}"
        else:
            failure = None
    compiled = compile_seconds(recording.buffer)
    per_kernel = tuple(sorted((name, round(value, 3)) for name, value in compiled.items()
                              if name.endswith("_kernel")))  # ours (``_x_kernel``), not numba's own overloads
    status = WarmUpStatus("failed" if failure else "done", time.perf_counter() - start, failure, per_kernel)
    with _WARM_LOCK:
        _STATUS[entry.module] = status
    return status


def dispatchers_in(namespace: dict[str, Any]) -> list[Any]:
    """The entry kernels of a module's namespace (``globals()``): its numba dispatchers (``@kernel``) but
    those another kernel there calls. A callee compiles inside its caller, and when the caller comes from the
    on-disk cache the callee's own dispatcher never compiles, so only the entry kernels show, by their
    ``signatures``, whether this process has its kernels ready."""
    from numba.core.dispatcher import Dispatcher

    found = [value for value in namespace.values() if isinstance(value, Dispatcher)]
    names = {d.py_func.__name__ for d in found}
    called = {name for d in found for name in d.py_func.__code__.co_names if name in names}
    return [d for d in found if d.py_func.__name__ not in called]


def warm_up_steps(pipeline: Any, dataset: str, options: dict[str, Any], target: str | Sequence[str],
                  params: dict[str, dict[str, Any]] | None = None) -> None:
    """Run ``pipeline``'s plan to ``target`` on a small ``dataset`` in a throwaway session: the steps' own
    calls, so the kernels compile for exactly the dtypes and ranks the steps pass."""
    from lab.core.pipeline import Session

    session = Session(pipeline, pipeline.dataset(dataset).load(options), dataset=dataset, options=options)
    session.run_plan(session.plan(target, params), params)


def run_warm_ups(prepare: Callable[[], None] | None = None,
                 on_done: Callable[[dict[str, WarmUpStatus]], None] | None = None) -> dict[str, WarmUpStatus]:
    """Run ``prepare()`` (importing the modules registers their warm-ups) then every registered warm-up not
    yet done, one after the other, all in this thread (its :func:`in_parallel` jobs too); ``on_done(status)``
    at the end. It makes this thread nice for good: call it in its own thread, :func:`warm_up_kernels`."""
    _lower_priority()
    _INLINE.active = True
    try:
        if prepare is not None:
            prepare()
        for entry in warm_ups().values():
            if kernel_warmup_status()[entry.module].state != "done" or not all_compiled(entry.kernels):
                _warm_one(entry)
    finally:
        _INLINE.active = False
    status = kernel_warmup_status()
    if on_done is not None:
        on_done(status)
    return status


def warm_up_kernels(*, prepare: Callable[[], None] | None = None,
                    on_done: Callable[[dict[str, WarmUpStatus]], None] | None = None) -> threading.Thread:
    """Start :func:`run_warm_ups` in one low-priority daemon thread (``lab-kernel-warmup``) and return it."""
    thread = threading.Thread(target=run_warm_ups, args=(prepare, on_done), name="lab-kernel-warmup",
                              daemon=True)
    thread.start()
    return thread


__all__ = ["WarmUp", "WarmUpStatus", "all_compiled", "bands", "compile_seconds", "dispatchers_in",
           "in_parallel", "kernel", "kernel_warmup_status", "needs_compiling", "register_warm_up",
           "run_warm_ups", "warm_up_kernels", "warm_up_steps", "warm_ups", "workers"]
