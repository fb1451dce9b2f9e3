"""Tests of `rr_actors/_registrar/messages.py`: a message whose text field holds something else is
refused, not fatal (the registrar actor's `_misfit`).
"""

from __future__ import annotations

import pickle
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core import runtime, wire
from rr_actors._core.replies import FutureReply, wait
from rr_actors._registrar import messages
from rr_actors._registrar.messages import Load
from rr_actors.testing import MemoryNetwork, catalog_snapshot, intercept

# -- for TestBadNames ----------------------------------------------------------------------

Method = Callable[[Any, Any], object]


class TestBadNames:
    """A name or an id that is not a str is refused with a `ConfigError`; no registrar dies of it.

    A careless caller (`unload(["id"])`, `call(provider, None, ...)`) and a buggy peer in
    another process (a raw `Load` whose server is `None`) used to make a registrar die of a
    `TypeError` deep in a handler (an unhashable id, `difflib` reading a name): the provider
    of every other consumer with it.
    """

    @pytest.mark.parametrize(
        ("arguments", "named"),
        [
            ({"target_rr": 5}, "target_rr"),
            ({"server": None}, "server"),
            ({"server": 5}, "server"),
            ({"query_id": ["not", "hashable"]}, "query_id"),
            ({"query_id": ""}, "query_id"),
        ],
        ids=["target_rr-int", "server-None", "server-int", "query_id-list", "query_id-empty"],
    )
    def test_a_call_with_a_name_or_id_that_is_not_a_str_is_a_config_error_naming_it(
        self, served_pair, serve, arguments, named
    ):
        provider, consumer, leaf = served_pair
        call: dict[str, Any] = {"target_rr": provider.name, "server": "leaf", **arguments}

        with pytest.raises(rr.ConfigError, match=named):
            consumer.call(call.pop("target_rr"), call.pop("server"), "x", timeout=10, **call)

        assert ([], ()) == (leaf.loads, catalog_snapshot(consumer).clients)
        assert "x" == consumer.call(provider.name, "leaf", "x", timeout=10).request  # both serve

    @pytest.mark.parametrize(
        ("method", "named"),
        [
            (lambda r, bad: r.unload(bad, timeout=10), "query_id"),
            (lambda r, bad: r.send_status(bad, rr.Status.FATAL, "", timeout=10), "query_id"),
            (lambda r, bad: r.update_response(bad, "new", timeout=10), "query_id"),
            (lambda r, bad: r.set_status_callback(bad, print, timeout=10), "query_id"),
            (lambda r, bad: r.server_queries(bad, timeout=10), "server"),
            (lambda r, bad: r.unregister_server(bad, timeout=10), "name"),
            (lambda r, bad: r.fetch_queries(r.name, bad, timeout=10), "server"),
        ],
        ids=[
            "unload",
            "send_status",
            "update_response",
            "set_status_callback",
            "server_queries",
            "unregister_server",
            "fetch_queries",
        ],
    )
    def test_an_unhashable_id_or_name_is_a_config_error_and_the_registrar_keeps_what_it_holds(
        self, make_registrar, serve, method: Method, named: str
    ):
        provider = make_registrar("provider")
        serve(provider, "leaf")
        held = provider.call(provider.name, "leaf", "x", timeout=10)
        before = catalog_snapshot(provider)

        with pytest.raises(rr.ConfigError, match=named):
            method(provider, ["not", "hashable"])

        assert before == catalog_snapshot(provider)
        provider.send_status(held.id, rr.Status.ERROR, "still serving", timeout=10)

    @pytest.fixture
    def memory_provider(self) -> Iterator[tuple[MemoryNetwork, rr.ResourceRegistrar]]:
        """A provider registrar served on an in-memory network (as if in a process of its own)."""
        network = MemoryNetwork(f"bad-names-{uuid.uuid4().hex[:8]}")
        provider = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=f"provider-{uuid.uuid4().hex[:8]}"), network=network
        )
        try:
            provider.register_server("leaf", load=lambda r: r, unload=lambda _r, _s: None)
            yield network, provider
        finally:
            provider.stop()
            network.close()

    @pytest.mark.parametrize(
        ("fields", "named"),
        [({"server": None}, "server"), ({"query_id": ["a"]}, "query_id")],
        ids=["server-None", "query_id-list"],
    )
    def test_a_load_from_another_process_with_a_field_of_the_wrong_type_is_refused(
        self,
        memory_provider: tuple[MemoryNetwork, rr.ResourceRegistrar],
        fields: dict[str, Any],
        named,
    ) -> None:
        network, provider = memory_provider
        load: dict[str, Any] = {"query_id": "q-1", "server": "leaf", "origin_rr": "peer", **fields}
        reply = FutureReply()
        peer = network.resolve(provider.name)
        assert peer is not None

        peer.tell(Load(load["query_id"], load["server"], "x", load["origin_rr"], (), reply))

        with pytest.raises(rr.ConfigError, match=named):
            wait(reply.future, 10, "the hostile load")
        assert "x" == provider.call(provider.name, "leaf", "x", timeout=10).response  # serving

    def test_a_status_message_that_is_not_a_str_is_a_config_error_and_nobody_hears_it(
        self, make_registrar, serve, inbox
    ):
        provider = make_registrar("provider")
        serve(provider, "leaf")
        heard = inbox()
        held = provider.call(provider.name, "leaf", "x", on_status=heard, timeout=10)

        with pytest.raises(rr.ConfigError, match="message"):
            provider.send_status(held.id, rr.Status.ERROR, 12345, timeout=10)  # type: ignore[arg-type]

        provider.send_status(held.id, rr.Status.ERROR, "a str", timeout=10)
        assert ["a str"] == [u.message for _, u in heard.updates]  # (events.jsonl stays readable)

    def test_settle_in_doubt_with_an_unhashable_id_is_a_config_error_and_the_registrar_serves(self):
        registrar = rr.ResourceRegistrar.start(f"settler-{uuid.uuid4().hex[:8]}")
        try:
            with pytest.raises(rr.ConfigError, match="query_id"):
                registrar.settle_in_doubt(["not", "hashable"])  # type: ignore[arg-type]

            assert [] == registrar.client_queries(timeout=10)
        finally:
            registrar.stop()


