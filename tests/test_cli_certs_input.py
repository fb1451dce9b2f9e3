"""`rr-actors certs issue` refuses input that would make a useless certificate or crash.

A careless `--address` (with a port, a scheme, brackets, blanks) would be written as a
DNS name that no peer ever dials, and the mistake would only show as a refused
handshake on another machine; a huge `--days` is a clear error, not a traceback.
"""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from cryptography import x509

from rr_actors._cli import main
from rr_actors._tools.certs import issue_cert
from rr_actors.errors import ConfigError


def certs(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    code = main(["certs", *argv], out)
    return code, out.getvalue()


@pytest.fixture
def ca_dir(tmp_path: Path) -> Path:
    directory = tmp_path / "certs"
    assert 0 == certs("init", str(directory), "--system", "lab")[0]
    return directory


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
