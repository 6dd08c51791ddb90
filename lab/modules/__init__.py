"""Teaching modules. A new module is one file here, registered in :data:`MODULES` below."""

from __future__ import annotations

from functools import cache

from lab.core.errors import UnknownName
from lab.core.pipeline import Pipeline

#: Module names, in the order the landing page and the viewer list them.
MODULES: tuple[str, ...] = ("calibration", "epipolar", "stereo", "sfm", "texture", "diffusion")


@cache
def get_pipeline(name: str) -> Pipeline:
    """The pipeline of module ``name`` (imported on first use)."""
    if name not in MODULES:
        raise UnknownName("module", f"no module {name!r}; modules are {list(MODULES)}")
    import importlib

    return importlib.import_module(f"lab.modules.{name}").PIPELINE


def all_pipelines() -> list[Pipeline]:
    return [get_pipeline(name) for name in MODULES]
