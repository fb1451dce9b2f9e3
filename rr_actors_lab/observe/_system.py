"""A page's view of every host: the states other hosts share, checked and merged into its hub.

```
 host B (sharing)                                   host A (serving a page)
 LiveSource ─► local Hub ─► Share ── delta (JSON puts, numbered) ──► SystemView ─► page Hub
                             │  └─── state (queryable: JSON) ◄──── asked at a gap ┘   │
                             │  └─── here (liveliness token) ────► live / stale       │
                             └ FaultDesk (queryable) ◄── JSON command ── page's button ┘
                  LinkWatch ─► "links" (each member's link: up, or cut since when, why)
```

The view runs on one executor thread (`rr-observe-system`; Zenoh's callbacks only queue):
a delta patches the mirror if it is the next `seq`, else the host's state is asked; a
newer state replaces it; a token says a host is here or gone; every `LINKS_EVERY` s the
hosts that lag are asked and `hosts`, `links`, `graph` refreshed. The system's event
stream goes to `_on_event`. `_crossing.py`: what crosses; `_share.py`: the sending side;
`_liveness.py`: hosts' and links' sections; `_faults_across.py`: fault commands.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rr_actors import events as events_module
from rr_actors._core.serial import SerialExecutor
from rr_actors._transport.zenoh.callbacks import tracked
from rr_actors._transport.zenoh.wire import ObserverKey
from rr_actors_lab.observe._crossing import decode, shared, valid_event, valid_section
from rr_actors_lab.observe._delta import apply
from rr_actors_lab.observe._faults import FaultRefused
from rr_actors_lab.observe._faults_across import send_fault
from rr_actors_lab.observe._hub import BATCH, Hub
from rr_actors_lab.observe._liveness import Liveness, Mirror
from rr_actors_lab.observe._share import FLUSH_TIMEOUT, LINKS_EVERY, Share
from rr_actors_lab.observe._sources import StatusNames, event_dict
from rr_actors_lab.observe._view import dependency_graph

if TYPE_CHECKING:
    import zenoh

    from rr_actors._core.bus import Subscription
    from rr_actors._transport.zenoh.net import Services

__all__ = ["ASK_EVERY", "EVENTS_WINDOW", "STATE_TIMEOUT", "SystemView"]

logger = logging.getLogger("rr_actors")

ASK_EVERY = 1.0
"""Seconds between two asks of one host's state (after a gap, a token back, a timeout)."""

STATE_TIMEOUT = 5.0
"""Seconds a host has to answer an ask for its state."""

EVENTS_WINDOW = 0.5
"""Seconds the system's event stream holds an event for others to overtake it (its
hybrid logical clock order; `ZenohNetwork.subscribe_events`)."""


