"""Who a TLS router is linked to, and why a `connect` endpoint is not: said on the logger.

Zenoh decides who gets in; this module only tells the operator, on the `rr_actors`
logger (the lines: docs/how-to/securing-registrars.md): INFO when a member links; WARNING
when a certificate of this system's CA but not in `members` links, or when a `connect`
endpoint has no link `GRACE` seconds after start or after its link is lost, with the
reason from a handshake of our own (`handshake_trouble`; one that finds nothing wrong
warns only if the next finds the same). Each at most once per address a minute. It also
keeps each member's link as last seen for the observer (`member_links`); a plain-TCP
network has no watch (`plain_unlinked`).

```
 Zenoh's thread: link event ─submit─► watch thread "rr-zenoh-watch" (SerialExecutor)
                                                 ├─ log INFO / WARNING per link
                                                 └─ every TICK s: each connect endpoint
                                                    linked? else after GRACE s:
                                                    handshake_trouble() ─► WARNING
```

The Zenoh callback only queues (it must never block). A link is "to" an endpoint when its
remote address is one of the endpoint host's addresses and its port the endpoint's, or a
port no `connect` endpoint has (two routers that dial each other share one link); a host
name is resolved again only while unlinked, at most every `GRACE` s.
"""

from __future__ import annotations

import functools
import ipaddress
import logging
import socket
import ssl
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import zenoh

from rr_actors._core.serial import SerialExecutor
from rr_actors._transport.zenoh import callbacks
from rr_actors._transport.zenoh.callbacks import tracked
from rr_actors._transport.zenoh.net import MemberLink
from rr_actors._transport.zenoh.ops.config import parse_endpoint, remote

if TYPE_CHECKING:
    from rr_actors._transport.zenoh.ops.tls import ZenohTLS

__all__ = ["GRACE", "REPEAT", "TICK", "LinkWatch", "handshake_trouble", "plain_unlinked"]

logger = logging.getLogger("rr_actors")

GRACE = 2.0  # seconds a connect endpoint may stay unlinked before we probe it
TICK = 0.5  # seconds between two looks at the connect endpoints
REPEAT = 60.0  # seconds between two WARNINGs about one address or endpoint


def _addresses(host: str) -> set[str]:
    """`host` and, for a name, the addresses it resolves to now (none if it does not)."""
    try:
        return {str(ipaddress.ip_address(host))}
    except ValueError:
        pass
    try:
        return {str(info[4][0]) for info in socket.getaddrinfo(host, None)} | {host}
    except OSError:
        return {host}


def _said(trouble: str | None) -> str:
    """Why an endpoint has no link, in words, from what its probe found (`None`: nothing)."""
    if trouble is None:
        return "the listener accepts this host's certificate; Zenoh has not linked yet"
    return trouble


class _Endpoint:
    def __init__(self, endpoint: str) -> None:
        _, self.host, self.port = parse_endpoint("connect", endpoint)
        self.endpoint = endpoint
        self.unlinked_since: float | None = None
        self.warned_at: float | None = None
        self.looked = False  # the first look counts from start, a later one from then
        self.reason: str | None = None  # why it had no link when last probed (None: linked)
        self.accepted = False  # its last probe found the listener accepting this host
        self.addresses: set[str] = set()  # the host's, when last resolved
        self.resolved_at: float | None = None

    def linked(
        self,
        links: set[tuple[str, int | None]],
        dialled: set[int],
        addresses: set[str] | None = None,
    ) -> bool:
        """Whether one of `links` (host, port) is to this endpoint: one of its host's
        `addresses` (those last resolved), and its port or one no connect endpoint has
        (`dialled`: the other host dialled us)."""
        addresses = self.addresses if addresses is None else addresses
        return any(
            host in addresses and (port == self.port or port not in dialled) for host, port in links
        )


