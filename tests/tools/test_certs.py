"""A system's certificates (`rr_actors_lab._tools.certs`): `rr-actors certs init` and
`rr-actors certs issue`, a system's CA and its hosts' certificates.

Run through `rr_actors.__main__.main` and once through the installed console script; the
certificates are proven usable by a real mutual-TLS handshake (Python's `ssl`, a real TCP
socket) and by `openssl verify`.
"""

from __future__ import annotations

import io
import ipaddress
import os
import shutil
import socket
import ssl
import stat
import subprocess
import sysconfig
import threading
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

import rr_actors as rr
from rr_actors.errors import ConfigError
from rr_actors_lab.__main__ import main
from rr_actors_lab._tools.certs import issue_cert
from tests.support.hosts import free_port
from tests.support.pki import make_ca
from tests.support.python import python
from tests.support.tls_lab import router


def certs(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    code = main(["certs", *argv], out)
    return code, out.getvalue()


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def load(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


@pytest.fixture
def ca_dir(tmp_path: Path) -> Path:
    directory = tmp_path / "certs"
    assert 0 == certs("init", str(directory), "--system", "lab")[0]
    return directory


def test_init_writes_the_ca_with_its_key_0600_in_a_0700_directory(tmp_path: Path) -> None:
    directory = tmp_path / "new" / "certs"

    code, out = certs("init", str(directory), "--system", "lab")

    assert 0 == code
    assert (0o700, 0o600) == (mode(directory), mode(directory / "ca.key"))
    assert f"wrote {directory}/ca.pem and {directory}/ca.key (0600)" in out
    assert "ca.key stays here" in " ".join(out.split())  # (wrapped at words)
    assert f"    rr-actors certs issue {directory} NAME --address ADDR\n" in out  # (whole)
    ca = load(directory / "ca.pem")
    assert "CN=lab,O=rr_actors CA" == ca.subject.rfc4514_string()
    constraints = ca.extensions.get_extension_for_class(x509.BasicConstraints)
    usage = ca.extensions.get_extension_for_class(x509.KeyUsage)
    assert (True, True) == (constraints.critical, constraints.value.ca)
    assert (True, True, True) == (usage.critical, usage.value.key_cert_sign, usage.value.crl_sign)
    assert ca.extensions.get_extension_for_class(x509.SubjectKeyIdentifier)
    assert 3649 < (ca.not_valid_after_utc - ca.not_valid_before_utc).days


def test_issue_writes_a_certificate_naming_the_member_and_every_address(ca_dir: Path) -> None:
    code, out = certs(
        "issue", str(ca_dir), "robot", "--address", "10.0.0.2", "--address", "robot.local"
    )

    assert 0 == code
    assert 0o600 == mode(ca_dir / "robot.key")
    assert f"wrote {ca_dir}/robot.pem and {ca_dir}/robot.key (0600)" in out
    assert "ca.key stays here" in " ".join(out.split())  # (wrapped at words)
    cert = load(ca_dir / "robot.pem")
    assert "robot" == cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value
    sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [ipaddress.ip_address("10.0.0.2")] == sans.get_values_for_type(x509.IPAddress)
    assert ["robot.local"] == sans.get_values_for_type(x509.DNSName)
    uses = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} == set(uses)
    usage = cert.extensions.get_extension_for_class(x509.KeyUsage)
    assert (True, True) == (usage.critical, usage.value.digital_signature)
    assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert x509.Version.v3 == cert.version
    assert 365 == (cert.not_valid_after_utc - cert.not_valid_before_utc).days  # + 5 minutes
    cert.verify_directly_issued_by(load(ca_dir / "ca.pem"))


def test_issue_without_an_address_names_the_member_as_a_dns_name(ca_dir: Path) -> None:
    assert 0 == certs("issue", str(ca_dir), "robot", "--days", "30")[0]

    cert = load(ca_dir / "robot.pem")
    sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert ["robot"] == sans.get_values_for_type(x509.DNSName)
    assert 30 == (cert.not_valid_after_utc - cert.not_valid_before_utc).days


def test_an_existing_name_is_refused_untouched_unless_forced(
    ca_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert 0 == certs("issue", str(ca_dir), "robot")[0]
    before = (ca_dir / "robot.pem").read_bytes(), (ca_dir / "robot.key").read_bytes()

    refused, _ = certs("issue", str(ca_dir), "robot", "--address", "10.0.0.9")

    assert 1 == refused
    assert (
        f"rr-actors certs: {ca_dir}/robot.pem and {ca_dir}/robot.key already exist: "
        "left untouched (--force replaces)\n"
    ) == capsys.readouterr().err
    assert before == ((ca_dir / "robot.pem").read_bytes(), (ca_dir / "robot.key").read_bytes())

    assert 0 == certs("issue", str(ca_dir), "robot", "--address", "10.0.0.9", "--force")[0]
    assert before[1] != (ca_dir / "robot.key").read_bytes()
    assert 0o600 == mode(ca_dir / "robot.key")
    assert [] == [p.name for p in ca_dir.iterdir() if p.name.startswith(".")]  # no temp left


def test_an_existing_ca_is_refused_untouched_unless_forced(
    ca_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = (ca_dir / "ca.key").read_bytes()

    assert 1 == certs("init", str(ca_dir), "--system", "lab")[0]
    assert f"{ca_dir}/ca.pem and {ca_dir}/ca.key already exist" in capsys.readouterr().err
    assert before == (ca_dir / "ca.key").read_bytes()

    assert 0 == certs("init", str(ca_dir), "--system", "lab", "--force")[0]
    assert before != (ca_dir / "ca.key").read_bytes()


@pytest.mark.parametrize("directory", ["empty", "missing"])
def test_issue_without_a_ca_says_how_to_make_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], directory: str
) -> None:
    where = tmp_path / directory
    if directory == "empty":
        where.mkdir()

    assert 1 == certs("issue", str(where), "robot")[0]

    err = capsys.readouterr().err
    assert f"no CA: {where}/ca.pem and {where}/ca.key missing" in err
    assert f"rr-actors certs init {where} --system NAME" in err
    assert (directory == "empty") == where.exists()


@pytest.mark.parametrize(
    ("name", "says"),
    [
        ("../robot", "name '../robot' is not a member name"),
        ("ca", "name 'ca' is the CA's own files"),
    ],
)
def test_a_name_that_is_not_a_member_name_is_refused(
    ca_dir: Path, capsys: pytest.CaptureFixture[str], name: str, says: str
) -> None:
    assert 1 == certs("issue", str(ca_dir), name)[0]

    assert says in capsys.readouterr().err
    assert ["ca.key", "ca.pem"] == sorted(p.name for p in ca_dir.iterdir())


# -- name lengths: one bound, NAME_MAX (64), a certificate's common name ---------------------


def test_names_of_64_characters_make_certificates_that_link_over_zenoh(tmp_path: Path) -> None:
    # the longest system, and the longest member names: one listens, one only connects
    # (its certificate names itself as a DNS name); the access control admits both
    system, listener, dialler = "s" * 64, "l" * 64, "d" * 64
    ca = tmp_path / "certs"
    assert 0 == certs("init", str(ca), "--system", system)[0]
    assert 0 == certs("issue", str(ca), listener, "--address", "127.0.0.1")[0]
    assert 0 == certs("issue", str(ca), dialler)[0]
    tls = {
        name: rr.ZenohTLS(
            ca=ca / "ca.pem",
            cert=ca / f"{name}.pem",
            key=ca / f"{name}.key",
            members=[listener, dialler],
        )
        for name in (listener, dialler)
    }
    endpoint = f"tls/127.0.0.1:{free_port()}"
    arrived = threading.Event()

    with router(tls[listener], [endpoint], [], system=system) as listening:
        listening.declare_subscriber(f"rr/{system}/**", lambda _sample: arrived.set())
        with router(tls[dialler], [], [endpoint], system=system) as dialling:
            for _ in range(50):  # until the link is up: at most 50 x 0.2 s
                dialling.put(f"rr/{system}/x", b"hi")
                if arrived.wait(0.2):
                    break

    assert arrived.is_set()
    assert f"CN={system},O=rr_actors CA" == load(ca / "ca.pem").subject.rfc4514_string()


@pytest.mark.parametrize(
    "argv",
    [
        ("init", "{dir}/new", "--system", "s" * 65),
        ("issue", "{dir}", "m" * 65),
    ],
    ids=["init --system", "issue NAME"],
)
def test_a_name_of_65_characters_is_one_line_naming_the_bound(
    ca_dir: Path, capsys: pytest.CaptureFixture[str], argv: tuple[str, ...]
) -> None:
    before = sorted(p.name for p in ca_dir.iterdir())

    code, _ = certs(*(arg.format(dir=ca_dir) for arg in argv))

    field = "system" if argv[0] == "init" else "name"
    assert 1 == code
    assert (
        f"rr-actors certs: {field} {argv[-1]!r} is 65 characters long: a "
        f"{'system' if field == 'system' else 'member'} name has at most 64 (NAME_MAX, the "
        f"longest common name a certificate holds)\n"
    ) == capsys.readouterr().err
    assert before == sorted(p.name for p in ca_dir.iterdir())
    assert not (ca_dir / "new").exists()


# -- the CA's directory and key are private ---------------------------------------------------


NOBODY = 65534


@pytest.mark.parametrize("dir_mode", [0o777, 0o1777, 0o770, 0o720])
def test_init_refuses_an_existing_directory_others_may_write_to(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], dir_mode: int
) -> None:
    directory = tmp_path / "shared"
    directory.mkdir()
    directory.chmod(dir_mode)

    assert 1 == certs("init", str(directory), "--system", "lab")[0]

    assert (
        f"rr-actors certs: the CA's directory {directory} is writable by group or others "
        f"(mode {dir_mode:04o}): they can put, rename or replace files in it (chmod 700 "
        f"{directory}, or use a directory of your own); nothing written (--force writes "
        f"anyway)\n"
    ) == capsys.readouterr().err
    assert ([], dir_mode) == (list(directory.iterdir()), mode(directory))


