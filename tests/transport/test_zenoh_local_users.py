"""Another user of this machine and a router on loopback (issue 29, item 2).

The AF_UNIX carrier lets only this user in (a 0700 runtime directory, a per-system key).
A `ZenohNetwork` that listens on `tcp/127.0.0.1` lets in everyone on the machine:
`test_plain_tcp_on_loopback_lets_another_local_user_run_code_here_as_the_warning_says`
runs a process as user `nobody` that joins such a router and sends a pickle for its
registrar, which is unpickled here (as this user, root), as the WARNING says.
`test_with_tls_another_local_user_gets_nothing_unpickled` gives the same process the
one-machine example of the how-to (`rr-actors certs` files, `tls/127.0.0.1`): it cannot
read the host's key, and plain TCP to the port, TLS with a certificate of its own CA and
the router's Unix socket are all refused before anything is unpickled.

`nobody` must be able to run this Python: where it lives under a directory others
cannot enter (root's home), the process runs in a mount namespace of its own in which
that directory is an empty tmpfs holding only the interpreter's tree (`_as_nobody`).
Everything else, the files of the system included, is as on the machine.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._tools import certs as certs_tool
from rr_actors._transport.codec import frame
from tests.support import pki
from tests.support.tls_lab import free_port

NOBODY = 65534
ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    os.geteuid() != 0 or not (shutil.which("unshare") and shutil.which("setpriv")),
    reason="runs a process as another user: needs root, unshare and setpriv",
)

_PWNED = threading.Event()
_RAN_AS: list[int] = []


def _pwned() -> None:
    """What the attacker's pickle calls when it is unpickled (in this process)."""
    _RAN_AS.append(os.geteuid())
    _PWNED.set()


class _Payload:
    def __reduce__(self) -> tuple[Any, ...]:
        return (_pwned, ())


ATTACKER = r"""
import json, os, select, sys, zenoh
from rr_actors._transport.zenoh.wire import MESSAGE, header

system, target, body, key = sys.argv[1], sys.argv[2], bytes.fromhex(sys.argv[3]), sys.argv[4]
outcome = {"uid": os.geteuid()}
try:
    open(key, "rb").close()
    outcome["key"] = "read"
except OSError as exc:
    outcome["key"] = type(exc).__name__
for label, config in json.loads(sys.argv[5]):
    try:
        session = zenoh.open(zenoh.Config.from_json5(config))
    except Exception:
        outcome[label] = "refused"
        continue
    zid = str(session.zid())
    token = session.liveliness().declare_token(f"rr/{system}/live/proc/{zid}")
    for _ in range(100):  # until the test says stop (a line on stdin): at most 100 x 0.1 s
        session.put(f"rr/{system}/reg/{target}", header(MESSAGE, zid) + body)
        if select.select([sys.stdin], [], [], 0.1)[0]:
            break
    token.undeclare()
    session.close()
    outcome[label] = "sent"
print(json.dumps(outcome), flush=True)
"""


