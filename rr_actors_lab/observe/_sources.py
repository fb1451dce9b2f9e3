"""Where the page's sections come from: a live supervision tree, or a directory of backups.

```
 LiveSource (a running Supervisor)
   tree watcher thread ── waits on the tree's condition (each publish) ──► "tree"
   event subscription ─── every event (to_dict + describe) ──────────────► events
        ├─ a StatusSent: named here, once (StatusNames)
        └─ marks registrars dirty ──► catalog refresher thread ──────────► "catalog/<name>",
                                      (Supervisor.run_in(name, catalog_of))  "graph"
 BackupSource (a state directory)
   poller thread ── a backup file changed ── read_backup ──► "files", "catalog/<name>", "graph"
```

Both only read, and unpickle nothing (they show the display texts each registrar stored:
a file may be another user's). Every wait is bounded; `close()` ends the threads.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from rr_actors import events
from rr_actors._registrar import snapshot
from rr_actors._store import read_backup
from rr_actors._supervision.watching import TreeAccess
from rr_actors.config import SupervisorSpec, managers
from rr_actors.errors import ConfigError
from rr_actors_lab.observe._hub import Hub
from rr_actors_lab.observe._view import (
    dependency_graph,
    resource_name,
    shown,
    summarise_catalog,
)

if TYPE_CHECKING:
    from rr_actors._core.bus import Subscription
    from rr_actors._registrar import ResourceRegistrar

__all__ = [
    "CATALOG_INTERVAL",
    "FULL_REFRESH",
    "BackupSource",
    "LiveSource",
    "Observable",
    "StatusNames",
    "TreeAccess",
    "backup_files",
]

logger = logging.getLogger("rr_actors")

CATALOG_INTERVAL = 0.5
"""Seconds between two rounds of catalog snapshots (each competes with the work it shows)."""

FULL_REFRESH = 5.0
"""Seconds after which every catalog is read again, even without an event about it."""

SNAPSHOT_TIMEOUT = 1.0
"""Seconds the observer waits for one registrar's catalog (a hung manager is skipped)."""

POLL_INTERVAL = 1.0
"""Seconds between two looks at a state directory's backup files."""

NAMES_KEPT = 10_000
"""Consumers (and resources) whose provider's events a `StatusNames` keeps to name a status
by (the oldest are forgotten first: a release missed in an `EventsDropped` is not kept)."""


class ChildView(Protocol):
    """What the observer reads of a child's snapshot (`rr_actors.ChildInfo`, a layer up)."""

    @property
    def kind(self) -> str: ...
    @property
    def isolation(self) -> str | None: ...
    @property
    def restart(self) -> str: ...
    @property
    def state(self) -> str: ...
    @property
    def pid(self) -> int | None: ...
    @property
    def restarts(self) -> int: ...
    @property
    def last_exit(self) -> str | None: ...


class Observable(Protocol):
    """The public part of a `Supervisor` the observer uses."""

    @property
    def name(self) -> str:
        """The supervisor's name."""

    @property
    def gave_up(self) -> Exception | None:
        """Its give-up error, if it gave up."""

    def snapshot(self, name: str) -> ChildView:
        """The snapshot of child `name` (before the start too)."""

    def subscribe(
        self, callback: Callable[[events.Event], object], *, maxsize: int = ...
    ) -> Subscription[events.Event]:
        """Subscribe to the tree's events."""

    def run_in(
        self, name: str, fn: Callable[[ResourceRegistrar], Any], *, timeout: float = ...
    ) -> Any:
        """Run `fn(registrar)` in manager `name`'s process."""


def event_dict(event: events.Event) -> dict[str, Any]:
    """An event as the page gets it: `to_dict` plus its `describe` line as `"text"`."""
    data = events.to_dict(event)
    data["text"] = events.describe(event)
    return data


