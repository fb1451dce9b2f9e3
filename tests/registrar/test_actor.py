"""Tests of `rr_actors/_registrar/actor.py`: the one dispatch table, and every step in it fires."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.replies import FutureReply
from rr_actors._registrar import Served, life
from rr_actors._registrar.actor import DISPATCH, MESSAGE_STEPS
from rr_actors._registrar.messages import (
    Abandon,
    ConsumerDown,
    KeptUnclaimed,
    PeersStopped,
    RunOnActor,
    StatusBatch,
)
from rr_actors._registrar.state import POINTS
from rr_actors.testing import (
    STEPS,
    actor_ref,
    catalog_snapshot,
    crash,
    expect_restart,
    intercept,
    run_on_actor,
)

# -- for TestMessages ----------------------------------------------------------------------

Hook = Callable[[object], None]


class Pair:
    """A provider with a `leaf` server and a consumer, both in this process."""

    def __init__(self, tmp_path: Path) -> None:
        uid = uuid.uuid4().hex[:8]
        self.tmp_path = tmp_path
        self.started: list[rr.ResourceRegistrar] = []
        self.provider = self.start(f"prov-{uid}")
        self.consumer = self.start(f"cons-{uid}")
        self.provider.register_server("leaf", load=lambda r: f"got {r}", unload=_no_unload)

    def start(self, config: rr.RegistrarConfig | str, **kwargs: object) -> rr.ResourceRegistrar:
        registrar = rr.ResourceRegistrar.start(config, **kwargs)  # type: ignore[arg-type]
        self.started.append(registrar)
        return registrar

    def held(self) -> rr.Query:
        """A query the consumer holds at the provider's `leaf`."""
        return self.consumer.call(self.provider.name, "leaf", uuid.uuid4().hex)

    def close(self) -> None:
        for registrar in reversed(self.started):
            registrar.stop()


def _no_unload(_request: object, _response: object) -> None:
    return None


def _raise(request: object) -> object:
    raise ValueError(f"no {request}")


def _load(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "load", before=hook)
    p.held()


def _unload(p: Pair, hook: Hook) -> None:
    query = p.held()
    intercept(p.provider, "unload", before=hook)
    p.consumer.unload(query.id)


def _abandon(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "abandon", before=hook)
    DIRECTORY.lookup(p.provider.name).tell(Abandon("no-such-id", p.consumer.name))


def _fetch(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "fetch", before=hook)
    p.consumer.fetch_queries(p.provider.name, "leaf")


def _status_notice(p: Pair, hook: Hook) -> None:
    query = p.held()
    intercept(p.consumer, "status_notice", before=hook)
    p.provider.send_status(query.id, rr.Status.WARNING, "hot")


def _status_batch(p: Pair, hook: Hook) -> None:
    # (a provider sends one to a registrar of another process; here, told directly)
    query = p.held()
    intercept(p.consumer, "status_batch", before=hook)
    answer = FutureReply()
    batch = StatusBatch(
        ((p.consumer.name, (query.id,)),), rr.Status.OK, "", f"{p.provider.name}/leaf", "e", answer
    )
    DIRECTORY.lookup(p.consumer.name).tell(batch)
    answer.future.get(timeout=5)


def _revoke(p: Pair, hook: Hook) -> None:
    p.held()
    intercept(p.consumer, "revoke", before=hook)
    p.provider.unregister_server("leaf")


def _response_updated(p: Pair, hook: Hook) -> None:
    query = p.held()
    intercept(p.consumer, "response_updated", before=hook)
    p.provider.update_response(query.id, "new")


def _consumer_down(p: Pair, hook: Hook) -> None:
    p.held()
    intercept(p.provider, "consumer_down", before=hook)
    # the wire mark of another process's death watch (one of this process is `peer_lost`)
    DIRECTORY.lookup(p.provider.name).tell(ConsumerDown(p.consumer.name))


def _reconcile(p: Pair, hook: Hook) -> None:
    p.held()
    intercept(p.provider, "reconcile", before=hook)
    Served(p.consumer).listening()  # reachable: it tells its providers what it holds


def _reconcile_ask(p: Pair, hook: Hook) -> None:
    p.held()
    intercept(p.consumer, "reconcile_ask", before=hook)
    Served(p.provider).listening()  # reachable: it asks its consumers what they hold


def _lost_everything(p: Pair, hook: Hook) -> None:
    p.held()
    intercept(p.consumer, "lost_everything", before=hook)
    # its supervisor restarted it without a backup: it reconciles with everyone
    life.lost_everything(p.consumer.name)


