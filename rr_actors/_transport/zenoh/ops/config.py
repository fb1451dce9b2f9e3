"""A Zenoh session's config from `ZenohNetwork`'s arguments: endpoints, TLS and access control.

The rules it writes down: docs/explanation/inside.md ("A Zenoh session's config").
"""

from __future__ import annotations

import ipaddress
import json
import logging
import re
import socket
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

import zenoh

from rr_actors._transport.zenoh.ops.access import user
from rr_actors._transport.zenoh.wire import Keys
from rr_actors.config import is_loopback
from rr_actors.errors import ConfigError

if TYPE_CHECKING:
    from rr_actors._transport.zenoh.ops.tls import ZenohTLS

logger = logging.getLogger("rr_actors")

_ENDPOINT = re.compile(
    r"(?P<proto>tcp|tls)/(\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<host>[A-Za-z0-9_.\-]+)):(?P<port>\d{1,5})"
)

# Every message kind Zenoh 1.10's ACL knows, so a member can do anything under rr/<system>/.
_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]


def remote(locator: str) -> tuple[str, int | None]:
    """The host and port of a locator such as `tls/10.0.0.2:7447` or `tls/[::1]:7447`."""
    address = locator.split("/", 1)[-1].split("#", 1)[0]
    host, _, port = address.rpartition(":")
    return host.strip("[]"), int(port) if port.isdigit() else None


def parse_endpoint(role: str, endpoint: object) -> tuple[str, str, int]:
    """`(protocol, host, port)` of a `tcp/` or `tls/` endpoint; ConfigError naming it."""
    match = _ENDPOINT.fullmatch(endpoint) if isinstance(endpoint, str) else None
    port = int(match["port"]) if match else -1
    if match is None or not 0 <= port <= 65535 or (role == "connect" and port == 0):
        raise ConfigError(
            f"{role} endpoint {endpoint!r} is malformed: expected 'tcp/<address>:<port>' "
            f"(or 'tls/<address>:<port>' with tls=ZenohTLS(...); a host name, an IPv4 "
            f"address or [an IPv6 address], and a port"
            f"{' from 1' if role == 'connect' else ' from 0'} to 65535)"
        )
    host = match["v6"] or match["host"]
    if match["v6"] is not None:
        try:
            ipaddress.IPv6Address(host)
        except ValueError as exc:
            raise ConfigError(f"{role} endpoint {endpoint!r} is malformed: {exc}") from None
    elif not all(0 < len(label) <= 63 for label in host.removesuffix(".").split(".")):
        # a name no resolver takes (Python's raises UnicodeError for it, not OSError)
        raise ConfigError(
            f"{role} endpoint {endpoint!r} is malformed: the host name {host!r} has an "
            f"empty label or one longer than 63 characters"
        )
    return match["proto"], host, port


def endpoints(role: str, given: object, *, tls: bool) -> tuple[str, ...]:
    """The endpoints of `role`, checked against `tls`; raises `ConfigError`."""
    if isinstance(given, str | bytes) or not isinstance(given, Iterable):
        example = "tls/10.0.0.1:7447" if tls else "tcp/10.0.0.1:7447"
        raise ConfigError(
            f"{role} must be a list of endpoints such as [{example!r}], not {given!r}"
        )
    checked = tuple(given)
    for endpoint in checked:
        protocol, _, _ = parse_endpoint(role, endpoint)
        if tls and protocol == "tcp":
            raise ConfigError(
                f"{role} endpoint {endpoint!r} is plain TCP, but this network has tls=: "
                f"use {'tls/' + endpoint[4:]!r} (with TLS, only tls/ links are opened or accepted)"
            )
        if not tls and protocol == "tls":
            raise ConfigError(
                f"{role} endpoint {endpoint!r} is a tls/ endpoint, but tls=None: pass "
                f"tls=rr.ZenohTLS(ca=..., cert=..., key=..., members=[...]) "
                f"(or use {'tcp/' + endpoint[4:]!r} for plain TCP)"
            )
    return checked


def _tls_settings(tls: ZenohTLS) -> dict[str, Any]:
    return {
        "root_ca_certificate": tls.ca,
        "listen_private_key": tls.key,
        "listen_certificate": tls.cert,
        "connect_private_key": tls.key,
        "connect_certificate": tls.cert,
        "enable_mtls": True,
        "verify_name_on_connect": True,
        "close_link_on_expiration": True,
    }


def _access_control(system: str, members: Iterable[str]) -> dict[str, Any]:
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {
                "id": "rr",
                "messages": _MESSAGES,
                "flows": ["egress", "ingress"],
                "permission": "allow",
                "key_exprs": [Keys(system).everything()],
            }
        ],
        "subjects": [
            {"id": "members", "cert_common_names": list(members)},
            {"id": "local", "link_protocols": ["unixsock-stream"]},
        ],
        "policies": [{"rules": ["rr"], "subjects": ["members", "local"]}],
    }


