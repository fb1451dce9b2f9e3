"""The how-to's openssl recipe makes certificates `rr.ZenohTLS` accepts (the page cannot lie).

`tests/test_docs.py` runs the page's commands too; here the openssl ones alone, in an empty
directory, and their result goes through `ZenohTLS` without a WARNING.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
from pathlib import Path

import pytest

import rr_actors as rr
from tests.test_docs import ROOT, blocks, commands

PAGE = ROOT / "docs" / "how-to" / "securing-registrars.md"


def openssl_commands() -> list[list[str]]:
    return [
        command
        for block in blocks(PAGE)
        if block.lang == "bash" and block.skip is None
        for command in commands(block.code)
        if command[0] == "openssl"
    ]


def test_the_pages_openssl_recipe_makes_certificates_zenoh_tls_accepts(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
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