def _touched(event: events.Event) -> tuple[str, ...] | None:
    """The registrars whose catalog an event changed (`None`: possibly every one)."""
    match event:
        case events.ConsumerAdded() | events.ConsumerReleased():
            return (event.registrar, event.consumer)
        case (
            events.ResourceLoaded()
            | events.LoadFailed()
            | events.ResourceUnloaded()
            | events.InDoubt()
            | events.CallAnswered()
            | events.CallFailed()
            | events.CallWithdrawn()
            | events.QueryForgotten()
        ):
            return (event.registrar,)
        case events.ChildStarted() | events.ChildRestarted() | events.ChildExited():
            return (event.child,)
        case (
            events.StatusSent()
            | events.StatusDelivered()
            | events.StatusHandled()
            | events.UnloadCutShort()
            | events.ManagerOverloaded()
            | events.ServerOverloaded()
            | events.ShareRefused()
            | events.ShareAdmitted()
            | events.StatusAnswered()
            | events.QueriesFetched()
            | events.ServerQueriesListed()
            | events.EventsUnpublished()
        ):
            return ()
        case events.SupervisorGaveUp() | events.EventsDropped():
            return None
    return None


def _keep(names: dict[tuple[str, str, str], str], key: tuple[str, str, str], value: str) -> None:
    """`names[key] = value`, forgetting the oldest beyond `NAMES_KEPT`."""
    names[key] = value
    while len(names) > NAMES_KEPT:
        del names[next(iter(names))]


class StatusNames:
    """Names each status sent by the resource it is about, once, as it enters a history, so every
    page (open during the send or later) draws the same row.

    `name`: the graph's label of the resource the consumer holds (by the catalog last known,
    else its `ConsumerAdded`), else the `ResourceLoaded`'s label, else the query id: the
    provider publishes those events before any status about them. Fed on one thread (not
    locked); a registrar is known by host and name; at most `NAMES_KEPT` of each are kept.
    """

    def __init__(self) -> None:
        self._held: dict[tuple[str, str, str], str] = {}  # (host, registrar, query id): resource
        self._loaded: dict[tuple[str, str, str], str] = {}  # (host, registrar, resource): name

    def note(self, event: events.Event) -> None:
        """Keep which resource each consumer holds, and each resource's name, from `event`
        (any event: only loads, unloads, consumers added and released are kept)."""
        match event:
            case events.ResourceLoaded() if event.label is not None:
                name = f"{event.registrar}/{event.server} {shown(event.label)}"
                _keep(self._loaded, (event.host, event.registrar, event.resource_id), name)
            case events.ResourceUnloaded():
                self._loaded.pop((event.host, event.registrar, event.resource_id), None)
            case events.ConsumerAdded():
                _keep(self._held, (event.host, event.registrar, event.query_id), event.resource_id)
            case events.ConsumerReleased():
                self._held.pop((event.host, event.registrar, event.query_id), None)

    def name(self, sent: events.StatusSent, catalog: Mapping[str, Any] | None) -> str:
        """`"<registrar>/<server> <label>"` of the resource `sent` is about, else
        `"<registrar> (query <first 8 of its id>)"`; `catalog`: the provider's summary, or
        `None`."""
        held = self._held.get((sent.host, sent.registrar, sent.query_id))
        name = resource_name(catalog, sent.query_id, held)
        if name is None and held is not None:
            name = self._loaded.get((sent.host, sent.registrar, held))
        return name or f"{sent.registrar} (query {sent.query_id[:8]})"


def catalog_of(registrar: ResourceRegistrar, *, timeout: float) -> Any:
    """The registrar's catalog summary (`rr_actors_lab.observe._view`): plain dicts, lists, strings.

    Runs in the registrar's process on the caller's thread; the registrar copies its rows on
    its actor thread (`rr_actors._registrar.snapshot`). No `repr` runs: the summary shows the
    display texts stored with each value.

    Raises:
        CallTimeoutError: the registrar did not answer within `timeout` seconds.
        RegistrarStoppedError: it was stopped.
        RegistrarUnavailableError: it died.
    """
    view = snapshot(registrar, timeout=timeout, check=False)
    return summarise_catalog(
        registrar.name,
        view.resources,
        view.clients,
        servers=view.servers,
        in_doubt=view.in_doubt,
    )