ROUTER_SESSIONS = 10_000
"""Sessions a host's router takes at most (Zenoh's own default, 1,000, refuses a tree of a
thousand process managers: each joins through it with a session of its own)."""
ROUTER_PENDING = 1_024
"""Sessions a host's router lets open at once (Zenoh's default, 100, refused 120-200 of
600 sessions opened together); strangers' handshakes are the gate's to limit."""


def session_config(
    mode: str,
    listen: list[str],
    connect: list[str],
    lease: float,
    *,
    system: str = "",
    tls: ZenohTLS | None = None,
) -> zenoh.Config:
    """The session's Zenoh config; with `tls`, mutual TLS and access control for `system`."""
    lease_ms = max(1, round(lease * 1000))
    remote = [endpoint for endpoint in listen if not endpoint.startswith("unixsock-stream/")]
    link: dict[str, Any] = {
        "tx": {
            "lease": lease_ms,
            "keep_alive": 4,
            # a link blocked for half the lease is closed: a frozen reader stalls no other
            "queue": {"congestion_control": {"block": {"wait_before_close": lease_ms * 500}}},
        }
    }
    if tls is not None:
        link["protocols"] = ["tls", "unixsock-stream"]
        link["tls"] = _tls_settings(tls)
    settings: dict[str, Any] = {
        "mode": mode,
        "listen": {"endpoints": listen},
        "connect": {
            "endpoints": connect,
            "exit_on_failure": mode == "client",
            "retry": {"period_init_ms": 250, "period_max_ms": 1000},
        },
        "scouting": {
            "multicast": {"enabled": False},
            "gossip": {"enabled": False},
            # a router's open waits `delay` ms (500) for links: with none to come, no wait
            **({"delay": 0} if mode == "router" and not connect and not remote else {}),
        },
        # no shared memory: a session keeps each peer's segment file open for good
        "transport": {"link": link, "shared_memory": {"enabled": False}},
    }
    if mode == "router":  # (its host's manager processes, one session each: inside.md)
        unicast = {"max_sessions": ROUTER_SESSIONS, "accept_pending": ROUTER_PENDING}
        settings["transport"]["unicast"] = unicast
    if tls is not None:
        settings["access_control"] = _access_control(system, tls.members)
    return zenoh.Config.from_json5(json.dumps(settings))


def _who_reaches(host: str) -> str:
    if is_loopback(host):
        return "every user and process on this machine"
    if host in ("0.0.0.0", "::"):  # noqa: S104 - naming the wildcard, not binding it
        return "anyone who can reach this machine (at any of its addresses)"
    return f"anyone who can reach {host}"


def _who_answers(host: str, port: int) -> str:
    if is_loopback(host):
        return f"every user and process on this machine (whoever listens on port {port} first)"
    return f"whoever answers at {host} port {port} (anyone who can listen there or sits between)"


def warn_plain_tcp(system: str, listen: Iterable[str], connect: Iterable[str]) -> None:
    """A WARNING per plain-TCP endpoint, naming who can send this process pickles."""
    me = user()
    for endpoint in listen:
        _, host, _ = parse_endpoint("listen", endpoint)
        logger.warning(
            "ZenohNetwork %r listens on %s in plain TCP (tls=None): %s can connect and run "
            "code as this user, %s (what crosses is pickles); use tls= and tls/ endpoints",
            system,
            endpoint,
            _who_reaches(host),
            me,
        )
    for endpoint in connect:
        _, host, port = parse_endpoint("connect", endpoint)
        logger.warning(
            "ZenohNetwork %r connects to %s in plain TCP (tls=None): %s can run code as "
            "this user, %s (what crosses is pickles); use tls= and tls/ endpoints",
            system,
            endpoint,
            _who_answers(host, port),
            me,
        )


PROBE_TIMEOUT = 0.5
"""Seconds a plain `connect` endpoint gets to accept a TCP connect that probes it."""


def warn_unreachable(system: str, connect: Iterable[str]) -> None:
    """A WARNING per plain-TCP `connect` endpoint that does not accept a connection now."""
    for endpoint in connect:
        _, host, port = parse_endpoint("connect", endpoint)
        try:
            with socket.create_connection((host, port), timeout=PROBE_TIMEOUT):
                pass
        except OSError as exc:
            logger.warning(
                "ZenohNetwork %r cannot reach connect endpoint %s now (%s); Zenoh keeps trying",
                system,
                endpoint,
                exc,
            )
