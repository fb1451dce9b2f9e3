"""What `rr.ZenohTLS` accepts is what Zenoh's TLS (rustls) uses, checked against Zenoh itself.

Two raw Zenoh sessions on loopback, mutual TLS with `verify_name_on_connect`, with the
files `rr-actors certs` makes and with each key type: those `ZenohTLS` accepts link and
carry a put; those it refuses Zenoh cannot even listen with. (How `ZenohNetwork` uses the
files is tested with it; this pins the rules of `ZenohTLS` to Zenoh's.)
"""

from __future__ import annotations

import json
import socket
import threading
from pathlib import Path

import pytest
import zenoh

import rr_actors as rr
from rr_actors._tools import certs as certs_tool
from rr_actors.errors import ConfigError
from tests.support.pki import issue, make_ca, make_intermediate


def config(directory: Path, me: str, listen: list[str], connect: list[str]) -> object:
    pair = {
        "private_key": str(directory / f"{me}.key"),
        "certificate": str(directory / f"{me}.pem"),
    }
    tls = {
        "root_ca_certificate": str(directory / "ca.pem"),
        **{f"listen_{k}": v for k, v in pair.items()},
        **{f"connect_{k}": v for k, v in pair.items()},
        "enable_mtls": True,
        "verify_name_on_connect": True,
    }
    return zenoh.Config.from_json5(
        json.dumps(
            {
                "mode": "peer",
                "listen": {"endpoints": listen},
                "connect": {"endpoints": connect},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
                "transport": {"link": {"tls": tls}},
            }
        )
    )


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def a_put_crosses(directory: Path) -> bool:
    """`listener` listens on tls/127.0.0.1, `dialler` dials it: does a put arrive within 10 s?"""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    arrived = threading.Event()
    with zenoh.open(config(directory, "listener", [endpoint], [])) as listener:
        subscriber = listener.declare_subscriber("rr/test/**", lambda _sample: arrived.set())
        with zenoh.open(config(directory, "dialler", [], [endpoint])) as dialler:
            for _ in range(50):  # until the link is up: at most 50 x 0.2 s
                dialler.put("rr/test/x", b"hi")
                if arrived.wait(0.2):
                    break
        subscriber.undeclare()
    return arrived.is_set()


def test_certificates_from_rr_actors_certs_link_two_zenoh_sessions(tmp_path: Path) -> None:
    certs_tool.init_ca(tmp_path, "lab")
    for name in ("listener", "dialler"):
        certs_tool.issue_cert(tmp_path, name, ["127.0.0.1"])
        rr.ZenohTLS(
            ca=tmp_path / "ca.pem",
            cert=tmp_path / f"{name}.pem",
            key=tmp_path / f"{name}.key",
            members=[name],
        )

    assert a_put_crosses(tmp_path)


@pytest.mark.parametrize("key_type", ["p256", "p384", "ed25519", "rsa2048"])
def test_a_key_type_zenoh_tls_accepts_zenoh_uses(tmp_path: Path, key_type: str) -> None:
    ca = make_ca(tmp_path)
    for name in ("listener", "dialler"):
        pem, key = issue(tmp_path, name, ("127.0.0.1",), ca=ca, key_type=key_type)
        rr.ZenohTLS(ca=ca[0], cert=pem, key=key, members=[name])

    assert a_put_crosses(tmp_path)


@pytest.mark.parametrize("key_type", ["p521", "rsa1024"])
def test_a_key_type_zenoh_tls_refuses_zenoh_cannot_listen_with(
    tmp_path: Path, key_type: str
) -> None:
    ca = make_ca(tmp_path)
    pem, key = issue(tmp_path, "listener", ("127.0.0.1",), ca=ca, key_type=key_type)
    with pytest.raises(ConfigError, match="Zenoh's TLS"):
        rr.ZenohTLS(ca=ca[0], cert=pem, key=key, members=["listener"])

    with pytest.raises(zenoh.ZError, match="failed to parse private key"):
        zenoh.open(config(tmp_path, "listener", [f"tls/127.0.0.1:{free_port()}"], []))


def test_a_ca_bundle_and_a_chain_zenoh_tls_accepts_zenoh_uses(tmp_path: Path) -> None:
    # the listener's certificate from one CA, the dialler's from an intermediate of another;
    # both trust both CAs
    first, second = make_ca(tmp_path / "first"), make_ca(tmp_path / "second")
    (tmp_path / "ca.pem").write_bytes(first[0].read_bytes() + second[0].read_bytes())
    issue(tmp_path, "listener", ("127.0.0.1",), ca=first)
    middle = make_intermediate(tmp_path / "second", second)
    pem, key = issue(tmp_path / "second", "dialler", ("127.0.0.1",), ca=middle)
    (tmp_path / "dialler.pem").write_bytes(pem.read_bytes() + middle[0].read_bytes())
    key.rename(tmp_path / "dialler.key")
    for name in ("listener", "dialler"):
        rr.ZenohTLS(
            ca=tmp_path / "ca.pem",
            cert=tmp_path / f"{name}.pem",
            key=tmp_path / f"{name}.key",
            members=[name],
        )

    assert a_put_crosses(tmp_path)
