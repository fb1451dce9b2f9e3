"""`ZenohTLS`: a host's certificates for mutual TLS between the hosts of a system.

Checked once, when made, with `cryptography`: a wrong file is a `ConfigError` in the
program that named it, not a handshake Zenoh refuses on its standard output only:

```
 ca.pem ───────────┐
 robot.pem ─ leaf ─┼─ signed by a CA of ca.pem, in date, both TLS uses ─┐
 robot.key ────────┘   matches the leaf, a type rustls signs with       ├─ ZenohTLS
 members ─────────── names like registrars', the leaf's CN among them ──┘   (name, addresses,
                                                                             not_after)
```

`ZenohNetwork` hands the paths to Zenoh and `members` to its access control.
"""

from __future__ import annotations

import datetime
import ipaddress
import logging
import os
from collections.abc import Iterable
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from rr_actors._transport.zenoh.ops.access import private_file_trouble
from rr_actors.config import check_name
from rr_actors.errors import ConfigError

logger = logging.getLogger("rr_actors")

_CURVES = (ec.SECP256R1, ec.SECP384R1)  # the ECDSA curves rustls signs and verifies with
_RSA_MIN_BITS = 2048


def _path(argument: str, value: object) -> str:
    if not isinstance(value, str | os.PathLike):
        raise ConfigError(f"{argument} must be a path (str or os.PathLike), not {value!r}")
    path = os.fsdecode(value)
    if "\0" in path:  # no file has one: open() would raise ValueError
        raise ConfigError(f"{argument} {path!r} is not a path (it holds a NUL character)")
    return os.path.abspath(path)


def _read(argument: str, path: str) -> bytes:
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{argument} {path} does not exist") from None
    except OSError as exc:
        raise ConfigError(f"{argument} {path} cannot be read: {exc.strerror or exc}") from None
    if b"-----BEGIN " not in data:
        raise ConfigError(f"{argument} {path} is not PEM (no '-----BEGIN ...' line)")
    return data


def _certificates(argument: str, path: str) -> list[x509.Certificate]:
    data = _read(argument, path)  # outside the try: a ConfigError is a ValueError too
    try:
        found = x509.load_pem_x509_certificates(data)
    except ValueError as exc:
        raise ConfigError(f"{argument} {path} holds no readable certificate: {exc}") from None
    if not found:
        raise ConfigError(f"{argument} {path} holds no certificate")
    return found


def _utc(moment: datetime.datetime) -> str:
    return moment.strftime("%Y-%m-%d %H:%M:%S UTC")


def _check_dates(what: str, cert: x509.Certificate, now: datetime.datetime) -> None:
    start, end = cert.not_valid_before_utc, cert.not_valid_after_utc
    if now < start:
        raise ConfigError(
            f"{what} is not yet valid: valid from {_utc(start)} to {_utc(end)}, now {_utc(now)}"
        )
    if now > end:
        raise ConfigError(
            f"{what} expired on {_utc(end)} (valid from {_utc(start)}; now {_utc(now)})"
        )


def _common_name(cert: x509.Certificate) -> str | None:
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    value = names[0].value if names else None
    return value if isinstance(value, str) and value else None


def _is_ca(cert: x509.Certificate) -> bool:
    try:
        return cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    except x509.ExtensionNotFound:
        return False


def _signed_by(cert: x509.Certificate, issuer: x509.Certificate) -> bool:
    try:
        cert.verify_directly_issued_by(issuer)
    except (ValueError, TypeError, InvalidSignature, UnsupportedAlgorithm):
        return False
    return True


def _check_key_type(path: str, key: object) -> None:  # (what rustls, Zenoh's TLS, signs)
    if isinstance(key, ec.EllipticCurvePrivateKey) and isinstance(key.curve, _CURVES):
        return
    if isinstance(key, ed25519.Ed25519PrivateKey):
        return
    if isinstance(key, rsa.RSAPrivateKey) and key.key_size >= _RSA_MIN_BITS:
        return
    kind = (
        f"EC {key.curve.name}"
        if isinstance(key, ec.EllipticCurvePrivateKey)
        else f"RSA {key.key_size} bits"
        if isinstance(key, rsa.RSAPrivateKey)
        else type(key).__name__
    )
    raise ConfigError(
        f"key {path} is {kind}, which Zenoh's TLS (rustls) cannot use: use ECDSA P-256 or "
        f"P-384, Ed25519, or RSA of {_RSA_MIN_BITS} bits or more"
    )