class LiveSource:
    """Keeps the hub's sections up to date with a running supervision tree.

    Args:
        sup: the supervisor.
        access: what the supervisor hands over besides its public methods.
        hub: where the sections go.
    """

    def __init__(self, sup: Observable, access: TreeAccess, hub: Hub | None = None) -> None:
        self.sup = sup
        self.access = access
        self.hub = hub if hub is not None else Hub()
        self.specs = {m.name: m for m in managers(access.spec)}
        self._closing = threading.Event()
        self._dirty_cond = threading.Condition()
        self._dirty: set[str] | None = None  # None: every registrar
        self._states: dict[str, str] = {}
        self._catalogs: dict[str, dict[str, Any]] = {}
        self._names = StatusNames()  # (the subscription's thread only)
        self._subscription: Subscription[events.Event] | None = None
        self._threads: list[threading.Thread] = []

    def start(self) -> None:
        """Subscribe to the tree's events and start the watcher and refresher threads."""
        self._subscription = self.sup.subscribe(self._on_event)
        for target, role in ((self._watch_tree, "tree"), (self._refresh_catalogs, "catalogs")):
            thread = threading.Thread(
                target=target, name=f"rr-observe-{self.sup.name}-{role}", daemon=True
            )
            thread.start()
            self._threads.append(thread)

    def close(self, timeout: float = 5.0) -> None:
        """Unsubscribe and end the threads (each within `timeout` seconds)."""
        self._closing.set()
        self.access.changes.wake()
        with self._dirty_cond:
            self._dirty_cond.notify_all()
        if self._subscription is not None:
            self._subscription.close(timeout=timeout)
        for thread in self._threads:
            thread.join(timeout)

    def snapshot(self) -> tuple[dict[str, Any], dict[str, Any]]:
        """`(tree, graph)` now, as the page gets them, read on the calling thread."""
        tree = self.tree()
        self._note_states(tree)
        self._refresh(None)
        graph: dict[str, Any] = self.hub.get("graph")
        return tree, graph

    # -- the supervision tree -------------------------------------------------------------

    def tree(self) -> dict[str, Any]:
        """The tree's snapshot as the page shows it (each child's as last published)."""
        spec = self.access.spec
        gave_up = self.sup.gave_up
        if gave_up is not None:
            state = "gave up"
        elif self.access.running():
            state = "running"
        else:
            state = "stopped"
        return {
            **self._supervisor(spec, self.sup.name),
            "state": state,
            "gave_up": str(gave_up) if gave_up is not None else None,
            "server_time": time.time(),
        }

    def _supervisor(self, spec: SupervisorSpec, name: str) -> dict[str, Any]:
        due = self.access.restart_due
        children = []
        for child in spec.children:
            info = self.sup.snapshot(child.name)
            entry: dict[str, Any] = {
                "name": child.name,
                "kind": info.kind,
                "isolation": info.isolation,
                "restart": info.restart,
                "state": info.state,
                "pid": info.pid,
                "restarts": info.restarts,
                "last_exit": info.last_exit,
                "restart_due": due.get(child.name) if info.state == "restarting" else None,
            }
            if isinstance(child, SupervisorSpec):
                entry.update(self._supervisor(child, child.name))
                entry["state"] = info.state
            else:
                entry["hang_after"] = child.hang_after if child.isolation == "process" else None
            children.append(entry)
        return {
            "name": name,
            "kind": "supervisor",
            "strategy": spec.strategy,
            "max_restarts": spec.max_restarts,
            "period": spec.period,
            "children": children,
        }

    def _watch_tree(self) -> None:
        changes = self.access.changes
        while not self._closing.is_set():  # read again at each publish
            seen = changes.version()  # (before the read: a publish during it wakes at once)
            try:
                tree = self.tree()
                self.hub.put("tree", tree)
                self._note_states(tree)
            except Exception:
                logger.exception("observer of %s: reading the tree failed", self.sup.name)
            changes.wait_changed(seen, timeout=FULL_REFRESH)

    def _note_states(self, tree: dict[str, Any]) -> None:
        states: dict[str, str] = {}

        def walk(node: dict[str, Any]) -> None:
            for child in node["children"]:
                if child["kind"] == "manager":
                    states[child["name"]] = child["state"]
                else:
                    walk(child)

        walk(tree)
        changed = [name for name, state in states.items() if self._states.get(name) != state]
        self._states = states
        if changed:
            self._mark(tuple(changed))

    # -- events ---------------------------------------------------------------------------

    def _on_event(self, event: events.Event) -> None:
        """Runs on the subscription's thread, one event at a time; names a status sent
        (`StatusNames`)."""
        if isinstance(event, events.StatusSent):
            section = self._catalogs.get(event.registrar)
            name = self._names.name(event, section and section["catalog"])
            self.hub.add_event({**event_dict(event), "resource": name})
        else:
            self._names.note(event)
            self.hub.add_event(event)
        touched = _touched(event)
        if touched != ():
            self._mark(touched)

    def _mark(self, names: tuple[str, ...] | None) -> None:
        with self._dirty_cond:
            if names is None:
                self._dirty = None
            elif self._dirty is not None:
                self._dirty.update(names)
            self._dirty_cond.notify()

    # -- the catalogs ---------------------------------------------------------------------

    def _registrars(self) -> dict[str, ResourceRegistrar | None]:
        """Every registrar to show: the managers (`None`), then the local consumers."""
        names: dict[str, ResourceRegistrar | None] = dict.fromkeys(self.specs)
        for registrar in self.access.registrars():
            if registrar.is_alive():
                names.setdefault(registrar.name, registrar)
        return names

    def _refresh_catalogs(self) -> None:
        while not self._closing.is_set():
            with self._dirty_cond:
                if self._dirty is not None and not self._dirty:
                    self._dirty_cond.wait(FULL_REFRESH)
                    if self._dirty is not None and not self._dirty:
                        self._dirty = None  # nothing happened for a while: read them all
                dirty, self._dirty = self._dirty, set()
            if self._closing.is_set():
                return
            try:
                self._refresh(dirty)
            except Exception:
                logger.exception("observer of %s: reading the catalogs failed", self.sup.name)
            self._closing.wait(CATALOG_INTERVAL)  # at most one round per interval

    def _refresh(self, dirty: set[str] | None) -> None:
        registrars = self._registrars()
        for name in list(self._catalogs):
            if name not in registrars:
                del self._catalogs[name]
                self.hub.remove(f"catalog/{name}")
        for name, local in registrars.items():
            if dirty is not None and name not in dirty and name in self._catalogs:
                continue
            section = self._read(name, local)
            self._catalogs[name] = section
            self.hub.put(f"catalog/{name}", section)
        catalogs = {name: s["catalog"] for name, s in self._catalogs.items()}  # (or last seen)
        states = {name: s["state"] for name, s in self._catalogs.items()}
        self.hub.put("graph", dependency_graph(catalogs, states))

    def _read(self, name: str, local: ResourceRegistrar | None) -> dict[str, Any]:
        """One registrar's catalog section; the last one known if it cannot be read now."""
        last = self._catalogs.get(name)
        known = last["catalog"] if last is not None else None
        if local is not None:
            state, kind = "running", "consumer"
        else:
            state = self._states.get(name) or self.sup.snapshot(name).state
            kind = f"{self.specs[name].isolation} manager"
        section = {"registrar": name, "kind": kind, "state": state, "available": False}
        if state != "running":
            return {**section, "catalog": known, "error": None}
        try:
            if local is not None:
                catalog = catalog_of(local, timeout=SNAPSHOT_TIMEOUT)
            else:
                read = functools.partial(catalog_of, timeout=SNAPSHOT_TIMEOUT)
                catalog = self.sup.run_in(name, read, timeout=SNAPSHOT_TIMEOUT + 0.5)
        except Exception as exc:  # noqa: BLE001 - dead, hung, stopping: show it, keep the last
            return {**section, "catalog": known, "error": f"{type(exc).__name__}: {exc}"}
        return {**section, "available": True, "catalog": catalog, "error": None}


