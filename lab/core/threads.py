"""torch's CPU threads for small work: one thread inside a block, shared by nested and concurrent blocks.

On a busy 2-core machine torch's OpenMP threads spin-wait on each other: a small network (a diffusion
denoiser, NeRF's 2D warm-up MLP) trains 10 to 30 times faster on one thread than on two. The modules
that train such networks wrap the loop in :func:`single_threaded`; torch is imported only when a block
is entered, so importing :mod:`lab.core` stays light.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

_THREADS_LOCK = threading.Lock()
_single_threaded = {"count": 0, "saved": 0}


@contextlib.contextmanager
def single_threaded(enabled: bool = True) -> Iterator[None]:
    """torch on one CPU thread inside the block (``torch.set_num_threads`` is process-wide: nested and
    concurrent blocks share it, and the last one out restores the count the first one found)."""
    if not enabled:
        yield
        return
    import torch

    with _THREADS_LOCK:
        if _single_threaded["count"] == 0:
            _single_threaded["saved"] = torch.get_num_threads()
            torch.set_num_threads(1)
        _single_threaded["count"] += 1
    try:
        yield
    finally:
        with _THREADS_LOCK:
            _single_threaded["count"] -= 1
            if _single_threaded["count"] == 0:
                torch.set_num_threads(_single_threaded["saved"])
