"""The multi-host tests' fixtures: two hosts (network namespaces joined by a veth), per test.

`two_hosts` needs root (`ip netns`); without it the test is skipped with the reason. CI runs as
root, so there they always run. Every test here also fails if it leaves a namespace of this
process behind (the autouse `no_leftover_namespaces`; a module's shared hosts are deleted with
the module, by `hosts.TwoHosts.close`); child processes (the workers) are
already counted by the root conftest's `no_leftovers`. See `tests/support/hosts.py`.
"""

from __future__ import annotations

import contextlib
import subprocess
from collections.abc import Iterator

import pytest

from tests.support import hosts


@pytest.fixture
def two_hosts() -> Iterator[hosts.TwoHosts]:
    """Hosts `a` (10.77.<n>.1) and `b` (10.77.<n>.2) on a veth; deleted after the test."""
    reason = hosts.require_root()
    if reason is not None:
        pytest.skip(reason)
    with hosts.TwoHosts() as made:
        yield made


@pytest.fixture(autouse=True)
def no_leftover_namespaces() -> Iterator[None]:
    """Fail the test if a network namespace it made outlives it (and delete it); those of
    a module's shared hosts, made before it, are theirs to delete."""
    if hosts.require_root() is not None:
        yield
        return
    before = set(hosts.ours())
    yield
    left = [name for name in hosts.ours() if name not in before]
    for name in left:
        with contextlib.suppress(subprocess.CalledProcessError):
            subprocess.run(["ip", "netns", "del", name], check=True)  # noqa: S607
    if left:
        pytest.fail(f"network namespaces left behind: {left}")
