"""Only members of the system get in (issue 23): mutual TLS and access control, on two hosts.

Host `a` (10.77.<n>.1) listens on `tls/<a>:7447` and serves `erm`; host `b` connects. The
certificates are made by the test (`tests/pki.py`): the system's CA "lab", members `robot`
(host a) and `operator` (host b), each naming its host's address.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import hosts
import pki

import rr_actors as rr

SYSTEM = "lab"
PORT = 7447
MEMBERS = ["robot", "operator"]


def erm_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server(
        "camera", load=lambda request: {"stream": request}, unload=lambda _q, _r: None
    )


def call_camera(registrar: rr.ResourceRegistrar, device: int) -> Any:
    query = registrar.call("erm", "camera", {"device": device}, timeout=10)
    registrar.unload(query.id)
    return query.response


def tls_files(directory: Path, name: str, address: str, ca: tuple[Path, Path]) -> dict[str, Any]:
    cert, key = pki.issue(directory, name, (address,), ca=ca)
    return {"ca": str(ca[0]), "cert": str(cert), "key": str(key), "members": MEMBERS}


def test_members_call_each_other_and_each_side_names_the_other(
    two_hosts: hosts.TwoHosts, tmp_path: Path
) -> None:
    a, b = two_hosts.a, two_hosts.b
    ca = pki.make_ca(tmp_path, SYSTEM)
    a.call(
        hosts.rr_join,
        system=SYSTEM,
        listen=[a.endpoint(PORT, "tls")],
        connect=[],
        tls=tls_files(tmp_path, "robot", a.address, ca),
        timeout=30,
    )
    a.call(hosts.rr_start, "erm", erm_setup, timeout=30)
    b.call(
        hosts.rr_join,
        system=SYSTEM,
        listen=[],
        connect=[a.endpoint(PORT, "tls")],
        tls=tls_files(tmp_path, "operator", b.address, ca),
        timeout=30,
    )
    b.call(hosts.rr_start, "app", timeout=30)
    b.call(hosts.rr_until_answered, "app", "erm", "camera", 10.0, timeout=30)
    assert b.call(hosts.rr_run, "app", call_camera, 3, timeout=30) == {"stream": {"device": 3}}
    assert f"ZenohNetwork 'lab': member 'operator' linked at {b.address}" in a.call(
        hosts.rr_logs, "INFO", timeout=10
    )
    assert f"ZenohNetwork 'lab': member 'robot' linked at {a.address}" in b.call(
        hosts.rr_logs, "INFO", timeout=10
    )