def _check_uses(path: str, cert: x509.Certificate) -> None:
    try:
        uses = set(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
    except x509.ExtensionNotFound:
        return  # no restriction: every use
    missing = [
        label
        for oid, label in (
            (ExtendedKeyUsageOID.SERVER_AUTH, "serverAuth (TLS server)"),
            (ExtendedKeyUsageOID.CLIENT_AUTH, "clientAuth (TLS client)"),
        )
        if oid not in uses
    ]
    if missing:
        raise ConfigError(
            f"cert {path} lacks the extended key usage {' and '.join(missing)}: a host both "
            f"listens and connects, so its certificate needs serverAuth and clientAuth"
        )


def _members(members: object) -> tuple[str, ...]:
    if isinstance(members, str | bytes) or not isinstance(members, Iterable):
        raise ConfigError(f"members must be a list of names such as ['robot'], not {members!r}")
    names = list(members)
    if not names:
        raise ConfigError("members is empty: name at least this host's certificate's name")
    for name in names:
        check_name("members:", name, "a member name")
    return tuple(dict.fromkeys(names))  # order kept, duplicates dropped


class ZenohTLS:
    """A host's CA, certificate, key and the system's members, checked when made.

    The system has its own certificate authority (`ca`); every host holds `ca`, its own
    certificate and key, and admits the hosts whose certificate's common name is in
    `members` (as ROS 2's SROS2 keystore: one CA per system, one identity per
    participant). Make the files with `rr-actors certs`: docs/how-to/securing-registrars.md.

    Args:
        ca: path (str or `os.PathLike`) to a PEM file of the system's CA certificate(s)
            (all are trusted: the old and the new CA while it is replaced).
        cert: path to this host's PEM certificate, then any intermediates, each signed
            by the next, the last by a CA of `ca`.
        key: path to its private key, PEM, unencrypted: ECDSA P-256 or P-384, Ed25519,
            or RSA of 2048 bits or more.
        members: the common names admitted (an iterable of str), named like registrars;
            non-empty, this host's own among them. Order kept, duplicates dropped.

    Attributes:
        ca, cert, key: the absolute paths.
        members: the names admitted, a tuple.
        name: this host's certificate's common name (its member name).
        addresses: the certificate's subject alternative names (IP addresses and DNS
            names, in its order): where peers may dial this host.
        not_after: when the certificate ends (a timezone-aware UTC datetime).

    Raises:
        ConfigError: naming the argument and file and what is wrong: a path that is not
            one; a file missing, unreadable or not PEM; `ca` without a CA certificate, or
            one out of date; `cert` out of date (with the dates, UTC), not signed by `ca`
            (or through an intermediate that is no CA), without a common name, or without
            both TLS uses; `key` not a private key, encrypted, of a type rustls cannot
            use, or not the certificate's; `members` not names, empty, or without this
            host's name.

    A key file open to group or others, or owned by another user, logs a WARNING naming
    the fix (`chmod 600`, `chown`). The object is read-only.
    """

    __slots__ = ("addresses", "ca", "cert", "key", "members", "name", "not_after")

    ca: str
    cert: str
    key: str
    members: tuple[str, ...]
    name: str
    addresses: tuple[str, ...]
    not_after: datetime.datetime

    def __init__(
        self,
        *,
        ca: str | os.PathLike[str],
        cert: str | os.PathLike[str],
        key: str | os.PathLike[str],
        members: Iterable[str],
    ) -> None:
        self.ca = _path("ca", ca)
        self.cert = _path("cert", cert)
        self.key = _path("key", key)
        self.members = _members(members)
        now = datetime.datetime.now(datetime.UTC)
        leaf = _leaf(self.cert, self.ca, now)
        name = _common_name(leaf)
        if name is None:
            raise ConfigError(
                f"cert {self.cert} has no subject common name: a member is known by it"
            )
        if name not in self.members:
            raise ConfigError(
                f"cert {self.cert} is {name!r}, which is not in members {list(self.members)}: "
                f"a host must be a member of its own system"
            )
        _check_key(self.key, leaf, self.cert)
        self.name = name
        self.not_after = leaf.not_valid_after_utc
        self.addresses = _addresses(leaf)

    def __setattr__(self, name: str, value: object) -> None:
        if hasattr(self, name):
            raise AttributeError(f"ZenohTLS.{name} is read-only: make a new ZenohTLS")
        object.__setattr__(self, name, value)

    def __repr__(self) -> str:
        return (
            f"ZenohTLS(name={self.name!r}, addresses={list(self.addresses)}, "
            f"not_after={_utc(self.not_after)!r}, members={list(self.members)}, "
            f"ca={self.ca!r}, cert={self.cert!r}, key={self.key!r})"
        )


def _addresses(cert: x509.Certificate) -> tuple[str, ...]:
    try:
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return ()
    return tuple(
        str(entry.value) for entry in names if isinstance(entry, x509.IPAddress | x509.DNSName)
    )


def authorities(path: str) -> list[x509.Certificate]:
    """The CA certificates of file `path`, each a CA and in date now (raises as `ZenohTLS`)."""
    return _authorities(path, datetime.datetime.now(datetime.UTC))


def leaf_of(
    chain: bytes, trusted: list[x509.Certificate], now: datetime.datetime
) -> x509.Certificate | None:
    """The host certificate first in PEM `chain` (a `cert` file) if the chain checks out
    at `now` up to one of `trusted`; else `None`."""
    try:
        certificates = x509.load_pem_x509_certificates(chain)
        if not certificates:
            return None
        return _checked_chain(certificates, trusted, "a certificate", "ca", now)
    except ValueError:  # (a ConfigError is one too)
        return None


def member_of(cert: x509.Certificate) -> str | None:
    return _common_name(cert)


def _authorities(path: str, now: datetime.datetime) -> list[x509.Certificate]:
    authorities = _certificates("ca", path)
    for authority in authorities:
        what = f"ca {path} ({authority.subject.rfc4514_string()})"
        if not _is_ca(authority):
            raise ConfigError(f"{what} is not a CA certificate (no BasicConstraints CA=true)")
        _check_dates(what, authority, now)
    return authorities


def _leaf(path: str, ca: str, now: datetime.datetime) -> x509.Certificate:
    chain = _certificates("cert", path)
    leaf = _checked_chain(chain, _authorities(ca, now), f"cert {path}", f"ca {ca}", now)
    _check_uses(path, leaf)
    return leaf


def _checked_chain(
    chain: list[x509.Certificate],
    authorities: list[x509.Certificate],
    what: str,
    ca: str,
    now: datetime.datetime,
) -> x509.Certificate:
    """The first of `chain`, once each is in date and signed by the next, the last by one
    of `authorities` (`what` and `ca` name them in the error)."""
    for index, link in enumerate(chain):
        this = what + (f" (intermediate {index})" if index else "")
        if index and not _is_ca(link):  # Zenoh's TLS (webpki) refuses such a chain
            raise ConfigError(
                f"{this} ({link.subject.rfc4514_string()}) is not a CA certificate (no "
                f"BasicConstraints CA=true), so it cannot sign the certificate before it"
            )
        _check_dates(this, link, now)
        issuers = chain[index + 1 : index + 2] or authorities
        if not any(_signed_by(link, issuer) for issuer in issuers):
            by = "the next certificate in it" if index + 1 < len(chain) else ca
            raise ConfigError(
                f"{this} ({link.subject.rfc4514_string()}, issued by "
                f"{link.issuer.rfc4514_string()}) is not signed by {by}"
            )
    return chain[0]


def member_addresses(pem: bytes, tls: ZenohTLS, name: str) -> tuple[str, ...]:
    """The IP addresses member `name`'s cert file `pem` names, checked as this host's
    own (in date, signed up to `tls.ca`, common name `name`, one of `tls.members`): what
    the gate never drops. Raises `ConfigError` saying why not."""
    if name not in tls.members:
        raise ConfigError(f"{name!r} is not in members {list(tls.members)}")
    what = f"the certificate of member {name!r}"
    try:
        chain = x509.load_pem_x509_certificates(pem)
    except ValueError as exc:
        raise ConfigError(f"{what} is not PEM certificates: {exc}") from None
    if not chain:
        raise ConfigError(f"{what} holds no certificate")
    now = datetime.datetime.now(datetime.UTC)
    authorities = _authorities(tls.ca, now)
    leaf = _checked_chain(chain, authorities, what, f"ca {tls.ca}", now)
    if _common_name(leaf) != name:
        raise ConfigError(f"{what} has the common name {_common_name(leaf)!r}")
    return tuple(address for address in _addresses(leaf) if _is_ip(address))


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


def _check_key(path: str, leaf: x509.Certificate, cert_path: str) -> None:
    """The key of `path` is `leaf`'s, of a type rustls uses; a WARNING if it is not private."""
    data = _read("key", path)
    try:
        private = serialization.load_pem_private_key(data, password=None)
    except TypeError:
        raise ConfigError(
            f"key {path} is encrypted: Zenoh reads an unencrypted key (keep it 0600 instead)"
        ) from None
    except (ValueError, UnsupportedAlgorithm) as exc:
        raise ConfigError(f"key {path} holds no readable private key: {exc}") from None
    _check_key_type(path, private)
    spki = serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    if private.public_key().public_bytes(*spki) != leaf.public_key().public_bytes(*spki):
        raise ConfigError(f"key {path} is not the private key of cert {cert_path}")
    trouble = private_file_trouble(path)
    if trouble is not None:
        logger.warning("private key %s %s", path, trouble)
