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
- every `TICK` s the socket table is read: a source address that holds more than `HOLD`
  connections to the port (queued, in a handshake, or linked: a member holds one link,
  and one connection while it re-joins) and has no link of a member's up is a flood.
  Every packet from it to the port is dropped from then on by the socket's filter, before
  the kernel answers its SYN: it costs the listener nothing more. A WARNING names it;
- the drops are lifted (INFO) once the socket has dropped nothing for `QUIET` s: the
  source stopped trying.

Links already up are not touched (each keeps the filter it was accepted with; a few
instructions per packet). A member's address is never dropped while its link is up
(members are trusted: a flood from a member's host is paid as Zenoh pays it); peers that
share one address with a flooding source (behind one NAT) and have no member's link up
are dropped with it; many flooding addresses at once, each under `HOLD`, are beyond this:
that is the firewall's job (`docs/how-to/securing-registrars.md`).

```
 thread "rr-zenoh-gate", every TICK s, per tls/ listen endpoint:
   gate.peers() (source -> connections) > HOLD, and no member's link from it?
     └─ gate.drop_from(dropped | {source}), WARNING
   gate.dropped() unchanged for QUIET s? └─ gate.drop_from({}), INFO
```
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import threading
import time
from collections.abc import Callable, Iterable

from rr_actors._platform import GATE_SOURCES, PLATFORM, ListenerGate
from rr_actors._transport.zenoh.config import parse_endpoint

__all__ = ["BACKLOG", "HOLD", "QUIET", "TICK", "HandshakeGate", "open_gates"]

logger = logging.getLogger("rr_actors")

BACKLOG = 16  # connections the kernel queues for Zenoh's accept at most
HOLD = 8  # connections a source without a member's link may hold to the port
TICK = 0.2  # seconds between two looks at the socket table
QUIET = 60.0  # seconds without a dropped packet before the drops are lifted


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


class HandshakeGate:
    """Drops the sources that flood a router's `tls/` listeners (see the module docstring).

    Args:
        system: the system's name, for the log lines.
        gates: the gates on the listening sockets (`open_gates`); closed by `close`.
        members_at: the remote addresses of the router's links to members now (called
            on the gate's thread).
        clock: seconds, monotonic (tests may pass their own).
        start: start the thread (tests call `look` themselves).
    """

    def __init__(
        self,
        system: str,
        gates: list[ListenerGate],
        members_at: Callable[[], set[str]],
        *,
        clock: Callable[[], float] = time.monotonic,
        start: bool = True,
    ) -> None:
        self._system = system
        self._gates = gates
        self._members_at = members_at
        self._clock = clock
        self._dropped: dict[int, set[str]] = {id(gate): set() for gate in gates}
        self._drops: dict[int, tuple[int, float]] = {}  # drop counter, when it last grew
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rr-zenoh-gate", daemon=True)
        if start and gates:
            self._thread.start()

    def dropping(self) -> set[str]:
        """The source addresses dropped now (at any gate)."""
        return set().union(*self._dropped.values())

    def close(self) -> None:
        """Stop, and let go of the sockets (idempotent); call before the session closes
        (a duplicate of a listening socket would keep its port listening)."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=5.0)
        for gate in self._gates:
            gate.close()
        self._gates = []

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
        """One look at each gate: drop the sources that flood it, lift quiet drops."""
        for gate in self._gates:
            self._drop_floods(gate)
            self._lift_when_quiet(gate)

    def _drop_floods(self, gate: ListenerGate) -> None:
        dropped = self._dropped[id(gate)]
        held = gate.peers()
        over = [source for source, n in held.items() if n > HOLD and source not in dropped]
        if not over:
            return
        members = self._members_at()
        for source in over:
            if source in members or len(dropped) >= GATE_SOURCES:
                continue
            dropped.add(source)
            gate.drop_from(dropped)
            self._drops[id(gate)] = (gate.dropped(), self._clock())
            logger.warning(
                "ZenohNetwork %r: %s holds %d connections to %s:%d and no member's link "
                "(failed or unfinished TLS handshakes: Zenoh's listener pauses 0.1 s after "
                "each failed one): its packets to that port are dropped until none has come "
                "for %g s",
                self._system,
                source,
                held[source],
                gate.address,
                gate.port,
                QUIET,
            )

    def _lift_when_quiet(self, gate: ListenerGate) -> None:
        dropped = self._dropped[id(gate)]
        if not dropped:
            return
        count, since = self._drops[id(gate)]
        now, latest = self._clock(), gate.dropped()
        if latest != count:
            self._drops[id(gate)] = (latest, now)
            return
        if now - since < QUIET:
            return
        gate.drop_from(())
        logger.info(
            "ZenohNetwork %r: %s:%d takes packets from %s again (none came for %g s)",
            self._system,
            gate.address,
            gate.port,
            ", ".join(sorted(dropped)),
            QUIET,
        )
        dropped.clear()
