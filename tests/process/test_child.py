"""The child's side of a manager process (`rr_actors._process.child`): its name in `ps`, and
what its `setup` is offered in doubt.

The kernel's 15-byte name of a manager process is the manager's name, not a prefix:
`ps -o comm` and `top` show that name; with a prefix of 11 bytes every manager read
`rr-actors: <first 4 characters>`. The long title `rr-actors: <name>` is the command
line's, where `setproctitle` is installed.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import SharedObjects, start_forkserver
from tests.support.supervising import kill_and_wait_restarted, linux_trick, process


@pytest.fixture(scope="module", autouse=True)
def forkserver() -> None:
    """Start the forkserver before the leak check counts this process's children."""
    start_forkserver()


def comm_after_set_title(name: str, *, fake_setproctitle: bool) -> tuple[str, str]:
    """`/proc/self/comm` of a fresh interpreter after `set_title(name)`, and the title set."""
    if fake_setproctitle:
        prelude = (
            "import sys, types; titles = []\n"
            "m = types.ModuleType('setproctitle'); m.setproctitle = titles.append\n"
            "sys.modules['setproctitle'] = m\n"
        )
    else:
        prelude = "import sys; titles = []; sys.modules['setproctitle'] = None\n"
    script = (
        prelude + "from rr_actors._process.child import set_title\n"
        f"set_title({name!r})\n"
        "print(open('/proc/self/comm', encoding='utf-8').read().strip())\n"
        "print(titles)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    )
    comm, titles = result.stdout.splitlines()
    return comm, titles


@linux_trick
@pytest.mark.parametrize("fake_setproctitle", [False, True])
def test_a_long_manager_name_keeps_its_first_15_bytes_as_the_process_name(
    fake_setproctitle: bool,
) -> None:
    comm, _ = comm_after_set_title("navigation-manager-2", fake_setproctitle=fake_setproctitle)

    assert "navigation-mana" == comm


@linux_trick
def test_with_setproctitle_the_command_line_keeps_the_long_title() -> None:
    comm, titles = comm_after_set_title("erm", fake_setproctitle=True)

    assert ("erm", "['rr-actors: erm']") == (comm, titles)


@linux_trick
def test_a_name_is_never_cut_inside_a_character() -> None:
    comm, _ = comm_after_set_title("é" * 10, fake_setproctitle=False)  # 2 bytes each

    assert "é" * 7 == comm


def _cmdline(pid: int) -> str:
    return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode().strip()


@pytest.mark.skipif(not Path("/proc").exists(), reason="reads /proc")
def test_a_manager_process_is_named_after_its_manager_in_ps(
    supervisors: Callable[..., rr.Supervisor], uid: str
) -> None:
    pytest.importorskip("setproctitle", reason="the whole command line needs setproctitle")
    name = f"erm-{uid}"
    sup = supervisors([process(name)]).start()
    pid = sup.child(name).pid
    assert pid is not None

    assert f"rr-actors: {name}" == _cmdline(pid)


@linux_trick
def test_without_setproctitle_the_kernel_name_of_a_manager_process_is_set() -> None:
    script = (
        "import sys; sys.modules['setproctitle'] = None\n"  # as if it were not installed
        "from rr_actors._process.child import set_title\n"
        "set_title('erm')\n"
        "print(open('/proc/self/comm').read().strip())\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    )

    assert "erm" == result.stdout.strip()


DEVICE = {"device": 1}


def offered(journal: Path) -> list[str]:
    """What each `setup` so far was offered in doubt, one entry per incarnation."""
    if not journal.exists():
        return []
    return [line.split(" ", 2)[2] for line in journal.read_text().splitlines()]


def gated_setup(journal: str, in_setup: Any, gate: Any) -> Callable[[rr.ResourceRegistrar], None]:
    """A manager's setup: incarnation 1 dies inside its load, incarnation 2 waits on
    `gate` inside setup (after `in_setup`), the others return at once."""

    def setup(registrar: rr.ResourceRegistrar) -> None:
        doubts = [q.request for q in registrar.in_doubt]
        with open(journal, "a", encoding="utf-8") as out:
            out.write(f"{os.getpid()} offered {doubts}\n")
        with open(journal, encoding="utf-8") as done:
            incarnation = len(done.read().splitlines())

        def load(request: Any) -> Any:
            if incarnation == 1:  # the load started a device, then the process died
                os.kill(os.getpid(), signal.SIGKILL)
            return request

        registrar.register_server("dev", load=load, unload=lambda r, s: None)
        if incarnation == 2:  # a slow re-adoption: the test kills it here
            in_setup.set()
            assert gate.wait(60.0), "the test did not kill this setup"

    return setup


def settle_each(registrar: rr.ResourceRegistrar) -> None:
    """Clean up what each in-doubt load started, then settle it."""
    for query in registrar.in_doubt:
        registrar.settle_in_doubt(query.id)


def settle_each_awaited(registrar: rr.ResourceRegistrar) -> None:
    """The same with coroutines: every clean-up at once, on a loop of the setup's own,
    each entry settled as its clean-up ends (`asettle_in_doubt`)."""

    async def clean_up(query: rr.Query) -> None:
        await asyncio.sleep(0)  # (what the load started, stopped)
        await registrar.asettle_in_doubt(query.id)

    async def all_of_them() -> None:
        await asyncio.gather(*(clean_up(query) for query in registrar.in_doubt))

    asyncio.run(all_of_them())


class TestInDoubtUntilSetupReturned:
    """An in-doubt entry is offered until a `setup` that saw it has returned (rule 16).

    Real manager processes, real SIGKILLs: the first incarnation dies inside a `load` (so its
    load is in doubt), the second is killed while its `setup` waits on a gate, the third's
    `setup` returns, the fourth must find nothing in doubt. Each `setup` writes what it was
    offered to a journal file. The thread placement is checked with a `setup` that raises.
    """

    pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")

    def test_an_in_doubt_load_is_offered_again_after_a_death_during_setup(
        self,
        supervisors: Callable[..., rr.Supervisor],
        uid: str,
        tmp_path: Path,
        process_helpers: SharedObjects,
    ) -> None:
        name = f"erm-{uid}"
        journal = tmp_path / "journal.txt"
        in_setup, gate = process_helpers.event(), process_helpers.event()
        spec = process(name, gated_setup(str(journal), in_setup, gate))
        sup = supervisors([spec], state_dir=tmp_path / "state", max_restarts=10, period=60.0)
        sup.start()
        app = sup.registrar(f"app-{uid}")
        with pytest.raises(rr.RegistrarUnavailableError):
            app.call(name, "dev", DEVICE, timeout=20.0)  # incarnation 1 dies in the load
        assert in_setup.wait(20.0)  # incarnation 2 is in its setup
        pid = int(journal.read_text().splitlines()[1].split()[0])
        os.kill(pid, signal.SIGKILL)
        sup.wait_restarted(name, timeout=20.0)  # incarnation 3: its setup returned
        kill_and_wait_restarted(sup, name, timeout=20.0)  # incarnation 4

        assert ["[]", str([DEVICE]), str([DEVICE]), "[]"] == offered(journal)

    @pytest.mark.parametrize(
        "settle", [settle_each, settle_each_awaited], ids=["blocking", "awaited"]
    )
    def test_an_entry_the_setup_settled_is_not_offered_again(
        self,
        supervisors: Callable[..., rr.Supervisor],
        uid: str,
        tmp_path: Path,
        process_helpers: SharedObjects,
        settle: Callable[[rr.ResourceRegistrar], None],
    ) -> None:
        name = f"erm-{uid}"
        journal = tmp_path / "journal.txt"
        in_setup, gate = process_helpers.event(), process_helpers.event()
        inner = gated_setup(str(journal), in_setup, gate)

        def setup(registrar: rr.ResourceRegistrar) -> None:
            settle(registrar)  # cleaned up at once, before a slow re-adoption
            inner(registrar)

        spec = process(name, setup)
        sup = supervisors([spec], state_dir=tmp_path / "state", max_restarts=10, period=60.0)
        sup.start()
        app = sup.registrar(f"app-{uid}")
        with pytest.raises(rr.RegistrarUnavailableError):
            app.call(name, "dev", DEVICE, timeout=20.0)
        assert in_setup.wait(20.0)
        pid = int(journal.read_text().splitlines()[1].split()[0])
        os.kill(pid, signal.SIGKILL)
        sup.wait_restarted(name, timeout=20.0)

        assert ["[]", str([DEVICE]), "[]"] == offered(journal)

    def test_settling_an_id_that_is_not_in_doubt_raises_unknown_query(self, tmp_path: Path) -> None:
        with rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name="erm-settle", backup_path=str(tmp_path / "erm.db"))
        ) as erm:
            erm.settle_in_doubt()  # nothing in doubt: a no-op
            with pytest.raises(rr.errors.UnknownQueryError):
                erm.settle_in_doubt("no-such-id")

    def test_a_thread_manager_whose_setup_raised_is_offered_its_in_doubt_load_again(
        self,
        tmp_path: Path,
    ) -> None:
        """The thread placement: a load cut short by the registrar's death, then a `setup`
        that raises (it stops the registrar), then one that returns, then one more start."""
        config = rr.RegistrarConfig(
            name="erm-thread-doubt", backup_path=str(tmp_path / "erm.db"), save_on_modify=True
        )
        seen: list[list[Any]] = []
        started = rr.ResourceRegistrar.start(config)
        loading, gate = threading.Event(), threading.Event()

        def load(request: Any) -> Any:
            loading.set()
            gate.wait(10.0)
            return request

        started.register_server("dev", load=load, unload=lambda r, s: None)
        app = rr.ResourceRegistrar.start("app-thread-doubt")
        failed: list[BaseException] = []

        def call() -> None:
            try:
                app.call(config.name, "dev", DEVICE)
            except rr.errors.RrError as exc:
                failed.append(exc)

        try:
            caller = threading.Thread(target=call)
            caller.start()
            assert loading.wait(10.0)
            rr.testing.crash(started)  # the load is cut short: in doubt
            assert started.wait_ended(10.0)
            gate.set()
            caller.join(10.0)
            assert [rr.RegistrarUnavailableError] == [type(exc) for exc in failed]

            def failing(registrar: rr.ResourceRegistrar) -> None:
                seen.append([q.request for q in registrar.in_doubt])
                raise RuntimeError("setup failed")

            def returning(registrar: rr.ResourceRegistrar) -> None:
                seen.append([q.request for q in registrar.in_doubt])

            with pytest.raises(RuntimeError):
                rr.ResourceRegistrar.start(config, setup=failing)
            rr.ResourceRegistrar.start(config, setup=returning).stop()
            rr.ResourceRegistrar.start(config, setup=returning).stop()
        finally:
            app.stop()

        assert [[DEVICE], [DEVICE], []] == seen


