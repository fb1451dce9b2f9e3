"""Real certificate files for tests, made with `cryptography` directly.

`make_ca` writes a system's CA; `issue` writes a host's certificate and key, signed by a CA
or self-signed, and can make the odd ones a test needs (expired, not yet valid, another
CA, no clientAuth, a key type Zenoh's TLS cannot use). Files are PEM; keys are PKCS#8,
unencrypted, mode 0600. The shape follows `rr-actors certs` (rr_actors_lab/_tools/certs.py)
unless told otherwise:

    ca_pem, ca_key = make_ca(tmp_path)
    pem, key = issue(tmp_path, "robot", ("10.0.0.2",), ca=(ca_pem, ca_key))
    old = issue(tmp_path, "old", ca=(ca_pem, ca_key), not_after=datetime.now(UTC) - DAY)
    mid = make_intermediate(tmp_path, (ca_pem, ca_key))  # a CA signed by the CA
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from collections.abc import Iterable
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

__all__ = ["DAY", "issue", "make_ca", "make_intermediate"]

DAY = datetime.timedelta(days=1)

PrivateKey = ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey | rsa.RSAPrivateKey


def _new_key(key_type: str) -> PrivateKey:
    """A key: `"p256"`, `"p384"`, `"p521"` (rustls refuses it), `"ed25519"`, `"rsaBITS"`."""
    if key_type in ("p256", "p384", "p521"):
        curve = {"p256": ec.SECP256R1, "p384": ec.SECP384R1, "p521": ec.SECP521R1}[key_type]
        return ec.generate_private_key(curve())
    if key_type == "ed25519":
        return ed25519.Ed25519PrivateKey.generate()
    if key_type.startswith("rsa"):
        return rsa.generate_private_key(public_exponent=65537, key_size=int(key_type[3:]))
    raise ValueError(f"unknown key_type {key_type!r}")


def _write(path: Path, data: bytes, mode: int = 0o644) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, mode)  # the umask may have taken bits off


def _save(directory: Path, stem: str, cert: x509.Certificate, key: PrivateKey) -> tuple[Path, Path]:
    pem, key_path = directory / f"{stem}.pem", directory / f"{stem}.key"
    _write(pem, cert.public_bytes(serialization.Encoding.PEM))
    private = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    _write(key_path, private, 0o600)
    return pem, key_path


def _hash(key: PrivateKey) -> hashes.SHA256 | None:
    return None if isinstance(key, ed25519.Ed25519PrivateKey) else hashes.SHA256()


def make_ca(
    directory: str | os.PathLike[str], system: str = "lab", *, stem: str = "ca"
) -> tuple[Path, Path]:
    """A CA for `system`: `directory/<stem>.pem` and `directory/<stem>.key`; their paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"rr_actors {system} CA")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + 3650 * DAY)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return _save(directory, stem, cert, key)


def make_intermediate(
    directory: str | os.PathLike[str],
    ca: tuple[str | os.PathLike[str], str | os.PathLike[str]],
    system: str = "mid",
    *,
    stem: str = "intermediate",
) -> tuple[Path, Path]:
    """An intermediate CA signed by `ca`: `directory/<stem>.pem` and `.key`; their paths.

    A host's certificate issued by it (`issue(..., ca=intermediate)`) is accepted with
    `ca` as the root when its file holds the host's certificate, then this one.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    root_cert, root_key = _load_ca(ca)
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"rr_actors {system}")]))
        .issuer_name(root_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + 365 * DAY)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(root_key, _hash(root_key))
    )
    return _save(directory, stem, cert, key)


def _load_ca(
    ca: tuple[str | os.PathLike[str], str | os.PathLike[str]],
) -> tuple[x509.Certificate, PrivateKey]:
    cert = x509.load_pem_x509_certificate(Path(ca[0]).read_bytes())
    key = serialization.load_pem_private_key(Path(ca[1]).read_bytes(), password=None)
    assert isinstance(key, PrivateKey)
    return cert, key


def issue(
    directory: str | os.PathLike[str],
    name: str | None,
    addresses: Iterable[str] = ("10.0.0.1",),
    *,
    ca: tuple[str | os.PathLike[str], str | os.PathLike[str]] | None = None,
    not_before: datetime.datetime | None = None,
    not_after: datetime.datetime | None = None,
    eku: Iterable[str] | None = ("server", "client"),
    key_type: str = "p256",
    stem: str | None = None,
) -> tuple[Path, Path]:
    """A host's certificate and key: `directory/<stem or name>.pem` and `.key`; their paths.

    Args:
        directory: where to write (made if missing).
        name: the subject common name (the member name); `None`: a subject without one
            (then give `stem`).
        addresses: the subject alternative names: IP addresses, else DNS names.
        ca: the issuing CA's `(pem, key)` paths; `None`: self-signed.
        not_before, not_after: the validity (default: 5 minutes ago, a year from now).
        eku: extended key uses among `"server"`, `"client"`; `None`: no such extension.
        key_type: see `_new_key` (default ECDSA P-256).
        stem: the files' name (default `name`).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    key = _new_key(key_type)
    attributes = [] if name is None else [x509.NameAttribute(NameOID.COMMON_NAME, name)]
    subject = x509.Name(attributes)
    issuer_cert, issuer_key = _load_ca(ca) if ca is not None else (None, key)
    now = datetime.datetime.now(datetime.UTC)
    sans: list[x509.GeneralName] = []
    for address in addresses:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(address)))
        except ValueError:
            sans.append(x509.DNSName(address))
    builder = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(issuer_cert.subject if issuer_cert is not None else subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before or now - datetime.timedelta(minutes=5))
        .not_valid_after(not_after or now + 365 * DAY)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
    )
    if sans:
        builder = builder.add_extension(x509.SubjectAlternativeName(sans), critical=False)
    if eku is not None:
        oids = {
            "server": ExtendedKeyUsageOID.SERVER_AUTH,
            "client": ExtendedKeyUsageOID.CLIENT_AUTH,
        }
        builder = builder.add_extension(
            x509.ExtendedKeyUsage([oids[use] for use in eku]), critical=False
        )
    if issuer_cert is not None:
        builder = builder.add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(issuer_cert.public_key()),
            critical=False,
        )
    cert = builder.sign(issuer_key, _hash(issuer_key))
    return _save(directory, stem or name or "noname", cert, key)
