"""One owner of a path at a time (`rr_actors._platform.lockfile`): a second claim is refused
naming the holder's pid, in this process or another; the lock goes with its owner's
`release` or its process's end (a SIGKILL too), never with a forked child's."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from rr_actors._platform import lockfile

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="POSIX flock and fork")


def test_a_second_claim_in_the_same_process_is_refused_naming_this_pid(tmp_path: Path) -> None:
    path = tmp_path / "x.lock"
    fd = lockfile.claim(path)
    try:
        with pytest.raises(lockfile.HeldError) as held:
            lockfile.claim(path)
        assert str(os.getpid()) == held.value.holder
    finally:
        lockfile.release(fd)


def test_a_released_lock_leaves_no_file_and_can_be_claimed_again(tmp_path: Path) -> None:
    path = tmp_path / "x.lock"
    lockfile.release(lockfile.claim(path))
    assert not path.exists()

    lockfile.release(lockfile.claim(path))


def test_a_release_never_removes_another_owners_lock_file(tmp_path: Path) -> None:
    path = tmp_path / "x.lock"
    first = lockfile.claim(path)
    path.unlink()  # (someone deleted it: a second owner may make its own now)
    second = lockfile.claim(path)
    try:
        lockfile.release(first)

        with pytest.raises(lockfile.HeldError):  # the second's file and lock are still there
            lockfile.claim(path)
    finally:
        lockfile.release(second)


def test_the_lock_file_is_the_owners_alone_whatever_the_umask(tmp_path: Path) -> None:
    path = tmp_path / "x.lock"
    before = os.umask(0o077 ^ 0o777)  # (a umask that would leave 0o077)
    try:
        fd = lockfile.claim(path)
    finally:
        os.umask(before)
    try:
        assert 0o600 == path.stat().st_mode & 0o777
    finally:
        lockfile.release(fd)


def _holder(path: Path, *, fork: bool = False, claim: str = "claim") -> subprocess.Popen[str]:
    """Another process that claims `path` (`lockfile.<claim>`) and says so, then waits to
    be killed; with `fork`, it forks a child first, which lives until the test's stdin
    closes."""
    program = textwrap.dedent(
        f"""
        import os, sys
        from rr_actors._platform import lockfile
        lockfile.{claim}({str(path)!r})
        if {fork!r}:
            started, running = os.pipe()
            if os.fork() == 0:  # (the child: past its fork hooks, until stdin closes)
                os.write(running, b"x")
                sys.stdin.read()
                os._exit(0)
            os.read(started, 1)
        print("held", flush=True)
        sys.stdin.read()
        """
    )
    child = subprocess.Popen(
        [sys.executable, "-c", program], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert child.stdout is not None
    assert "held\n" == child.stdout.readline()
    return child


def test_a_child_forked_from_the_owner_does_not_keep_the_lock_after_the_owner_died(
    tmp_path: Path,
) -> None:
    # (a load that forks, say): were the child to share the lock, the owner's restart
    # would be refused for as long as the child lives
    path = tmp_path / "x.lock"
    owner = _holder(path, fork=True)
    try:
        owner.send_signal(signal.SIGKILL)
        owner.wait(10)

        lockfile.release(lockfile.claim(path))  # (its forked child still lives)
    finally:
        owner.kill()
        owner.communicate(timeout=10)  # (stdin closed: the child exits)


# -- claim_file: one owner of a file, whatever its name (issue 51, finding 3) ---------------------

file_locks = pytest.mark.skipif(not lockfile.FILE_LOCKS, reason="flock apart from POSIX locks")


@file_locks
def test_a_file_claimed_by_one_name_is_refused_by_a_hard_link_naming_this_pid(
    tmp_path: Path,
) -> None:
    path, link = tmp_path / "x.db", tmp_path / "y.db"
    path.write_bytes(b"")
    os.link(path, link)
    fd = lockfile.claim_file(path)
    try:
        with pytest.raises(lockfile.HeldError) as held:
            lockfile.claim_file(link)
    finally:
        assert fd is not None
        lockfile.release_file(fd)

    assert (str(os.getpid()), True) == (held.value.holder, path.exists())


@pytest.mark.parametrize("claim", ["claim", pytest.param("claim_file", marks=file_locks)])
def test_a_claim_held_by_another_process_is_refused_naming_it_and_free_once_it_was_killed(
    tmp_path: Path, claim: str
) -> None:
    # `claim` names the lock file; `claim_file` is asked by another name of the file
    path, link = tmp_path / "x.db", tmp_path / "y.db"
    path.write_bytes(b"")
    os.link(path, link)
    asked = path if claim == "claim" else link
    child = _holder(path, claim=claim)
    try:
        with pytest.raises(lockfile.HeldError) as held:
            getattr(lockfile, claim)(asked)
        assert str(child.pid) == held.value.holder
    finally:
        child.send_signal(signal.SIGKILL)
        child.communicate(timeout=10)  # (reaped, its pipes closed)

    assert path.exists()  # (left by the dead: not a lock)
    fd = getattr(lockfile, claim)(asked)
    assert fd is not None
    (lockfile.release if claim == "claim" else lockfile.release_file)(fd)
