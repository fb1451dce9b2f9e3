"""Keep a flood of failed TLS handshakes from locking members out of a router's `tls/` port.

Zenoh 1.10's TLS listener pauses its accept loop 100 ms after every handshake that fails
(`TLS_ACCEPT_THROTTLE_TIME` in zenoh-link-tls, a constant), and it takes up to 64
connections into handshakes at once. Anyone who reaches the port can queue connections
faster than that: each is paid 100 ms later, and a member's connection waits behind them
(2 s of flood, minutes of lock-out). So, for each `tls/` listen endpoint, on the
platform's gate on Zenoh's own listening socket (`_platform.linux_gate`; none on other
platforms, where only a firewall helps):

- the accept queue is shortened to `BACKLOG`: whatever is queued when a flood is seen
  costs the listener at most (`BACKLOG` + 64) x 0.1 s;
- every `TICK` s the socket table is read, counting per source address the connections
  past the TCP handshake only (queued for accept, in a TLS handshake, linked, closing).
  Half-open ones never count: a SYN with any source address (a member's) costs nothing
  to forge, and the kernel holds what it answered for a minute while nobody is there to
  reset it; completing the handshake takes receiving our SYN-ACK at that address;
- a member's address (`member_addresses`: named in a member's certificate, or of a
  member's link, up now or since this router started: `members`) is never dropped.
  Every other address is a stranger, and strangers may hold `HOLD` connections, each
  and together:
  - a stranger over `HOLD` floods: every packet from it to the port is dropped by the
    socket's filter, before the kernel answers its SYN (it costs the listener nothing
    more), for `DROP` s (WARNING; INFO when it ends);
  - strangers together over `HOLD`, each under it (one machine's many addresses, or
    many machines), at two looks in a row, flood too: the port then takes packets from
    members' addresses only, for `DROP` s (WARNING naming those; INFO when it ends).
    (Two looks: members that dial a router just started are strangers to it until
    linked, and their handshakes, however many, end within a look; a flood's stay.)

  A drop ends on time, whatever the source sends meanwhile: one that waited for quiet
  would last as long as anyone keeps sending with that source address.

Links already up are not touched (each keeps the filter it was accepted with; a few
instructions per packet). What is left to the firewall
(`docs/how-to/securing-registrars.md`): a flood from a member's address (members are
trusted; so are hosts behind a member's NAT), a flood of packets that fills the link, a
member's first link from an address its certificate does not name while the port takes
members' addresses only, more than `GATE_SOURCES` members' addresses (no filter holds
them: the port is then not turned to members only), platforms without a gate.

```
 thread "rr-zenoh-gate", every TICK s:
   member_addresses() ─► members (once per look)
   per tls/ listen endpoint:
     drops and a members-only spell whose DROP s are over ─► lifted, INFO
     gate.peers(): connections past the TCP handshake, per source
       a stranger over HOLD ─► dropped for DROP s, WARNING
       strangers not dropped, together over HOLD, twice ─► members only for DROP s, WARNING
     └─ gate.admit_only(members) while members only, else gate.drop_from(dropped)
```
"""

from __future__ import annotations

import dataclasses
import ipaddress
import logging
import socket
import threading
import time
from collections.abc import Callable, Iterable

from rr_actors._platform import GATE_SOURCES, PLATFORM, ListenerGate
from rr_actors._transport.zenoh.config import parse_endpoint

__all__ = ["BACKLOG", "DROP", "HOLD", "TICK", "HandshakeGate", "open_gates"]

logger = logging.getLogger("rr_actors")

BACKLOG = 16  # connections the kernel queues for Zenoh's accept at most
HOLD = 8  # connections strangers may hold to the port: each address, and all together
TICK = 0.2  # seconds between two looks at the socket table
DROP = 60.0  # seconds a drop (or a members-only spell) lasts, whatever is sent meanwhile


def open_gates(listen: Iterable[str]) -> list[ListenerGate]:
    """The platform's gates on this process's listening sockets of the `tls/` endpoints
    of `listen` (Zenoh's, once its session is open); none for port 0 or where the
    platform has no gate."""
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
    """What the gate keeps of one listening socket."""

    gate: ListenerGate
    dropped: dict[str, float] = dataclasses.field(default_factory=dict)  # source -> until
    members_only: float | None = None  # until when only members' addresses get in
    admitted: frozenset[str] = frozenset()  # the members' addresses let in meanwhile
    crowded: bool = False  # strangers together held more than HOLD at the last look


class HandshakeGate:
    """Drops the sources that flood a router's `tls/` listeners (see the module docstring).

    Args:
        system: the system's name, for the log lines.
        gates: the gates on the listening sockets (`open_gates`); closed by `close`.
        member_addresses: the members' addresses now (`members.MemberAddresses.now`),
            called once per look, on the gate's thread.
        clock: seconds, monotonic (tests may pass their own).
        start: start the thread (tests call `look` themselves).
    """

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
        """The source addresses dropped now (at any gate; not counting a members-only
        spell's)."""
        return {source for port in self._ports for source in port.dropped}

    def members_only(self) -> bool:
        """Whether some gate takes packets from members' addresses only now."""
        return any(port.members_only is not None for port in self._ports)

    def close(self) -> None:
        """Stop, and let go of the sockets (idempotent); call before the session closes
        (a duplicate of a listening socket would keep its port listening)."""
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
