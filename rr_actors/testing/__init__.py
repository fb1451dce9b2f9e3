"""Helpers for testing code built on rr_actors (and rr_actors itself).

Placement-independent helpers: [`crash`][rr_actors.testing.crash] and
[`catalog_snapshot`][rr_actors.testing.catalog_snapshot] accept a `ResourceRegistrar` (a
registrar in this process) or a [`RemoteRegistrar`][rr_actors.testing.RemoteRegistrar] (a
registrar in a manager process of a system). Both are the one handle class,
`rr.Registrar`, with the same methods, so one test body exercises both placements.

State that a test shares with callbacks which may run in another process (journals,
events, barriers) comes from [`SharedObjects`][rr_actors.testing.SharedObjects].

Seams for tests that must make a race happen on purpose, or look at what a registrar
still waits for. They name the registrar's steps (`intercept`) and what it holds
(`pending_work`) in words that are part of this module's contract, so a test never
reaches into private handler tables, and renaming a step breaks such a test loudly
(`ConfigError`) instead of turning it into a test that races nothing:

- [`run_on_actor`][rr_actors.testing.run_on_actor]: run code on a registrar's actor
  thread (hold it busy at a chosen moment);
- [`intercept`][rr_actors.testing.intercept]: run hooks before or after one of its named
  steps ([`STEPS`][rr_actors.testing.STEPS]);
- [`call_futures`][rr_actors.testing.call_futures]: choose the future class its callers
  wait on (to make an answer race a timeout);
- [`pending_work`][rr_actors.testing.pending_work]: what it still waits for;
- [`expect_restart`][rr_actors.testing.expect_restart]: say a restart is coming, as a
  supervisor does (no death watch when the registrar dies).

What those seams and `RemoteRegistrar` take, so a test needs no private module:

- [`CallAttempt`][rr_actors.testing.CallAttempt] (and its
  [`AttemptState`][rr_actors.testing.AttemptState]): the class to subclass for
  `call_futures`;
- [`System`][rr_actors.testing.System]: the system of registrars across processes that
  `RemoteRegistrar.start` starts a manager process on (`System.create()`, `close()`);
- [`start_forkserver`][rr_actors.testing.start_forkserver]: start the forkserver that
  manager processes are forked from now, before a check that counts child processes.

A carrier to test against without processes:

- [`MemoryNetwork`][rr_actors.testing.MemoryNetwork]: an in-memory carrier (a test
  double of a system across processes: `ResourceRegistrar.start(config,
  network=MemoryNetwork())`); what a test sends through its `resolve(name)` and `run`
  crosses it as frames, as on the AF_UNIX and Zenoh carriers; `cut(name)` is a
  `SIGKILL` of the process serving `name`.

Where they live: `seams.py`, `shared.py`, `memory.py` (re-exported here).
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
