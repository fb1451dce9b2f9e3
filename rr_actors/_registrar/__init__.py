"""The resource registrar: its handle, its actor (in a few modules, by side), its messages.

```
 handle       Registrar, the one handle user code holds wherever the actor lives: its
              blocking methods and their awaitable twins written once; `Here`, the
              actor in this process (ResourceRegistrar's); StatusWatch
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
```

Each module calls only those listed below it (`pyproject.toml`, "Inside the registrar").
"""

from rr_actors._registrar.handle import (
    Registrar,
    ResourceRegistrar,
    StatusWatch,
    snapshot,
    start_registrar,
)
from rr_actors._registrar.life import CatalogView, Served
from rr_actors._registrar.messages import give_back

__all__ = [
    "CatalogView",
    "Registrar",
    "ResourceRegistrar",
    "Served",
    "StatusWatch",
    "give_back",
    "snapshot",
    "start_registrar",
]