class _Sent:
    """A control pipe's child end that keeps what is sent (`_Control`'s `send`)."""

    def __init__(self) -> None:
        self.messages: list[Any] = []

    def send(self, message: Any) -> None:
        self.messages.append(message)


def event_line(*, hold: float) -> tuple[Any, _Sent]:
    """A child's event line forwarding to `_Sent` (this process's events stay unnumbered: a
    manager process numbers them as it starts, `main` or `standby`, not its line)."""
    from rr_actors._process import child  # noqa: PLC0415 - the module under test

    sent = _Sent()
    line = child._EventLine(sent, "held", on=True, tally=None, hold=hold)  # type: ignore[arg-type]
    return line, sent


class TestTheEventsOfAStartFollowReady:
    """A manager process sends the events of its start (`CatalogRestored`, its setup's)
    after `Ready`: the supervisor's process reads `Ready` first, and the restart does not
    wait for their pickling, their passage and their unpickling (issue 52 part 5)."""

    def test_events_published_before_ready_are_held_then_sent_in_order(self) -> None:
        from rr_actors._process.control import Events, Ready  # noqa: PLC0415

        line, sent = event_line(hold=60.0)
        try:
            first = rr.events.ChildRestarted("sup", "a", 1, 0.0)
            second = rr.events.ChildRestarted("sup", "b", 2, 0.0)
            line.hub.publish(first)
            line.hub.publish(second)

            assert not line.forwarder.wait_sent(timeout=0.2)  # held: not sent before Ready
            assert sent.messages == []
            sent.send(Ready(os.getpid()))
            line.started()

            assert line.forwarder.wait_sent(timeout=10.0)
            batches = [m.batch for m in sent.messages[1:] if isinstance(m, Events)]
            assert isinstance(sent.messages[0], Ready)
            assert [first, second] == [e for batch in batches for e in batch]
        finally:
            line.flush(timeout=5.0)

    def test_events_published_after_the_start_are_sent_at_once(self) -> None:
        line, sent = event_line(hold=60.0)
        try:
            line.started()
            event = rr.events.ChildRestarted("sup", "a", 1, 0.0)
            line.hub.publish(event)

            assert line.forwarder.wait_sent(timeout=10.0)
            assert [event] == [e for m in sent.messages for e in m.batch]
        finally:
            line.flush(timeout=5.0)

    def test_a_start_longer_than_the_hold_forwards_its_events_without_ready(self) -> None:
        line, sent = event_line(hold=0.05)
        try:
            event = rr.events.ChildRestarted("sup", "a", 1, 0.0)
            line.hub.publish(event)

            assert line.forwarder.wait_sent(timeout=10.0)  # (no `started()`: a long setup)
            assert [event] == [e for m in sent.messages for e in m.batch]
        finally:
            line.flush(timeout=5.0)


