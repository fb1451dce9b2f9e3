"""The resource registrar: its messages, its actor (split by role) and its handle.

- `handle`: `Registrar`, the one handle user code holds wherever the actor lives, its
  blocking methods and their awaitable twins written once; `Here`, the actor in this
  process (`ResourceRegistrar`'s); `StatusWatch`; `calls`: the call protocol on the
  caller's thread;
- `actor`: the registrar actor, dispatching to its roles `provider` (loads; `matching`
  runs user code off the actor), `unloading`, `servers`, `consumer`, `status`,
  `presence` (peers lost for good or reachable again) and `lifecycle`, which share
  `state`; `starting`: the start protocol, and `Served`/`Network`, how a carrier sees it;
- `endpoints`: the resource server and client actors; `messages`: everything they tell
  each other, as data; `deathwatch`: the one place that says a registrar will not come
  back (the layers above call it, never build a message); `loading`: what a load
  callback runs inside; `probes`: the testing seam on named steps.
"""

from rr_actors._registrar.handle import (
    Registrar,
    ResourceRegistrar,
    StatusWatch,
    snapshot,
    start_registrar,
)
from rr_actors._registrar.lifecycle import CatalogView
from rr_actors._registrar.loading import MAX_DEPENDENCY_DEPTH
from rr_actors._registrar.messages import give_back
from rr_actors._registrar.starting import Served

__all__ = [
    "MAX_DEPENDENCY_DEPTH",
    "CatalogView",
    "Registrar",
    "ResourceRegistrar",
    "Served",
    "StatusWatch",
    "give_back",
    "snapshot",
    "start_registrar",
]
