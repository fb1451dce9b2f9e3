"""A system's certificates in two steps (`rr-actors certs init` / `rr-actors certs issue`).

```
 certs init DIR --system lab      ──> DIR/ca.pem, DIR/ca.key (0600)        stays here
 certs issue DIR robot --address… ──> DIR/robot.pem, DIR/robot.key (0600)  to the host
                                       signed with DIR/ca.key                 with ca.pem
```

The certificates are what `ZenohTLS` accepts (ECDSA P-256 keys, PKCS#8, unencrypted,
0600; certificates 0644). A file is written to a temporary file in the same directory,
then renamed over its name (never half a file); without `force`, hard-linked instead, so
what appeared there meanwhile is never replaced. The CA stays private: DIR is made 0700,
and without `force` a DIR or `ca.key` another user owns, or that group or others may
write, is refused (the check `ZenohTLS` makes of a host's key).
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import ipaddress
import os
import re
from collections.abc import Iterable
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from rr_actors._transport.zenoh.ops.access import private_dir_trouble, private_file_trouble
from rr_actors.config import check_name
from rr_actors.errors import ConfigError

__all__ = ["CA_DAYS", "CLOCK_SKEW", "init_ca", "issue_cert"]

CA_DAYS = 3650
"""Days a CA made by `init_ca` is valid."""

CLOCK_SKEW = datetime.timedelta(minutes=5)
"""A certificate is valid from this long before it is made: hosts' clocks differ a little."""


def _key_usage(*, digital_signature: bool = False, cert_sign: bool = False) -> x509.KeyUsage:
    return x509.KeyUsage(
        digital_signature=digital_signature,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=cert_sign,
        crl_sign=cert_sign,
        encipher_only=False,
        decipher_only=False,
    )


def _pem(cert: x509.Certificate) -> bytes:
    return cert.public_bytes(serialization.Encoding.PEM)


def _pkcs8(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _refuse_existing(paths: Iterable[Path], force: bool) -> None:
    existing = [str(p) for p in paths if os.path.lexists(p)]  # a symlink too, even dangling
    if existing and not force:
        raise ConfigError(
            f"{' and '.join(existing)} already exist{'s' if len(existing) == 1 else ''}: "
            f"left untouched (--force replaces)"
        )


def _install(tmp: Path, path: Path, force: bool) -> None:
    """Rename `tmp` to `path`; without `force`, FileExistsError if `path` exists by now."""
    if force:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)  # atomic: fails if another writer made `path` since we looked
    except FileExistsError:
        raise
    except OSError:  # a file system without hard links: the look before is all there is
        if os.path.lexists(path):
            raise FileExistsError(errno.EEXIST, "exists", str(path)) from None
        os.replace(tmp, path)


def _write_all(files: dict[Path, tuple[bytes, int]], *, force: bool) -> None:
    """Write each file (data, mode) to a temporary name in its directory, then rename them all;
    without `force`, a file that appeared meanwhile stops it (`ConfigError`, the rest undone)."""
    temporary: dict[Path, Path] = {}
    installed: list[Path] = []
    try:
        for path, (data, mode) in files.items():
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            temporary[path] = tmp
            os.fchmod(fd, mode)  # exactly `mode`, whatever the umask
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        for path, tmp in temporary.items():
            _install(tmp, path, force)
            installed.append(path)
    except FileExistsError as exc:
        for path in installed:
            path.unlink()
        existing = exc.filename2 if exc.filename2 is not None else exc.filename  # os.link's
        raise ConfigError(f"{existing} already exists: left untouched (--force replaces)") from None
    except OSError as exc:
        raise ConfigError(f"cannot write {', '.join(map(str, files))}: {exc}") from exc
    finally:
        for tmp in temporary.values():
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()


def _refuse_unsafe(what: str, path: Path, trouble: str | None, force: bool) -> None:
    if trouble is not None and not force:
        raise ConfigError(f"{what} {path} {trouble}; nothing written (--force writes anyway)")


