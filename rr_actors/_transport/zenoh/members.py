"""Which addresses are members': those the handshake gate (`gate`) never drops.

A TLS router knows a member by the certificate of its link, and Zenoh tells the
listener no more of that certificate than its common name. So each router answers a
`get` on `rr/<system>/cert/<its name>` with its own cert file (public: what it shows in
every handshake), and fetches the certificate of each member that links to it. A
member's addresses are then, from the strongest:

- the IP addresses its certificate names (subjectAltName), kept once the certificate
  checks out as the handshake checks this host's own (`tls.member_addresses`: signed up
  to the system's CA, in date, its common name the one it linked with): where the CA
  says the member is, also while it is out of reach, also after it went away;
- the remote address of its link up now (behind a NAT, say, where no certificate names
  it);
- the addresses its links came from since this router started (the last `LEARNED`).

Nothing here trusts what a member says of itself: a certificate anyone relays is the
CA's word. One that does not check out is said once (WARNING) and not used.

```
 thread "rr-zenoh-gate" (the gate's), at each look: MemberAddresses.now()
   session.info.links(): member links up ─► learned addresses
   a member linked, its certificate not known ─► session.get(rr/<system>/cert/<name>)
   replies in (try_recv, never blocks) ─► tls.member_addresses() ─► named addresses
 Zenoh's thread: a get on rr/<system>/cert/<this host> ─► the cert file's bytes
```
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from rr_actors._transport.zenoh.watch import remote
from rr_actors._transport.zenoh.wire import Keys
from rr_actors.errors import ConfigError

if TYPE_CHECKING:
    from rr_actors._transport.zenoh.tls import ZenohTLS

__all__ = ["ASK_AGAIN", "LEARNED", "MemberAddresses"]

logger = logging.getLogger("rr_actors")

LEARNED = 4  # addresses kept per member, of those its links came from (the newest)
ASK_AGAIN = 5.0  # seconds before a certificate asked for and not had is asked for again
_ASK_TIMEOUT = 2.0  # seconds a get of a certificate waits for its answer


class MemberAddresses:
    """The addresses of the members of one router's system (see the module docstring).

    Args:
        system: the system's name, for the log lines.
        session: the router's open Zenoh session.
        tls: this host's files (its cert is what it answers with) and the members.
        clock: seconds, monotonic (tests may pass their own).

    `now` is called by one thread (the gate's); `close` by the session's closer.
    """

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
            self._keys.certificate(tls.name), lambda query: query.reply(query.key_expr, pem)
        )

    def close(self) -> None:
        """Stop answering for this host's certificate (idempotent)."""
        try:
            self._queryable.undeclare()  # type: ignore[no-untyped-call]
        except Exception:
            logger.debug("undeclaring the certificate's queryable failed", exc_info=True)

    def now(self) -> set[str]:
        """The members' addresses now: named in their certificates, or their links' (up
        now, or the last `LEARNED` each since this router started). Asks for the
        certificate of a member linked whose certificate is not known yet, without
        waiting for it (it counts from a later call)."""
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
        """(member name, remote address) of each TLS link of the router to a member."""
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
        """Keep the addresses of `name`'s certificate `pem`, if it checks out (True)."""
        from rr_actors._transport.zenoh.tls import member_addresses  # noqa: PLC0415 - cryptography

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
