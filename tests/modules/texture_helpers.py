"""What the texture module's tests share: a small procedural sample and a generator step run to its end."""

from __future__ import annotations

from typing import Any

from lab.core import Image
from lab.data.textures import procedural


def small_sample(size: int = 16, *, colour: bool = False, seed: int = 0, pattern: str = "blobs") -> Image:
    return procedural(pattern=pattern, size=size, colour=colour, seed=seed).state["sample"]


def drive(generator: Any) -> tuple[list[Any], Any]:
    """Run a generator step to its end: (progress snapshots, result)."""
    snapshots = []
    while True:
        try:
            snapshots.append(next(generator))
        except StopIteration as stop:
            return snapshots, stop.value
