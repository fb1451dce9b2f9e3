"""What the mission holds: the robot and the LiDARs it loaded, and how it lets them go.

robot() / lidar(name) ── Trees.call_with_retry ──► rm / cm (waiting out their restarts)
    │  the query id is held, (id, provider), until it is unloaded or forgotten
    └─ on_status ─► a queue ─► next_event(): the drive hears every status on its thread
robot_once(timeout)      F6: one call to rm, no retry (it fails fast during the cut)
release(id)              F1: the dead LiDAR's id unloaded (through cm's restarts)
forget(provider)         F6: the ids the station forgot when rm was lost (rule 19)
unload_now(provider)     F6: cm's LiDARs unloaded at once (they lost their program)
unload_all()             the end: every id held, newest first ─► catalogs(): rows left
"""

from __future__ import annotations

import contextlib
import functools
import os
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import rr_actors as rr
from rr_actors.testing import catalog_snapshot
from rr_actors_lab.mission.config import MANAGERS, MissionConfig
from rr_actors_lab.mission.faults import retry_through_restarts
from rr_actors_lab.mission.hosts import Trees

__all__ = ["Loads", "StatusEvent"]


@dataclass(frozen=True)
class StatusEvent:
    """A status a query of the mission heard (queued by its callback).

    Attributes:
        kind: which of the mission's queries heard it.
        query_id: that query's id.
        update: what it heard.
        at: when (monotonic seconds).
    """

    kind: Literal["lidar", "robot"]
    query_id: str
    update: rr.StatusUpdate
    at: float


def _catalog_size(registrar: rr.ResourceRegistrar) -> int:
    """Rows in a registrar's catalog (run inside the manager, via `Supervisor.run_in`)."""
    view = catalog_snapshot(registrar)
    return len(view.resources) + len(view.clients)


