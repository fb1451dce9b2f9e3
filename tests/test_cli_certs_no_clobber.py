"""`rr-actors certs` never replaces a name it was not told to (review of issue 23): not a
dangling symlink, and not a file another writer made after the check for existing ones
(two `certs issue` at once would otherwise leave one's certificate with the other's key).
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives.asymmetric import ec

from rr_actors._cli import main
from rr_actors._tools.certs import issue_cert
from rr_actors.errors import ConfigError


def certs(*argv: str) -> int:
    return main(["certs", *argv], io.StringIO())


@pytest.fixture
def ca_dir(tmp_path: Path) -> Path:
    directory = tmp_path / "certs"
    assert 0 == certs("init", str(directory), "--system", "lab")
    return directory


def test_issue_refuses_a_name_that_is_a_dangling_symlink_and_leaves_it(
    ca_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (ca_dir / "robot.key").symlink_to(ca_dir / "elsewhere.key")

    assert 1 == certs("issue", str(ca_dir), "robot")

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