class SystemView:
    """Keeps a page's hub up to date with every host's shared state.

    Sections of the page's hub: `hosts`, `links`, `graph`, and per host
    `host/<member>/tree`, `host/<member>/catalog/<registrar>`, `host/<member>/ended`; every
    host's events, each with its `member` (from `subscribe`, in `hlc` order, when given).

    Args:
        hub: the page's hub.
        services: the router's session and what goes with it.
        member: this host's member name (`None`: it shares nothing, only shows).
        share: this host's share (its own state comes from it directly, not over Zenoh).
        subscribe: the system's event stream (`ZenohNetwork.subscribe_events`), or `None`.
    """

    def __init__(
        self,
        hub: Hub,
        services: Services,
        member: str | None,
        share: Share | None,
        subscribe: Callable[..., Subscription[events_module.Event]] | None = None,
    ) -> None:
        self.hub = hub
        self.member = member
        self._services = services
        self._keys = services.keys
        self._share = share
        self._mirrors: dict[str, Mirror] = {}
        self._names = StatusNames()  # (the event stream's thread only)
        self._liveness = Liveness(member, services, self._mirrors)
        self._executor = SerialExecutor("rr-observe-system", every=(LINKS_EVERY, self._tick))
        session = services.session
        if share is not None:
            own = self._mirror(share.member)
            own.here = True
            share.listen(self._on_own)
            self._executor.submit(functools.partial(self._own_state, share.state()))
        self._deltas = session.declare_subscriber(
            self._keys.observers("delta"), tracked(session, self._on_delta)
        )
        self._tokens = session.liveliness().declare_subscriber(
            self._keys.observers("here"), tracked(session, self._on_token), history=True
        )
        self._links_listener = session.info.declare_link_events_listener(
            tracked(session, self._on_link), history=False
        )
        self._events_of_system = (
            None if subscribe is None else subscribe(self._on_event, window=EVENTS_WINDOW)
        )
        self._sending = threading.Condition()  # fault commands under way (`fault`)
        self._faults_sent = 0
        self._closed = False
        # (a network that left already closes it inside `on_leave`: its `close` ends by
        # calling `_forget`, set before)
        self._forget: Callable[[], None] = lambda: None
        self._forget = services.on_leave(self.close)  # (its threads call Zenoh: ended
        # before the session closes, even if the observer stays open: `keep_serving`)

    def _on_link(self, _event: Any) -> None:  # (Zenoh's thread: a link came or went)
        self._executor.submit(functools.partial(self._refresh, graph=False))

    def _on_event(self, event: events_module.Event) -> None:  # (its subscriber thread)
        """An event of the system's stream into the page's history, with its `member`; a status sent
        is named now (`StatusNames`, from its host's events and that host's catalog in the hub)."""
        data = event_dict(event)
        member = data["member"] = data.get("host") or "?"
        if isinstance(event, events_module.StatusSent):
            section = self.hub.get(f"host/{member}/catalog/{event.registrar}")
            data["resource"] = self._names.name(event, section and section["catalog"])
        else:
            self._names.note(event)
        self.hub.add_event(data)

    def flush(self, timeout: float = FLUSH_TIMEOUT) -> bool:
        """Wait until what it was told before this call is in the page's hub (this host's own
        state included); whether within `timeout` seconds (calling thread, never its own)."""
        return self._executor.flush(timeout=timeout)

    def close(self, timeout: float = 5.0) -> None:
        """Stop following the hosts (within `timeout` seconds, and as long again for the
        fault commands under way). Its network closes it too, before its session closes
        (`Services.on_leave`): none of its threads calls Zenoh after."""
        with self._sending:
            self._closed = True
        for declared in (self._deltas, self._tokens, self._links_listener):
            with contextlib.suppress(Exception):
                declared.undeclare()  # type: ignore[no-untyped-call]
        if self._events_of_system is not None:
            self._events_of_system.close(timeout=timeout)
        self._executor.close(timeout=0)
        self._executor.join(timeout)
        with self._sending:
            self._sending.wait_for(lambda: self._faults_sent == 0, timeout)
        self._forget()

    def _mirror(self, member: str) -> Mirror:
        mirror = self._mirrors.get(member)
        if mirror is None:
            mirror = self._mirrors[member] = Mirror(member)
        return mirror

    def _on_own(self, message: dict[str, Any]) -> None:  # (the share's thread: queue it)
        self._executor.submit(functools.partial(self._own, message))

    def _local(self, member: str) -> bool:
        return self._share is not None and member == self._share.member

    # -- Zenoh's threads: queue ------------------------------------------------------------

    def _on_delta(self, sample: zenoh.Sample) -> None:
        at = self._keys.parse_observer(str(sample.key_expr))
        if at is None or self._local(at.member):
            return
        data = sample.payload.to_bytes()
        self._executor.submit(functools.partial(self._delta, at.member, data))

    def _on_token(self, sample: zenoh.Sample) -> None:
        import zenoh  # noqa: PLC0415 - (the zenoh extra; imported already by the session)

        at = self._keys.parse_observer(str(sample.key_expr))
        if at is None or self._local(at.member):
            return
        here = sample.kind == zenoh.SampleKind.PUT
        self._executor.submit(functools.partial(self._token, at.member, here))

    def _on_reply(self, member: str, reply: Any) -> None:
        ok = getattr(reply, "ok", None)
        if ok is not None:
            data = ok.payload.to_bytes()
            self._executor.submit(functools.partial(self._state, member, data))

    # -- the executor's thread -------------------------------------------------------------

    def _token(self, member: str, here: bool) -> None:
        mirror = self._mirror(member)
        mirror.here, mirror.synced = here, False  # (back: what it missed comes with its state)
        mirror.since = time.time()
        mirror.why = "" if here else self._liveness.why(member)
        if here:
            self._ask(mirror, force=True)
        self._refresh(graph=True)

    def _ask(self, mirror: Mirror, *, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - mirror.asked < ASK_EVERY:
            return
        mirror.asked = now
        key = self._keys.observer(ObserverKey(mirror.member, "state"))
        try:
            self._services.session.get(
                key, functools.partial(self._on_reply, mirror.member), timeout=STATE_TIMEOUT
            )
        except Exception:
            logger.debug("observer: asking %s for its state failed", mirror.member, exc_info=True)

    def _state(self, member: str, data: bytes) -> None:
        message = decode(member, data)
        if message is None or not isinstance(message.get("sections"), dict):
            return
        self._apply_state(self._mirror(member), message)

    def _own_state(self, message: dict[str, Any]) -> None:
        self._apply_state(self._mirror(message["member"]), message)

    def _apply_state(self, mirror: Mirror, message: dict[str, Any]) -> None:
        if (
            mirror.synced
            and mirror.instance == message["instance"]
            and message["seq"] <= mirror.seq
        ):
            return  # (older than what it has)
        if mirror.instance != message["instance"]:
            mirror.last_event = 0
        sections = {
            key: value
            for key, value in message["sections"].items()
            if isinstance(key, str) and shared(key) and valid_section(key, value)
        }
        mirror.instance, mirror.seq, mirror.sections = message["instance"], message["seq"], sections
        mirror.synced = True
        newest_instance, newest_seq = mirror.newest  # (a delta newer than this state came)
        mirror.behind = newest_instance == mirror.instance and newest_seq > mirror.seq
        if not self._local(mirror.member) and not mirror.here:
            mirror.synced = False  # (a late answer from a host that went meanwhile)
        self._events(mirror, message.get("events"))
        self._publish(mirror, set(sections) | mirror.published)
        self._refresh(graph=True)

    def _delta(self, member: str, data: bytes) -> None:
        message = decode(member, data)
        if message is None:
            return
        self._apply_delta(self._mirror(member), message)

    def _own(self, message: dict[str, Any]) -> None:
        self._apply_delta(self._mirror(message["member"]), message)

    def _apply_delta(self, mirror: Mirror, message: dict[str, Any]) -> None:
        if mirror.newest[0] != message["instance"] or mirror.newest[1] < message["seq"]:
            mirror.newest = (message["instance"], message["seq"])
        same = mirror.instance == message["instance"]
        if same and message["seq"] <= mirror.seq:
            return  # (already in the state it has)
        if not (mirror.synced and same and message["seq"] == mirror.seq + 1):
            if self._local(mirror.member):
                self._own_state(self._share.state() if self._share else message)
            elif mirror.here:
                mirror.behind = True  # (asked now, or at the next tick)
                self._ask(mirror)
            return
        changed = set()
        try:
            items = message.get("sections")
            if not isinstance(items, list):
                raise TypeError("sections")  # noqa: TRY301 - one way out for any bad shape
            updated = dict(mirror.sections)
            for key, how, value in items:
                if not isinstance(key, str) or not shared(key):
                    continue
                new = apply(updated.get(key), value) if how == "p" else value
                if not valid_section(key, new):
                    raise TypeError(key)  # noqa: TRY301
                if new is None:
                    updated.pop(key, None)
                else:
                    updated[key] = new
                changed.add(key)
        except (TypeError, ValueError, KeyError, AttributeError, IndexError):
            logger.debug("observer: a malformed delta from %s", mirror.member, exc_info=True)
            mirror.synced = False
            self._ask(mirror, force=True)
            return
        mirror.sections, mirror.seq = updated, message["seq"]
        self._events(mirror, message.get("events"))
        self._publish(mirror, changed)
        self._refresh(graph=any(k.startswith("catalog/") or k == "host" for k in changed))

    def _events(self, mirror: Mirror, events: Any) -> None:
        if not isinstance(events, list):
            return
        for event in events[-BATCH:]:
            if not valid_event(event) or event["seq"] <= mirror.last_event:
                continue
            if self._events_of_system is not None and event["type"] != "ObserverFault":
                continue  # (the system's event stream brings it)
            mirror.last_event = event["seq"]
            self.hub.add_event({**event, "member": mirror.member, "host_seq": event["seq"]})

    def _publish(self, mirror: Mirror, keys: set[str]) -> None:
        """Put sections `keys` of `mirror` into the page's hub (under `host/<member>/`)."""
        for key in sorted(keys):
            if key in ("host", "links"):
                continue  # (in "hosts" and "links")
            value = mirror.sections.get(key)
            self.hub.put(f"host/{mirror.member}/{key}", value)
            if value is None:
                mirror.published.discard(key)
            else:
                mirror.published.add(key)

    def _tick(self) -> None:
        try:
            for mirror in list(self._mirrors.values()):
                lagging = not mirror.synced or mirror.behind
                if mirror.here and lagging and not self._local(mirror.member):
                    self._ask(mirror)
            self._refresh(graph=False)
        except Exception:
            if not self._executor.closed:
                logger.exception("observer: following the hosts failed")

    def _refresh(self, *, graph: bool) -> None:
        for mirror in self._mirrors.values():  # a cut found by the link watch names its cause
            if not mirror.here and not self._local(mirror.member):
                mirror.why = self._liveness.why(mirror.member)
        self.hub.put("hosts", self._liveness.hosts())
        self.hub.put("links", self._liveness.links())
        if graph:
            self.hub.put("graph", self._graph())

    def _graph(self) -> dict[str, Any]:
        catalogs: dict[str, dict[str, Any] | None] = {}
        states: dict[str, str] = {}
        hosts: dict[str, str] = {}
        for mirror in self._mirrors.values():
            stale = not (mirror.here and mirror.synced) and not self._local(mirror.member)
            for key, section in mirror.sections.items():
                if not key.startswith("catalog/"):
                    continue
                name = section["registrar"]
                catalogs[name] = section["catalog"]
                states[name] = "stale" if stale else section["state"]
                hosts[name] = mirror.member
        return dependency_graph(catalogs, states, hosts=hosts)

    # -- a fault on another host ---------------------------------------------------------------

    def fault(self, member: str, kind: str, data: dict[str, Any]) -> str:
        """Ask host `member` to inject a fault into one of its managers; what it did. Waits up to
        `FAULT_TIMEOUT` seconds, on the calling thread (a server worker).

        Raises:
            FaultRefused: that host refused (its reason), did not answer, or is not known.
        """
        if member not in self._mirrors or self._local(member):
            raise FaultRefused(f"no host {member!r} shares its tree with this page", 404)
        if self.member is None:
            raise FaultRefused("this page's host has no member name to send a command as", 403)
        with self._sending:
            if self._closed:
                raise FaultRefused("this page's host left the system", 503)
            self._faults_sent += 1
        try:
            return send_fault(self._services, self.member, member, kind, data)
        finally:
            with self._sending:
                self._faults_sent -= 1
                self._sending.notify_all()