def plain_unlinked(
    session: zenoh.Session, connect: tuple[str, ...], *, timeout: float
) -> list[tuple[str, str]]:
    """The plain-TCP `connect` endpoints with no link now, each with why (a TCP connect within
    `timeout` seconds each), for a `ZenohNetwork` with `tls=None`; on the caller's thread."""
    endpoints = [_Endpoint(endpoint) for endpoint in connect]
    if not endpoints:
        return []
    try:
        with callbacks.calling(session):
            links = {
                remote(str(link.dst))
                for link in session.info.links()
                if str(link.dst).startswith("tcp/")
            }
    except Exception:  # noqa: BLE001 - the session closed under us: nothing to name
        return []
    dialled = {endpoint.port for endpoint in endpoints}
    unlinked = []
    for endpoint in endpoints:
        if endpoint.linked(links, dialled, _addresses(endpoint.host)):
            continue
        try:
            with socket.create_connection((endpoint.host, endpoint.port), timeout=timeout):
                reason = "it accepts a TCP connection; Zenoh has not linked yet"
        except OSError as exc:
            reason = f"cannot reach it ({exc.strerror or exc})"
        unlinked.append((endpoint.endpoint, reason))
    return unlinked


class LinkWatch:
    """The watch of one router session (`ZenohNetwork` with `tls=`); see the module docstring.

    Args:
        system: the system's name, for the log lines.
        session: the router's open Zenoh session.
        tls: this host's files and the members.
        connect: the router's `connect` endpoints.
        clock: seconds, monotonic (tests may pass their own).
    """

    def __init__(
        self,
        system: str,
        session: zenoh.Session,
        tls: ZenohTLS,
        connect: tuple[str, ...],
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._system = system
        self._session = session
        self._tls = tls
        self._clock = clock
        self._endpoints = [_Endpoint(endpoint) for endpoint in connect]
        self._warned: dict[str, float] = {}  # non-member address -> when we said so
        self._members: dict[str, MemberLink] = {}  # (written by the watch thread only)
        self._started = clock()
        self._thread = SerialExecutor("rr-zenoh-watch", every=(TICK, self._guarded))
        self._listener = session.info.declare_link_events_listener(
            tracked(session, self._on_event), history=True
        )

    def close(self) -> None:
        """Stop watching (idempotent); call before the session closes."""
        if self._thread.closed:
            return
        self._thread.close(timeout=0)
        try:
            self._listener.undeclare()  # type: ignore[no-untyped-call]
        except Exception:
            logger.debug("undeclaring the link events listener failed", exc_info=True)
        self._thread.join(5.0)

    # -- the thread ------------------------------------------------------------------------

    def _on_event(self, event: Any) -> None:  # (Zenoh's thread: never blocks)
        self._thread.submit(functools.partial(self._guarded, event))

    def _guarded(self, event: Any = None) -> None:
        """Log a link `event`, or (`None`: every `TICK` s) look at the connect endpoints."""
        try:
            if event is not None:
                self._on_link(event)
            else:
                self._look_at_endpoints()
        except Exception:
            if self._thread.closed:
                return  # the session closed under us
            logger.exception("ZenohNetwork %r: watching its links failed", self._system)

    def _on_link(self, event: Any) -> None:
        link = event.link
        if not str(link.dst).startswith("tls/"):
            return  # this host's own processes (unixsock-stream)
        name, (where, _) = link.auth_identifier, remote(str(link.dst))
        self._note_members()
        if event.kind != zenoh.SampleKind.PUT:
            logger.info("ZenohNetwork %r: link to %r at %s closed", self._system, name, where)
            return
        if name in self._tls.members:
            logger.info("ZenohNetwork %r: member %r linked at %s", self._system, name, where)
            return
        now = self._clock()
        last = self._warned.get(where)
        if last is not None and now - last < REPEAT:
            return
        self._warned[where] = now
        logger.warning(
            "ZenohNetwork %r: %r at %s linked with a certificate signed by this system's CA "
            "(%s) but is not in members %s: every message of it is dropped both ways",
            self._system,
            name,
            where,
            self._tls.ca,
            list(self._tls.members),
        )

    def _note_members(self) -> None:
        """Note which members are linked now, and since when (on a link event)."""
        now = time.time()
        linked: dict[str, str] = {}
        for link in self._session.info.links():
            if str(link.dst).startswith("tls/") and link.auth_identifier in self._tls.members:
                linked[link.auth_identifier] = remote(str(link.dst))[0]
        for name, at in linked.items():
            known = self._members.get(name)
            if known is None or not known.up:
                self._members[name] = MemberLink(name, True, now, at, "")
        for name, known in list(self._members.items()):
            if known.up and name not in linked:
                why = f"the link to {known.where} closed (nothing heard within the lease)"
                self._members[name] = MemberLink(name, False, now, known.where, why)

    def member_links(self) -> list[MemberLink]:
        """Each member this router has been linked to, as last seen (any thread); a cut one's `why`
        is the watch's last probe of its address."""
        links = []
        for known in list(self._members.values()):
            why = known.why
            if not known.up:
                for endpoint in self._endpoints:
                    if endpoint.reason and known.where in (endpoint.addresses or {endpoint.host}):
                        why = f"{why}; {endpoint.reason}"
                        break
            links.append(known._replace(why=why))
        return links

    def _linked(self) -> set[tuple[str, int | None]]:
        """The (host, port) of each TLS link to a member (the watch's thread, or a
        caller's: `unlinked`)."""
        with callbacks.calling(self._session):
            return {
                remote(str(link.dst))
                for link in self._session.info.links()
                if str(link.dst).startswith("tls/") and link.auth_identifier in self._tls.members
            }

    def _look_at_endpoints(self) -> None:
        if not self._endpoints:
            return
        linked = self._linked()
        dialled = {endpoint.port for endpoint in self._endpoints}
        now = self._clock()
        for endpoint in self._endpoints:
            first, endpoint.looked = not endpoint.looked, True
            if not endpoint.linked(linked, dialled) and (
                endpoint.resolved_at is None or now - endpoint.resolved_at >= GRACE
            ):  # a name is looked up again only while unlinked, and not at every tick
                endpoint.addresses, endpoint.resolved_at = _addresses(endpoint.host), now
            if endpoint.linked(linked, dialled):  # `warned_at` stays: a flapping link is
                endpoint.unlinked_since = None  # no reason for more than a WARNING a minute
                endpoint.reason = None
                endpoint.accepted = False
                continue
            if endpoint.unlinked_since is None:  # unlinked since start, or since its link went
                endpoint.unlinked_since = self._started if first else now
            if now - endpoint.unlinked_since < GRACE:
                continue
            if endpoint.warned_at is not None and now - endpoint.warned_at < REPEAT:
                continue
            trouble = handshake_trouble(self._tls, endpoint.host, endpoint.port)
            if endpoint.linked(self._linked(), dialled):  # it linked while the probe ran (a
                endpoint.unlinked_since = None  # probe takes up to seconds): no warning
                continue
            if trouble is None and not endpoint.accepted:
                # The listener accepts this host: nothing to name yet. Zenoh's link is most
                # likely on its way (Zenoh dials again every second at most, or the peer,
                # which just started listening, is dialling us), and its link event comes
                # after Zenoh's own handshake, later than ours. Look again a GRACE later.
                endpoint.accepted, endpoint.unlinked_since = True, self._clock()
                continue
            endpoint.accepted = False
            endpoint.warned_at = now
            endpoint.reason = reason = _said(trouble)
            logger.warning(
                "ZenohNetwork %r has no link to connect endpoint %s: %s; calls to registrars "
                "there fail (UnknownRegistrarError) until it links",
                self._system,
                endpoint.endpoint,
                reason,
            )

    def _probe(self, endpoint: _Endpoint) -> str:
        return _said(handshake_trouble(self._tls, endpoint.host, endpoint.port))

    # -- asked by callers ------------------------------------------------------------------

    def unlinked(self) -> list[tuple[str, str]]:
        """The `connect` endpoints with no link to a member now, each with why (the last probe; one
        not probed yet is probed now, up to a handshake's timeout), on the caller's thread."""
        if self._thread.closed or not self._endpoints:
            return []
        linked = self._linked()
        dialled = {endpoint.port for endpoint in self._endpoints}
        unlinked = []
        for endpoint in self._endpoints:
            addresses = endpoint.addresses or _addresses(endpoint.host)  # (not looked at yet)
            if endpoint.linked(linked, dialled, addresses):
                continue
            reason = endpoint.reason
            if reason is None:
                reason = endpoint.reason = self._probe(endpoint)
            unlinked.append((endpoint.endpoint, reason))
        return unlinked


# -- why a connect endpoint is not linked: our own handshake ---------------------------------

_ALERT_WAIT = 0.5  # seconds to wait for the listener's alert after our side of the handshake

# OpenSSL's X509_V_ERR_* codes for what the listener's certificate does wrong
_NOT_YET_VALID, _EXPIRED = 9, 10
_NAME_MISMATCH = {62, 63, 64}  # hostname, email, IP address


def _context(tls: ZenohTLS) -> ssl.SSLContext:
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)  # checks the name and the chain
    context.minimum_version = ssl.TLSVersion.TLSv1_3  # as Zenoh's rustls
    context.load_verify_locations(cafile=tls.ca)
    context.load_cert_chain(tls.cert, tls.key)
    return context