# -- backups ---------------------------------------------------------------------------------


def backup_files(state_dir: str | os.PathLike[str]) -> list[Path]:
    """The catalog backups (`*.db`) of a state directory, sorted by name.

    Raises:
        ConfigError: `state_dir` does not exist, is not a directory, or holds no backup.
    """
    path = Path(os.fspath(state_dir))
    if not path.exists():
        raise ConfigError(f"state directory {str(path)!r} does not exist")
    if not path.is_dir():
        raise ConfigError(f"state directory {str(path)!r} is not a directory")
    files = sorted(p for p in path.glob("*.db") if p.is_file())
    if not files:
        raise ConfigError(f"state directory {str(path)!r} holds no catalog backup (*.db)")
    return files


def read_catalogs(files: list[Path]) -> dict[str, dict[str, Any]]:
    """Read every backup (registrar name: the file's stem) into catalog summaries, unpickling
    nothing.

    Raises:
        CatalogCorruptError: a file is not a readable catalog (the error names it).
    """
    catalogs = {}
    for file in files:
        backup = read_backup(file, unpickle=False)
        catalogs[file.stem] = {
            **summarise_catalog(file.stem, backup.resources, backup.clients),
            "schema_version": backup.schema_version,
        }
    return catalogs


def _signature(file: Path) -> tuple[int, ...]:
    sig: list[int] = []
    for suffix in ("", "-wal"):
        try:
            stat = os.stat(f"{file}{suffix}")
        except OSError:
            sig.extend((0, 0))
        else:
            sig.extend((stat.st_mtime_ns, stat.st_size))
    return tuple(sig)