# -- load_error -------------------------------------------------------------------------------


class UnprintableError(Exception):
    """An exception whose `str()` raises (a careless `__str__`, user code like any other)."""

    def __str__(self) -> str:
        raise ValueError("no text for this error")


class TestLoadError:
    """Whatever `load` raises fails the call with `ResourceLoadError` (rule 4), even an
    exception whose `str()` raises."""

    def test_a_load_that_raises_an_exception_whose_str_raises_fails_the_call_and_loads_again(
        self, make_registrar, shared
    ):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        loads = shared.list()

        def load(request: Any) -> Any:
            loads.append(request)
            if len(loads) == 1:
                raise UnprintableError()
            return "loaded"

        provider.register_server("flaky", load=load, unload=lambda _r, _s: None, timeout=10)

        with pytest.raises(rr.ResourceLoadError) as failed:
            consumer.call(provider.name, "flaky", "x", timeout=5)

        assert "UnprintableError" == failed.value.stack[-1].exc_type
        assert "loaded" == consumer.call(provider.name, "flaky", "x", timeout=5).response
        assert ["x", "x"] == loads  # the failed load left nothing loading


# -- check_picklable -------------------------------------------------------------------------


def test_small_builtin_data_is_known_picklable_without_pickling_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def refuse(value: Any) -> bytes:
        raise TypeError("pickled")

    monkeypatch.setattr(messages.cloudpickle, "dumps", refuse)
    messages.check_picklable({"server": "edge/resource", "request": ("shared-2", 1)}, "it")
    with pytest.raises(rr.ConfigError, match="it cannot be pickled, so the catalog"):
        messages.check_picklable({"at": uuid.UUID(int=1)}, "it")  # (not builtin data)


