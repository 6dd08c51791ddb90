"""The modules a viewer offers: the one registry :mod:`lab.modules` (``MODULES``, ``get_pipeline``).

The viewer keeps no list of modules of its own. A :class:`ModuleCatalog` reads the registry on each
call, or, when a server is started with an explicit set of pipelines (``lab.server.start(modules=...)``,
tests with a toy pipeline), offers exactly those.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from lab.core.errors import UnknownName
from lab.core.pipeline import Pipeline
from lab.modules import MODULES, get_pipeline


class ModuleCatalog:
    """The modules a viewer offers: :mod:`lab.modules`' registry by default, or an explicit set."""

    def __init__(self, modules: Mapping[str, Pipeline] | Iterable[Pipeline] | None = None) -> None:
        if modules is None:
            self._explicit: dict[str, Pipeline] | None = None
        elif isinstance(modules, Mapping):
            self._explicit = dict(modules)
        else:
            self._explicit = {p.name: p for p in modules}

    def names(self) -> list[str]:
        """The module names, in the registry's order (the landing page's)."""
        if self._explicit is not None:
            return list(self._explicit)
        return list(MODULES)

    def get(self, name: str) -> Pipeline:
        """The pipeline of module ``name``; :class:`UnknownName` lists the modules there are."""
        if self._explicit is not None:
            if name not in self._explicit:
                raise UnknownName("module", f"no module {name!r}; modules are {list(self._explicit)}")
            return self._explicit[name]
        return get_pipeline(name)


__all__ = ["ModuleCatalog"]