def _blocks_on_restored(
    restored: Any, release: Any, name: str, heard: list[Any]
) -> Callable[[rr.events.Event], None]:
    """A subscriber that blocks (bounded) on the second `CatalogRestored` of `name`."""

    def callback(event: rr.events.Event) -> None:
        heard.append(event)
        mine = [e for e in heard if getattr(e, "registrar", None) == name]
        restorations = sum(isinstance(e, rr.events.CatalogRestored) for e in mine)
        if isinstance(event, rr.events.CatalogRestored) and event in mine and restorations == 2:
            restored.set()
            assert release.wait(60.0), "the test never released the subscriber"

    return callback


def test_a_subscriber_blocked_on_catalog_restored_does_not_delay_serving(tmp_path: Path) -> None:
    """A restarted manager serves while a subscriber still holds its `CatalogRestored`;
    each incarnation's `CatalogRestored` comes before its other events (`restore-first`)."""
    restored, release = threading.Event(), threading.Event()
    heard: list[rr.events.Event] = []
    name = f"blocked-{os.getpid()}"
    sup = rr.Supervisor([process(name)], state_dir=str(tmp_path))
    subscription = sup.subscribe(_blocks_on_restored(restored, release, name, heard))
    with subscription, sup:
        app = sup.registrar(f"app-{os.getpid()}")
        app.call(name, "echo", "before", timeout=30.0)
        try:
            kill_and_wait_restarted(sup, name)
            assert restored.wait(30.0)  # the subscriber holds the restart's event now

            app.call(name, "echo", "after", timeout=30.0)  # served meanwhile
            assert not release.is_set()
        finally:
            release.set()
        assert sup.flush_events(timeout=30.0)
        assert subscription.wait_delivered(timeout=30.0)
    by_pid: dict[int, list[type]] = {}
    for event in heard:
        if getattr(event, "registrar", None) == name:
            by_pid.setdefault(event.pid, []).append(type(event))
    assert len(by_pid) == 2
    for kinds in by_pid.values():
        assert kinds[0] is rr.events.CatalogRestored
        assert rr.events.CatalogRestored not in kinds[1:]


