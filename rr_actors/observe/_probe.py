"""Reading a live registrar's catalog for the observer, in the registrar's own process.

    LiveSource ──Supervisor.run_in(name, catalog_of)──► manager process: catalog_of(registrar)
                                                          ├─ actor thread: copy the rows (one turn)
                                                          └─ this thread: summarise (bounded reprs)
               ◄── catalog summary (plain dicts and strings: nothing of the user's to unpickle)

This is the one place the observer reaches into the registrar's actor: it asks it, through
the handle's private `_ask` (as `rr_actors.testing.catalog_snapshot` does), to copy its
catalog rows and its servers' names on its own thread, so the copy is consistent and the
registrar is held for a copy only; the `repr`s are made on the calling thread.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from rr_actors._core.directory import Reply
from rr_actors._registrar import ResourceRegistrar
from rr_actors._registrar.actor import RegistrarActor
from rr_actors.observe._view import summarise_catalog

__all__ = ["SNAPSHOT_TIMEOUT", "catalog_of"]

SNAPSHOT_TIMEOUT = 2.0
"""Seconds the observer waits for a registrar to copy its catalog."""


def _copy_rows(actor: RegistrarActor, reply: Reply) -> None:
    """Runs on the registrar's actor thread: copy the rows (it must never raise here)."""
    try:
        shared = actor.shared
        resources = [  # (a restored row decodes its values here, once, on this thread)
            dataclasses.replace(r, consumers=dict(r.consumers))
            for r in shared.catalog.read_all().values()
        ]
        clients = [dataclasses.replace(c) for c in shared.catalog.clients.values()]
        reply.set_result((resources, clients, list(shared.servers)))
    except Exception as exc:  # noqa: BLE001 - an exception here would kill the registrar
        reply.set_error(exc)


def catalog_of(registrar: ResourceRegistrar, *, timeout: float = SNAPSHOT_TIMEOUT) -> Any:
    """The registrar's catalog summary (see `rr_actors.observe._view`).

    Runs in the registrar's process (through `Supervisor.run_in` for a manager), on the
    caller's thread; the registrar's actor thread only copies the rows.

    Args:
        registrar: a registrar of this process.
        timeout: seconds to wait for the registrar.

    Returns:
        The catalog summary: plain dicts, lists and strings.

    Raises:
        CallTimeoutError: the registrar did not answer within `timeout`.
        RegistrarStoppedError: it was stopped.
        RegistrarUnavailableError: it died.
    """
    resources, clients, servers = registrar._ask(_copy_rows, timeout, "the observer's snapshot")
    return summarise_catalog(
        registrar.name, resources, clients, servers=servers, in_doubt=registrar.in_doubt
    )
