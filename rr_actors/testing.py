"""Helpers for testing code built on rr_actors (and rr_actors itself)."""

from __future__ import annotations

from typing import Any

import pykka

from rr_actors._registrar import CatalogView, ResourceRegistrar, _Crash, _Request
from rr_actors._replies import FutureReply, wait

__all__ = ["CatalogView", "catalog_snapshot", "crash", "running_actors"]


def crash(registrar: ResourceRegistrar, *, timeout: float = 5.0) -> None:
    """Make a registrar's actor die as if it hit a bug (the in-process analogue of SIGKILL).

    Nothing is cleaned up the way `stop()` would: its callers get
    `RegistrarUnavailableError`, its backup keeps what was written, and unless a supervisor
    will restart it, the providers release its consumer ids (death watch).
    Returns once the actor is dead.
    """
    ref = registrar._ref
    ref.tell(_Crash())
    ref.actor_stopped.wait(timeout)


def catalog_snapshot(registrar: ResourceRegistrar, *, timeout: float = 5.0) -> CatalogView:
    """A copy of the registrar's catalog rows, after checking the catalog's invariants.

    Raises:
        AssertionError: an index of the catalog disagrees with its rows.
    """
    reply = FutureReply()
    registrar._ref.tell(_Request(lambda actor, r: actor.op_snapshot(r), reply))
    view: CatalogView = wait(reply.future, timeout, "catalog_snapshot()")
    return view


def running_actors() -> list[Any]:
    """The pykka actors still running in this process."""
    return list(pykka.ActorRegistry.get_all())