def _client_loaded(p: Pair, hook: Hook) -> None:
    intercept(p.consumer, "client_loaded", before=hook)
    p.held()
    p.consumer.client_queries()  # (the answer is recorded before the next message)


def _call_failed(p: Pair, hook: Hook) -> None:
    p.provider.register_server("broken", load=_raise, unload=_no_unload)
    intercept(p.consumer, "call_failed", before=hook)
    with pytest.raises(rr.ResourceLoadError):
        p.consumer.call(p.provider.name, "broken", "x")


def _take_outcomes(p: Pair, hook: Hook) -> None:
    p.provider.register_server("broken", load=_raise, unload=_no_unload)
    intercept(p.consumer, "take_outcomes", before=hook)
    with pytest.raises(rr.ResourceLoadError):  # a failure wakes the consumer at once
        p.consumer.call(p.provider.name, "broken", "x")


def _answer(p: Pair, hook: Hook) -> None:
    query = p.held()
    intercept(p.consumer, "answer", before=hook)  # the provider's answer to its Unload
    p.consumer.unload(query.id)


def _flush(p: Pair, hook: Hook) -> None:
    config = rr.RegistrarConfig(
        name=f"flushing-{uuid.uuid4().hex[:8]}",
        backup_path=p.tmp_path / "f.db",
        save_on_modify=False,
        save_interval=0.05,
    )
    intercept(p.start(config), "flush", before=hook)


def _crash(p: Pair, hook: Hook) -> None:
    intercept(p.consumer, "crash", before=hook)
    crash(p.consumer)


def _register_server(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "register_server", before=hook)
    p.provider.register_server("other", load=str, unload=_no_unload)


def _unregister_server(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "unregister_server", before=hook)
    p.provider.unregister_server("leaf")


def _release(p: Pair, hook: Hook) -> None:
    query = p.held()
    intercept(p.consumer, "release", before=hook)
    p.consumer.unload(query.id)


def _send_status(p: Pair, hook: Hook) -> None:
    query = p.held()
    intercept(p.provider, "send_status", before=hook)
    p.provider.send_status(query.id, rr.Status.OK)


def _server_queries(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "server_queries", before=hook)
    p.provider.server_queries("leaf")


def _client_queries(p: Pair, hook: Hook) -> None:
    intercept(p.consumer, "client_queries", before=hook)
    p.consumer.client_queries()


def _set_status_callback(p: Pair, hook: Hook) -> None:
    query = p.held()
    intercept(p.consumer, "set_status_callback", before=hook)
    p.consumer.set_status_callback(query.id, lambda _q, _u: None)


def _update_response(p: Pair, hook: Hook) -> None:
    query = p.held()
    intercept(p.provider, "update_response", before=hook)
    p.provider.update_response(query.id, "new")


def _settle_in_doubt(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "settle_in_doubt", before=hook)
    p.provider.settle_in_doubt()  # nothing in doubt: settling all of it does nothing


def _save(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "save", before=hook)
    p.provider.save_catalog()


def _stop(p: Pair, hook: Hook) -> None:
    intercept(p.consumer, "stop", before=hook)
    p.consumer.stop()


def _ready(p: Pair, hook: Hook) -> None:
    p.start(
        f"setup-{uuid.uuid4().hex[:8]}",
        setup=lambda registrar: intercept(registrar, "ready", before=hook),
    )


def _reachable(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "reachable", before=hook)
    Served(p.provider).listening()


def _peer_lost(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "peer_lost", before=hook)
    Served(p.provider).peer_lost(p.consumer.name)


def _peers_stopped(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "peers_stopped", before=hook)
    p.provider.tell(PeersStopped((p.consumer.name,)))  # (as its supervisor, the tree's stop)


def _peer_reachable(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "peer_reachable", before=hook)
    Served(p.provider).peer_reachable(p.consumer.name)


def _reconcile_retry(p: Pair, hook: Hook) -> None:
    p.held()
    with expect_restart(p.provider.name):  # (no death watch: it may come back)
        crash(p.provider)
    intercept(p.consumer, "reconcile_retry", before=hook)
    Served(p.consumer).peer_reachable(p.provider.name)  # it cannot answer: retried


def _kept_unclaimed(p: Pair, hook: Hook) -> None:
    intercept(p.consumer, "kept_unclaimed", before=hook)
    DIRECTORY.lookup(p.consumer.name).tell(KeptUnclaimed(p.provider.name, ("no-such-id",)))


def _yield_name(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "yield_name", before=hook)
    Served(p.provider).yield_name("another registrar of its name is kept (a test)")


def _keep_name(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "keep_name", before=hook)
    Served(p.provider).keep_name(FutureReply())  # (not yielding: it answers False)


