"""Keep a flood of failed TLS handshakes from locking members out of a router's `tls/` port.

Strangers over `HOLD` connections are dropped for `DROP` s, members never. How and why:
docs/explanation/inside.md ("The handshake gate").
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import ipaddress
import logging
import socket
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from rr_actors._platform import GATE_SOURCES, PLATFORM, ListenerGate
from rr_actors._transport.zenoh.callbacks import tracked
from rr_actors._transport.zenoh.ops.config import parse_endpoint, remote
from rr_actors._transport.zenoh.wire import Keys
from rr_actors.errors import ConfigError

if TYPE_CHECKING:
    from rr_actors._transport.zenoh.ops.tls import ZenohTLS

logger = logging.getLogger("rr_actors")

BACKLOG = 16  # connections the kernel queues for Zenoh's accept at most
HOLD = 8  # connections strangers may hold to the port: each address, and all together
TICK = 0.2  # seconds between two looks at the socket table
DROP = 60.0  # seconds a drop (or a members-only spell) lasts, whatever is sent meanwhile


def open_gates(listen: Iterable[str]) -> list[ListenerGate]:
    """The platform's gates on the listening sockets of `listen`'s `tls/` endpoints."""
    gates = []
    for endpoint in listen:
        if not endpoint.startswith("tls/"):
            continue
        _, host, port = parse_endpoint("listen", endpoint)
        try:
            addresses = [str(ipaddress.ip_address(host))]
        except ValueError:
            try:
                addresses = sorted({str(i[4][0]) for i in socket.getaddrinfo(host, port)})
            except OSError:
                addresses = []
        gate = None
        for address in addresses:
            gate = PLATFORM.listener_gate(address, port) if port else None
            if gate is not None:
                gate.shorten_backlog(BACKLOG)
                gates.append(gate)
                break
        if gate is None:
            logger.debug("no gate on the listening socket of %s (%s)", endpoint, PLATFORM.name)
    return gates


@dataclasses.dataclass
class _Port:
    gate: ListenerGate
    dropped: dict[str, float] = dataclasses.field(default_factory=dict)  # source -> until
    members_only: float | None = None  # until when only members' addresses get in
    admitted: frozenset[str] = frozenset()  # the members' addresses let in meanwhile
    crowded: bool = False  # strangers together held more than HOLD at the last look


class HandshakeGate:
    """Drops the sources that flood a router's `tls/` listeners: docs/explanation/inside.md
    ("What the gate leaves to the firewall")."""

    def __init__(
        self,
        system: str,
        gates: list[ListenerGate],
        member_addresses: Callable[[], set[str]],
        *,
        clock: Callable[[], float] = time.monotonic,
        start: bool = True,
    ) -> None:
        self._system = system
        self._ports = [_Port(gate) for gate in gates]
        self._member_addresses = member_addresses
        self._clock = clock
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rr-zenoh-gate", daemon=True)
        if start and gates:
            self._thread.start()

    def dropping(self) -> set[str]:
        """The source addresses dropped now (not counting a members-only spell's)."""
        return {source for port in self._ports for source in port.dropped}

    def members_only(self) -> bool:
        return any(port.members_only is not None for port in self._ports)

    def close(self) -> None:
        """Stop, and let go of the sockets (idempotent), before the session closes."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=5.0)
        for port in self._ports:
            port.gate.close()
        self._ports = []

    def _run(self) -> None:
        while not self._stop.wait(TICK):
            try:
                self.look()
            except Exception:
                if self._stop.is_set():
                    return  # the session closed under us
                logger.exception(  # once: the gate is a second line, the firewall the first
                    "ZenohNetwork %r: the gate on its tls/ listeners failed and is off",
                    self._system,
                )
                return

    def look(self) -> None:
        """One look at each gate: lift the drops whose time is over, drop the floods."""
        members = frozenset(self._member_addresses())
        now = self._clock()
        for port in self._ports:
            changed = self._lift_due(port, now)
            changed |= self._drop_floods(port, members, now)
            if port.members_only is not None and port.admitted != members:
                port.admitted, changed = members, True  # (a member's certificate came in)
            if changed:
                self._filter(port)

    def _lift_due(self, port: _Port, now: float) -> bool:
        due = sorted(source for source, until in port.dropped.items() if until <= now)
        ended = port.members_only is not None and port.members_only <= now
        if not due and not ended:
            return False
        for source in due:
            del port.dropped[source]
        if ended:
            port.members_only = None
        lifted = [*due, *(["every address"] if ended else [])]
        logger.info(
            "ZenohNetwork %r: %s:%d takes packets from %s again (dropped for %g s)",
            self._system,
            port.gate.address,
            port.gate.port,
            ", ".join(lifted),
            DROP,
        )
        return True

    def _drop_floods(self, port: _Port, members: frozenset[str], now: float) -> bool:
        held = port.gate.peers()
        strangers = {
            source: n
            for source, n in held.items()
            if source not in members and source not in port.dropped
        }
        changed = False
        for source, n in sorted(strangers.items()):
            if n <= HOLD or len(port.dropped) >= GATE_SOURCES:
                continue
            del strangers[source]
            port.dropped[source] = now + DROP
            changed = True
            logger.warning(
                "ZenohNetwork %r: %s holds %d connections to %s:%d and is not a member's "
                "address (failed or unfinished TLS handshakes: Zenoh's listener pauses 0.1 s "
                "after each failed one): its packets to that port are dropped for %g s",
                self._system,
                source,
                n,
                port.gate.address,
                port.gate.port,
                DROP,
            )
        together = sum(strangers.values())
        crowded, port.crowded = port.crowded, together > HOLD
        if port.members_only is None and crowded and port.crowded:
            if len(members) > GATE_SOURCES:
                return changed  # (no filter holds them all: the firewall's job)
            port.members_only, port.admitted, changed = now + DROP, members, True
            logger.warning(
                "ZenohNetwork %r: %d addresses, none a member's, hold %d connections to "
                "%s:%d (failed or unfinished TLS handshakes): the port takes packets only "
                "from members' addresses (%s) for %g s",
                self._system,
                len(strangers),
                together,
                port.gate.address,
                port.gate.port,
                ", ".join(sorted(members)) or "none known yet",
                DROP,
            )
        return changed

    @staticmethod
    def _filter(port: _Port) -> None:
        if port.members_only is not None:
            port.gate.admit_only(port.admitted)
        else:
            port.gate.drop_from(port.dropped)  # (none: the filter is taken off)


LEARNED = 4  # addresses kept per member, of those its links came from (the newest)
ASK_AGAIN = 5.0  # seconds before a certificate asked for and not had is asked for again
_ASK_TIMEOUT = 2.0  # seconds a get of a certificate waits for its answer


def _reply_with(pem: bytes, query: zenoh.Query) -> None:
    query.reply(query.key_expr, pem)


class MemberAddresses:
    """The members' addresses the gate never drops: inside.md ("Which addresses are members'")."""

    def __init__(
        self,
        system: str,
        session: zenoh.Session,
        tls: ZenohTLS,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._system = system
        self._session = session
        self._tls = tls
        self._keys = Keys(system)
        self._clock = clock
        self._named: dict[str, tuple[str, ...]] = {}  # member -> its certificate's IPs
        self._learned: dict[str, collections.OrderedDict[str, None]] = {}
        self._asking: dict[str, Any] = {}  # member -> the replies of its get
        self._asked: dict[str, float] = {}  # member -> when last asked
        self._refused: set[str] = set()  # members whose certificate we said we refused
        self._up: set[str] = set()  # members linked at the last call
        pem = Path(tls.cert).read_bytes()  # (read once: what Zenoh read when it opened)
        self._queryable = session.declare_queryable(
            self._keys.certificate(tls.name),
            tracked(session, functools.partial(_reply_with, pem)),
        )

    def close(self) -> None:
        try:
            self._queryable.undeclare()  # type: ignore[no-untyped-call]
        except Exception:
            logger.debug("undeclaring the certificate's queryable failed", exc_info=True)

    def now(self) -> set[str]:
        """The members' addresses now, from their certificates or links (never waits)."""
        up = self._links()
        for name in {name for name, _ in up} - self._up:
            self._asked.pop(name, None)  # linked anew (restarted, maybe with a new certificate)
        self._up = {name for name, _ in up}
        for name, address in up:
            seen = self._learned.setdefault(name, collections.OrderedDict())
            seen[address] = None
            seen.move_to_end(address)
            while len(seen) > LEARNED:
                seen.popitem(last=False)
        self._take_replies()
        now = self._clock()
        for name in self._up - self._asking.keys():
            asked = self._asked.get(name)
            if asked is None or (name not in self._named and now - asked >= ASK_AGAIN):
                self._asked[name] = now
                try:
                    self._asking[name] = self._session.get(
                        self._keys.certificate(name), timeout=_ASK_TIMEOUT
                    )
                except zenoh.ZError:  # (the session closing under us: asked again later)
                    logger.debug("asking for %r's certificate failed", name, exc_info=True)
        known = {address for _, address in up}
        for addresses in (*self._named.values(), *self._learned.values()):
            known.update(addresses)
        return known

    def _links(self) -> set[tuple[str, str]]:
        """(member, remote address) of each TLS link of the router to a member."""
        return {
            (str(link.auth_identifier), remote(str(link.dst))[0])
            for link in self._session.info.links()
            if str(link.dst).startswith("tls/") and link.auth_identifier in self._tls.members
        }

    def _take_replies(self) -> None:
        for name, replies in list(self._asking.items()):
            while True:
                try:
                    reply = replies.try_recv()
                except zenoh.ZError:  # no more replies (the get ended)
                    del self._asking[name]
                    break
                if reply is None:
                    break  # none yet
                if reply.ok is not None and self._check(name, reply.ok.payload.to_bytes()):
                    del self._asking[name]
                    break

    def _check(self, name: str, pem: bytes) -> bool:
        """Keep the addresses of `name`'s certificate `pem`, if it checks out."""
        from rr_actors._transport.zenoh.ops.tls import member_addresses  # noqa: PLC0415 - cryptography

        try:
            self._named[name] = member_addresses(pem, self._tls, name)
        except ConfigError as exc:
            if name not in self._refused:
                self._refused.add(name)
                logger.warning(
                    "ZenohNetwork %r: member %r answered for its certificate with one that "
                    "does not hold: %s; the handshake gate knows only its links' addresses",
                    self._system,
                    name,
                    exc,
                )
            return False
        return True
