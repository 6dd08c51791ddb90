"""Vision Lab: an interactive 3D computer-vision lab (architecture: DESIGN.md, shared with the project).

For notebooks and scripts, :func:`open_session` runs a module headless, exactly as the CLI and the
REST API do::

    import lab

    session = lab.open_session("calibration", num_views=12, seed=0)  # dataset options as keywords
    session.run("detect_corners", {"window": 7})
    session.run_until("refine_calibration")
    K = session.get("K")
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # imported lazily: ``import lab`` stays cheap
    from lab.core.pipeline import Pipeline, Session

__version__ = "0.1.0"


def resolve_dataset(pipeline: Pipeline, dataset: str | os.PathLike[str] | None,
                    options: dict[str, Any] | None = None) -> tuple[str | None, dict[str, Any]]:
    """Which dataset of ``pipeline`` to load, and with which options.

    ``dataset`` is a dataset name (``"synthetic"``), None for the module's default (its first
    dataset), or the path of an existing file or folder: then the module's first dataset that
    takes a path (e.g. ``folder``) is used with option ``path`` set to it. Raises
    :class:`~lab.core.errors.UnknownName` for a name that is neither a dataset nor an existing
    path, :class:`~lab.core.errors.InvalidValue` when the module reads no files.
    """
    from lab.core.errors import InvalidValue, UnknownName

    options = dict(options or {})
    if dataset is None:
        return None, options
    text = os.fspath(dataset)
    names = [d.name for d in pipeline.datasets]
    if text in names:
        return text, options
    path = Path(text).expanduser()
    if not path.exists():
        raise UnknownName("dataset", f"module {pipeline.name!r} has no dataset {text!r} and no file or "
                                     f"folder {text!r} exists; datasets are {names}")
    readers = [d for d in pipeline.datasets if d.takes_path]
    if not readers:
        raise InvalidValue("dataset", f"module {pipeline.name!r} reads no files or folders; "
                                      f"datasets are {names}")
    if "path" in options:
        raise InvalidValue("options.path", f"given twice: as the dataset {text!r} and as option "
                                           f"path={options['path']!r}")
    options["path"] = str(path)
    return readers[0].name, options


def open_session(module: str | Pipeline, dataset: str | os.PathLike[str] | None = None, *, seed: int = 0,
                 options: dict[str, Any] | None = None, **more_options: Any) -> Session:
    """Open a session on a module (by name, or a :class:`~lab.core.pipeline.Pipeline`).

    ``dataset`` as in :func:`resolve_dataset`; the dataset's options are keywords (e.g.
    ``num_views=12``, or ``columns=9, rows=6`` for a folder of photos) or the dict ``options``
    (for a dataset option named ``seed`` or ``options``); ``seed`` seeds every step's ``rng``.
    Equivalent to ``lab.core.open_session(get_pipeline(module), dataset, options, seed=seed)``.
    """
    options = {**(options or {}), **more_options}
    from lab.core.pipeline import open_session as open_pipeline_session

    if isinstance(module, str):
        from lab.modules import get_pipeline

        pipeline = get_pipeline(module)
    else:
        pipeline = module
    name, resolved = resolve_dataset(pipeline, dataset, options)
    return open_pipeline_session(pipeline, name, resolved, seed=seed)


__all__ = ["__version__", "open_session", "resolve_dataset"]
