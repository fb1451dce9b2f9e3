"""Whether a file's names may have changed, told by inotify (`rr_actors._platform.linux_names`).

- A watch armed on a SQLite file and its `-wal` stays quiet through commits and
  checkpoints (else every commit would `stat` again), and is told, before the next call
  returns, of each way a backup's name can lose its file: the file or its `-wal` deleted
  or replaced, its directory renamed, a symbolic link of the path pointed elsewhere.
- Two watches that share a directory each keep its watch until both let go; two threads
  asking theirs at once (two stores' registrars) both get answers.
- A child forked from the process: a watch of the parent is never quiet there.
- inotify instances (128 a user, shared by all its programs): a process of one store (a
  process manager's) makes none, its store stats; a tree of process managers with a
  `state_dir` holds one only in its processes of several stores, whatever its size, and
  leaves the user's other programs theirs (a user namespace's lowered limit).
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
import textwrap
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors._platform.linux import _HELD
from rr_actors._platform.linux_names import InotifyNameWatch, watch_names

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="inotify")


@pytest.fixture(autouse=True)
def two_stores() -> None:
    """This process makes its instance, as one of several stores does (the supervisor's)."""
    watch_names()


@pytest.fixture
def armed(tmp_path: Path) -> Iterator[tuple[Path, sqlite3.Connection, InotifyNameWatch]]:
    """A WAL-mode SQLite file at `<tmp>/d/p.db` (through a symbolic link `<tmp>/link`), a
    commit made, and a watch armed on its names."""
    (tmp_path / "d").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "d")
    path = tmp_path / "link" / "p.db"
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("CREATE TABLE t (x)")
    watch = watch_names()
    assert watch is not None
    assert watch.arm([str(path), f"{path}-wal"])
    try:
        yield path, db, watch
    finally:
        watch.close()
        db.close()


def test_an_armed_watch_stays_quiet_through_commits_and_checkpoints(
    armed: tuple[Path, sqlite3.Connection, InotifyNameWatch],
) -> None:
    _, db, watch = armed
    for n in range(3000):
        db.execute("INSERT INTO t VALUES (?)", (b"x" * 1000,))
        if n % 500 == 0:
            db.execute("PRAGMA wal_checkpoint(PASSIVE)")
    db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    db.execute("INSERT INTO t VALUES (1)")

    assert watch.quiet()


def replace(path: Path) -> None:
    other = path.with_name("other")
    other.write_bytes(b"another program's file")
    other.replace(path)


def relink(path: Path) -> None:
    link = path.parent
    (link.parent / "elsewhere").mkdir()
    link.unlink()
    link.symlink_to(link.parent / "elsewhere")


def rename_directory(path: Path) -> None:
    path.resolve().parent.rename(path.parent.parent / "moved")


def remove_another_name(path: Path) -> None:
    os.link(path, f"{path}.2")
    os.unlink(f"{path}.2")


CHANGES: dict[str, Callable[[Path], None]] = {
    "file deleted": lambda path: path.unlink(),
    "-wal deleted": lambda path: Path(f"{path}-wal").unlink(),
    "file replaced": replace,
    "-wal replaced": lambda path: replace(Path(f"{path}-wal")),
    "directory renamed": rename_directory,
    "link pointed elsewhere": relink,
    "another name removed": remove_another_name,
}


@pytest.mark.parametrize("change", CHANGES.values(), ids=CHANGES.keys())
def test_a_watch_is_told_of_each_way_a_name_loses_its_file(
    armed: tuple[Path, sqlite3.Connection, InotifyNameWatch], change: Callable[[Path], None]
) -> None:
    path, _, watch = armed
    assert watch.quiet()

    change(path)

    assert not watch.quiet()
    assert not watch.quiet()  # (until armed again)


def test_two_watches_of_one_directory_each_keep_its_watch_until_both_let_go(
    tmp_path: Path,
) -> None:
    (tmp_path / "d").mkdir()
    one, two = tmp_path / "d" / "one", tmp_path / "d" / "two"
    one.touch()
    two.touch()
    first, second = watch_names(), watch_names()
    assert first is not None
    assert second is not None
    assert first.arm([str(one)])
    assert second.arm([str(two)])

    first.close()
    (tmp_path / "d").rename(tmp_path / "moved")

    assert (False, False) == (first.quiet(), second.quiet())
    second.close()


def test_two_threads_ask_their_watches_at_once(tmp_path: Path) -> None:
    paths = [tmp_path / "one", tmp_path / "two"]
    errors: list[BaseException] = []
    answers: list[bool] = []

    def ask(path: Path) -> None:
        path.touch()
        watch = watch_names()
        assert watch is not None
        watch.arm([str(path)])
        try:
            answers.append(all(watch.quiet() for _ in range(20_000)))
        except BaseException as exc:  # (a RuntimeError from a poll object asked twice)
            errors.append(exc)
        finally:
            watch.close()

    threads = [threading.Thread(target=ask, args=(path,)) for path in paths]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)

    assert ([], [True, True]) == (errors, answers)


def test_a_watch_armed_again_is_quiet_until_the_next_change(tmp_path: Path) -> None:
    path = tmp_path / "p"
    path.touch()
    watch = watch_names()
    assert watch is not None
    watch.arm([str(path)])
    replace(path)
    assert not watch.quiet()

    assert watch.arm([str(path)])
    quiet_after_arming = watch.quiet()
    path.unlink()

    assert (True, False) == (quiet_after_arming, watch.quiet())
    assert not watch.arm([str(path)])  # (a name of no file: never quiet)
    assert not watch.quiet()
    watch.close()


