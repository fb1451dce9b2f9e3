"""The observer: a live web page of a supervision tree, and its text drawings.

Open one with [`Supervisor.observe`][rr_actors.Supervisor.observe] (or `rr-actors demo
--observe`); `rr-actors observe --state DIR` shows a state directory's backups the same
way, and [`Supervisor.graph`][rr_actors.Supervisor.graph] / `rr-actors graph` draw the
tree and the dependency graph as Mermaid or DOT text.

```
 Supervisor ── events (subscribe) ──────────► LiveSource ─┐
     │    └── snapshots (tree condition) ────►            │
     └── run_in(name, catalog_of) ───────────►            ├─► Hub ─► web server ─► pages
 state directory ── read_backup (read-only) ─► BackupSource┘     (SSE: sections, events)
```

Across hosts (a supervisor on a `ZenohNetwork`), `_share` shares each host's state as
JSON and `_system` keeps a page of every host (`observe_system`: a page from a member
without a tree); `_crossing` (what crosses, and its checks), `_liveness` (the hosts'
and links' sections), `_faults_across` (fault commands to another host). Beside every
Zenoh session (`_feed.Across`, attached when imported): the system's event stream
(`_feed`, `ZenohNetwork.subscribe_events`; each batch sealed by its host, `_seal`) and
a router's link watch (`_links`).

Modules: `_view` (what is shown, as data), `_hub` (the sections and recent events, for
every page), `_sources` (live tree, backups; a registrar's catalog, read in its own
process), `_faults` (teaching mode), `_server` (Starlette app, uvicorn thread),
`_observer` (the `Observer` handle), `_text` (Mermaid and DOT), `_commands` (the
command line). The web server's dependencies are the `observe` extra and are imported
only when an observer opens; the drawings need nothing more than rr_actors.
"""

from rr_actors.observe._observer import (
    Observer,
    observe_backups,
    observe_system,
    require_extra,
)
from rr_actors.observe._text import FORMATS

__all__ = ["FORMATS", "Observer", "observe_backups", "observe_system", "require_extra"]