def _client(endpoint: str, tls: dict[str, Any] | None = None) -> str:
    config: dict[str, Any] = {
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    if tls is not None:
        config["transport"] = {"link": {"tls": tls}}
    return json.dumps(config)


def _hidden_ancestor(path: Path) -> Path | None:
    """The first directory above `path` that others cannot enter, or `None`."""
    for parent in reversed(path.parents):
        if not os.stat(parent).st_mode & 0o001:
            return parent
    return None


def _as_nobody(*argv: str) -> subprocess.Popen[str]:
    """`python -c ATTACKER *argv` as user `nobody`, able to run this interpreter.

    The interpreter's trees (its base installation and, in a virtual environment such as
    CI's, the environment) may lie under directories others cannot enter (/root, a 0700
    temporary directory): then the attacker runs in a mount namespace where a tmpfs lies
    over each such directory with only those trees put back.
    """
    python = [sys.executable, "-c", ATTACKER, *argv]
    setpriv = ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups"]
    trees: dict[Path, set[Path]] = {}  # a hidden directory -> the trees under it to show
    for prefix in {Path(sys.base_prefix).resolve(), Path(sys.prefix).resolve()}:
        hidden = _hidden_ancestor(prefix)
        if hidden is not None:
            trees.setdefault(hidden, set()).add(hidden / prefix.relative_to(hidden).parts[0])
    if not trees:
        command = [*setpriv, *python]
    else:
        steps = []
        for hidden, shown in sorted(trees.items()):
            stashes = {tree: tempfile.mkdtemp() for tree in sorted(shown)}
            steps += [f'mount --bind "{tree}" "{stash}"' for tree, stash in stashes.items()]
            steps.append(f'mount -t tmpfs -o mode=0755 none "{hidden}"')
            for tree, stash in stashes.items():
                steps += [
                    f'mkdir -p "{tree}"',
                    f'mount --move "{stash}" "{tree}"',
                    f'rmdir "{stash}"',
                ]
        script = " && ".join(steps) + ' ; exec "$@"'
        command = ["unshare", "--mount", "--propagation", "private", "sh", "-c", script, "sh"]
        command += [*setpriv, *python]
    return subprocess.Popen(
        command,
        cwd="/",
        env={"PATH": os.environ["PATH"], "PYTHONPATH": str(ROOT), "HOME": "/"},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _outcome(attacker: subprocess.Popen[str], *, stop: bool = False) -> dict[str, Any]:
    out, err = attacker.communicate("stop\n" if stop else "", timeout=60)
    assert 0 == attacker.returncode, err
    result: dict[str, Any] = json.loads(out)
    return result


@pytest.fixture
def victim_setup() -> Iterator[None]:
    _PWNED.clear()
    _RAN_AS.clear()
    yield
    _PWNED.clear()


def test_plain_tcp_on_loopback_lets_another_local_user_run_code_here_as_the_warning_says(
    victim_setup: None, caplog: pytest.LogCaptureFixture
) -> None:
    system, port = f"t-{uuid.uuid4().hex[:8]}", free_port()
    with caplog.at_level(logging.WARNING, logger="rr_actors"):
        net = rr.ZenohNetwork(system=system, listen=[f"tcp/127.0.0.1:{port}"], tls=None)
    erm = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="erm"), network=net)
    try:
        attacker = _as_nobody(
            system, "erm", frame(7, _Payload()).hex(), "/nonexistent",
            json.dumps([["tcp", _client(f"tcp/127.0.0.1:{port}")]]),
        )  # fmt: skip
        pwned = _PWNED.wait(30)
        outcome = _outcome(attacker, stop=True)
    finally:
        erm.stop()
        net.close()

    assert (True, [0]) == (pwned, _RAN_AS)  # unpickled here, run as root
    assert (NOBODY, "sent") == (outcome["uid"], outcome["tcp"])
    assert any(
        "every user and process on this machine can connect and run code as this user, root"
        in message
        for message in caplog.messages
    )


def test_with_tls_another_local_user_gets_nothing_unpickled(
    victim_setup: None, tmp_path: Path
) -> None:
    # the how-to's one-machine example: its certificates, its endpoint
    certs = tmp_path / "certs"
    certs_tool.init_ca(certs, "docs")
    certs_tool.issue_cert(certs, "laptop", ["127.0.0.1"])
    tls = rr.ZenohTLS(
        ca=certs / "ca.pem", cert=certs / "laptop.pem", key=certs / "laptop.key",
        members=["laptop"],
    )  # fmt: skip
    # what the other user has: the system's ca.pem (public) and a certificate of its own CA
    theirs = Path(tempfile.mkdtemp())
    try:
        shutil.copy(certs / "ca.pem", theirs / "system-ca.pem")
        own_ca = pki.make_ca(theirs / "own", system="docs")
        own_cert, own_key = pki.issue(theirs / "own", "laptop", ("127.0.0.1",), ca=own_ca)
        for path in [theirs, *theirs.rglob("*")]:
            os.chown(path, NOBODY, NOBODY)
        system, port = f"t-{uuid.uuid4().hex[:8]}", free_port()
        net = rr.ZenohNetwork(system=system, listen=[f"tls/127.0.0.1:{port}"], tls=tls)
        erm = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="erm"), network=net)
        try:
            attempts = [
                ["tcp", _client(f"tcp/127.0.0.1:{port}")],
                [
                    "tls",
                    _client(
                        f"tls/127.0.0.1:{port}",
                        {
                            "root_ca_certificate": str(theirs / "system-ca.pem"),
                            "connect_certificate": str(own_cert),
                            "connect_private_key": str(own_key),
                            "enable_mtls": True,
                        },
                    ),
                ],
                ["unix", _client(f"unixsock-stream/{net.address.socket_path}")],
            ]
            attacker = _as_nobody(
                system, "erm", frame(7, _Payload()).hex(), str(certs / "laptop.key"),
                json.dumps(attempts),
            )  # fmt: skip
            outcome = _outcome(attacker)
        finally:
            erm.stop()
            net.close()
    finally:
        shutil.rmtree(theirs)

    assert {
        "uid": NOBODY,
        "key": "PermissionError",
        "tcp": "refused",
        "tls": "refused",
        "unix": "refused",
    } == outcome
    assert not _PWNED.is_set()