def test_init_refuses_a_directory_of_another_user(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if os.geteuid() != 0:
        pytest.skip("chown to another user needs root")
    directory = tmp_path / "theirs"
    directory.mkdir(mode=0o700)
    os.chown(directory, NOBODY, NOBODY)

    assert 1 == certs("init", str(directory), "--system", "lab")[0]

    err = capsys.readouterr().err
    assert f"the CA's directory {directory} is owned by nobody (uid {NOBODY}), not by " in err
    assert [] == list(directory.iterdir())


def test_init_with_force_writes_into_a_directory_others_may_write_to(tmp_path: Path) -> None:
    directory = tmp_path / "shared"
    directory.mkdir()
    directory.chmod(0o777)

    assert 0 == certs("init", str(directory), "--system", "lab", "--force")[0]

    assert 0o600 == mode(directory / "ca.key")


@pytest.mark.parametrize(
    ("key_mode", "says"),
    [(0o640, "readable"), (0o604, "readable"), (0o620, "writable"), (0o606, "readable")],
)
def test_issue_refuses_a_ca_key_open_to_group_or_others(
    ca_dir: Path, capsys: pytest.CaptureFixture[str], key_mode: int, says: str
) -> None:
    key = ca_dir / "ca.key"
    key.chmod(key_mode)

    assert 1 == certs("issue", str(ca_dir), "robot")[0]

    assert (
        f"rr-actors certs: the CA's key {key} is {says} by group or others (mode "
        f"{key_mode:04o}): chmod 600 {key}; nothing written (--force writes anyway)\n"
    ) == capsys.readouterr().err
    assert ["ca.key", "ca.pem"] == sorted(p.name for p in ca_dir.iterdir())


def test_issue_refuses_a_ca_key_of_another_user(
    ca_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if os.geteuid() != 0:
        pytest.skip("chown to another user needs root")
    key = ca_dir / "ca.key"
    os.chown(key, NOBODY, NOBODY)  # still 0600: root reads it, but it is not root's

    assert 1 == certs("issue", str(ca_dir), "robot")[0]

    err = capsys.readouterr().err
    assert f"the CA's key {key} is owned by nobody (uid {NOBODY}), not by this user" in err
    assert ["ca.key", "ca.pem"] == sorted(p.name for p in ca_dir.iterdir())


def test_issue_refuses_a_ca_directory_others_may_write_to(
    ca_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ca_dir.chmod(0o777)

    assert 1 == certs("issue", str(ca_dir), "robot")[0]

    err = capsys.readouterr().err
    assert f"the CA's directory {ca_dir} is writable by group or others (mode 0777)" in err
    assert ["ca.key", "ca.pem"] == sorted(p.name for p in ca_dir.iterdir())


def test_issue_with_force_signs_with_a_key_that_is_not_private(ca_dir: Path) -> None:
    (ca_dir / "ca.key").chmod(0o644)
    ca_dir.chmod(0o777)

    assert 0 == certs("issue", str(ca_dir), "robot", "--force")[0]

    assert 0o600 == mode(ca_dir / "robot.key")


@pytest.mark.parametrize("days", ["0", "-3", "soon"])
def test_days_that_are_not_a_positive_number_are_a_usage_error(
    ca_dir: Path, capsys: pytest.CaptureFixture[str], days: str
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        certs("issue", str(ca_dir), "robot", "--days", days)

    assert 2 == exit_info.value.code
    assert f"a positive whole number of days, not {days!r}" in capsys.readouterr().err


def test_the_console_script_makes_both(tmp_path: Path) -> None:
    script = Path(sysconfig.get_path("scripts")) / "rr-actors"

    def run(*argv: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [str(script), "certs", *argv],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
            cwd=tmp_path,
        )

    init = run("init", "certs", "--system", "lab")
    issue = run("issue", "certs", "robot", "--address", "127.0.0.1")
    again = run("issue", "certs", "robot")

    assert (0, "") == (init.returncode, init.stderr)
    assert (0, "") == (issue.returncode, issue.stderr)
    assert "wrote certs/robot.pem and certs/robot.key (0600)" in issue.stdout
    assert 1 == again.returncode
    assert "certs/robot.pem and certs/robot.key already exist" in again.stderr


# -- the certificates work ----------------------------------------------------------------------


def test_openssl_verifies_an_issued_certificate_against_the_ca(ca_dir: Path) -> None:
    openssl = shutil.which("openssl")
    assert openssl is not None, "no openssl (apt-get install -y openssl; .ci/run does)"
    assert 0 == certs("issue", str(ca_dir), "robot", "--address", "10.0.0.2")[0]

    result = subprocess.run(
        [openssl, "verify", "-CAfile", "ca.pem", "robot.pem"],
        cwd=ca_dir,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )

    assert (0, "robot.pem: OK\n") == (result.returncode, result.stdout)


def context(side: ssl._SSLMethod, directory: Path, name: str, ca: Path) -> ssl.SSLContext:
    ctx = ssl.SSLContext(side)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_3  # as Zenoh's
    ctx.load_cert_chain(directory / f"{name}.pem", directory / f"{name}.key")
    ctx.load_verify_locations(ca)
    ctx.verify_mode = ssl.CERT_REQUIRED
    return ctx


def handshake(directory: Path, server: str, client: str, *, client_ca: Path) -> str:
    """A TLS 1.3 handshake over TCP on 127.0.0.1: the client's common name the server saw.

    Raises the client's `ssl.SSLError` if either side refuses.
    """
    server_ctx = context(ssl.PROTOCOL_TLS_SERVER, directory, server, directory / "ca.pem")
    client_ctx = context(ssl.PROTOCOL_TLS_CLIENT, client_ca.parent, client, client_ca)
    assert client_ctx.check_hostname  # the server must name the address dialled
    seen: list[str] = []
    with socket.create_server(("127.0.0.1", 0)) as listener:
        port = listener.getsockname()[1]

        def serve() -> None:
            conn, _ = listener.accept()
            with conn:
                try:
                    with server_ctx.wrap_socket(conn, server_side=True) as tls:
                        subject = dict(x[0] for x in tls.getpeercert()["subject"])
                        seen.append(subject["commonName"])
                        tls.sendall(b"ok")
                except (ssl.SSLError, OSError):
                    pass

        thread = threading.Thread(target=serve)
        thread.start()
        try:
            with (
                socket.create_connection(("127.0.0.1", port), timeout=10) as raw,
                client_ctx.wrap_socket(raw, server_hostname="127.0.0.1") as tls,
            ):
                assert b"ok" == tls.recv(2)  # TLS 1.3: the server's verdict arrives here
        finally:
            thread.join(10)
            assert not thread.is_alive()
    return seen[0]


def test_two_issued_certificates_complete_a_mutual_tls_handshake(ca_dir: Path) -> None:
    assert 0 == certs("issue", str(ca_dir), "robot", "--address", "127.0.0.1")[0]
    assert 0 == certs("issue", str(ca_dir), "station", "--address", "10.0.0.1")[0]

    assert "station" == handshake(ca_dir, "robot", "station", client_ca=ca_dir / "ca.pem")


def test_a_listener_not_naming_the_address_dialled_is_refused_by_the_client(
    ca_dir: Path,
) -> None:
    assert 0 == certs("issue", str(ca_dir), "robot", "--address", "10.0.0.2")[0]
    assert 0 == certs("issue", str(ca_dir), "station", "--address", "10.0.0.1")[0]

    with pytest.raises(ssl.SSLCertVerificationError, match="IP address mismatch"):
        handshake(ca_dir, "robot", "station", client_ca=ca_dir / "ca.pem")


def test_a_client_of_another_ca_is_refused_by_the_listener(ca_dir: Path, tmp_path: Path) -> None:
    assert 0 == certs("issue", str(ca_dir), "robot", "--address", "127.0.0.1")[0]
    other = tmp_path / "other"
    make_ca(other, "lab")
    assert 0 == certs("issue", str(other), "intruder")[0]
    # the intruder trusts the system's CA (it got ca.pem), but its own is another CA's
    shutil.copy(ca_dir / "ca.pem", other / "trusted.pem")

    with pytest.raises((ssl.SSLError, ConnectionError), match=r"unknown ca|reset|EOF"):
        handshake(ca_dir, "robot", "intruder", client_ca=other / "trusted.pem")


def test_certs_help_lists_init_and_issue() -> None:
    result = python("-m", "rr_actors_lab", "certs", "--help", timeout=30)

    assert 0 == result.returncode
    assert "init" in result.stdout
    assert "issue" in result.stdout


def test_without_cryptography_certs_says_which_extra_to_install(tmp_path: Path) -> None:
    code = (
        "import sys\n"
        "sys.modules['cryptography'] = None  # as if not installed: importing it fails\n"
        "from rr_actors_lab.__main__ import main\n"
        "sys.exit(main(['certs', 'init', 'certs', '--system', 'lab']))\n"
    )
    result = python("-c", code, timeout=60, cwd=tmp_path)

    assert 2 == result.returncode
    assert result.stderr.startswith("rr-actors certs needs an extra: pip")
    assert '[zenoh]"' in result.stderr
    assert [] == list(tmp_path.iterdir())


# -- from test_cli_certs_input.py -----------------------------------------------------------------
# `rr-actors certs issue` refuses input that would make a useless certificate or crash.
#
# A careless `--address` (with a port, a scheme, brackets, blanks) would be written as a
# DNS name that no peer ever dials, and the mistake would only show as a refused
# handshake on another machine; a huge `--days` is a clear error, not a traceback.


@pytest.mark.parametrize(
    "address",
    ["10.0.0.2:7447", "tls/10.0.0.2:7447", "[::1]", "robot local", "", "-robot", "a..b"],
)
def test_issue_refuses_an_address_that_is_neither_an_ip_nor_a_dns_name(
    ca_dir: Path, address: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _ = certs("issue", str(ca_dir), "robot", f"--address={address}")

    assert 1 == code
    assert f"--address {address!r} is not an IP address or DNS name" in capsys.readouterr().err
    assert not (ca_dir / "robot.pem").exists()
    assert not (ca_dir / "robot.key").exists()


@pytest.mark.parametrize("address", ["10.0.0.2", "::1", "robot.local", "robot_1", "Robot-2.lan."])
def test_issue_takes_ip_addresses_and_dns_names(ca_dir: Path, address: str) -> None:
    assert 0 == certs("issue", str(ca_dir), "robot", f"--address={address}")[0]

    cert = x509.load_pem_x509_certificate((ca_dir / "robot.pem").read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [address] == [str(name.value) for name in names]


def test_issue_cert_refuses_one_string_for_its_addresses(ca_dir: Path) -> None:
    with pytest.raises(ConfigError, match=r"addresses must be a list such as \['10\.0\.0\.2'\]"):
        issue_cert(ca_dir, "robot", "10.0.0.2")


@pytest.mark.parametrize("days", ["3000000", "10000000000"])
def test_issue_refuses_days_past_the_year_9999_with_an_error_not_a_traceback(
    ca_dir: Path, days: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _ = certs("issue", str(ca_dir), "robot", "--days", days)

    assert 1 == code
    assert f"days {days} ends after the year 9999" in capsys.readouterr().err
    assert not (ca_dir / "robot.pem").exists()


# -- from test_cli_certs_no_clobber.py ------------------------------------------------------------
# `rr-actors certs` never replaces a name it was not told to (review of issue 23): not a
# dangling symlink, and not a file another writer made after the check for existing ones
# (two `certs issue` at once would otherwise leave one's certificate with the other's key).


def test_issue_refuses_a_name_that_is_a_dangling_symlink_and_leaves_it(
    ca_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (ca_dir / "robot.key").symlink_to(ca_dir / "elsewhere.key")

    assert 1 == certs("issue", str(ca_dir), "robot")[0]

    assert "robot.key already exists: left untouched" in capsys.readouterr().err
    assert str(ca_dir / "elsewhere.key") == os.readlink(ca_dir / "robot.key")
    assert not (ca_dir / "robot.pem").exists()


def test_issue_leaves_a_file_another_writer_made_after_its_check(
    ca_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The other writer's `robot.key` appears while the new key is made (after the check
    for existing names, before the files are renamed into place)."""
    real = ec.generate_private_key

    def racing(*args: Any, **kwargs: Any) -> Any:
        (ca_dir / "robot.key").write_bytes(b"the other writer's key")
        return real(*args, **kwargs)

    monkeypatch.setattr(ec, "generate_private_key", racing)

    with pytest.raises(ConfigError, match=r"robot\.key already exists: left untouched"):
        issue_cert(ca_dir, "robot", ["10.0.0.2"])

    assert b"the other writer's key" == (ca_dir / "robot.key").read_bytes()
    assert not (ca_dir / "robot.pem").exists()  # no certificate without its key
    assert [] == [p.name for p in ca_dir.iterdir() if p.name.endswith(".tmp")]


def test_issue_with_force_replaces_both_files(ca_dir: Path) -> None:
    pem, key = issue_cert(ca_dir, "robot", ["10.0.0.2"])
    old = pem.read_bytes(), key.read_bytes()

    issue_cert(ca_dir, "robot", ["10.0.0.2"], force=True)

    assert old[0] != pem.read_bytes()
    assert old[1] != key.read_bytes()
    assert [] == [p.name for p in ca_dir.iterdir() if p.name.endswith(".tmp")]