class TestLoadDeadline:
    """A `Load`'s deadline crosses (issue 53) as itself to a process that reads the same
    monotonic clock (the platform names it), else as the seconds left, read on the
    receiver's own clock, which no other host's clock is compared with."""

    @pytest.mark.parametrize("clocks", [("host-a", "host-b"), (None, None)], ids=["two", "unnamed"])
    def test_to_another_clock_it_crosses_as_the_seconds_left_and_arrives_on_the_receivers(
        self, monkeypatch: pytest.MonkeyPatch, clocks: tuple[str | None, str | None]
    ):
        monkeypatch.setattr(messages, "_CLOCK", clocks[0])  # the sender's
        monkeypatch.setattr(runtime, "monotonic", lambda: 1000.0)
        load = Load("q", "leaf", "x", "consumer", (), FutureReply(), deadline=1002.5)
        pickled = pickle.dumps(load.detached())
        monkeypatch.setattr(messages, "_CLOCK", clocks[1])  # the receiver's
        monkeypatch.setattr(runtime, "monotonic", lambda: 7.0)
        arrived = pickle.loads(pickled)
        assert 9.5 == arrived.deadline  # 2.5 s left, as when it left
        assert ("q", "x", None) == (arrived.query_id, arrived.request, arrived.reply)
        assert "clock" not in arrived.__dict__

    def test_on_one_clock_it_crosses_as_itself_its_time_on_the_way_counted(
        self, monkeypatch: pytest.MonkeyPatch
    ):
        monkeypatch.setattr(messages, "_CLOCK", "host-a")
        monkeypatch.setattr(runtime, "monotonic", lambda: 1000.0)
        load = Load("q", "leaf", "x", "consumer", (), FutureReply(), deadline=1002.5)
        pickled = pickle.dumps(load.detached())
        monkeypatch.setattr(runtime, "monotonic", lambda: 1004.0)  # 4 s in a pipe
        arrived = pickle.loads(pickled)
        assert 1002.5 == arrived.deadline  # passed: its caller gave up on the way
        assert "clock" not in arrived.__dict__

    def test_a_load_without_a_deadline_crosses_without_one(self):
        load = Load("q", "leaf", "x", "consumer", (), FutureReply())
        assert pickle.loads(pickle.dumps(load.detached())).deadline is None

    @pytest.mark.across_processes("the load waits in the pipe between two processes")
    @pytest.mark.not_zenoh("holds the link's reading thread: Zenoh's would miss its lease")
    @pytest.mark.skipif(messages._CLOCK is None, reason="the platform names no clock")
    def test_a_load_whose_caller_gave_up_while_it_waited_in_the_pipe_never_runs(
        self, make_registrar, gates, shared
    ):
        """Its time in the pipe counts (issue 53): the provider's thread that reads the
        link is held while the load waits behind it, past its caller's timeout; when the
        provider reads it, it is shed and its `load` never runs. The caller's `Abandon`
        (which withdraws a load not yet started) is held back meanwhile, so the deadline
        alone decides, as when a load races its `Abandon` to a free worker."""
        provider = make_registrar("provider", max_workers=2)
        consumer = make_registrar("consumer")
        holding, release, giving_up, proceed = gates(), gates(), gates(), gates()
        started = shared.list()

        def load(request: Any) -> Any:
            started.append(request)
            return request

        def hold_back_the_abandon(registrar: Any) -> None:
            def before(query: Any) -> None:  # (the caller's thread, as it gives up)
                if query.request == "late":
                    giving_up.set()
                    proceed.wait(30)

            intercept(registrar, "withdraw", before=before)

        provider.register_server("leaf", load=load, unload=lambda r, s: None)
        consumer.run(hold_back_the_abandon, timeout=10)
        holder = HoldsTheReader(provider.name, holding, release)
        with ThreadPoolExecutor(2) as pool:
            held = pool.submit(consumer.call, provider.name, "leaf", holder, timeout=60)
            assert holding.wait(30)  # the link's reader unpickles it: the next load waits
            late = pool.submit(consumer.call, provider.name, "leaf", "late", timeout=0.5)
            assert giving_up.wait(30)  # its caller gave up; the load is still in the pipe
            release.set()
            assert "holder" == held.result(timeout=30).response
            # a load sent after it has run, so it would have run before
            assert "next" == consumer.call(provider.name, "leaf", "next", timeout=30).response
            proceed.set()
            with pytest.raises(rr.CallTimeoutError):
                late.result(timeout=30)
        assert ["holder", "next"] == list(started)
        assert 2 == len(provider.server_queries("leaf")) == len(consumer.client_queries())


class HoldsTheReader:
    """A request whose unpickling, in the process that serves registrar `provider`, holds
    the thread that reads the link it came by until `release` is set (`holding` set
    meanwhile): the messages behind it wait in the pipe. Elsewhere it unpickles as itself."""

    def __init__(self, provider: str, holding: Any, release: Any) -> None:
        self.provider, self.holding, self.release = provider, holding, release

    def __reduce__(self) -> Any:
        return (_hold_the_reader, (self.provider, self.holding, self.release))


def _hold_the_reader(provider: str, holding: Any, release: Any) -> Any:
    from rr_actors._core.directory import DIRECTORY  # noqa: PLC0415

    if not any(peer.name == provider for peer in DIRECTORY.local_peers()):
        return HoldsTheReader(provider, holding, release)
    holding.set()
    release.wait(30)
    return "holder"


def test_a_reconciles_answer_crosses_as_a_wire_type_by_the_c_pickler() -> None:
    answer = messages.Reconciled(("q-1", "q-2"), "life-1")

    assert wire.plain(answer)  # (so no cloudpickle pass, as every message)
    assert answer == pickle.loads(wire.dumps(answer))