def _snapshot(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "snapshot", before=hook)
    catalog_snapshot(p.provider)


def _ping(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "ping", before=hook)
    pong = FutureReply()
    p.provider._actor.ping(pong)  # a manager process's heartbeat
    assert pong.future.get(timeout=5) is None


def _open_client(p: Pair, hook: Hook) -> None:
    intercept(p.consumer, "open_client", before=hook)
    p.held()  # the first call to a server starts its client


def _run_on_actor(p: Pair, hook: Hook) -> None:
    intercept(p.provider, "run_on_actor", before=hook)
    run_on_actor(p.provider, lambda: None).get(timeout=5)


DRIVERS: dict[str, Callable[[Pair, Hook], None]] = {
    "load": _load,
    "unload": _unload,
    "abandon": _abandon,
    "fetch": _fetch,
    "status_notice": _status_notice,
    "status_batch": _status_batch,
    "revoke": _revoke,
    "response_updated": _response_updated,
    "consumer_down": _consumer_down,
    "reconcile": _reconcile,
    "reconcile_ask": _reconcile_ask,
    "lost_everything": _lost_everything,
    "client_loaded": _client_loaded,
    "call_failed": _call_failed,
    "take_outcomes": _take_outcomes,
    "answer": _answer,
    "flush": _flush,
    "crash": _crash,
    "register_server": _register_server,
    "unregister_server": _unregister_server,
    "release": _release,
    "send_status": _send_status,
    "server_queries": _server_queries,
    "client_queries": _client_queries,
    "set_status_callback": _set_status_callback,
    "update_response": _update_response,
    "settle_in_doubt": _settle_in_doubt,
    "save": _save,
    "stop": _stop,
    "ready": _ready,
    "reachable": _reachable,
    "peer_lost": _peer_lost,
    "peer_reachable": _peer_reachable,
    "peers_stopped": _peers_stopped,
    "reconcile_retry": _reconcile_retry,
    "kept_unclaimed": _kept_unclaimed,
    "yield_name": _yield_name,
    "keep_name": _keep_name,
    "snapshot": _snapshot,
    "ping": _ping,
    "open_client": _open_client,
    "run_on_actor": _run_on_actor,
}


class TestMessages:
    """The registrar's vocabulary as data: one dispatch table, and every step name in it fires.

    `intercept` accepts the step names of the actor's dispatch table; each test below makes a
    registrar handle one message, through the public API where one reaches it, and checks
    that a hook on that message's step ran. A message added to the table without a way to
    reach it here fails `test_every_message_step_has_a_driver_here`.
    """

    @pytest.fixture
    def pair(self, tmp_path: Path) -> Iterator[Pair]:
        made = Pair(tmp_path)
        yield made
        made.close()

    def test_the_message_steps_are_the_step_names_of_the_dispatch_table(self) -> None:
        names = [step for step, _ in DISPATCH.values()]

        assert len(set(names)) == len(names)  # one step per message, none shared
        assert frozenset(names) == MESSAGE_STEPS
        assert MESSAGE_STEPS | POINTS == STEPS
        assert not MESSAGE_STEPS & POINTS

    def test_every_message_step_has_a_driver_here(self) -> None:
        assert sorted(MESSAGE_STEPS) == sorted(DRIVERS)

    @pytest.mark.parametrize("step", sorted(DRIVERS))
    def test_intercept_on_a_message_step_runs_its_hook_when_that_message_is_handled(
        self, pair: Pair, step: str
    ) -> None:
        fired = threading.Event()
        seen: list[type] = []

        def hook(message: object) -> None:
            seen.append(type(message))
            fired.set()

        DRIVERS[step](pair, hook)

        assert fired.wait(5.0)
        kinds = [kind for kind, (name, _) in DISPATCH.items() if name == step]
        assert kinds == seen[:1]  # the hook saw the message of that table entry

    def test_a_second_call_to_a_server_finds_its_client_without_asking_the_actor(
        self,
        pair: Pair,
    ) -> None:
        opened: list[object] = []
        intercept(pair.consumer, "open_client", before=opened.append)

        pair.held()
        pair.held()

        assert 1 == len(opened)
        assert actor_ref(pair.consumer, client=(pair.provider.name, "leaf")).is_alive()


# -- the record -----------------------------------------------------------------------------


def _parts(actor: Any, reply: Any) -> None:
    """Each part in the actor's record, with the other parts it holds itself (none: it
    reaches them through the record), and whether the record is what it holds."""
    record = actor.shared
    parts = {name: part for name, part in vars(record).items() if hasattr(part, "registrar")}
    names = {id(part): name for name, part in parts.items()}
    reply.set_result(
        {
            name: (
                part.registrar is record,
                sorted(names[id(v)] for v in vars(part).values() if id(v) in names),
            )
            for name, part in parts.items()
        }
    )


