"""An event batch's seal: the certificate of the host that sent it, and its signature.

```
 a member process (the router or a manager)         a system-wide subscriber (any member)
 encode(batch) ─► Seal.seal(data): the host's       Seal.open(data, attachment):
   certificate chain (its `cert` file) and the ─►     the chain: in date, up to the CA
   signature of the key (`key`) over SHA-256          (`ca`), its common name in `members`
   of the system's name and the batch                 (cached); the signature over the
 put rr/<s>/ev/<zid>, the seal as Zenoh's            system and the batch, by its key
   attachment                                         ─► the member name, or None
```

A link cannot say whose a batch is once a router member forwards it, so the host that
made it signs it (docs/how-to/securing-registrars.md). A seal is `b"rs1" | chain length
(2 bytes, big endian) | the chain (PEM) | the signature` (ECDSA or RSA-PSS with SHA-256,
or Ed25519) over SHA-256 of `rr-events/<system>\0` and the batch. It stops a member
naming another host in its events, not one that runs code on another member.
"""

from __future__ import annotations

import datetime
import hashlib
import logging
import struct
import threading
from pathlib import Path
from typing import Any

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, ed25519, padding, rsa

from rr_actors._transport.zenoh.ops.tls import ZenohTLS, authorities, leaf_of, member_of
from rr_actors.errors import ConfigError

__all__ = ["CHAINS_KEPT", "Seal"]

logger = logging.getLogger("rr_actors")

CHAINS_KEPT = 64
"""Certificate chains a subscriber keeps checked (one per member host, normally); past it,
it checks them again."""

_MAGIC = b"rs1"
_HEAD = struct.Struct("!3sH")  # magic, length of the chain
_PSS = padding.PSS(mgf=padding.MGF1(hashes.SHA256()), salt_length=padding.PSS.DIGEST_LENGTH)


class Seal:
    """Seals the event batches this process sends and opens those it receives, with the
    certificates of `tls` (see the module docstring). Thread-safe.

    Args:
        tls: this host's certificates and the system's members.
        system: the system's name (in what is signed).
    """

    def __init__(self, tls: ZenohTLS, system: str) -> None:
        self._tls = tls
        self._context = f"rr-events/{system}\0".encode()
        self._lock = threading.Lock()
        self._signing: tuple[Any, bytes] | None = None  # the key, the seal's head
        self._trusted: list[Any] | None = None  # the CA's certificates
        self._chains: dict[bytes, tuple[str, Any, datetime.datetime] | None] = {}

    def _digest(self, data: bytes) -> bytes:
        digest = hashlib.sha256(self._context)
        digest.update(data)
        return digest.digest()

    def seal(self, data: bytes) -> bytes:
        """The seal of batch `data` (on the sending thread).

        Raises:
            ConfigError: the host's key or certificate cannot be read any more.
        """
        key, head = self._signing or self._load_signing()
        digest = self._digest(data)
        if isinstance(key, ec.EllipticCurvePrivateKey):
            return head + key.sign(digest, ec.ECDSA(hashes.SHA256()))
        if isinstance(key, rsa.RSAPrivateKey):
            return head + key.sign(digest, _PSS, hashes.SHA256())
        assert isinstance(key, ed25519.Ed25519PrivateKey)  # (`ZenohTLS` allows no other kind)
        return head + key.sign(digest)

    def _load_signing(self) -> tuple[Any, bytes]:
        tls = self._tls
        try:
            chain = Path(tls.cert).read_bytes()
            key = serialization.load_pem_private_key(Path(tls.key).read_bytes(), password=None)
        except (OSError, ValueError, TypeError, UnsupportedAlgorithm) as exc:
            raise ConfigError(
                f"cannot seal events with cert {tls.cert} and key {tls.key}: {exc}"
            ) from None
        if not isinstance(
            key, ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey | ed25519.Ed25519PrivateKey
        ):
            raise ConfigError(f"key {tls.key} cannot sign ({type(key).__name__})")
        self._signing = key, _HEAD.pack(_MAGIC, len(chain)) + chain
        return self._signing

    def open(self, data: bytes, seal: bytes | None) -> str | None:
        """The member whose certificate sealed batch `data` with `seal`; `None` if none did (never
        raises)."""
        if seal is None or len(seal) < _HEAD.size:
            return None
        magic, length = _HEAD.unpack_from(seal)
        end = _HEAD.size + length
        checked = (
            None if magic != _MAGIC or len(seal) <= end else self._chain(seal[_HEAD.size : end])
        )
        if checked is None or datetime.datetime.now(datetime.UTC) > checked[2]:
            return None
        member, public, _ = checked
        return member if _verified(public, seal[end:], self._digest(data)) else None

    def _chain(self, chain: bytes) -> tuple[str, Any, datetime.datetime] | None:
        """What certificate chain `chain` says (its member, its public key, when it ends),
        if the system's CA issued it to a member; checked once, then kept."""
        with self._lock:
            if chain in self._chains:
                return self._chains[chain]
        now = datetime.datetime.now(datetime.UTC)
        leaf = leaf_of(chain, self._authorities(), now)
        member = None if leaf is None else member_of(leaf)
        checked = None
        if leaf is not None and member in self._tls.members:
            assert member is not None
            checked = member, leaf.public_key(), leaf.not_valid_after_utc
        with self._lock:
            if len(self._chains) >= CHAINS_KEPT:
                self._chains.clear()
            self._chains[chain] = checked
        return checked

    def _authorities(self) -> list[Any]:
        if self._trusted is None:
            try:
                self._trusted = authorities(self._tls.ca)
            except ConfigError as exc:
                logger.warning("cannot check the seals of events: %s", exc)
                return []
        return self._trusted


def _verified(public: Any, signature: bytes, digest: bytes) -> bool:
    """Whether `signature` is `public`'s over `digest` (as `Seal.seal` signs)."""
    try:
        if isinstance(public, ec.EllipticCurvePublicKey):
            public.verify(signature, digest, ec.ECDSA(hashes.SHA256()))
        elif isinstance(public, rsa.RSAPublicKey):
            public.verify(signature, digest, _PSS, hashes.SHA256())
        elif isinstance(public, ed25519.Ed25519PublicKey):
            public.verify(signature, digest)
        else:
            return False
    except (InvalidSignature, ValueError, TypeError, UnsupportedAlgorithm):
        return False
    return True
