"""The resource registrar: its messages, its actor (split by role) and its handle.

- `protocol`: the `Registrar` API both placements implement;
- `handle`: `ResourceRegistrar`, what user code holds; `calls`: the call protocol on the
  caller's thread; `aio`: the handles' awaitable twins and `StatusWatch`, written once;
- `actor`: the registrar actor, dispatching to its roles `provider` (loads; `matching`
  runs user code off the actor), `unloading`, `servers`, `consumer`, `status`,
  `presence` (peers lost for good or reachable again) and `lifecycle`, which share
  `state`; `starting`: the start protocol, and `Served`/`Network`, how a carrier sees it;
- `endpoints`: the resource server and client actors; `messages`: everything they tell
  each other, as data; `deathwatch`: the one place that says a registrar will not come
  back (the layers above call it, never build a message); `loading`: what a load
  callback runs inside; `probes`: the testing seam on named steps.
"""

from typing import TYPE_CHECKING

from rr_actors._registrar.aio import StatusWatch
from rr_actors._registrar.handle import ResourceRegistrar, snapshot, start_registrar
from rr_actors._registrar.life import CatalogView, Served
from rr_actors._registrar.messages import MAX_DEPENDENCY_DEPTH, give_back
from rr_actors._registrar.protocol import LoadCallback, Registrar, UnloadCallback

__all__ = [
    "MAX_DEPENDENCY_DEPTH",
    "CatalogView",
    "LoadCallback",
    "Registrar",
    "ResourceRegistrar",
    "Served",
    "StatusWatch",
    "UnloadCallback",
    "give_back",
    "snapshot",
    "start_registrar",
]

if TYPE_CHECKING:  # mypy checks that the handle implements the protocol
    _implements: type[Registrar] = ResourceRegistrar
