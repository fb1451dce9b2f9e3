"""The resource registrar: its handle, its actor (in a few modules, by side), its messages.

```
 handle       ResourceRegistrar, what user code holds; aio: its awaitable twins
 actor        the registrar actor: started (`launch`), its dispatch table
 life         its life: start, restore, presence (peers lost, reachable), stop, death,
              the death watch; `Served`: how a carrier sees it
 provider     a resource's life: load once, share, release, unload once; the servers
              and their actors, which run user code
 status       statuses sent, fanned out in one pass per process, climbing dependencies
 consumer     a call's life after it was sent: answered, in flight, held, released,
              reconciled; the client actors
 calls        the call protocol on the caller's thread, and its attempt's states
 display      display texts, made once, user code off the actor
 state        the record every part shares, the probes on its steps
 messages     everything they tell each other, as data; what a load callback runs in
 protocol     the `Registrar` API both placements implement (its callbacks' types)
```

Each module calls only those listed below it (`pyproject.toml`, "Inside the registrar").
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
