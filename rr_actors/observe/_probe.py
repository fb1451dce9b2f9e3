"""Reading a live registrar's catalog for the observer, in the registrar's own process.

    LiveSource ──Supervisor.run_in(name, catalog_of)──► manager process: catalog_of(registrar)
                                                          ├─ actor thread: copy the rows (one turn)
                                                          └─ this thread: summarise (stored texts)
               ◄── catalog summary (plain dicts and strings: nothing of the user's to unpickle)

The registrar copies its rows and its servers' names on its own actor thread
(`rr_actors._registrar.snapshot`, as `rr_actors.testing.catalog_snapshot` does), so the copy
is consistent and the registrar is held for a copy only. No `repr` runs here: the summary
shows the display texts the registrar made once, when it stored each value.
"""

from __future__ import annotations

from typing import Any

from rr_actors._registrar import ResourceRegistrar, snapshot
from rr_actors.observe._view import summarise_catalog

__all__ = ["SNAPSHOT_TIMEOUT", "catalog_of"]

SNAPSHOT_TIMEOUT = 2.0
"""Seconds the observer waits for a registrar to copy its catalog."""


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
    view = snapshot(registrar, timeout=timeout, check=False)
    return summarise_catalog(
        registrar.name,
        view.resources,
        view.clients,
        servers=view.servers,
        in_doubt=view.in_doubt,
    )
