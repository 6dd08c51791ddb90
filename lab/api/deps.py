"""FastAPI dependencies shared by the routers (and by routers other helpers add, e.g. lessons).

All live state is in ``app.state.store`` (a :class:`~lab.core.store.SessionStore` the viewer
shares); ``app.state.catalog`` knows the modules, ``app.state.runs`` tracks running steps and
``app.state.pools`` (:class:`~lab.api.runs.RunPools`) run them and load datasets; ``app.state.worker``
(:class:`~lab.api.workers.WorkerIdentity`, None for a lone server) says which of several processes this is.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Path, Request

from lab.api.errors import ModuleUnavailable, log
from lab.api.runs import RunPools
from lab.api.workers import WorkerIdentity
from lab.core.errors import LabError, UnknownName
from lab.core.pipeline import Pipeline, Session
from lab.core.store import SessionStore


@dataclass(frozen=True)
class ModuleCatalog:
    """The modules an app serves: their names, in listing order, and how to get a pipeline."""

    names: tuple[str, ...]
    loader: Callable[[str], Pipeline]

    def get(self, name: str) -> Pipeline:
        """The pipeline of module ``name``: UnknownName (404) when not served, ModuleUnavailable (503)
        when broken."""
        if name not in self.names:
            raise UnknownName("module", f"no module {name!r}; modules are {list(self.names)}")
        try:
            pipeline = self.loader(name)
        except LabError:
            raise
        except KeyError:
            raise UnknownName("module", f"no module {name!r}; modules are {list(self.names)}") from None
        except Exception as exc:  # a module that fails to import must not take the API down with it
            log.exception("module %s failed to load", name)
            raise ModuleUnavailable("module", f"module {name!r} failed to load "
                                              f"({type(exc).__name__}: {exc})") from None
        if not isinstance(pipeline, Pipeline):
            raise ModuleUnavailable("module", f"module {name!r} has no pipeline "
                                              f"(got {type(pipeline).__name__})")
        return pipeline

    @classmethod
    def of(cls, loader: Callable[[str], Pipeline] | None, names: Sequence[str] | None) -> ModuleCatalog:
        if loader is None or names is None:
            from lab import modules as registry

            loader = loader or registry.get_pipeline
            names = registry.MODULES if names is None else names
        return cls(tuple(names), loader)


def get_store(request: Request) -> SessionStore:
    return request.app.state.store


def get_catalog(request: Request) -> ModuleCatalog:
    return request.app.state.catalog


def get_pools(request: Request) -> RunPools:
    return request.app.state.pools


def client_address(request: Request) -> str | None:
    """The address a request comes from, which the per-client session cap counts.

    The socket's peer, unless the app was made with ``trust_forwarded_for`` (one trusted proxy in
    front): then the last ``X-Forwarded-For`` entry, the one that proxy appended.
    """
    if getattr(request.app.state, "trust_forwarded_for", False):
        hops = [hop.strip() for hop in request.headers.get("x-forwarded-for", "").split(",") if hop.strip()]
        if hops:
            return hops[-1]
    return request.client.host if request.client is not None else None


SessionId = Annotated[str, Path(description="The session's id, as returned by POST /api/sessions.")]


def get_worker(request: Request) -> WorkerIdentity | None:
    """This process's worker identity when several share a database (None for a lone server)."""
    return getattr(request.app.state, "worker", None)


def check_session_owner(request: Request, session_id: str) -> None:
    """421 (:class:`~lab.api.workers.Misdirected`) when ``session_id`` lives in another worker process."""
    worker = get_worker(request)
    if worker is not None:
        worker.check_owner(session_id)


def get_session(request: Request, session_id: SessionId) -> Session:
    """The live session ``session_id``: 421 naming its worker when another process holds it
    (:mod:`lab.api.workers`), else 404 ``field: session`` saying whether it expired, was deleted or
    never was."""
    check_session_owner(request, session_id)
    return get_store(request).get(session_id)


StoreDep = Annotated[SessionStore, Depends(get_store)]
CatalogDep = Annotated[ModuleCatalog, Depends(get_catalog)]
SessionDep = Annotated[Session, Depends(get_session)]
PoolsDep = Annotated[RunPools, Depends(get_pools)]
ClientDep = Annotated[str | None, Depends(client_address)]
