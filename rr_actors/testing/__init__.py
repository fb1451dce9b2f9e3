"""Helpers for testing code built on rr_actors (and rr_actors itself).

Placement-independent helpers: [`crash`][rr_actors.testing.crash] and
[`catalog_snapshot`][rr_actors.testing.catalog_snapshot] accept a `ResourceRegistrar` or a
[`RemoteRegistrar`][rr_actors.testing.RemoteRegistrar] (the one handle class,
`rr.Registrar`), so one test body exercises both placements. State shared with callbacks
in another process comes from [`SharedObjects`][rr_actors.testing.SharedObjects].

Seams to make a race happen on purpose, named in words that are this module's contract (a
renamed step fails loudly with `ConfigError`, never races nothing):
[`run_on_actor`][rr_actors.testing.run_on_actor] (hold the actor thread busy),
[`intercept`][rr_actors.testing.intercept] (hooks around a step of
[`STEPS`][rr_actors.testing.STEPS]), [`call_futures`][rr_actors.testing.call_futures]
(the future class callers wait on, a [`CallAttempt`][rr_actors.testing.CallAttempt]
subclass; [`AttemptState`][rr_actors.testing.AttemptState]),
[`pending_work`][rr_actors.testing.pending_work] (what it still waits for),
[`expect_restart`][rr_actors.testing.expect_restart] (no death watch for a coming restart).
[`System`][rr_actors.testing.System] and
[`start_forkserver`][rr_actors.testing.start_forkserver] serve `RemoteRegistrar`;
[`MemoryNetwork`][rr_actors.testing.MemoryNetwork] is an in-memory carrier (`cut(name)`
is a `SIGKILL` of the process serving `name`).
"""

from __future__ import annotations

from rr_actors._process.control import start_forkserver
from rr_actors._process.remote import RemoteRegistrar
from rr_actors._registrar.actor import STEPS
from rr_actors._registrar.calls import AttemptState, CallAttempt
from rr_actors._registrar.life import CatalogView
from rr_actors._transport.unix.system import System
from rr_actors.testing.memory import MemoryAddress, MemoryNetwork
from rr_actors.testing.seams import (
    Installed,
    PendingWork,
    actor_ref,
    call_futures,
    catalog_snapshot,
    crash,
    expect_restart,
    intercept,
    pending_work,
    run_on_actor,
    running_actors,
)
from rr_actors.testing.shared import Records, SharedObjects

__all__ = [
    "STEPS",
    "AttemptState",
    "CallAttempt",
    "CatalogView",
    "Installed",
    "MemoryAddress",
    "MemoryNetwork",
    "PendingWork",
    "Records",
    "RemoteRegistrar",
    "SharedObjects",
    "System",
    "actor_ref",
    "call_futures",
    "catalog_snapshot",
    "crash",
    "expect_restart",
    "intercept",
    "pending_work",
    "run_on_actor",
    "running_actors",
    "start_forkserver",
]