def test_each_part_of_a_registrar_holds_its_record_and_no_other_part() -> None:
    registrar = rr.ResourceRegistrar.start(f"record-{uuid.uuid4().hex[:8]}")
    try:
        reply = FutureReply()
        actor_ref(registrar).tell(RunOnActor(_parts, reply))
        held: dict[str, tuple[bool, list[str]]] = reply.future.get(timeout=5)
    finally:
        registrar.stop()
    assert len(held) >= 13  # (the actor built each from the record, and put it there)
    assert {name: (True, []) for name in held} == held


FIRST_START = textwrap.dedent(
    """
    import rr_actors._registrar  # (what a forkserver preloads)
    from rr_actors._registrar import start_registrar
    from rr_actors._registrar.messages import text_fields
    from rr_actors.config import RegistrarConfig

    before = text_fields.cache_info().misses
    registrar = start_registrar(RegistrarConfig(name="first"))
    registrar.stop(timeout=10)
    print(text_fields.cache_info().misses - before)
    """
)


def test_the_first_registrar_of_a_process_walks_no_message_fields_its_imports_did() -> None:
    # issue 69 goal 3: each manager process's registrar walked the fields of its 42
    # message kinds (a forked process's cache starts as its forkserver's, empty)
    result = subprocess.run(
        [sys.executable, "-c", FIRST_START],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )

    assert (0, "0\n") == (result.returncode, result.stdout), result.stderr


# -- what one call runs (issue 71 item 5: `benchmarks/call_files.py`) -----------------------


def _files_of_a_dedup_hit(tmp_path: Path) -> set[str]:
    """The source files every thread ran during one dedup-hit call from a registrar of this
    process to a durable one (the registrars' threads traced from their start)."""
    seen: set[str] = set()

    def profile(frame: FrameType, event: str, _arg: object) -> None:
        if event == "call":
            seen.add(frame.f_code.co_filename)

    tag = uuid.uuid4().hex[:8]
    threading.setprofile(profile)  # (the threads started from now on)
    sys.setprofile(profile)
    try:
        provider = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(
                name=f"hit-p-{tag}", backup_path=tmp_path / "p.db", save_on_modify=True
            )
        )
        consumer = rr.ResourceRegistrar.start(f"hit-c-{tag}")
        try:
            provider.register_server("res", load=lambda r: r, unload=lambda r, s: None)
            for _ in range(2):  # (the load, then a first hit)
                consumer.call(provider.name, "res", "x", timeout=10)
            seen.clear()
            consumer.call(provider.name, "res", "x", timeout=10)
            return set(seen)
        finally:
            consumer.stop(timeout=10)
            provider.stop(timeout=10)
    finally:
        sys.setprofile(None)
        threading.setprofile(None)


@pytest.mark.parametrize(
    "module",
    [
        "rr_actors/_registrar/messages.py",  # (the text-field check is the dispatch's own)
        "rr_actors/_catalog/records.py",  # (a turn's changes are `None` or not empty)
        "rr_actors/_core/queues.py",  # (the outcome's `LateQueue` is the actor module's)
    ],
)
def test_a_dedup_hit_to_a_durable_registrar_of_this_process_runs_no_code_of(
    module: str, tmp_path: Path
) -> None:
    ran = _files_of_a_dedup_hit(tmp_path)
    assert [] == sorted(path for path in ran if Path(path).as_posix().endswith(module))


def test_a_registrar_start_runs_no_code_of_the_log_throttle(tmp_path: Path) -> None:
    # (what a restarted manager's start builds: the throttle of unknown messages comes at
    # the first one, `RegistrarActor.unknown`)
    seen: set[str] = set()

    def profile(frame: FrameType, event: str, _arg: object) -> None:
        if event == "call":
            seen.add(Path(frame.f_code.co_filename).as_posix())

    threading.setprofile(profile)
    sys.setprofile(profile)
    try:
        config = rr.RegistrarConfig(
            name=f"start-{uuid.uuid4().hex[:8]}", backup_path=tmp_path / "s.db"
        )
        registrar = rr.ResourceRegistrar.start(config)
        registrar.register_server("res", load=lambda r: r, unload=lambda r, s: None)
    finally:
        sys.setprofile(None)
        threading.setprofile(None)
    registrar.stop(timeout=10)
    assert [] == sorted(path for path in seen if path.endswith("rr_actors/_core/throttle.py"))
