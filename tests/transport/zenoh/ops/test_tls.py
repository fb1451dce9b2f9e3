"""`rr.ZenohTLS(ca=, cert=, key=, members=)` (`rr_actors._transport.zenoh.ops.tls`):
every file and name checked when it is made; `TestWhatZenohUses`: what it accepts, Zenoh
uses; `TestTheHowTosRecipe`: the how-to's openssl recipe makes what it accepts.
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import re
import shutil
import subprocess
import threading
from pathlib import Path

import pytest
import zenoh

import rr_actors as rr
from rr_actors._transport.zenoh.ops.tls import member_addresses
from rr_actors.errors import ConfigError
from rr_actors_lab._tools import certs as certs_tool
from tests.support import pki
from tests.support.hosts import free_port
from tests.support.pki import DAY, issue, make_ca, make_intermediate
from tests.support.python import python
from tests.test_docs import ROOT, blocks, commands

NOW = datetime.datetime.now(datetime.UTC)


@pytest.fixture
def ca(tmp_path: Path) -> tuple[Path, Path]:
    return make_ca(tmp_path / "ca", "lab")


@pytest.fixture
def robot(tmp_path: Path, ca: tuple[Path, Path]) -> tuple[Path, Path]:
    return issue(tmp_path / "hosts", "robot", ("10.0.0.2", "robot.local"), ca=ca)


def tls(ca: Path, pair: tuple[Path, Path], members: object = ("robot", "station")) -> rr.ZenohTLS:
    return rr.ZenohTLS(ca=ca, cert=pair[0], key=pair[1], members=members)


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


PAGE = ROOT / "docs" / "how-to" / "securing-registrars.md"


def openssl_commands() -> list[list[str]]:
    return [
        command
        for block in blocks(PAGE)
        if block.lang == "bash" and block.skip is None
        for command in commands(block.code)
        if command[0] == "openssl"
    ]


# -- a good one ---------------------------------------------------------------------------------


def test_certificates_from_the_certs_commands_are_accepted(tmp_path: Path) -> None:
    certs_tool.init_ca(tmp_path, "lab")
    certs_tool.issue_cert(tmp_path, "robot", ["10.0.0.2", "robot.local"], days=30)

    got = rr.ZenohTLS(
        ca=str(tmp_path / "ca.pem"),
        cert=tmp_path / "robot.pem",
        key=tmp_path / "robot.key",
        members=["station", "robot", "station"],
    )

    assert str(tmp_path / "ca.pem") == got.ca
    assert (str(tmp_path / "robot.pem"), str(tmp_path / "robot.key")) == (got.cert, got.key)
    assert ("station", "robot") == got.members
    assert "robot" == got.name
    assert ("10.0.0.2", "robot.local") == got.addresses
    assert datetime.timedelta(days=30) - datetime.timedelta(minutes=1) < got.not_after - NOW
    assert datetime.UTC == got.not_after.tzinfo
    assert "name='robot'" in repr(got)
    assert "10.0.0.2" in repr(got)


def test_its_attributes_are_read_only(ca: tuple[Path, Path], robot: tuple[Path, Path]) -> None:
    got = tls(ca[0], robot)

    with pytest.raises(AttributeError, match=r"ZenohTLS\.members is read-only"):
        got.members = ("intruder",)


def test_paths_are_made_absolute(
    tmp_path: Path, ca: tuple[Path, Path], robot: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)

    got = rr.ZenohTLS(
        ca=os.path.relpath(ca[0]),
        cert=os.path.relpath(robot[0]),
        key=os.path.relpath(robot[1]),
        members=["robot"],
    )

    assert (str(ca[0]), str(robot[0]), str(robot[1])) == (got.ca, got.cert, got.key)


@pytest.mark.parametrize("key_type", ["p384", "ed25519", "rsa2048"])
def test_every_key_type_rustls_signs_with_is_accepted(
    tmp_path: Path, ca: tuple[Path, Path], key_type: str
) -> None:
    pair = issue(tmp_path, "robot", ca=ca, key_type=key_type)

    assert "robot" == tls(ca[0], pair).name


def test_a_certificate_without_extended_key_usage_is_accepted(
    tmp_path: Path, ca: tuple[Path, Path]
) -> None:
    pair = issue(tmp_path, "robot", ca=ca, eku=None)

    assert "robot" == tls(ca[0], pair).name


def test_a_chain_leaf_first_then_an_intermediate_is_accepted(
    tmp_path: Path, ca: tuple[Path, Path]
) -> None:
    middle = make_intermediate(tmp_path, ca)
    pem, key = issue(tmp_path, "robot", ca=middle)
    chain = tmp_path / "chain.pem"
    chain.write_bytes(pem.read_bytes() + middle[0].read_bytes())

    assert "robot" == tls(ca[0], (chain, key)).name


def test_a_chain_without_its_intermediate_is_not_signed_by_ca(
    tmp_path: Path, ca: tuple[Path, Path]
) -> None:
    pair = issue(tmp_path, "robot", ca=make_intermediate(tmp_path, ca))

    with pytest.raises(ConfigError, match=rf"^cert {pair[0]} .* is not signed by ca {ca[0]}$"):
        tls(ca[0], pair)


def test_a_ca_file_may_hold_several_cas(tmp_path: Path, ca: tuple[Path, Path]) -> None:
    other = make_ca(tmp_path / "other", "lab")
    bundle = tmp_path / "bundle.pem"
    bundle.write_bytes(other[0].read_bytes() + ca[0].read_bytes())
    pair = issue(tmp_path, "robot", ca=ca)

    assert "robot" == tls(bundle, pair).name


# -- files --------------------------------------------------------------------------------------


@pytest.mark.parametrize("which", ["ca", "cert", "key"])
@pytest.mark.parametrize(
    "fault",
    ["missing", "a directory", "not PEM"],
    ids=["a_missing_file", "a_file_that_cannot_be_read", "a_file_that_is_not_pem"],
)
def test_a_file_missing_unreadable_or_not_pem_is_a_config_error_naming_it(
    tmp_path: Path, ca: tuple[Path, Path], robot: tuple[Path, Path], which: str, fault: str
) -> None:
    paths = {"ca": ca[0], "cert": robot[0], "key": robot[1]}
    bad, error = {  # (a directory: open() fails as for a file root cannot read)
        "missing": (tmp_path / "nowhere.pem", "does not exist$"),
        "a directory": (tmp_path, "cannot be read: Is a directory"),
        "not PEM": (tmp_path / "binary.der", "is not PEM"),
    }[fault]
    if fault == "not PEM":
        bad.write_bytes(b"\x30\x82\x01\x0a not pem")
    paths[which] = bad

    with pytest.raises(ConfigError, match=rf"^{which} {bad} {error}"):
        rr.ZenohTLS(**paths, members=["robot"])


def test_a_path_that_is_not_a_path_is_a_config_error(ca: tuple[Path, Path]) -> None:
    with pytest.raises(ConfigError, match=r"^cert must be a path .*, not 42$"):
        rr.ZenohTLS(ca=ca[0], cert=42, key=ca[1], members=["robot"])


def test_a_cert_file_holding_only_a_key_has_no_certificate(
    ca: tuple[Path, Path], robot: tuple[Path, Path]
) -> None:
    with pytest.raises(ConfigError, match=rf"^cert {robot[1]} holds no .*certificate"):
        tls(ca[0], (robot[1], robot[1]))


def test_a_key_file_holding_a_certificate_has_no_private_key(
    ca: tuple[Path, Path], robot: tuple[Path, Path]
) -> None:
    with pytest.raises(ConfigError, match=rf"^key {robot[0]} holds no readable private key"):
        tls(ca[0], (robot[0], robot[0]))


def test_an_encrypted_key_is_a_config_error(
    tmp_path: Path, ca: tuple[Path, Path], robot: tuple[Path, Path]
) -> None:
    from cryptography.hazmat.primitives import serialization  # noqa: PLC0415

    key = serialization.load_pem_private_key(robot[1].read_bytes(), password=None)
    encrypted = tmp_path / "encrypted.key"
    encrypted.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.BestAvailableEncryption(b"secret"),
        )
    )
    encrypted.chmod(0o600)

    with pytest.raises(ConfigError, match=rf"^key {encrypted} is encrypted"):
        tls(ca[0], (robot[0], encrypted))


# -- the certificate ----------------------------------------------------------------------------


def test_a_key_that_is_not_the_certificates_is_a_config_error(
    tmp_path: Path, ca: tuple[Path, Path], robot: tuple[Path, Path]
) -> None:
    _, other_key = issue(tmp_path, "robot", ca=ca, stem="other")

    with pytest.raises(
        ConfigError, match=rf"^key {other_key} is not the private key of cert {robot[0]}$"
    ):
        tls(ca[0], (robot[0], other_key))


@pytest.mark.parametrize("who", ["self-signed", "another CA", "another system's CA"])
def test_a_certificate_not_signed_by_ca_is_a_config_error(
    tmp_path: Path, ca: tuple[Path, Path], who: str
) -> None:
    other = {
        "self-signed": None,
        "another CA": make_ca(tmp_path / "other", "lab"),
        "another system's CA": make_ca(tmp_path / "other", "factory"),
    }[who]
    pair = issue(tmp_path, "robot", ca=other)

    with pytest.raises(ConfigError, match=rf"^cert {pair[0]} .* is not signed by ca {ca[0]}$"):
        tls(ca[0], pair)


def test_an_expired_certificate_is_a_config_error_with_its_dates(
    tmp_path: Path, ca: tuple[Path, Path]
) -> None:
    end = datetime.datetime(2025, 3, 1, 12, 0, tzinfo=datetime.UTC)
    pair = issue(tmp_path, "robot", ca=ca, not_before=end - 30 * DAY, not_after=end)

    with pytest.raises(
        ConfigError,
        match=rf"^cert {pair[0]} expired on 2025-03-01 12:00:00 UTC \(valid from 2025-01-30 ",
    ):
        tls(ca[0], pair)


def test_a_certificate_not_yet_valid_is_a_config_error_with_its_dates(
    tmp_path: Path, ca: tuple[Path, Path]
) -> None:
    start = (NOW + 2 * DAY).replace(microsecond=0)
    pair = issue(tmp_path, "robot", ca=ca, not_before=start, not_after=start + DAY)

    with pytest.raises(
        ConfigError,
        match=rf"^cert {pair[0]} is not yet valid: valid from {start:%Y-%m-%d %H:%M:%S} UTC",
    ):
        tls(ca[0], pair)


def test_an_expired_ca_is_a_config_error(tmp_path: Path, robot: tuple[Path, Path]) -> None:
    from cryptography import x509  # noqa: PLC0415
    from cryptography.hazmat.primitives import hashes, serialization  # noqa: PLC0415

    # the same CA key and name, certified for a time that is over
    ca_pem = tmp_path / "ca" / "ca.pem"
    current = x509.load_pem_x509_certificate(ca_pem.read_bytes())
    key = serialization.load_pem_private_key((tmp_path / "ca" / "ca.key").read_bytes(), None)
    builder = x509.CertificateBuilder(
        issuer_name=current.issuer,
        subject_name=current.subject,
        public_key=current.public_key(),
        serial_number=x509.random_serial_number(),
        not_valid_before=NOW - 10 * DAY,
        not_valid_after=NOW - DAY,
        extensions=list(current.extensions),
    )
    expired = tmp_path / "expired-ca.pem"
    expired.write_bytes(
        builder.sign(key, hashes.SHA256()).public_bytes(serialization.Encoding.PEM)  # type: ignore[arg-type]
    )

    with pytest.raises(ConfigError, match=rf"^ca {expired} \(CN=rr_actors lab CA\) expired on "):
        tls(expired, robot)


def test_a_ca_file_holding_a_host_certificate_is_a_config_error(
    ca: tuple[Path, Path], robot: tuple[Path, Path]
) -> None:
    with pytest.raises(ConfigError, match=rf"^ca {robot[0]} \(CN=robot\) is not a CA certificate"):
        tls(robot[0], robot)


def test_a_certificate_without_a_common_name_is_a_config_error(
    tmp_path: Path, ca: tuple[Path, Path]
) -> None:
    pair = issue(tmp_path, None, ca=ca, stem="anonymous")

    with pytest.raises(ConfigError, match=rf"^cert {pair[0]} has no subject common name"):
        tls(ca[0], pair)


@pytest.mark.parametrize(
    ("eku", "missing"),
    [(("server",), "clientAuth"), (("client",), "serverAuth")],
)
def test_a_certificate_lacking_a_tls_use_is_a_config_error(
    tmp_path: Path, ca: tuple[Path, Path], eku: tuple[str, ...], missing: str
) -> None:
    pair = issue(tmp_path, "robot", ca=ca, eku=eku)

    with pytest.raises(
        ConfigError, match=rf"^cert {pair[0]} lacks the extended key usage .*{missing}"
    ):
        tls(ca[0], pair)


@pytest.mark.parametrize(("key_type", "kind"), [("p521", "EC secp521r1"), ("rsa1024", "RSA 1024")])
def test_a_key_type_rustls_cannot_use_is_a_config_error(
    tmp_path: Path, ca: tuple[Path, Path], key_type: str, kind: str
) -> None:
    pair = issue(tmp_path, "robot", ca=ca, key_type=key_type)

    with pytest.raises(ConfigError, match=rf"^key {pair[1]} is {kind}.*rustls"):
        tls(ca[0], pair)


# -- members ------------------------------------------------------------------------------------


def test_own_name_not_in_members_is_a_config_error(
    ca: tuple[Path, Path], robot: tuple[Path, Path]
) -> None:
    with pytest.raises(ConfigError, match=r"is 'robot', which is not in members \['station'\]"):
        tls(ca[0], robot, ["station"])


@pytest.mark.parametrize("members", [[], ()])
def test_empty_members_is_a_config_error(
    ca: tuple[Path, Path], robot: tuple[Path, Path], members: object
) -> None:
    with pytest.raises(ConfigError, match=r"^members is empty"):
        tls(ca[0], robot, members)


@pytest.mark.parametrize("bad", ["", ".hidden", "a/b", "robot station", 7, "ro*", ["robot"]])
def test_a_member_name_that_is_not_a_name_is_a_config_error(
    ca: tuple[Path, Path], robot: tuple[Path, Path], bad: object
) -> None:
    with pytest.raises(
        ConfigError, match=rf"^members: {re.escape(repr(bad))} is not a member name"
    ):
        tls(ca[0], robot, ["robot", bad])


def test_a_member_name_of_65_characters_is_a_config_error_naming_the_bound(
    ca: tuple[Path, Path], robot: tuple[Path, Path]
) -> None:
    assert ("robot", "m" * 64) == tls(ca[0], robot, ["robot", "m" * 64]).members

    with pytest.raises(ConfigError) as caught:
        tls(ca[0], robot, ["robot", "m" * 65])

    assert str(caught.value).startswith(
        f"members: {'m' * 65!r} is 65 characters long: a member name has at most 64 (NAME_MAX"
    )


def test_members_given_as_one_string_is_a_config_error(
    ca: tuple[Path, Path], robot: tuple[Path, Path]
) -> None:
    with pytest.raises(ConfigError, match=r"^members must be a list of names"):
        tls(ca[0], robot, "robot")


# -- the key's mode -----------------------------------------------------------------------------


def test_a_key_readable_by_group_or_others_logs_a_warning_naming_it(
    ca: tuple[Path, Path], robot: tuple[Path, Path], caplog: pytest.LogCaptureFixture
) -> None:
    robot[1].chmod(0o640)

    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        tls(ca[0], robot)

    assert [
        (
            "rr_actors",
            logging.WARNING,
            f"private key {robot[1]} is readable by group or "
            f"others (mode 0640): chmod 600 {robot[1]}",
        )
    ] == caplog.record_tuples


def test_a_key_of_mode_0600_logs_nothing(
    ca: tuple[Path, Path], robot: tuple[Path, Path], caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.DEBUG, logger="rr_actors"):
        tls(ca[0], robot)

    assert [] == caplog.record_tuples


def test_importing_rr_actors_imports_neither_cryptography_nor_zenoh() -> None:
    code = (
        "import sys, rr_actors\n"
        "assert 'cryptography' not in sys.modules and 'zenoh' not in sys.modules\n"
        "assert 'ZenohTLS' in rr_actors.__all__\n"
        "rr_actors.ZenohTLS\n"
        "assert 'cryptography' in sys.modules and 'zenoh' not in sys.modules\n"
    )
    result = python("-c", code, timeout=60)

    assert (0, "") == (result.returncode, result.stderr)


def test_without_cryptography_rr_zenoh_tls_says_which_extra_to_install() -> None:
    code = (
        "import sys\n"
        "sys.modules['cryptography'] = None  # as if not installed: importing it fails\n"
        "import rr_actors\n"
        "try:\n"
        "    rr_actors.ZenohTLS\n"
        "except ImportError as exc:\n"
        "    print(exc)\n"
    )
    result = python("-c", code, timeout=60)

    assert (0, "") == (result.returncode, result.stderr)
    assert result.stdout.startswith("rr.ZenohTLS needs an extra: pip install")


# -- bad arguments ---------------------------------------------------------------------------------
# `rr.ZenohTLS` turns every bad argument into a `ConfigError` naming it (review of issue 23).


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


# -- a member's certificate, as another host gets it (the handshake gate's, issue 40) -----------


def test_a_members_certificate_gives_the_ip_addresses_it_names(
    tmp_path: Path, ca: tuple[Path, Path], robot: tuple[Path, Path]
) -> None:
    middle = make_intermediate(tmp_path, ca)
    pem, _ = issue(tmp_path, "station", ("10.0.0.1", "station.local", "fd00::1"), ca=middle)

    addresses = member_addresses(
        pem.read_bytes() + middle[0].read_bytes(), tls(ca[0], robot), "station"
    )

    assert ("10.0.0.1", "fd00::1") == addresses


@pytest.mark.parametrize(
    ("case", "why"),
    [
        ("another member's", r"the certificate of member 'station' has the common name 'robot'"),
        (
            "another CA's",
            r"the certificate of member 'station' \(CN=station, .* is not signed by ca ",
        ),
        ("expired", r"the certificate of member 'station' expired on "),
        ("not a member's", r"'stranger' is not in members \['robot', 'station'\]"),
        ("not PEM", r"the certificate of member 'station' is not PEM certificates"),
    ],
)
def test_a_certificate_that_is_not_the_members_own_is_a_config_error(
    tmp_path: Path, ca: tuple[Path, Path], robot: tuple[Path, Path], case: str, why: str
) -> None:
    end = NOW - DAY
    name = "stranger" if case == "not a member's" else "station"
    pem = {
        "another member's": robot[0].read_bytes(),
        "another CA's": issue(tmp_path, "station", ca=make_ca(tmp_path / "o", "lab"))[
            0
        ].read_bytes(),
        "expired": issue(tmp_path, "station", ca=ca, not_before=end - DAY, not_after=end)[
            0
        ].read_bytes(),
        "not a member's": issue(tmp_path, "stranger", ca=ca)[0].read_bytes(),
        "not PEM": b"10.0.0.1",
    }[case]

    with pytest.raises(ConfigError, match=f"^{why}"):
        member_addresses(pem, tls(ca[0], robot), name)


class TestWhatZenohUses:
    """What `rr.ZenohTLS` accepts is what Zenoh's TLS (rustls) uses, checked against Zenoh itself.

    Two raw Zenoh sessions on loopback, mutual TLS with `verify_name_on_connect`, with the
    files `rr-actors certs` makes and with each key type: those `ZenohTLS` accepts link and
    carry a put; those it refuses Zenoh cannot even listen with. (How `ZenohNetwork` uses the
    files is tested with it; this pins the rules of `ZenohTLS` to Zenoh's.)
    """

    def test_certificates_from_rr_actors_certs_link_two_zenoh_sessions(
        self, tmp_path: Path
    ) -> None:
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
    def test_a_key_type_zenoh_tls_accepts_zenoh_uses(self, tmp_path: Path, key_type: str) -> None:
        ca = make_ca(tmp_path)
        for name in ("listener", "dialler"):
            pem, key = issue(tmp_path, name, ("127.0.0.1",), ca=ca, key_type=key_type)
            rr.ZenohTLS(ca=ca[0], cert=pem, key=key, members=[name])

        assert a_put_crosses(tmp_path)

    @pytest.mark.parametrize("key_type", ["p521", "rsa1024"])
    def test_a_key_type_zenoh_tls_refuses_zenoh_cannot_listen_with(
        self, tmp_path: Path, key_type: str
    ) -> None:
        ca = make_ca(tmp_path)
        pem, key = issue(tmp_path, "listener", ("127.0.0.1",), ca=ca, key_type=key_type)
        with pytest.raises(ConfigError, match="Zenoh's TLS"):
            rr.ZenohTLS(ca=ca[0], cert=pem, key=key, members=["listener"])

        with pytest.raises(zenoh.ZError, match="failed to parse private key"):
            zenoh.open(config(tmp_path, "listener", [f"tls/127.0.0.1:{free_port()}"], []))

    def test_a_ca_bundle_and_a_chain_zenoh_tls_accepts_zenoh_uses(self, tmp_path: Path) -> None:
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


class TestTheHowTosRecipe:
    """The how-to's openssl recipe makes certificates `rr.ZenohTLS` accepts (the page cannot lie).

    `tests/test_docs.py` runs the page's commands too; here the openssl ones alone, in an empty
    directory, and their result goes through `ZenohTLS` without a WARNING.
    """

    def test_the_pages_openssl_recipe_makes_certificates_zenoh_tls_accepts(
        self, tmp_path: Path, caplog: pytest.LogCaptureFixture
    ) -> None:
        openssl = shutil.which("openssl")
        assert openssl is not None, "no openssl (apt-get install -y openssl; .ci/run does)"
        recipe = openssl_commands()
        assert 5 <= len(recipe), recipe  # two keys, two certificates, a verify
        for command in recipe:
            result = subprocess.run(
                [openssl, *command[1:]],
                cwd=tmp_path,
                capture_output=True,
                text=True,
                timeout=60,
                check=False,
            )
            assert 0 == result.returncode, (command, result.stderr)

        with caplog.at_level(logging.WARNING, logger="rr_actors"):
            tls = rr.ZenohTLS(
                ca=tmp_path / "ca.pem",
                cert=tmp_path / "station.pem",
                key=tmp_path / "station.key",
                members=["station"],
            )

        assert ("station", ("10.0.0.1", "station.local")) == (tls.name, tls.addresses)
        assert [] == caplog.record_tuples  # the keys are 0600 as written
