"""One TLS handshake of our own, to say why Zenoh has no link to a `connect` endpoint.

zenoh-python 1.10 does not tell Python that a handshake was refused: a refused
`zenoh.open` returns normally, retries every 1-4 s and logs the reason at DEBUG on stdout.
So when a `connect` endpoint stays unlinked, rr_actors dials it once with Python's `ssl`
and the same files (`watch` decides when), and names what went wrong:

- the listener's alert, sent when it refuses this host's certificate (TLS 1.3 sends it
  after the client's side of the handshake, so the probe reads once to receive it):
  `unknown ca`, `certificate expired`, `certificate required`, ...;
- or its own verdict on the listener's certificate, the checks Zenoh makes as a client:
  not signed by this system's CA, or not naming the address dialled
  (`verify_name_on_connect`), or out of its validity dates;
- or that the address cannot be reached at all.

Runs on `watch`'s thread; never on a Zenoh callback (it blocks up to `timeout`).
"""

from __future__ import annotations

import socket
import ssl
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rr_actors._transport.zenoh.tls import ZenohTLS

__all__ = ["handshake_trouble"]

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

    Args:
        tls: this host's files (`ca`, `cert`, `key` are paths).
        host: the address dialled (an IP or a DNS name), checked against the listener's
            certificate as Zenoh does.
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