def _directory(directory: str | os.PathLike[str], *, force: bool) -> Path:
    """`directory`, made 0700 if missing; an existing one must be private (or `force`)."""
    path = Path(directory)
    if not path.exists():
        try:
            path.mkdir(mode=0o700, parents=True)
            path.chmod(0o700)  # the umask may have taken bits off
        except OSError as exc:
            raise ConfigError(f"cannot make the directory {path}: {exc}") from exc
    if not path.is_dir():
        raise ConfigError(f"{path} is not a directory")
    _refuse_unsafe("the CA's directory", path, private_dir_trouble(path), force)
    return path


def init_ca(
    directory: str | os.PathLike[str], system: str, *, force: bool = False
) -> tuple[Path, Path]:
    """Make a system's certificate authority: `directory/ca.pem` and `directory/ca.key`.

    Subject `CN=<system>, O=rr_actors CA`, valid `CA_DAYS` days (BasicConstraints CA=true,
    keyCertSign and cRLSign, critical; ECDSA P-256). The directory is made 0700 if missing.

    Args:
        directory: where the files go.
        system: the system's name (as `ZenohNetwork(system=...)`), named in the CA.
        force: replace existing files (hosts given the new `ca.pem` stop accepting the old
            CA's certificates), and write into a directory that is not private.

    Returns:
        The paths of `ca.pem` and `ca.key`.

    Raises:
        ConfigError: `system` is not a system name (or longer than 64 characters); without
            `force`, `ca.pem` or `ca.key` exists, or the directory is another user's or
            writable by group or others (nothing is written); the directory cannot be made
            or written.
    """
    check_name("system", system, "a system name")
    path = _directory(directory, force=force)
    pem, key_path = path / "ca.pem", path / "ca.key"
    _refuse_existing((pem, key_path), force)
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name(  # the CN is the system alone: a name fills it (NAME_MAX, 64)
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "rr_actors CA"),
            x509.NameAttribute(NameOID.COMMON_NAME, system),
        ]
    )
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - CLOCK_SKEW)
        .not_valid_after(now + datetime.timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(_key_usage(cert_sign=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write_all({pem: (_pem(cert), 0o644), key_path: (_pkcs8(key), 0o600)}, force=force)
    return pem, key_path


CaKey = ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey


def _load_ca(directory: Path, *, force: bool) -> tuple[x509.Certificate, CaKey]:
    """The CA of `directory`; its key and the directory must be private (or `force`)."""
    pem, key_path = directory / "ca.pem", directory / "ca.key"
    missing = [str(p) for p in (pem, key_path) if not p.is_file()]
    if missing:
        raise ConfigError(
            f"no CA: {' and '.join(missing)} missing "
            f"(make one with: rr-actors certs init {directory} --system NAME)"
        )
    # Whoever can read ca.key can make members; whoever can write it, or the directory,
    # can swap in a CA of their own: sign with neither.
    _refuse_unsafe("the CA's key", key_path, private_file_trouble(key_path), force)
    _refuse_unsafe("the CA's directory", directory, private_dir_trouble(directory), force)
    try:
        cert = x509.load_pem_x509_certificate(pem.read_bytes())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{pem} is not a readable PEM certificate: {exc}") from None
    try:
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError, UnsupportedAlgorithm) as exc:
        raise ConfigError(f"{key_path} is not a readable unencrypted private key: {exc}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey):
        raise ConfigError(f"{key_path}: only an EC or Ed25519 CA key signs here")
    spki = serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    if key.public_key().public_bytes(*spki) != cert.public_key().public_bytes(*spki):
        raise ConfigError(f"{key_path} is not the private key of {pem}")
    return cert, key


_LABEL = re.compile(r"(?!-)[A-Za-z0-9_\-]{1,63}(?<!-)")
"""One label of a DNS name peers dial (as `ZenohNetwork`'s endpoints take them)."""


def _is_dns_name(address: str) -> bool:
    labels = address.removesuffix(".").split(".")
    return len(address) <= 253 and all(_LABEL.fullmatch(label) for label in labels)


def _names(name: str, addresses: Iterable[str]) -> list[x509.GeneralName]:
    if isinstance(addresses, str | bytes):
        raise ConfigError(f"addresses must be a list such as ['10.0.0.2'], not {addresses!r}")
    given = list(dict.fromkeys(addresses))
    if not given:  # a host that only connects: the name, which nobody dials
        return [x509.DNSName(name)]
    sans: list[x509.GeneralName] = []
    for address in given:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(address)))
            continue
        except ValueError:
            pass
        if not isinstance(address, str) or not _is_dns_name(address):
            raise ConfigError(
                f"--address {address!r} is not an IP address or DNS name (give the host "
                f"alone, as peers put it in their endpoints: 10.0.0.2, ::1 or robot.local; "
                f"no port, no 'tls/', no brackets)"
            )
        sans.append(x509.DNSName(address))
    return sans


def issue_cert(
    directory: str | os.PathLike[str],
    name: str,
    addresses: Iterable[str] = (),
    *,
    days: int = 365,
    force: bool = False,
) -> tuple[Path, Path]:
    """Issue a host's certificate with the CA in `directory`: `NAME.pem` and `NAME.key`.

    Common name `name`; subject alternative names every address (IP, else DNS; default `name`
    as DNS), which peers check the address they dial against. serverAuth and clientAuth, not
    a CA, ECDSA P-256; valid from `CLOCK_SKEW` ago for `days` days; the key written 0600.

    Args:
        directory: holds `ca.pem` and `ca.key` (from `init_ca`); the files go there.
        name: the member name, as in `ZenohTLS(members=...)`.
        addresses: the IP addresses and DNS names peers dial this host at.
        days: how long the certificate is valid, a positive int.
        force: replace an existing certificate of that name, and sign with a CA key or in a
            directory that is not private.

    Returns:
        The paths of `NAME.pem` and `NAME.key`.

    Raises:
        ConfigError: `name` is not a member name (or over 64 characters) or is `ca`; `days`
            is not a positive int or ends after 9999; `addresses` is a str, or an address is
            neither an IP address nor a DNS name; no readable CA in `directory`; without
            `force` (nothing is written): the files exist, or `ca.key` or `directory` is
            another user's or open to group or others.
    """
    check_name("name", name, "a member name")
    if name == "ca":
        raise ConfigError("name 'ca' is the CA's own files: name the host otherwise")
    if isinstance(days, bool) or not isinstance(days, int) or days < 1:
        raise ConfigError(f"days must be a positive whole number, not {days!r}")
    path = Path(directory)  # its CA files are checked next: missing, they say how to make them
    ca_cert, ca_key = _load_ca(path, force=force)
    pem, key_path = path / f"{name}.pem", path / f"{name}.key"
    _refuse_existing((pem, key_path), force)
    sans = _names(name, addresses)
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    try:
        not_after = now + datetime.timedelta(days=days)
    except OverflowError:  # past the year 9999, datetime's last (and X.509's)
        raise ConfigError(f"days {days} ends after the year 9999: give fewer days") from None
    try:
        issuer_ski = ca_cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
        aki = x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(issuer_ski)
    except x509.ExtensionNotFound:
        aki = x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - CLOCK_SKEW)
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(digital_signature=True), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .add_extension(x509.SubjectAlternativeName(sans), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(aki, critical=False)
        .sign(ca_key, None if isinstance(ca_key, ed25519.Ed25519PrivateKey) else hashes.SHA256())
    )
    try:
        cert.verify_directly_issued_by(ca_cert)
    except (ValueError, TypeError, InvalidSignature) as exc:  # pragma: no cover - a broken CA
        raise ConfigError(f"{path / 'ca.pem'} cannot issue: {exc}") from exc
    _write_all({pem: (_pem(cert), 0o644), key_path: (_pkcs8(key), 0o600)}, force=force)
    return pem, key_path
