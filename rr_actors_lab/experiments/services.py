"""A generic manager for experiments: one resource server with a chosen load time and dependencies.

Use it in a plan when the managers' own work does not matter, only the shape of the tree:

```toml
[[tree.children]]
name = "db"
setup = "rr_actors_lab.experiments.services:service"

[[tree.children]]
name = "api"
setup = "rr_actors_lab.experiments.services:service"
options = { load_s = 0.005, uses = ["db/resource"] }   # each load loads from db too
```

The thesis mission's managers (`rr_actors_lab.mission.managers:erm_setup`, `cm_setup`,
`rm_setup`) are the other ready-made choice: their resources are real OS processes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import rr_actors as rr
from rr_actors._core import runtime

__all__ = ["long_request", "service"]


def service(
    registrar: rr.ResourceRegistrar,
    *,
    server: str = "resource",
    load_s: float = 0.0,
    unload_s: float = 0.0,
    uses: Sequence[str] = (),
    uses_request: Any = None,
    status_every: float = 0.0,
    list_every: float = 0.0,
    max_pending: int | None = None,
    holds: Sequence[str] = (),
) -> None:
    """Register one resource server whose loads take `load_s` and load what it `uses`.

    Runs in the manager, as every `setup` does. The response to a request is
    `{"server": "<registrar>/<server>", "request": request}`. With `status_every`, a thread
    of the manager sends a `WARNING` status (`"scheduled"`) about the first query the server
    holds; with `list_every`, one lists its queries (`server_queries`, published as
    `ServerQueriesListed` for the check's `fetch` rule). Both end with the registrar.

    Args:
        registrar: the manager's registrar.
        server: the server's name.
        load_s: seconds each load takes (the load's worker thread waits).
        unload_s: seconds each unload takes.
        uses: `"manager/server"` of other managers (a bare `"manager"`: its server
            `resource`): each load calls every one with the same request (dependencies of
            the resource, released with it).
        uses_request: the request each load sends to `uses` instead of its own (`None`: its
            own): every resource then depends on one shared resource there.
        status_every: seconds between two statuses the server sends (0: none).
        list_every: seconds between two listings of the server's queries (0: none).
        max_pending: the server's own `max_pending` (loads queued or running at once;
            `None`: its registrar's): past it, loads are refused (`ServerOverloaded`).
        holds: `"manager/server"` of other managers (a bare `"manager"`: its server
            `resource`) a thread of the manager calls once, with the request `"held by
            <registrar>"`, as soon as it answers (trying again every 0.05 s), and holds
            until the registrar stops: a dependency of the manager, not of a resource (a
            provider `stop(parallel=True)` stops after it, whatever their start order).

    Raises:
        ConfigError: `status_every` or `list_every` is negative or not finite, or
            `max_pending` is not an int >= 1 (nor `None`).
    """
    for field, value in (("status_every", status_every), ("list_every", list_every)):
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not number or not math.isfinite(value) or value < 0:
            raise rr.ConfigError(f"{field} must be a finite number >= 0, got {value!r}")

    def load(request: Any) -> dict[str, Any]:
        for target in uses:
            manager, _, name = target.partition("/")
            sent = request if uses_request is None else uses_request
            registrar.call(manager, name or "resource", sent)
        if load_s > 0:
            runtime.sleep(load_s)
        return {"server": f"{registrar.name}/{server}", "request": request}

    def unload(_request: Any, _response: Any) -> None:
        if unload_s > 0:
            runtime.sleep(unload_s)

    registrar.register_server(server, load=load, unload=unload, max_pending=max_pending)
    if status_every > 0:
        runtime.Thread(
            target=_send_statuses,
            args=(registrar, server, status_every),
            name=f"rr-scheduled-status-{registrar.name}",
            daemon=True,
        ).start()
    if list_every > 0:
        runtime.Thread(
            target=_list_queries,
            args=(registrar, server, list_every),
            name=f"rr-scheduled-list-{registrar.name}",
            daemon=True,
        ).start()
    if holds:
        runtime.Thread(
            target=_hold,
            args=(registrar, tuple(holds)),
            name=f"rr-held-{registrar.name}",
            daemon=True,
        ).start()


def _hold(registrar: rr.ResourceRegistrar, targets: Sequence[str]) -> None:
    """Call each of `targets` once (every 0.05 s until answered) and hold the answer until
    the registrar stops (its stop releases it); until the registrar stops."""
    for target in targets:
        manager, _, name = target.partition("/")
        while registrar.is_alive():
            try:
                registrar.call(manager, name or "resource", f"held by {registrar.name}")
                break
            except rr.RegistrarStoppedError:
                return
            except rr.RrError:
                runtime.sleep(0.05)  # (not serving yet, or restarting: the next try)


def _send_statuses(registrar: rr.ResourceRegistrar, server: str, every: float) -> None:
    """Every `every` s, a `WARNING` about the first query `server` holds; until the
    registrar stops."""
    while True:
        runtime.sleep(every)
        if not registrar.is_alive():
            return
        try:
            held = registrar.server_queries(server)
            if held:
                registrar.send_status(held[0].id, rr.Status.WARNING, "scheduled", timeout=every)
        except rr.RegistrarStoppedError:
            return
        except rr.RrError:
            continue  # (released meanwhile, a consumer unreachable: the next one)


def _list_queries(registrar: rr.ResourceRegistrar, server: str, every: float) -> None:
    """Every `every` s, `server_queries(server)` (its registrar publishes the answer);
    until the registrar stops."""
    while True:
        runtime.sleep(every)
        if not registrar.is_alive():
            return
        try:
            registrar.server_queries(server, timeout=every)
        except rr.RegistrarStoppedError:
            return
        except rr.RrError:
            continue  # (timed out: the next one)


def long_request(key: str, _context: Any) -> dict[str, Any]:
    """A plan's `factory`: a request of plain values (`request_digest` digests it) that a
    template cannot make (a `frozenset`, `bytes`), whose `repr` passes the 200 characters
    an error message shows of it (`describe`): as `simlong` calls."""
    return {
        **{f"{n}-field-of-a-long-request": f"{key}-{n}-value-long-enough" for n in "abcd"},
        "z-set": frozenset({key}),
        "z-bytes": key.encode(),
    }
