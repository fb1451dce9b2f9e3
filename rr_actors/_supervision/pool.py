"""A pool: a nested supervisor in an OS process of its own, with its thread managers.

`SupervisorSpec(isolation="process")`. Many managers share one process (memory per
manager is a thread manager's), each still supervised and restarted alone; the process
is one child of its parent, so a SIGKILL of it restarts only its managers. The idea is
Orleans' silo hosting grains, told in OTP's words: a supervisor whose children share its
node, itself a child of a supervisor on another node.

```
 parent Node ── Starting.start_pool ─► ProcessManager (its process: `pool_manager`)
                                          │ child.main: the pool's own registrar (its name,
                                          │ no servers), then `setup` = PoolSetup:
                                          ▼
                                        Tree + Node (this module's `run`): thread managers,
                                        served on the system (the parent's address), their
                                        events relayed to the process's hub (HOOKS.hub)
 Stop (control pipe) ─► HOOKS.before_stop: the pool's Node stops its managers, in reverse
 the pool's Node gives up ─► tree.escalate: the process exits (POOL_GAVE_UP_EXIT): one
                             crash of the pool in its parent (OTP's escalation)
```

Heartbeats go to the pool's own registrar, so a hung pool process is killed and
restarted; a hang of one thread manager inside it is not seen (as for any thread manager).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
from typing import TYPE_CHECKING

from rr_actors._core import runtime, wire
from rr_actors._process.child import HOOKS
from rr_actors._process.control import POOL_GAVE_UP_EXIT
from rr_actors.config import Durability, ManagerSpec, SupervisorSpec, managers
from rr_actors.errors import ConfigError, SupervisorGaveUpError

if TYPE_CHECKING:
    from rr_actors._registrar import ResourceRegistrar
    from rr_actors._transport.messenger import Address

__all__ = [
    "POOL_HEARTBEAT",
    "POOL_STOP_MARGIN",
    "PoolSetup",
    "is_pool",
    "pool_manager",
    "pool_setup",
]

logger = logging.getLogger("rr_actors")

POOL_HEARTBEAT = 1.0
"""Seconds between heartbeats to a pool's process (hung after three missed): its one
registrar shares the process's interpreter with every manager of the pool."""

POOL_STOP_MARGIN = 5.0
"""Seconds a pool's process gets to stop beyond the sum of its managers' `shutdown`."""

_STOP_SHARE = 0.8  # of a Stop's timeout, what the pool's managers get (its registrar, the rest)


def is_pool(spec: ManagerSpec | SupervisorSpec) -> bool:
    """Whether `spec` is a supervisor that runs in an OS process of its own."""
    return isinstance(spec, SupervisorSpec) and spec.isolation == "process"


def pool_manager(spec: SupervisorSpec) -> ManagerSpec:
    """How the parent starts and watches a pool's process: as a process manager named
    after the pool (its restart type; `shutdown` and `start_timeout` its managers' sums)."""
    members = managers(spec)
    return ManagerSpec(
        spec.name,
        isolation="process",
        restart=spec.restart,
        shutdown=sum(m.shutdown for m in members) + POOL_STOP_MARGIN,
        heartbeat=POOL_HEARTBEAT,
        start_timeout=sum(m.start_timeout for m in members) or 30.0,
    )


def pool_setup(
    spec: SupervisorSpec,
    address: Address | None,
    durability: Durability,
    state_dir: str | os.PathLike[str] | None,
) -> bytes:
    """The pickled `setup` of a pool's registrar (`ConfigError`: a setup cannot be pickled)."""
    own = spec.state_dir if spec.state_dir is not None else state_dir
    inner = dataclasses.replace(spec, isolation="thread", state_dir=own)
    try:
        return wire.dumps(PoolSetup(inner, address, durability))
    except Exception as exc:
        raise ConfigError(f"a setup in pool {spec.name!r} is not picklable: {exc}") from exc


class PoolSetup:
    """`setup(registrar)` of a pool's registrar: start its supervisor in this process.

    Runs on the pool process's main thread, before it reports ready: every manager of
    the pool has restored its catalog and serves when it returns.
    """

    def __init__(
        self, spec: SupervisorSpec, address: Address | None, durability: Durability
    ) -> None:
        self.spec = spec
        self.address = address
        self.durability = durability

    def __call__(self, registrar: ResourceRegistrar) -> None:
        from rr_actors._supervision.policy import Node  # noqa: PLC0415 - policy imports us
        from rr_actors._supervision.tree import Tree  # noqa: PLC0415

        network = self.address.attach() if self.address is not None else None
        tree = Tree(self.spec, clock=runtime.monotonic, network=network, durability=self.durability)
        tree.escalate = _gave_up
        tree.processes.open(0, 0.0)  # (the system given: no spares, all threads)
        if HOOKS.hub is not None:
            tree.events.publisher.relay_to(HOOKS.hub)  # forwarded to the parent, when it listens
        node = Node(self.spec, tree)
        node.start()

        def stop(timeout: float, restarting: bool) -> None:
            node.stop(timeout=timeout * _STOP_SHARE, restarting=restarting)

        HOOKS.before_stop = stop


def _gave_up(error: SupervisorGaveUpError) -> None:
    """The pool's supervisor gave up: its process ends, its parent decides (the managers'
    catalogs keep what they committed, as after a SIGKILL)."""
    logger.error("%s: its process exits, its parent decides", error)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(POOL_GAVE_UP_EXIT)
