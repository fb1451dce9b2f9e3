"""Placement-independent helpers: kill a registrar, look at its catalog, list actors."""

from __future__ import annotations

import functools
from typing import Any

import pykka

from rr_actors._process.remote import FORWARD_MARGIN, RemoteRegistrar
from rr_actors._registrar import ResourceRegistrar, snapshot
from rr_actors._registrar.life import CatalogView

__all__ = ["catalog_snapshot", "crash", "running_actors"]


def crash(registrar: ResourceRegistrar | RemoteRegistrar, *, timeout: float = 5.0) -> None:
    """Make a registrar die as if it hit a bug: no cleanup the way `stop()` would do it.

    For a `ResourceRegistrar` its actor dies (the in-process analogue of SIGKILL); for a
    `RemoteRegistrar` its manager process gets SIGKILL. Either way its callers get
    `RegistrarUnavailableError`, its backup keeps what was written, and unless a supervisor
    will restart it, the providers release its consumer ids (death watch). Returns once it
    is dead and the providers were told.

    Args:
        registrar: the registrar to kill.
        timeout: seconds to wait for its death.
    """
    if isinstance(registrar, RemoteRegistrar):
        registrar.kill(timeout=timeout)
        return
    registrar._actor.crash()
    registrar._actor.died.wait(timeout)  # the actor's death handling ran, death watch included


def catalog_snapshot(
    registrar: ResourceRegistrar | RemoteRegistrar, *, timeout: float = 5.0
) -> CatalogView:
    """A copy of the registrar's catalog rows, after checking the catalog's invariants.

    Args:
        registrar: a registrar of this process, or a `RemoteRegistrar` (the snapshot is
            taken in its process and sent back).
        timeout: seconds to wait for the registrar.

    Raises:
        AssertionError: an index of the catalog disagrees with its rows.
        CallTimeoutError: no answer within `timeout` seconds.
        RegistrarUnavailableError: the registrar died.
    """
    if isinstance(registrar, RemoteRegistrar):
        there = functools.partial(catalog_snapshot, timeout=timeout)
        remote: CatalogView = registrar.run(there, timeout=timeout + FORWARD_MARGIN)
        return remote
    return snapshot(registrar, timeout=timeout, check=True)


def running_actors() -> list[Any]:
    """The pykka actors still running in this process."""
    return list(pykka.ActorRegistry.get_all())