def _alert(exc: ssl.SSLError) -> str:
    reason = exc.reason or str(exc)
    if "ALERT_" in reason:
        alert = reason.split("ALERT_", 1)[1].lower().replace("_", " ")
        return f"the listener refused this host's certificate ({alert})"
    return f"the TLS handshake failed ({reason})"


def _verdict(exc: ssl.SSLCertVerificationError, host: str, tls: ZenohTLS) -> str:
    code = exc.verify_code
    if code in _NAME_MISMATCH:
        return (
            f"the listener's certificate does not name {host} (an impostor, or its "
            f"certificate was issued without --address {host})"
        )
    if code == _EXPIRED:
        return "the listener's certificate has expired"
    if code == _NOT_YET_VALID:
        return "the listener's certificate is not valid yet (check both hosts' clocks)"
    return (
        f"the listener's certificate is not signed by this system's CA {tls.ca} "
        f"({exc.verify_message})"
    )


def handshake_trouble(tls: ZenohTLS, host: str, port: int, *, timeout: float = 2.0) -> str | None:
    """Why a mutual-TLS link with `host:port` fails, in words; `None` if the listener accepts us.

    zenoh-python 1.10 does not tell Python that a handshake was refused (it retries and logs
    at DEBUG), so this dials once with Python's `ssl` and the same files, and names the
    listener's alert (`unknown ca`, `certificate expired`, ...; TLS 1.3 sends it after the
    client's side, so the probe reads once), or its own verdict on the listener's
    certificate (Zenoh's client checks: CA, `verify_name_on_connect`, dates), or that the
    address cannot be reached. Blocks up to `timeout`: the watch thread only.

    Args:
        tls: this host's files (`ca`, `cert`, `key` are paths).
        host: the address dialled (an IP or a DNS name).
        port: the listener's TCP port.
        timeout: seconds for the connection and the handshake each.

    Never raises for the peer's doing: every failure is the returned reason.
    """
    try:
        context = _context(tls)
    except (OSError, ssl.SSLError) as exc:  # the files changed since ZenohTLS read them
        return f"this host's own TLS files cannot be loaded ({exc})"
    try:
        return _dial(context, host, port, timeout)
    except ssl.SSLCertVerificationError as exc:
        return _verdict(exc, host, tls)
    except ssl.SSLError as exc:
        return _alert(exc)
    except TimeoutError:
        return f"no TLS handshake within {timeout:g} s"
    except OSError as exc:
        return f"cannot reach it ({exc.strerror or exc})"


def _dial(context: ssl.SSLContext, host: str, port: int, timeout: float) -> str | None:
    """Connect, hand shake, then read once for the listener's alert (raises what fails)."""
    with (
        socket.create_connection((host, port), timeout=timeout) as raw,
        context.wrap_socket(raw, server_hostname=host) as conn,
    ):
        conn.settimeout(_ALERT_WAIT)
        try:
            if conn.recv(1) == b"":
                return "the listener closed the connection after the handshake"
        except TimeoutError:
            pass  # no alert: our certificate is accepted
    return None