def test_an_event_forwarded_as_its_journal_pickle_arrives_as_the_event() -> None:
    """The forwarder sends the journal's pickle of an event, not the event pickled again:
    the supervisor's process unpickles the event itself, in the order published."""
    import pickle  # noqa: PLC0415

    from rr_actors._process import child  # noqa: PLC0415
    from rr_actors._process.tally import Tally  # noqa: PLC0415

    tally = Tally.create()
    assert tally is not None
    sent = _Sent()
    line = child._EventLine(sent, "kept", on=True, tally=tally.path, hold=60.0)  # type: ignore[arg-type]
    try:
        published = [rr.events.ChildRestarted("sup", f"c{n}", n, 0.0) for n in range(3)]
        for event in published:
            line.hub.publish(event)
        line.started()
        assert line.forwarder.wait_sent(timeout=10.0)

        batches = [pickle.loads(pickle.dumps(m)) for m in sent.messages]
        assert published == [e for m in batches for e in m.batch]
        assert all(isinstance(e, child._Pickled) for m in sent.messages for e in m.batch)
    finally:
        line.flush(timeout=5.0)
        tally.close()


def needs_the_empty_image_made(registrar: rr.ResourceRegistrar) -> None:
    """A manager's setup, run with no backup: it fails unless its process was forked with
    the empty catalog's image made (`schema.empty_image`, in the forkserver's preload)."""
    from rr_actors._store import schema  # noqa: PLC0415 - in the manager's process

    if not schema._IMAGES:
        raise RuntimeError("this manager process would build the empty catalog itself")


def test_a_manager_process_is_forked_with_the_empty_catalog_image_already_made() -> None:
    """The image a fresh backup is written from is made once, in the forkserver, not in
    each manager process that creates its backup (a manager without one shows it)."""
    name = f"img-{os.getpid()}"
    sup = rr.Supervisor([process(name, needs_the_empty_image_made, restart="temporary")])
    try:
        sup.start()
        started = sup.which_children()
    finally:
        sup.stop()
    assert [name] == [child.name for child in started]


def test_a_stop_with_no_time_left_stops_the_registrar_with_no_config_error(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A `Stop` whose bound ran out (0 s) stops the registrar with the least time a stop
    takes (1 ms): its deadline passed is not a `timeout=0`, which `ConfigError` rejected,
    logged as "did not stop cleanly" with its traceback, the exit code 1."""
    from rr_actors._process import child, control  # noqa: PLC0415 - the module under test

    exits: list[int] = []
    monkeypatch.setattr(child, "_exit", lambda code, _attached: exits.append(code))
    registrar = rr.ResourceRegistrar.start("stopped-at-once")
    given: list[float | None] = []
    stop = registrar.stop

    def recorded(timeout: float | None = None) -> None:  # (the least time, but a real stop:
        given.append(timeout)  # one that took over 1 ms on a loaded machine would be
        stop(timeout=10.0)  # "not clean", and is not what this test is of)

    monkeypatch.setattr(registrar, "stop", recorded)
    line, sent = event_line(hold=0.0)
    loop = child._ControlLoop(None, sent, registrar, None, threading.Event(), line)  # type: ignore[arg-type]
    loop.stop(control.Stop(0.0))

    assert ([control.STOPPED_EXIT], [], [0.001]) == (exits, caplog.records, given)
    assert not registrar.is_alive()
