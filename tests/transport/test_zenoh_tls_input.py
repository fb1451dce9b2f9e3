"""`rr.ZenohTLS` turns every bad argument into a `ConfigError` naming it (review of issue 23)."""

from __future__ import annotations

from pathlib import Path

import pytest

import rr_actors as rr
from tests.support import pki


@pytest.mark.parametrize("argument", ["ca", "cert", "key"])
def test_a_path_with_a_nul_character_is_a_config_error_naming_it(
    tmp_path: Path, argument: str
) -> None:
    ca = pki.make_ca(tmp_path / "lab", "lab")
    cert, key = pki.issue(tmp_path / "robot", "robot", ("127.0.0.1",), ca=ca)
    paths = {"ca": str(ca[0]), "cert": str(cert), "key": str(key)}
    paths[argument] += "\0"

    with pytest.raises(
        rr.ConfigError, match=rf"{argument} '.*\\x00' is not a path \(it holds a NUL"
    ):
        rr.ZenohTLS(members=["robot"], **paths)


@pytest.mark.parametrize("host", ["robot..local", ".robot", "a" * 64 + ".local"])
@pytest.mark.parametrize("protocol", ["tls", "tcp"])
@pytest.mark.parametrize("role", ["listen", "connect"])
def test_an_endpoint_whose_host_name_no_resolver_takes_is_a_config_error_naming_it(
    tmp_path: Path, host: str, protocol: str, role: str
) -> None:
    """Else the link watch logged an ERROR with a traceback every 0.5 s (a UnicodeError
    from the lookup), and a plain TCP network's open raised the UnicodeError."""
    tls = None
    if protocol == "tls":
        ca = pki.make_ca(tmp_path / "lab", "lab")
        cert, key = pki.issue(tmp_path / "robot", "robot", ("127.0.0.1",), ca=ca)
        tls = rr.ZenohTLS(ca=ca[0], cert=cert, key=key, members=["robot"])
    endpoint = f"{protocol}/{host}:7447"

    with pytest.raises(rr.ConfigError, match=rf"{role} endpoint '{endpoint}' is malformed"):
        rr.ZenohNetwork(system="lab", tls=tls, **{role: [endpoint]})


def test_a_chain_through_a_certificate_that_is_not_a_ca_is_a_config_error(tmp_path: Path) -> None:
    """A member's certificate signing another (here a name of another member): Zenoh's TLS
    refuses the chain in every handshake, so `ZenohTLS` refuses it when made."""
    ca = pki.make_ca(tmp_path / "lab", "lab")
    member = pki.issue(tmp_path / "stranger", "stranger", ("127.0.0.1",), ca=ca)
    forged, key = pki.issue(tmp_path / "forged", "robot", ("127.0.0.1",), ca=member)
    chain = tmp_path / "chain.pem"
    chain.write_bytes(forged.read_bytes() + member[0].read_bytes())

    with pytest.raises(
        rr.ConfigError, match=r"\(intermediate 1\) \(CN=stranger\) is not a CA certificate"
    ):
        rr.ZenohTLS(ca=ca[0], cert=chain, key=key, members=["robot"])
