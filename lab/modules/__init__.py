"""The teaching modules: THE registry every front end (viewer, REST, CLI, grader) lists them from.

A module is one package here (``lab/modules/<name>/``, see docs/adding-a-module.md) whose
``__init__`` defines ``PIPELINE``; adding one is one line in :data:`MODULES`. Packages are imported
on first use, so listing the modules does not load PyTorch or compile kernels.
"""

from __future__ import annotations

import importlib
from functools import cache

from lab.core.errors import UnknownName
from lab.core.pipeline import Pipeline

#: Module names, in the order the landing page and the viewer list them.
MODULES: tuple[str, ...] = ("calibration", "epipolar", "stereo", "sfm", "texture", "diffusion", "nerf",
                            "splatting")


@cache
def get_pipeline(name: str) -> Pipeline:
    """The pipeline of module ``name`` (its package imported on first use); :class:`UnknownName` else."""
    if name not in MODULES:
        raise UnknownName("module", f"no module {name!r}; modules are {list(MODULES)}")
    pipeline = importlib.import_module(f"lab.modules.{name}").PIPELINE
    if not isinstance(pipeline, Pipeline):
        raise TypeError(f"lab.modules.{name}.PIPELINE is a {type(pipeline).__name__}, not a Pipeline")
    return pipeline


__all__ = ["MODULES", "get_pipeline"]