class BackupSource:
    """Keeps the hub's sections up to date with the backups of a state directory (read once at
    construction, then polled every `POLL_INTERVAL` seconds on a thread; nothing written).

    Raises:
        ConfigError: the directory does not exist or holds no backup.
        CatalogCorruptError: a backup is not a readable catalog (the error names it).
    """

    def __init__(self, state_dir: str | os.PathLike[str], hub: Hub) -> None:
        self.state_dir = Path(os.fspath(state_dir))
        self.hub = hub
        self._files = backup_files(self.state_dir)
        self._catalogs = read_catalogs(self._files)  # raises before anything is served
        self._signatures = {f.stem: _signature(f) for f in self._files}
        self._errors: dict[str, str] = {}
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._publish()

    def start(self) -> None:
        """Start looking for changes."""
        self._thread = threading.Thread(target=self._poll, name="rr-observe-backups", daemon=True)
        self._thread.start()

    def close(self, timeout: float = 5.0) -> None:
        """Stop looking (within `timeout` seconds)."""
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def _poll(self) -> None:
        while not self._closing.wait(POLL_INTERVAL):
            try:
                self._look()
            except Exception:
                logger.exception("observer: reading the backups in %s failed", self.state_dir)

    def _look(self) -> None:
        files = sorted(p for p in self.state_dir.glob("*.db") if p.is_file())
        changed = {f.stem for f in files} != set(self._catalogs) | set(self._errors)
        for file in files:
            signature = _signature(file)
            if self._signatures.get(file.stem) == signature:
                continue
            self._signatures[file.stem] = signature
            changed = True
            try:
                self._catalogs.update(read_catalogs([file]))
                self._errors.pop(file.stem, None)
            except Exception as exc:  # noqa: BLE001 - shown on the page, named
                self._catalogs.pop(file.stem, None)
                self._errors[file.stem] = str(exc)
        names = {f.stem for f in files}
        for gone in (set(self._catalogs) | set(self._errors)) - names:
            self._catalogs.pop(gone, None)
            self._errors.pop(gone, None)
            self._signatures.pop(gone, None)
            self.hub.remove(f"catalog/{gone}")
        self._files = files
        if changed:
            self._publish()

    def _publish(self) -> None:
        files = []
        for file in self._files:
            name = file.stem
            catalog = self._catalogs.get(name)
            files.append(
                {
                    "registrar": name,
                    "path": str(file),
                    "schema_version": catalog["schema_version"] if catalog else None,
                    "resources": len(catalog["resources"]) if catalog else None,
                    "clients": len(catalog["clients"]) if catalog else None,
                    "error": self._errors.get(name),
                }
            )
            self.hub.put(
                f"catalog/{name}",
                {
                    "registrar": name,
                    "kind": "backup",
                    "state": "backup" if catalog else "unreadable",
                    "available": catalog is not None,
                    "catalog": catalog,
                    "error": self._errors.get(name),
                },
            )
        self.hub.put("files", {"state_dir": str(self.state_dir), "files": files})
        self.hub.put("graph", dependency_graph(dict(self._catalogs)))
