"""The observer: a live web page of a supervision tree, and its text drawings.

Open one with `observe(sup)` (or `rr-actors demo --observe`); `rr-actors observe --state
DIR` shows a state directory's backups the same way, and `graph(sup)` / `rr-actors graph`
draw the tree and the dependency graph as Mermaid or DOT text. (`sup.observe()` and
`sup.graph()`, their former spellings, warn and call these for one release.)

```
 Supervisor ── events (subscribe) ──────────► LiveSource ─┐
     │    └── snapshots (tree condition) ────►            │
     └── run_in(name, catalog_of) ───────────►            ├─► Hub ─► web server ─► pages
 state directory ── read_backup (read-only) ─► BackupSource┘     (SSE: sections, events)
```

Across hosts (a supervisor on a `ZenohNetwork`), `_share` shares each host's state and
`_system` keeps a page of every host (`observe_system`). Beside every Zenoh session
(`_feed.Across`): the system's event stream (`_feed`, sealed by `_seal`) and a router's
link watch (`_links`). Each module's role: docs/reference/modules.md. The web server's
dependencies are the `observe` extra, imported only when an observer opens.
"""

from rr_actors_lab.observe._observer import (
    Observer,
    graph,
    observe,
    observe_backups,
    observe_system,
    require_extra,
)
from rr_actors_lab.observe._text import FORMATS

__all__ = [
    "FORMATS",
    "Observer",
    "graph",
    "observe",
    "observe_backups",
    "observe_system",
    "require_extra",
]