class Loads:
    """The queries the mission holds, loaded from the managers and unloaded at the end.

    Every call waits out a restart of its manager but `robot_once` and `unload_now` (F6 wants
    them to fail fast). Runs on the mission's thread; the status callbacks only queue.

    Args:
        config: the mission (its timeouts, the programs' rates, the seed).
        sup: the managers' trees.
        app: the mission's registrar.
        bus: the programs' topics.
        say: tells one line of the story.

    Attributes:
        failed_unloads: the unloads at the end that failed (each was told).
    """

    def __init__(
        self,
        config: MissionConfig,
        sup: Trees,
        app: rr.ResourceRegistrar,
        bus: Path,
        *,
        say: Callable[[str], None],
    ) -> None:
        self._config = config
        self._sup = sup
        self._app = app
        self._bus = bus
        self._say = say
        self._events: queue.SimpleQueue[StatusEvent] = queue.SimpleQueue()
        self._held: list[tuple[str, str]] = []  # (query id, provider) the mission holds
        self.failed_unloads = 0

    # -- loading ------------------------------------------------------------------------

    def robot(self) -> rr.Query:
        """Load the robot from `rm`, waiting out a restart of it; the mission holds the id."""
        return self._load("rm", "robot", self._robot_request(), self._robot_cb)

    def lidar(self, name: str) -> rr.Query:
        """Load LiDAR `name` from `cm`, waiting out a restart of it; the mission holds the id."""
        return self._load("cm", "lidar", self._lidar_request(name), self._lidar_cb)

    def robot_once(self, *, timeout: float) -> rr.Query:
        """Load the robot from `rm` in one call (no retry); the mission holds the id.

        Raises:
            RegistrarUnavailableError, UnknownRegistrarError: `rm` is not reachable now.
        """
        robot = self._app.call(
            "rm", "robot", self._robot_request(), on_status=self._robot_cb, timeout=timeout
        )
        self._held.append((robot.id, "rm"))
        return robot

    def _load(
        self, provider: str, server: str, request: dict[str, Any], on_status: rr.StatusCallback
    ) -> rr.Query:
        query = self._sup.call_with_retry(
            self._app,
            provider,
            server,
            request,
            on_status=on_status,
            timeout=self._config.call_timeout,
        )
        self._held.append((query.id, provider))
        return query

    def holds(self, query_id: str) -> bool:
        """Whether the mission holds `query_id` (not let go of already)."""
        return any(query_id == held for held, _ in self._held)

    def next_event(self, timeout: float) -> StatusEvent | None:
        """The next status a query heard, waiting `timeout` seconds at most for one."""
        try:
            return self._events.get(timeout=timeout)
        except queue.Empty:
            return None

    # -- letting go ---------------------------------------------------------------------

    def release(self, query_id: str) -> None:
        """Unload `query_id` from `cm`, waiting out a restart of it; it is held no more."""
        with contextlib.suppress(rr.UnknownQueryError):
            retry_through_restarts(
                self._sup,
                "cm",
                lambda: self._app.unload(query_id),
                timeout=self._config.call_timeout,
            )
        self._held = [(q, p) for q, p in self._held if q != query_id]

    def forget(self, provider: str) -> None:
        """Hold what `provider` served no more, without unloading it (it forgot it)."""
        self._held = [(q, p) for q, p in self._held if p != provider]

    def unload_now(self, provider: str) -> None:
        """Unload what `provider` served, each in one call (no retry); held no more.

        A provider that died before it answered (`RegistrarUnavailableError`: F6's cut
        may find cm killed by its heartbeat meanwhile) released the id all the same: it
        does so when it reconciles with the mission after its restart (rule 20).
        """
        for query_id in [q for q, p in self._held if p == provider]:
            try:
                self._app.unload(query_id)
            except rr.UnknownQueryError:
                pass  # it forgot it already
            except rr.RegistrarUnavailableError:
                self._say(
                    f"{provider} died before it answered the unload of {query_id[:8]}; it "
                    "releases it when it reconciles after its restart"
                )
        self.forget(provider)

    def unload_all(self) -> None:
        """Unload everything the mission holds, newest first; a failure is told and counted."""
        timeout = self._config.call_timeout
        for query_id, provider in reversed(self._held):
            try:
                # A provider restarted meanwhile still knows the id (its catalog is durable);
                # one that had committed the unload before it died no longer does.
                with contextlib.suppress(rr.UnknownQueryError):
                    retry_through_restarts(
                        self._sup,
                        provider,
                        functools.partial(self._app.unload, query_id),
                        timeout=timeout,
                    )
            except rr.RrError as exc:
                self.failed_unloads += 1
                self._say(f"unloading {query_id[:8]} failed: {exc}")
        self._held.clear()
        self._say("everything unloaded")

    def catalogs(self) -> dict[str, int]:
        """The rows left in the mission's catalog and in each manager's (-1: not read)."""
        sup = self._sup
        entries = {"mission": _catalog_size(self._app)}
        for name in MANAGERS:
            try:
                entries[name] = int(
                    retry_through_restarts(
                        sup,
                        name,
                        functools.partial(sup.run_in, name, _catalog_size),
                        timeout=self._config.call_timeout,
                    )
                )
            except rr.RrError as exc:
                self._say(f"could not read the catalog of {name}: {exc}")
                entries[name] = -1
        return entries

    # -- requests and callbacks ---------------------------------------------------------

    def _robot_request(self) -> dict[str, Any]:
        cfg = self._config
        return {
            "robot": "jackal",
            "bus": str(self._bus),
            "watch_pid": os.getpid(),
            "driver_rate": cfg.driver_rate,
            "nav_rate": cfg.nav_rate,
            "cmd_timeout": cfg.cmd_timeout,
            "scan_timeout": cfg.scan_timeout,
        }

    def _lidar_request(self, name: str) -> dict[str, Any]:
        return {
            "name": name,
            "bus": str(self._bus),
            "watch_pid": os.getpid(),
            "rate": self._config.lidar_rate,
            "seed": self._config.seed,
        }

    def _lidar_cb(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        self._events.put(StatusEvent("lidar", query.id, update, time.monotonic()))

    def _robot_cb(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        self._events.put(StatusEvent("robot", query.id, update, time.monotonic()))