FORKED = textwrap.dedent(
    """
    import os, sys
    from rr_actors._platform.linux_names import watch_names

    watch, _ = watch_names(), watch_names()  # (two stores: the process's instance is made)
    watch.arm([sys.argv[1]])
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:
        child, _ = watch_names(), watch_names()
        armed = child.arm([sys.argv[1]])
        os.write(write, f"{watch.quiet()} {armed} {child.quiet()}".encode())
        os._exit(0)
    os.waitpid(pid, 0)
    print(os.read(read, 100).decode(), watch.quiet())
    """
)


def test_a_watch_of_the_parent_is_never_quiet_in_a_forked_child(tmp_path: Path) -> None:
    """In the child, the parent's watch says "may have changed" (the caller stats); one
    the child makes works; the parent's own goes on as before."""
    path = tmp_path / "p"
    path.touch()

    done = subprocess.run(
        [sys.executable, "-c", FORKED, str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )

    assert "False True True True" == done.stdout.strip()


# -- inotify instances: one per process of several stores, none per process manager -------

ONE_STORE = textwrap.dedent(
    """
    import os, sys
    from rr_actors._platform.linux_names import watch_names

    def instances():
        fds = [f"/proc/self/fd/{fd}" for fd in os.listdir("/proc/self/fd")]
        links = [os.readlink(fd) for fd in fds if os.path.lexists(fd)]  # (not the listing's)
        return links.count("anon_inode:inotify")

    first = watch_names()
    alone = (first.armable, first.arm([sys.argv[1]]), first.quiet(), instances())
    second = watch_names()
    armed = (first.arm([sys.argv[1]]), second.arm([sys.argv[1]]), instances())
    print(alone, (first.armable, second.armable, *armed))
    """
)


def test_a_process_of_one_store_makes_no_instance_until_a_second_watch(tmp_path: Path) -> None:
    """A process manager's one store stats (not `armable`: never quiet, no instance); a
    second watch makes the instance, which makes the first `armable`: it joins at its next
    `arm` (its store does not ask it till then, issue 71 item 5)."""
    path = tmp_path / "p"
    path.touch()

    done = subprocess.run(
        [sys.executable, "-c", ONE_STORE, str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )

    assert "(False, False, False, 0) (True, True, True, True, 1)" == done.stdout.strip()


def _instances(pid: int) -> int:
    """Process `pid`'s own inotify instances: its descriptors of one, less the copies an
    exit watch holds (`PidfdExitWatch.held`: the same instances as its managers')."""
    fds = Path(f"/proc/{pid}/fd")
    inotify = {fd.name for fd in fds.iterdir() if os.readlink(fd) == "anon_inode:inotify"}
    return len(inotify - {str(fd) for fd in (_HELD if pid == os.getpid() else ())})


def _echo(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("echo", load=lambda r: r, unload=lambda r, s: None)


def test_a_tree_holds_an_instance_per_process_of_several_stores_not_per_manager(
    tmp_path: Path,
) -> None:
    managers = [rr.ManagerSpec(f"m{i}", _echo, isolation="process") for i in range(4)]
    pool = rr.SupervisorSpec(
        "pool", tuple(rr.ManagerSpec(f"p{i}", _echo) for i in range(2)), isolation="process"
    )
    with rr.Supervisor([*managers, pool], state_dir=str(tmp_path)) as sup:
        app = sup.registrar("app")
        for name in ("m0", "m1", "m2", "m3", "p0", "p1"):  # (each commits to its backup)
            app.call(name, "echo", "r")
        held = {name: _instances(sup.child(name).pid) for name in ("m0", "m1", "m2", "m3")}
        in_pool = _instances(sup.child("pool").pid)

    assert ({f"m{i}": 0 for i in range(4)}, 1) == (held, in_pool)


STARVED = textwrap.dedent(
    """
    import ctypes, os, sys
    import rr_actors as rr

    def echo(registrar):
        registrar.register_server("echo", load=lambda r: r, unload=lambda r, s: None)

    with open("/proc/sys/user/max_inotify_instances", "w") as limit:  # (this namespace's)
        limit.write("3")
    specs = [rr.ManagerSpec(f"m{i}", echo, isolation="process") for i in range(4)]
    with rr.Supervisor(specs, state_dir=sys.argv[1]) as sup:
        app = sup.registrar("app")
        for i in range(4):  # (each commits to its backup)
            app.call(f"m{i}", "echo", "r")
        fd = ctypes.CDLL(None, use_errno=True).inotify_init1(os.O_CLOEXEC)
        print("another program gets an instance:", fd >= 0)
    """
)


def _user_namespace() -> list[str]:
    """A command prefix running as root of a new user namespace (its own inotify limits)."""
    prefix = [shutil.which("unshare") or "unshare", "--user", "--map-root-user"]
    try:
        subprocess.run([*prefix, "true"], check=True, capture_output=True, timeout=30)
    except (OSError, subprocess.SubprocessError) as exc:  # (CI has them: fail, not skip)
        pytest.fail(f"no user namespace here (unshare --user --map-root-user): {exc}")
    return prefix


def test_a_tree_of_more_managers_than_the_users_instances_leaves_its_programs_one(
    tmp_path: Path,
) -> None:
    """4 process managers with a `state_dir` under a limit of 3 instances (one each would
    take them all, and the user's editor or file watcher would get none)."""
    done = subprocess.run(
        [*_user_namespace(), sys.executable, "-c", STARVED, str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )

    assert "another program gets an instance: True" == done.stdout.strip()
