"""Tests of `rr_actors/_registrar/messages.py`: a message whose text field holds something else is
refused, not fatal (`misfit`).
"""

from __future__ import annotations

import pickle
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core import runtime
from rr_actors._core.replies import FutureReply, wait
from rr_actors._registrar import messages
from rr_actors._registrar.messages import Load
from rr_actors.testing import MemoryNetwork, catalog_snapshot

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
        self, make_registrar, serve, arguments, named
    ):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        leaf = serve(provider, "leaf")
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
    """A `Load`'s deadline crosses as the seconds left (issue 53): each process reads it
    on its own monotonic clock, which no other process's clock is compared with."""

    def test_it_crosses_as_the_seconds_left_and_arrives_on_the_receivers_clock(
        self, monkeypatch: pytest.MonkeyPatch
    ):
        monkeypatch.setattr(runtime, "monotonic", lambda: 1000.0)  # the sender's clock
        load = Load("q", "leaf", "x", "consumer", (), FutureReply(), deadline=1002.5)
        pickled = pickle.dumps(load.detached())
        monkeypatch.setattr(runtime, "monotonic", lambda: 7.0)  # the receiver's
        arrived = pickle.loads(pickled)
        assert 9.5 == arrived.deadline  # 2.5 s left, as when it left
        assert ("q", "x", None) == (arrived.query_id, arrived.request, arrived.reply)

    def test_a_load_without_a_deadline_crosses_without_one(self):
        load = Load("q", "leaf", "x", "consumer", (), FutureReply())
        assert pickle.loads(pickle.dumps(load.detached())).deadline is None
