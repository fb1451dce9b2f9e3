"""Tests of `rr_actors/_registrar/status.py`: statuses sent, fanned out and climbing.

Rule 9 in every placement (`TestStatus`), one pass per process to many consumer
registrars (`TestFanout`), a status on its way as its consumer releases the id
(`TestReleaseCrossing`), and a status its consumer cannot take (`TestTooLarge`).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import threading
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import psutil
import pytest

import rr_actors as rr
from rr_actors._core import runtime
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.replies import FutureReply, let_go
from rr_actors._core.workers import Workers
from rr_actors._registrar.calls import CallAttempt
from rr_actors._registrar.messages import Ping, Unload
from rr_actors._registrar.status import Runner, _Call
from rr_actors.testing import STEPS, RemoteRegistrar, call_futures, catalog_snapshot, intercept
from tests.registrar.conftest import placement_network
from tests.support.waiting import wait_for

# -- for TestStatus ------------------------------------------------------------------------


def own_ids(inbox):
    """For each update an inbox got: (the query's id, the update's query_id)."""
    return [(query.id, update.query_id) for query, update in inbox.updates]


# -- for TestFanout ------------------------------------------------------------------------

PROCESSES = 3


REGISTRARS = 8  # per process


IDS = 2  # per registrar


STATUS_STEPS = [step for step in ("status_batch", "status_notice") if step in STEPS]


def host_setup(
    address: Any, provider: str, *, hang: bool = False, count: bool = False
) -> Callable[[rr.ResourceRegistrar], None]:
    """A manager's setup: REGISTRARS consumer registrars in its process, and `probe`.

    With `hang`, the callbacks of the first registrar's ids block at the first status
    until `probe` is asked to release them, and those of the second raise (after
    recording). With `count`, the status messages each registrar handles are counted,
    and once `probe` is asked to (`fail-next`), the next batch a registrar handles is
    answered with an error after it was delivered (a relay that fails after delivering).
    """

    def setup(host: rr.ResourceRegistrar) -> None:
        network = address.attach()  # (a carrier's `Address`: this process joined it already)
        lock = threading.Lock()
        heard: dict[str, list[str]] = collections.defaultdict(list)
        steps: collections.Counter[str] = collections.Counter()
        release = threading.Event()
        fail_next = threading.Event()
        consumers: list[rr.ResourceRegistrar] = []

        def fail_once(_message: object) -> None:
            with lock:
                failing = fail_next.is_set()
                fail_next.clear()
            if failing:
                raise rr.RrError("the relay fails after it delivered")

        def recorder(number: int) -> Callable[[rr.Query, rr.StatusUpdate], None]:
            def record(query: rr.Query, update: rr.StatusUpdate) -> None:
                with lock:
                    heard[query.id].append(update.message)
                    first = len(heard[query.id]) == 1
                if hang and number == 0 and first:
                    release.wait(30)
                if hang and number == 1:
                    raise RuntimeError("a consumer's bug")

            return record

        def counter(step: str) -> Callable[[object], None]:
            def counted(_message: object) -> None:
                with lock:
                    steps[step] += 1

            return counted

        for number in range(REGISTRARS):
            consumer = rr.ResourceRegistrar.start(f"{host.name}-c{number}", network=network)
            consumers.append(consumer)
            for step in STATUS_STEPS if count else ():
                intercept(consumer, step, before=counter(step))
            if count and "status_batch" in STATUS_STEPS:
                intercept(consumer, "status_batch", after=fail_once)
            for _ in range(IDS):
                consumer.call(provider, "leaf", "r", on_status=recorder(number), timeout=20)

        def probe(request: tuple[str, str]) -> Any:
            with lock:
                if request[0] == "heard":
                    return {query_id: list(said) for query_id, said in heard.items()}
                if request[0] == "steps":
                    return dict(steps)
            if request[0] == "release":
                release.set()
            elif request[0] == "fail-next":
                fail_next.set()
            elif request[0] == "stop":
                release.set()
                for consumer in reversed(consumers):
                    consumer.stop()
            return None

        host.register_server("probe", load=probe, unload=lambda _r, _s: None)

    return setup


class Fanout:
    """The provider here, and PROCESSES manager processes of consumer registrars."""

    def __init__(self, placement: str) -> None:
        self.network = placement_network(placement)
        self.uid = uuid.uuid4().hex[:8]
        self.provider = rr.ResourceRegistrar.start(f"prov-{self.uid}", network=self.network)
        self.provider.register_server("leaf", load=lambda r: r, unload=lambda _r, _s: None)
        self.hosts: list[RemoteRegistrar] = []
        self.query_id = ""

    def start(self, **kwargs: Any) -> Fanout:
        """Start the manager processes (`host_setup(**kwargs)` in each)."""
        setup = host_setup(self.network.address, self.provider.name, **kwargs)
        for number in range(PROCESSES):
            config = rr.RegistrarConfig(name=f"host{number}-{self.uid}", call_timeout=20.0)
            self.hosts.append(RemoteRegistrar.start(config, self.network, setup=setup))
        self.query_id = self.provider.server_queries("leaf")[0].id
        return self

    def send(
        self, message: str, *, timeout: float = 20.0, status: rr.Status = rr.Status.UPDATE
    ) -> rr.StatusDelivery:
        return self.provider.send_status(self.query_id, status, message, timeout=timeout)

    def ask(self, host: RemoteRegistrar, op: str) -> Any:
        return host.call(host.name, "probe", (op, uuid.uuid4().hex), timeout=20).response

    def heard(self) -> list[dict[str, list[str]]]:
        """What each process's consumer ids heard, by process."""
        return [self.ask(host, "heard") for host in self.hosts]

    def close(self) -> None:
        for host in self.hosts:
            with contextlib.suppress(rr.RrError):
                self.ask(host, "stop")
            host.stop()
        self.provider.stop()
        self.network.close()


def wait_heard(
    fanout: Fanout, done: Callable[[list[dict[str, list[str]]]], bool]
) -> list[dict[str, list[str]]]:
    """What was heard, once `done(heard)` (or once 15 s passed: then what was heard)."""
    heard: list[list[dict[str, list[str]]]] = [fanout.heard()]

    def read() -> bool:
        heard[0] = fanout.heard()
        return done(heard[0])

    wait_for(read, timeout=15.0)
    return heard[0]


# -- for TestReleaseCrossing ---------------------------------------------------------------


def _echo(request: object) -> object:
    return request


def _no_unload(_request: object, _response: object) -> None:
    return None


def _signalling(provider: rr.Registrar, signal: str) -> rr.StatusCallback:
    """A server's `on_status` that tells registrar `signal` each status's message (its server
    `seen` loads it), from the provider's process: the status was sent on by then."""

    def on_status(_query: rr.Query, update: rr.StatusUpdate) -> None:
        provider.call(signal, "seen", update.message, timeout=20)

    return on_status


def send(provider: rr.Registrar, query_id: str, message: str) -> None:
    provider.send_status(query_id, rr.Status.UPDATE, message, timeout=20)


def _hang(_request: object, _response: object) -> None:  # (past the provider's unload_timeout)
    threading.Event().wait(5)


class Crossing:
    """A provider in a manager process; here, a consumer and a relay registrar.

    Both hold one resource there, the relay's id first: once the provider knows they share
    a process, its statuses for them go to the relay as one batch, which a test holds back
    there (`intercept`) while the consumer releases its id. The relay's callback blocks on
    the status `"hold"` until `go` is set.
    """

    def __init__(self, placement: str) -> None:
        self.network = placement_network(placement)
        uid = uuid.uuid4().hex[:8]
        config = rr.RegistrarConfig(name=f"prov-{uid}", call_timeout=20.0, unload_timeout=1.0)
        self.provider = RemoteRegistrar.start(config, self.network)
        self.provider.register_server("leaf", load=_echo, unload=_no_unload)
        self.relay = rr.ResourceRegistrar.start(f"relay-{uid}", network=self.network)
        self.consumer = rr.ResourceRegistrar.start(f"cons-{uid}", network=self.network)
        self.heard: list[str] = []  # what the consumer's callback heard
        self.relay_heard: list[str] = []
        self.go = threading.Event()
        self.relay.call(self.provider.name, "leaf", "r", on_status=self.relayed, timeout=20)
        self.query = self.consumer.call(
            self.provider.name, "leaf", "r", on_status=self.record, timeout=20
        )
        self.send("warm-up")  # (the provider learns that both are in this process)

    def record(self, _query: rr.Query, update: rr.StatusUpdate) -> None:
        self.heard.append(update.message)

    def relayed(self, _query: rr.Query, update: rr.StatusUpdate) -> None:
        self.relay_heard.append(update.message)
        if update.message == "hold":
            self.go.wait(20)

    def send(self, message: str, status: rr.Status = rr.Status.UPDATE) -> None:
        self.provider.send_status(self.query.id, status, message, timeout=20)

    def close(self) -> None:
        self.go.set()
        for registrar in (self.consumer, self.relay, self.provider):
            with contextlib.suppress(rr.RrError):
                registrar.stop()
        self.network.close()


# -- for TestOneWay ------------------------------------------------------------------------


class Ways:
    """A provider in a manager process; here, a relay and a consumer registrar, both holding
    resource `"r"` there (the relay's id first: it is the one the provider picks as this
    process's relay). Nothing was sent yet: the provider does not know they share a process.
    What each one's callbacks hear is recorded by request (`heard[name][request]`).
    """

    def __init__(self, placement: str) -> None:
        self.network = placement_network(placement)
        uid = uuid.uuid4().hex[:8]
        config = rr.RegistrarConfig(name=f"prov-{uid}", call_timeout=20.0)
        self.provider = RemoteRegistrar.start(config, self.network)
        self.provider.register_server("leaf", load=_echo, unload=_no_unload)
        self.relay = rr.ResourceRegistrar.start(f"relay-{uid}", network=self.network)
        self.consumer = rr.ResourceRegistrar.start(f"cons-{uid}", network=self.network)
        self.heard: dict[str, dict[str, list[str]]] = collections.defaultdict(
            lambda: collections.defaultdict(list)
        )
        self.ids: dict[str, str] = {}  # request -> a consumer id of its resource
        self.hold("relay", "r")
        self.hold("consumer", "r")

    def hold(self, who: str, request: str) -> None:
        """Registrar `who` ("relay" or "consumer") calls for `request`, recording its statuses."""
        registrar = self.relay if who == "relay" else self.consumer
        said = self.heard[who][request]
        query = registrar.call(
            self.provider.name,
            "leaf",
            request,
            on_status=lambda _q, update: said.append(update.message),
            timeout=20,
        )
        self.ids.setdefault(request, query.id)

    def send(self, request: str, message: str) -> None:
        self.provider.send_status(self.ids[request], rr.Status.UPDATE, message, timeout=20)

    def close(self) -> None:
        for registrar in (self.consumer, self.relay, self.provider):
            with contextlib.suppress(rr.RrError):
                registrar.stop()
        self.network.close()


class Held:
    """Hooks that hold a registrar's actor at the status messages named, each until let go."""

    def __init__(self, *messages: str) -> None:
        self.reached = {message: threading.Event() for message in messages}
        self.go = {message: threading.Event() for message in messages}

    def __call__(self, message: Any) -> None:  # (the registrar's actor thread)
        if message.message in self.reached:
            self.reached[message.message].set()
            assert self.go[message.message].wait(20)

    def release(self) -> None:
        for go in self.go.values():
            go.set()


# -- for TestTooLarge ----------------------------------------------------------------------

LIMIT = 100_000


"""The consumer's `max_message_bytes`."""


class TestStatus:
    """Status notifications (DESIGN rule 9)."""

    pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)

    def test_status_reaches_every_consumer_with_its_own_query_id(
        self, make_registrar, serve, inbox
    ):
        provider, one, two = (make_registrar(n) for n in ("provider", "one", "two"))
        serve(provider, "leaf")
        boxes = [inbox() for _ in range(3)]
        queries = [
            one.call(provider.name, "leaf", "cam", on_status=boxes[0]),
            one.call(provider.name, "leaf", "cam", on_status=boxes[1]),
            two.call(provider.name, "leaf", "cam", on_status=boxes[2]),
        ]

        provider.send_status(queries[0].id, rr.Status.WARNING, "hot")

        for box, query in zip(boxes, queries, strict=True):
            assert [(query.id, query.id)] == own_ids(box)
        (_, update) = boxes[2].updates[0]
        assert (rr.Status.WARNING, "hot", f"{provider.name}/leaf") == (
            update.status,
            update.message,
            update.source,
        )

    def test_send_status_works_with_any_consumer_id_of_the_resource(self, served_pair, inbox):
        provider, consumer, _leaf = served_pair
        first, second = inbox(), inbox()
        consumer.call(provider.name, "leaf", "cam", on_status=first)
        q2 = consumer.call(provider.name, "leaf", "cam", on_status=second)

        provider.send_status(q2.id, rr.Status.OK, "")

        assert (1, 1) == (len(first.updates), len(second.updates))

    def test_the_provider_server_s_on_status_runs_once_per_status(self, make_registrar, serve):
        provider, one, two = (make_registrar(n) for n in ("provider", "one", "two"))
        leaf = serve(provider, "leaf")
        query = one.call(provider.name, "leaf", "cam")
        one.call(provider.name, "leaf", "cam")
        two.call(provider.name, "leaf", "cam")

        provider.send_status(query.id, rr.Status.ERROR, "broken")

        ((seen_query, update),) = leaf.statuses
        assert (query.id, query.id, rr.Status.ERROR) == (
            seen_query.id,
            update.query_id,
            update.status,
        )

    def test_status_climbs_the_dependency_chain_to_the_top_consumer(
        self, make_registrar, serve, inbox
    ):
        consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
        leaf = serve(producer, "leaf")
        composite = serve(
            agent, "composite", lambda r: agent.call(producer.name, "leaf", r).response
        )
        top = inbox()
        query = consumer.call(agent.name, "composite", "x", on_status=top)
        (leaf_query,) = producer.server_queries("leaf")

        producer.send_status(leaf_query.id, rr.Status.FATAL, "unplugged")

        assert 1 == len(leaf.statuses)
        assert 1 == len(composite.statuses)
        assert [(query.id, query.id)] == own_ids(top)
        (_, update) = top.updates[0]
        assert (rr.Status.FATAL, "unplugged", f"{producer.name}/leaf") == (
            update.status,
            update.message,
            update.source,
        )

    def test_status_climbs_every_path_and_each_callback_runs_once(
        self, make_registrar, serve, inbox
    ):
        """A diamond: top needs left and right, both need the same leaf."""
        consumer, provider, producer = (make_registrar(n) for n in ("consumer", "mid", "producer"))
        leaf = serve(producer, "leaf")
        left = serve(provider, "left", lambda r: provider.call(producer.name, "leaf", "shared").id)
        right = serve(
            provider, "right", lambda r: provider.call(producer.name, "leaf", "shared").id
        )

        def both(request):
            provider.call(provider.name, "left", request)
            provider.call(provider.name, "right", request)
            return "top"

        top = serve(provider, "top", both)
        box = inbox()
        query = consumer.call(provider.name, "top", "x", on_status=box)
        some_leaf_id = producer.server_queries("leaf")[0].id

        producer.send_status(some_leaf_id, rr.Status.WARNING, "drifting")

        assert [1, 1, 1, 1] == [len(s.statuses) for s in (leaf, left, right, top)]
        assert [(query.id, query.id)] == own_ids(box)

    def test_a_consumer_client_on_an_intermediate_dependency_hears_the_status(
        self, make_registrar, serve, inbox
    ):
        consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
        serve(producer, "leaf")
        middle = inbox()
        serve(
            agent,
            "composite",
            lambda r: agent.call(producer.name, "leaf", r, on_status=middle).response,
        )
        consumer.call(agent.name, "composite", "x")
        (leaf_query,) = producer.server_queries("leaf")

        producer.send_status(leaf_query.id, rr.Status.UPDATE, "new frame rate")

        assert [(leaf_query.id, leaf_query.id)] == own_ids(middle)

    def test_send_status_returns_after_every_callback_on_the_path_ran(
        self, make_registrar, serve, shared
    ):
        consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
        serve(producer, "leaf")
        serve(agent, "composite", lambda r: agent.call(producer.name, "leaf", r).response)
        ran = shared.event()

        def slow_callback(query, update):
            threading.Event().wait(0.2)  # work that takes a while
            ran.set()

        consumer.call(agent.name, "composite", "x", on_status=slow_callback)
        (leaf_query,) = producer.server_queries("leaf")

        producer.send_status(leaf_query.id, rr.Status.OK, "")

        assert ran.is_set()

    def test_send_status_gives_up_on_a_hung_callback_and_names_it(self, served_pair, gates, inbox):
        """Issue 53: a hung callback is given up on within the timeout, and named; the
        others were reached. Mutation caught: `send_status` waits for every callback
        (it raised `CallTimeoutError` for all of them)."""
        provider, consumer, _leaf = served_pair
        gate = gates()
        box = inbox()
        hung = consumer.call(provider.name, "leaf", "x", on_status=lambda q, u: gate.wait(30))
        heard = consumer.call(provider.name, "leaf", "x", on_status=box)
        try:
            first = provider.send_status(hung.id, rr.Status.OK, "1", timeout=2.0)
            second = provider.send_status(hung.id, rr.Status.OK, "2", timeout=2.0)
        finally:
            gate.set()

        expected = rr.StatusDelivery((heard.id,), (hung.id,))
        assert (expected, expected) == (first, second)
        assert ["1", "2"] == [update.message for _query, update in box.updates]

    @pytest.mark.thread_only("the loop a coroutine callback was registered from is here")
    def test_a_hung_coroutine_callback_is_given_up_on_a_hung_server_on_status_is_not(
        self, make_registrar
    ):
        """`send_status`'s docstring (review of the fan-out): a client's coroutine callback
        is given up on after the patience as a plain one is; a server's own `on_status`
        is not: it is waited for within the `timeout` (`CallTimeoutError`)."""
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        hang_server, gate = threading.Event(), threading.Event()

        def on_status(_query: rr.Query, _update: rr.StatusUpdate) -> None:
            if hang_server.is_set():
                gate.wait(30)

        provider.register_server("leaf", load=lambda r: r, unload=_no_unload, on_status=on_status)

        async def hung(_query: rr.Query, _update: rr.StatusUpdate) -> None:
            await asyncio.to_thread(gate.wait, 30)

        async def main() -> tuple[rr.StatusDelivery, BaseException | None]:
            query = await consumer.acall(provider.name, "leaf", "r", on_status=hung)
            send = functools.partial(provider.send_status, query.id, rr.Status.UPDATE)
            delivery = await asyncio.to_thread(send, "1", timeout=1.0)
            hang_server.set()
            try:
                await asyncio.to_thread(send, "2", timeout=0.5)
            except rr.CallTimeoutError as exc:
                return delivery, exc
            finally:
                gate.set()
            return delivery, None

        delivery, error = asyncio.run(main())

        assert ((), 1) == (delivery.reached, len(delivery.gave_up))
        assert isinstance(error, rr.CallTimeoutError)

    def test_a_status_callback_that_raises_does_not_stop_delivery(self, served_pair, inbox):
        provider, consumer, _leaf = served_pair

        def broken(query, update):
            raise RuntimeError("callback bug")

        box = inbox()
        query = consumer.call(provider.name, "leaf", "x", on_status=broken)
        consumer.call(provider.name, "leaf", "x", on_status=box)

        provider.send_status(query.id, rr.Status.OK, "")

        assert 1 == len(box.updates)

    def test_a_released_consumer_no_longer_hears_status(self, served_pair, inbox):
        provider, consumer, _leaf = served_pair
        gone, kept = inbox(), inbox()
        released = consumer.call(provider.name, "leaf", "x", on_status=gone)
        still = consumer.call(provider.name, "leaf", "x", on_status=kept)
        consumer.unload(released.id)

        provider.send_status(still.id, rr.Status.OK, "")

        assert ([], 1) == (gone.updates, len(kept.updates))

    def test_a_status_callback_may_call_unload_and_send_status_on_the_sender(
        self, served_pair, serve, shared
    ):
        provider, consumer, _leaf = served_pair
        serve(provider, "spare")
        done = shared.list()

        def reentrant(query, update):
            if update.status is rr.Status.WARNING:
                spare = consumer.call(provider.name, "spare", "backup", timeout=5)
                provider.send_status(spare.id, rr.Status.OK, "from a callback", timeout=5)
                consumer.unload(spare.id, timeout=5)
                another = provider.call(provider.name, "spare", "own", timeout=5)
                provider.unload(another.id, timeout=5)
                done.append(update.status)

        query = consumer.call(provider.name, "leaf", "x", on_status=reentrant)

        provider.send_status(query.id, rr.Status.WARNING, "", timeout=10)

        assert [rr.Status.WARNING] == done
        assert [] == provider.server_queries("spare")

    def test_a_server_on_status_may_call_its_own_registrar(self, make_registrar, shared):
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        provider.register_server("spare", load=lambda r: r, unload=lambda r, s: None)
        done = shared.list()

        def on_status(query, update):
            spare = provider.call(provider.name, "spare", "replacement", timeout=5)
            provider.unload(spare.id, timeout=5)
            done.append(query.id)

        provider.register_server(
            "leaf", load=lambda r: r, unload=lambda r, s: None, on_status=on_status
        )
        query = consumer.call(provider.name, "leaf", "x")

        provider.send_status(query.id, rr.Status.ERROR, "", timeout=10)

        assert [query.id] == done

    def test_a_status_callback_may_unload_the_resource_it_hears_about(self, served_pair):
        provider, consumer, leaf = served_pair

        def give_up(query, update):
            consumer.unload(query.id, timeout=5)

        query = consumer.call(provider.name, "leaf", "x", on_status=give_up)

        provider.send_status(query.id, rr.Status.FATAL, "dead", timeout=10)

        assert [("x", {"resource": "x"})] == leaf.unloads
        assert ((), ()) == (
            catalog_snapshot(provider).resources,
            catalog_snapshot(consumer).clients,
        )

    def test_send_status_for_an_unknown_id_raises(self, make_registrar, serve):
        provider = make_registrar("provider")
        serve(provider, "leaf")

        with pytest.raises(rr.UnknownQueryError):
            provider.send_status(str(uuid.uuid4()), rr.Status.OK, "")

    def test_only_the_provider_can_send_status_about_a_resource(self, served_pair):
        provider, consumer, _leaf = served_pair
        query = consumer.call(provider.name, "leaf", "x")

        with pytest.raises(rr.UnknownQueryError):
            consumer.send_status(query.id, rr.Status.OK, "")

    def test_a_consumer_sending_status_with_its_own_id_is_told_who_sends_it(self, served_pair):
        provider, consumer, _leaf = served_pair
        query = consumer.call(provider.name, "leaf", "x")

        with pytest.raises(rr.UnknownQueryError) as raised:
            consumer.send_status(query.id, rr.Status.WARNING, "low")

        assert (
            f"query id {query.id!r} is one {consumer.name!r} holds at {provider.name}/leaf, "
            f"not one it serves: only the provider, {provider.name!r}, sends statuses about it"
        ) == str(raised.value)

    def test_a_hung_callback_up_a_dependency_path_is_named_as_given_up(
        self, make_registrar, serve, gates
    ):
        """Issue 53: a callback given up on at hop 2 is named by the sender at hop 0; the
        dependency's own consumer id (hop 1) was reached. Mutation caught: the ids given
        up on beyond a notice are not carried back in its answer."""
        consumer, agent, producer = (make_registrar(n) for n in ("consumer", "agent", "producer"))
        serve(producer, "leaf")
        serve(agent, "composite", lambda r: agent.call(producer.name, "leaf", r).response)
        gate = gates()
        top = consumer.call(agent.name, "composite", "x", on_status=lambda q, u: gate.wait(30))
        (leaf_query,) = producer.server_queries("leaf")
        try:
            delivery = producer.send_status(leaf_query.id, rr.Status.WARNING, "", timeout=2.0)
        finally:
            gate.set()

        assert rr.StatusDelivery((leaf_query.id,), (top.id,)) == delivery

    def test_send_status_s_timeout_bounds_the_wait(self, make_registrar, serve, gates):
        """Rule 9: "`send_status` returns when the notification has been delivered ... (a
        `timeout` bounds it)".

        Mutation caught: `send_status` ignores its `timeout` and waits the registrar's default
        `call_timeout` (30 s here): its hung callback must be given up on within seconds.
        """
        provider = make_registrar("provider", call_timeout=30.0)
        consumer = make_registrar("consumer")
        serve(provider, "leaf")
        gate = gates()
        query = consumer.call(provider.name, "leaf", "x", on_status=lambda q, u: gate.wait(30))

        with ThreadPoolExecutor(1) as pool:
            # (2 s: 1 s of patience, then 1 s for the answer to come back, under load too)
            sending = pool.submit(provider.send_status, query.id, rr.Status.OK, "", timeout=2.0)
            try:
                delivery = sending.result(timeout=10)  # (15 s, half the default, if ignored)
            finally:
                gate.set()  # let the hung callback (and a send_status that ignored its timeout) end

        assert rr.StatusDelivery((), (query.id,)) == delivery

    def test_a_status_callback_may_send_a_status_that_reaches_its_own_client(
        self, served_pair, inbox, shared
    ):
        """Rule 9: a status callback may call `send_status` on the sender without deadlock.

        Here the nested status is for another resource the same consumer holds at the same
        server. Mutation caught: status callbacks run on the registrar's actor thread, or on
        any one thread per client, instead of on workers: the nested delivery then waits
        behind the running callback (a deadlock, cut by the nested call's timeout).
        """
        provider, consumer, _leaf = served_pair
        box = inbox()
        outcome = shared.list()
        other = consumer.call(provider.name, "leaf", "b", on_status=box)

        def reentrant(query, update):
            try:
                provider.send_status(other.id, rr.Status.OK, "nested", timeout=5)
            except rr.CallTimeoutError:
                outcome.append("deadlocked")
            else:
                outcome.append("delivered")

        first = consumer.call(provider.name, "leaf", "a", on_status=reentrant)

        provider.send_status(first.id, rr.Status.WARNING, "outer", timeout=15)

        assert ["delivered"] == outcome
        assert [(other.id, "nested")] == [(u.query_id, u.message) for _, u in box.updates]

    def test_a_status_callback_may_send_a_status_that_reaches_its_own_id(self, served_pair, shared):
        """Rule 9: a callback that sends a status about the resource it hears of waits for
        its own id's next callback. Each id hears its statuses one at a time, but a
        callback that waits for a registrar lets its id's next status start: that one
        runs beside it (issue 51 finding 6), not after the nested send timed out."""
        provider, consumer, _leaf = served_pair
        heard, outcome = shared.list(), shared.list()

        def reentrant(query, update):
            heard.append(update.message)
            if update.message != "outer":
                return
            try:
                provider.send_status(query.id, rr.Status.OK, "inner", timeout=5)
            except rr.CallTimeoutError:
                outcome.append("deadlocked")
            else:
                outcome.append("delivered")

        query = consumer.call(provider.name, "leaf", "a", on_status=reentrant)

        provider.send_status(query.id, rr.Status.WARNING, "outer", timeout=15)

        assert (["delivered"], ["outer", "inner"]) == (list(outcome), list(heard))

    def test_a_server_on_status_may_call_and_send_status_on_its_own_server(
        self, make_registrar, shared
    ):
        """Rule 9: the provider server's `on_status` may `call` its own server and `send_status`
        about another of its resources without deadlock.

        Mutation caught: `on_status` runs on an actor thread (the registrar's or the server's)
        instead of on a worker: the nested load and the nested `on_status` then wait behind
        the running callback.
        """
        provider, consumer = make_registrar("provider"), make_registrar("consumer")
        seen, outcome, other_ids = shared.list(), shared.list(), shared.list()

        def on_status(query, update):
            seen.append(query.request)
            if query.request != "a":
                return
            try:
                spare = provider.call(provider.name, "leaf", "spare", timeout=5)
                provider.unload(spare.id, timeout=5)
                provider.send_status(other_ids[0], rr.Status.OK, "nested", timeout=5)
            except rr.CallTimeoutError as exc:
                outcome.append(f"deadlocked: {exc}")
            else:
                outcome.append("done")

        provider.register_server(
            "leaf", load=lambda r: r, unload=lambda r, s: None, on_status=on_status
        )
        other_ids.append(consumer.call(provider.name, "leaf", "b").id)
        query = consumer.call(provider.name, "leaf", "a")

        provider.send_status(query.id, rr.Status.ERROR, "outer", timeout=20)

        assert ["done"] == outcome
        assert ["a", "b"] == seen

    def test_a_status_callback_that_gets_no_thread_is_skipped_and_its_registrar_keeps_serving(
        self,
        monkeypatch: pytest.MonkeyPatch,
    ) -> None:
        provider = rr.ResourceRegistrar.start(f"P-{uuid.uuid4().hex[:8]}")
        consumer = rr.ResourceRegistrar.start(f"C-{uuid.uuid4().hex[:8]}")
        heard: list[rr.StatusUpdate] = []
        try:
            provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: None)
            query = consumer.call(
                provider.name, "leaf", "a", on_status=lambda _q, u: heard.append(u)
            )

            def no_thread(_self: Workers, _task: Any, **_options: Any) -> None:
                raise RuntimeError("can't start new thread")

            monkeypatch.setattr(Workers, "submit", no_thread)  # say, too many hung callbacks
            provider.send_status(query.id, rr.Status.WARNING, "hot", timeout=5)

            assert [] == heard
            assert consumer.is_alive()
            assert [query.id] == [q.id for q in consumer.client_queries()]
        finally:
            monkeypatch.undo()
            consumer.stop()
            provider.stop()


class Said:
    """A status callback that records each update's message (in `said`); with `gate`, it
    blocks on it at the status `"0"` (a hung callback until the gate is set)."""

    def __init__(self, said: Any, gate: Any = None) -> None:
        self.said = said
        self.gate = gate

    def __call__(self, _query: rr.Query, update: rr.StatusUpdate) -> None:
        self.said.append(update.message)
        if self.gate is not None and update.message == "0":
            self.gate.wait(60)


class AwaitedSaid(Said):
    """`Said` as a coroutine callback (it runs on its loop): at `"0"` it awaits the gate
    on a thread of its own (`asyncio.to_thread`), its loop free meanwhile."""

    async def __call__(self, _query: rr.Query, update: rr.StatusUpdate) -> None:  # type: ignore[override]
        self.said.append(update.message)
        if self.gate is not None and update.message == "0":
            await asyncio.to_thread(self.gate.wait, 60)


def threads_of(registrar: Any, placement: str) -> int:
    """The threads of `registrar`'s process now."""
    if placement == "thread":
        return threading.active_count()
    return psutil.Process(registrar.pid).num_threads()


class TestHungConsumer:
    """A consumer whose status callback never returns (issue 53): it costs one thread,
    its statuses coalesce behind it, and `send_status` gives up on it, naming it."""

    STATUSES = 2_000

    @pytest.mark.timeout(240)  # (2,000 statuses to a manager process: 45 s at a load of 8)
    @pytest.mark.parametrize("hang", [Said, AwaitedSaid], ids=["plain", "coroutine"])
    def test_a_hung_callback_costs_a_bounded_number_of_threads_and_is_named_as_given_up(
        self, served_pair, gates, shared, registrar_placement, hang
    ):
        """Plain or coroutine alike. Mutation caught: `send_status` waits for every
        callback (it raised `CallTimeoutError` at the first status, and each of the 2,000
        waited its timeout); a status queued behind a busy callback starts a thread;
        coalescing undone (the hung id hears every status once its callback returns; a
        coroutine one's were each a task queued on its loop)."""
        provider, consumer, _leaf = served_pair
        gate = gates()
        hung_said, said = shared.list(), shared.list()
        hung = consumer.call(provider.name, "leaf", "x", on_status=hang(hung_said, gate))
        others = [consumer.call(provider.name, "leaf", "x") for _ in range(2)]
        heard = consumer.call(provider.name, "leaf", "x", on_status=Said(said))
        before = threads_of(consumer, registrar_placement)

        deliveries = []
        for number in range(self.STATUSES):
            status = rr.Status.FATAL if number in (700, 1400) else rr.Status.UPDATE
            deliveries.append(provider.send_status(hung.id, status, str(number), timeout=4.0))
        after = threads_of(consumer, registrar_placement)
        gate.set()
        wait_for(lambda: len(hung_said) == 4, timeout=15.0)

        assert after - before <= 10
        reached = {heard.id, *(query.id for query in others)}
        assert all((set(d.reached), d.gave_up) == (reached, (hung.id,)) for d in deliveries), (
            deliveries[:2]
        )
        assert [str(n) for n in range(self.STATUSES)] == list(said)
        # (the latest status, and every FATAL, in arrival order)
        assert ["0", "700", "1400", str(self.STATUSES - 1)] == list(hung_said)

    def test_a_hung_server_on_status_holds_one_thread_not_its_registrars_workers(
        self, make_registrar, gates, shared
    ):
        """A server's own `on_status` runs on the status runner, behind one that hangs
        (it is not given up on: each `send_status` times out), each status once and in
        order (rule 9: never coalesced, as a consumer's callbacks are). Mutation caught:
        on the registrar's workers, each status held one of them, and a load of another
        server of the registrar waited behind them (`max_workers=2`); coalesced (review
        of issue 53: `send_status` acknowledged statuses its `on_status` never heard)."""
        provider = make_registrar("provider", max_workers=2)
        consumer = make_registrar("consumer")
        gate, said = gates(), shared.list()

        def on_status(_query: rr.Query, update: rr.StatusUpdate) -> None:
            said.append(update.message)
            assert gate.wait(60)

        provider.register_server("leaf", load=lambda r: r, unload=_no_unload, on_status=on_status)
        provider.register_server("other", load=lambda r: r, unload=_no_unload)
        query = consumer.call(provider.name, "leaf", "x", timeout=10)
        try:
            for number in range(6):
                with pytest.raises(rr.CallTimeoutError):
                    provider.send_status(query.id, rr.Status.UPDATE, str(number), timeout=0.3)
            assert "y" == consumer.call(provider.name, "other", "y", timeout=10).response
        finally:
            gate.set()
        assert wait_for(lambda: 6 == len(said), timeout=10)
        assert ["0", "1", "2", "3", "4", "5"] == list(said)  # (each, once the hung one returned)


class TestFanout:
    """A status to many consumer registrars of several processes, in one pass per process
    (rule 9; issue 34 item 2).

    The provider serves in this process; each of three manager processes runs eight consumer
    registrars that hold two ids each of one resource, their callbacks recording what they
    hear there. The manager's own registrar serves `probe`, through which the test reads
    what was recorded in its process and releases a hung callback.
    """

    pytestmark = pytest.mark.usefixtures("by_value")

    @pytest.fixture(params=["process", "zenoh"])
    def fanout(self, request: pytest.FixtureRequest) -> Iterator[Callable[..., Fanout]]:
        made: list[Fanout] = []

        def make(**kwargs: Any) -> Fanout:
            made.append(Fanout(request.param))
            return made[-1].start(**kwargs)

        yield make
        for each in made:
            each.close()

    @pytest.mark.parametrize("status", [rr.Status.FATAL, rr.Status.UPDATE], ids=["fatal", "update"])
    def test_each_consumer_id_of_every_process_hears_each_status_once_and_in_order(
        self, fanout: Callable[..., Fanout], status: rr.Status
    ) -> None:
        """`FATAL`s: each heard, in order. `UPDATE`s: in order, none twice, the last heard;
        one behind a callback still running may coalesce to its latest (below)."""
        tree = fanout()
        tree.send("warm-up")  # (the provider learns which process each registrar is in)
        burst = [f"s{n}" for n in range(8)]
        for message in burst:  # sent back to back: each still on its way as the next leaves
            with contextlib.suppress(rr.CallTimeoutError):
                tree.send(message, timeout=0.01, status=status)
        tree.send("last")

        expected = ["warm-up", *burst, "last"]
        heard = wait_heard(tree, lambda h: all(s[-1:] == ["last"] for p in h for s in p.values()))
        lists = [list(process.values()) for process in heard]

        assert [REGISTRARS * IDS] * PROCESSES == [len(process) for process in heard]
        if status is rr.Status.FATAL:
            assert [[expected] * REGISTRARS * IDS] * PROCESSES == lists
        else:  # (each id's: a subsequence of what was sent, its first and last kept)
            assert [[[True] * 3] * REGISTRARS * IDS] * PROCESSES == [
                [
                    [s == [m for m in expected if m in s], s[0] == "warm-up", s[-1] == "last"]
                    for s in process
                ]
                for process in lists
            ]

    def test_a_burst_held_behind_a_running_callback_keeps_its_fatals_only(
        self,
        fanout: Callable[..., Fanout],
    ) -> None:
        """Why the test above sends its burst as `FATAL`s (issue 68 item 1: with `UPDATE`s
        it failed once under load in CI): behind a callback still running, an id's queued
        statuses coalesce to its latest and its `FATAL`s (rule 9's exception, inside.md
        "Statuses"), so an id whose callback still ran as its next two arrived heard one
        fewer. Forced: registrar 0's callbacks hang at the first status until all came."""
        tree = fanout(hang=True)  # (in each process: registrar 0's callbacks hang, 1's raise)
        with contextlib.suppress(rr.CallTimeoutError):  # (registrar 0's: given up on)
            tree.send("first", timeout=2.0)
        updates, fatals = [f"u{n}" for n in range(8)], [f"f{n}" for n in range(8)]
        for message in updates:  # (each answered once the others' callbacks returned)
            tree.send(message, timeout=10.0)
        for message in fatals:
            tree.send(message, timeout=10.0, status=rr.Status.FATAL)
        tree.send("last", timeout=10.0)
        for host in tree.hosts:
            tree.ask(host, "release")

        heard = wait_heard(tree, lambda h: all(s[-1] == "last" for p in h for s in p.values()))
        held = [["first", *fatals, "last"]] * IDS  # (registrar 0's: the UPDATEs coalesced)
        others = [["first", *updates, *fatals, "last"]] * (REGISTRARS - 1) * IDS
        assert [sorted(held + others)] * PROCESSES == [sorted(p.values()) for p in heard]

    def test_a_status_reaches_the_consumer_registrars_of_a_process_as_one_message(
        self,
        fanout: Callable[..., Fanout],
    ) -> None:
        tree = fanout(count=True)
        tree.send("warm-up")  # (one message to each registrar: their answers say where they are)
        before = [tree.ask(host, "steps") for host in tree.hosts]

        tree.send("one")
        tree.send("two")

        after = [tree.ask(host, "steps") for host in tree.hosts]
        handled = [
            {
                step: counts.get(step, 0) - was.get(step, 0)
                for step in ("status_batch", "status_notice")
            }
            for was, counts in zip(before, after, strict=True)
        ]
        assert [{"status_batch": 2, "status_notice": 0}] * PROCESSES == handled
        assert [[["warm-up", "one", "two"]] * REGISTRARS * IDS] * PROCESSES == [
            list(process.values()) for process in tree.heard()
        ]

    def test_a_hung_or_raising_callback_keeps_no_other_consumer_of_its_process_from_hearing(
        self,
        fanout: Callable[..., Fanout],
    ) -> None:
        tree = fanout(hang=True)  # (in each process: registrar 0's callbacks hang, 1's raise)
        everyone = PROCESSES * REGISTRARS * IDS

        first = tree.send("first", timeout=1.0)  # (the hung callbacks: given up on)
        heard = wait_heard(tree, lambda h: all(len(p) == REGISTRARS * IDS for p in h))

        assert [[["first"]] * REGISTRARS * IDS] * PROCESSES == [list(p.values()) for p in heard]
        assert (everyone - PROCESSES * IDS, PROCESSES * IDS) == (
            len(first.reached),
            len(first.gave_up),
        )
        second = tree.send("second", timeout=1.0)  # (a hung callback holds its own id's next)
        healthy = REGISTRARS * IDS - IDS
        heard = wait_heard(
            tree, lambda h: all(sum(len(s) == 2 for s in p.values()) == healthy for p in h)
        )
        assert [sorted([["first"]] * IDS + [["first", "second"]] * healthy)] * PROCESSES == [
            sorted(p.values()) for p in heard
        ]
        hung = {query_id for p in heard for query_id, said in p.items() if said == ["first"]}
        assert (hung, hung) == (set(first.gave_up), set(second.gave_up))
        assert not hung & set(second.reached)
        for host in tree.hosts:
            tree.ask(host, "release")
        wait_heard(tree, lambda h: all(len(s) == 2 for p in h for s in p.values()))
        third = tree.send("third")  # (every callback returns now: delivered everywhere, in order)
        assert [[["first", "second", "third"]] * REGISTRARS * IDS] * PROCESSES == [
            list(p.values()) for p in tree.heard()
        ]
        assert (everyone, ()) == (len(third.reached), third.gave_up)

    def test_a_relay_that_fails_after_delivering_runs_no_callback_twice(
        self,
        fanout: Callable[..., Fanout],
    ) -> None:
        tree = fanout(count=True)
        tree.send("warm-up")
        for host in tree.hosts:
            tree.ask(host, "fail-next")

        tree.send("again")  # (each part is sent again to its own registrar: delivered there)

        assert [[["warm-up", "again"]] * REGISTRARS * IDS] * PROCESSES == [
            list(process.values()) for process in tree.heard()
        ]


class TestRunner:
    """The runner of a process's status callbacks: each id's in arrival order."""

    def test_a_callback_given_up_as_slow_keeps_its_id_s_next_status_behind_it(self) -> None:
        """Issue 51 finding 6: the watchdog gave up every callback that ran `SLICE` of
        wall-clock (one that only waited for the CPU too), and that id's next status ran
        beside it. Forced: x's and y's first callbacks wait until z's ran. z's arrived
        last, so it runs only on a drainer the watchdog started once x's was given up,
        and that drainer took x's second first if x's lane was open."""
        runner = Runner()
        heard: list[tuple[str, str]] = []
        lock = threading.Lock()
        z_ran = threading.Event()
        ended = threading.Semaphore(0)

        def hear(query: rr.Query, update: rr.StatusUpdate) -> None:
            with lock:
                heard.append((query.id, f"{update.message} starts"))
            if query.id == "z":
                z_ran.set()
            elif update.message == "one":
                assert z_ran.wait(10)  # (past the watchdog's slice: given up)
            with lock:
                heard.append((query.id, f"{update.message} ends"))

        def status(query_id: str, message: str) -> _Call:
            query = rr.Query(query_id, "leaf", "prov", "cons", "r", "r")
            update = rr.StatusUpdate(query_id, rr.Status.UPDATE, message, "prov/leaf")
            return _Call(hear, query, update, ended.release)

        runner.run([status("x", "one"), status("x", "two"), status("y", "one"), status("z", "one")])

        assert all(ended.acquire(timeout=10) for _ in range(4))
        assert [
            ("x", "one starts"),
            ("x", "one ends"),
            ("x", "two starts"),
            ("x", "two ends"),
        ] == [entry for entry in heard if entry[0] == "x"]

    def test_statuses_queued_behind_a_busy_callback_coalesce_to_the_latest_and_every_fatal(
        self,
    ) -> None:
        """Issue 53: behind a callback that runs, an id's queue keeps its latest status and
        every `FATAL`, in arrival order; a status replaced is acknowledged with the one that
        replaced it. Mutation caught: no coalescing (every status runs); a `FATAL`
        coalesced away; the replaced ones never acknowledged."""
        runner = Runner()
        heard: list[str] = []
        began, go = threading.Event(), threading.Event()
        acked: list[str] = []

        def hear(_query: rr.Query, update: rr.StatusUpdate) -> None:
            heard.append(update.message)
            if update.message == "busy":
                began.set()
                assert go.wait(10)

        def status(message: str, code: rr.Status = rr.Status.UPDATE) -> _Call:
            query = rr.Query("x", "leaf", "prov", "cons", "r", "r")
            update = rr.StatusUpdate("x", code, message, "prov/leaf")
            done = functools.partial(acked.append, message)
            return _Call(hear, query, update, done, deadline=runtime.monotonic() + 60.0)

        runner.run([status("busy")])
        assert began.wait(10)
        fatal = rr.Status.FATAL
        sent = [status("u1"), status("f1", fatal), status("u2"), status("u3"), status("f2", fatal)]
        runner.run(sent[:3])
        runner.run(sent[3:])
        runner.run([status("u4")])
        go.set()

        wait_for(lambda: len(acked) == 7, timeout=10.0)
        assert ["busy", "f1", "f2", "u4"] == heard
        assert ["busy", "f1", "f2", "u1", "u2", "u3", "u4"] == acked

    def test_a_callback_that_waits_for_a_registrar_is_still_given_up_on_at_its_deadline(
        self,
    ) -> None:
        """Review of the fan-out: a callback that let its lane go (`let_go`: it waits for a
        registrar) was no longer checked against its deadline, its sender never answered.
        Mutation caught: running calls found only through the lanes' holders."""
        runner = Runner()
        began, go = threading.Event(), threading.Event()
        acked: list[str] = []
        gave_up: list[str] = []
        settled = threading.Event()

        def hear(_query: rr.Query, _update: rr.StatusUpdate) -> None:
            let_go()  # (as a `call` from inside it would)
            began.set()
            assert go.wait(10)

        def done() -> None:
            acked.append("x")
            settled.set()

        query = rr.Query("x", "leaf", "prov", "cons", "r", "r")
        update = rr.StatusUpdate("x", rr.Status.UPDATE, "wait", "prov/leaf")
        try:
            runner.run([_Call(hear, query, update, done, None, runtime.monotonic() + 0.3, gave_up)])
            assert began.wait(10)
            assert settled.wait(3.0), "a callback that waits for a registrar never given up on"
            assert (["x"], ["x"]) == (acked, gave_up)
        finally:
            go.set()

    def test_a_status_merged_into_a_later_one_is_given_up_on_at_its_own_deadline(
        self,
    ) -> None:
        """Review of the fan-out: a status coalesced into a later one was settled only at
        the later one's deadline (never, if it had none). Mutation caught: only the newest
        call's deadline checked."""
        runner = Runner()
        began, go = threading.Event(), threading.Event()
        acked: list[str] = []
        gave_up: list[str] = []
        first = threading.Event()

        def hear(_query: rr.Query, update: rr.StatusUpdate) -> None:
            if update.message == "busy":
                began.set()
                assert go.wait(10)

        def status(message: str, deadline: float | None) -> _Call:
            def done() -> None:
                acked.append(message)
                first.set()

            query = rr.Query("x", "leaf", "prov", "cons", "r", "r")
            update = rr.StatusUpdate("x", rr.Status.UPDATE, message, "prov/leaf")
            return _Call(hear, query, update, done, None, deadline, gave_up)

        try:
            runner.run([status("busy", None)])
            assert began.wait(10)
            runner.run([status("a", runtime.monotonic() + 0.3)])
            runner.run([status("b", None)])  # (a is merged into it)
            assert first.wait(3.0), "a merged status never given up on at its own deadline"
            assert (["a"], ["x"]) == (acked, gave_up)
        finally:
            go.set()
        wait_for(lambda: len(acked) == 3, timeout=10.0)
        assert ["a", "busy", "b"] == acked

    def test_a_callback_that_raises_system_exit_leaves_the_runner_running_the_next(self) -> None:
        runner = Runner()
        heard: list[str] = []
        ended = threading.Semaphore(0)

        def hear(query: rr.Query, update: rr.StatusUpdate) -> None:
            heard.append(f"{query.id} {update.message}")
            if query.id == "x":
                raise SystemExit(3)

        def status(query_id: str, message: str) -> _Call:
            query = rr.Query(query_id, "leaf", "prov", "cons", "r", "r")
            update = rr.StatusUpdate(query_id, rr.Status.UPDATE, message, "prov/leaf")
            return _Call(hear, query, update, ended.release)

        runner.run([status("x", "one")])
        assert ended.acquire(timeout=10)
        runner.run([status("y", "one")])  # (its drainer counted no thread that had ended)

        assert ended.acquire(timeout=10)
        assert ["x one", "y one"] == heard


class TestReleaseCrossing:
    """A status on its way to a consumer as the consumer releases its id (rule 9).

    Across processes the status and the answer to the consumer's `Unload` travel on two
    connections: the answer may come first. The answer carries the statuses sent to that id
    whose acknowledgement has not come; the consumer delivers those that did not reach it
    first before it forgets the id and before `unload` returns, and no status twice.
    """

    pytestmark = pytest.mark.usefixtures("by_value")

    @pytest.fixture(params=["process", "zenoh"])
    def crossing(self, request: pytest.FixtureRequest) -> Iterator[Crossing]:
        made = Crossing(request.param)
        yield made
        made.close()

    def test_a_status_the_release_overtakes_reaches_the_consumer_once_before_unload_returns(
        self, crossing: Crossing
    ) -> None:
        held, parts = threading.Event(), []

        def hold(batch: Any) -> None:  # (the relay's actor, until the release returned)
            parts.extend(batch.parts)
            held.set()
            assert crossing.go.wait(20)

        with intercept(crossing.relay, "status_batch", before=hold), ThreadPoolExecutor(1) as pool:
            sent = pool.submit(crossing.send, "unplugged", rr.Status.FATAL)
            assert held.wait(10)  # on its way to the consumer, held back at its relay
            assert crossing.consumer.name in dict(parts)

            crossing.consumer.unload(crossing.query.id)
            heard_when_released = list(crossing.heard)
            crossing.go.set()
            sent.result(20)  # (delivered along the whole path: the relay went on)

        assert ["warm-up", "unplugged"] == heard_when_released
        assert ["warm-up", "unplugged"] == crossing.heard  # (the late notice found it gone)
        assert ["warm-up", "unplugged"] == crossing.relay_heard
        assert [] == crossing.consumer.client_queries()

    def test_a_status_an_earlier_lifes_unload_answer_took_reaches_the_restart_s_release(
        self, crossing: Crossing
    ) -> None:
        """The consumer's earlier life sent an `Unload` and was killed before its answer came;
        its restart releases the id again. The provider released it on the first: the answer
        to the restart's (`UnknownQueryError`) carries the statuses still on their way to it
        (`simshare` seed 27: the first answer, carrying them, died with the life it went to)."""
        held = threading.Event()

        def hold(_batch: Any) -> None:  # (the relay's actor, until the release returned)
            held.set()
            assert crossing.go.wait(20)

        with intercept(crossing.relay, "status_batch", before=hold), ThreadPoolExecutor(1) as pool:
            sent = pool.submit(crossing.send, "unplugged", rr.Status.FATAL)
            assert held.wait(10)  # on its way to the consumer, held back at its relay
            lost = FutureReply()  # (the earlier life's: its answer goes nowhere now)
            DIRECTORY.lookup(crossing.provider.name).tell(
                Unload(crossing.query.id, crossing.consumer.name, lost)
            )
            assert ["unplugged"] == [s.message for s in lost.future.get(timeout=10)]

            crossing.consumer.unload(crossing.query.id)  # (the restart's: unknown there now)
            heard_when_released = list(crossing.heard)
            crossing.go.set()
            sent.result(20)

        assert ["warm-up", "unplugged"] == heard_when_released
        assert ["warm-up", "unplugged"] == crossing.heard
        assert [] == crossing.consumer.client_queries()

    def test_a_status_that_reached_the_consumer_first_is_not_delivered_again_at_its_release(
        self, crossing: Crossing
    ) -> None:
        notices: list[str] = []
        intercept(crossing.consumer, "status_notice", after=lambda m: notices.append(m.message))

        with ThreadPoolExecutor(1) as pool:
            sent = pool.submit(crossing.send, "hold")  # (unacknowledged: the relay's callback
            assert wait_for(lambda: ["warm-up", "hold"] == crossing.heard)  # holds its batch)

            crossing.consumer.unload(crossing.query.id)
            crossing.go.set()
            sent.result(20)

        assert ["hold"] == notices  # the answer carried it; it had come its own way first
        assert ["warm-up", "hold"] == crossing.heard
        assert [] == crossing.consumer.client_queries()

    def test_a_status_crossing_a_release_whose_unload_overran_reaches_the_consumer_before_it(
        self, crossing: Crossing
    ) -> None:
        provider = crossing.provider.name
        other = rr.ResourceRegistrar.start(
            f"other-{uuid.uuid4().hex[:8]}", network=crossing.network
        )
        crossing.provider.register_server("hangs", load=_echo, unload=_hang)
        heard: list[str] = []
        mine = crossing.consumer.call(
            provider, "hangs", "h", on_status=lambda _q, u: heard.append(u.message), timeout=20
        )
        theirs = other.call(provider, "hangs", "h", timeout=20)
        crossing.send("relay chosen")  # (this process's statuses go to the relay from now on)
        crossing.provider.send_status(mine.id, rr.Status.UPDATE, "warm-up", timeout=20)
        held = threading.Event()

        def hold(batch: Any) -> None:  # (the relay's actor, until the release returned)
            if batch.message == "unplugged":
                held.set()
                assert crossing.go.wait(20)

        try:
            with (
                intercept(crossing.relay, "status_batch", before=hold),
                ThreadPoolExecutor(1) as pool,
            ):
                sent = pool.submit(
                    crossing.provider.send_status, mine.id, rr.Status.FATAL, "unplugged", timeout=20
                )
                assert held.wait(10)  # on its way to the consumer, held back at the relay
                other.unload(theirs.id, timeout=20)
                with pytest.raises(rr.CallTimeoutError, match="unload callback"):
                    crossing.consumer.unload(mine.id, timeout=20)  # (the last: it unloads)
                heard_when_released = list(heard)
                crossing.go.set()
                sent.result(20)
        finally:
            other.stop()

        assert ["warm-up", "unplugged"] == heard_when_released
        assert ["warm-up", "unplugged"] == heard
        assert [crossing.query.id] == [q.id for q in crossing.consumer.client_queries()]


class TestOneWay:
    """A consumer registrar's statuses keep one way until that way drained (rule 9: each
    consumer hears them in the order sent; issue 68 item 1).

    A provider sends the statuses of a consumer registrar in another process on its own
    connection while it does not know that process, or while the registrar is the only
    consumer there, and as a batch to a relay registrar of that process (another connection)
    once it knows two there. A status held on the first way must not be overtaken by the
    next on the second: a test holds it at the consumer's actor (`intercept`) while the next
    one reaches the relay.
    """

    pytestmark = pytest.mark.usefixtures("by_value")

    @pytest.fixture(params=["process", "zenoh"])
    def ways(self, request: pytest.FixtureRequest) -> Iterator[Ways]:
        made = Ways(request.param)
        yield made
        made.close()

    def test_a_status_on_its_way_before_the_consumer_s_process_was_known_is_not_overtaken(
        self, ways: Ways
    ) -> None:
        held = Held("s1", "s2")
        try:
            with (
                intercept(ways.consumer, "status_batch", before=held),
                ThreadPoolExecutor(3) as pool,
            ):
                first = pool.submit(ways.send, "r", "s1")  # (to each registrar: where is it?)
                assert held.reached["s1"].wait(10)
                second = pool.submit(ways.send, "r", "s2")  # (the consumer's: not known yet)
                assert wait_for(lambda: ["s1", "s2"] == ways.heard["relay"]["r"], 10)
                held.go["s1"].set()
                first.result(20)  # (answered: the provider knows both share a process)
                assert held.reached["s2"].wait(10)  # s2 on its way, held at the consumer

                third = pool.submit(ways.send, "r", "s3")  # (both known: through the relay)
                assert wait_for(lambda: ["s1", "s2", "s3"] == ways.heard["relay"]["r"], 10)
                held.go["s2"].set()
                second.result(20)
                third.result(20)
        finally:
            held.release()

        assert ["s1", "s2", "s3"] == ways.heard["consumer"]["r"]

    def test_a_status_on_its_way_to_a_lone_consumer_is_not_overtaken_once_its_relay_joins(
        self, ways: Ways
    ) -> None:
        ways.send("r", "warm-up")  # (the provider learns that both are in this process)
        ways.send("r", "relay chosen")  # (this process's statuses go to the relay from now on)
        ways.hold("consumer", "s")  # (alone there: its statuses about "s" go to it directly)
        held = Held("one")
        try:
            with (
                intercept(ways.consumer, "status_notice", before=held),
                ThreadPoolExecutor(2) as pool,
            ):
                first = pool.submit(ways.send, "s", "one")
                assert held.reached["one"].wait(10)  # on its way, held at the consumer
                ways.hold("relay", "s")  # (two consumers of "s" there now: through the relay)

                second = pool.submit(ways.send, "s", "two")
                assert wait_for(lambda: ["two"] == ways.heard["relay"]["s"], 10)
                held.go["one"].set()
                first.result(20)
                second.result(20)
        finally:
            held.release()

        assert ["one", "two"] == ways.heard["consumer"]["s"]

    def test_a_status_a_relay_marked_reached_is_not_overtaken_by_the_next_one_an_unload_carries(
        self, ways: Ways
    ) -> None:
        """The relay marks a status reached for the consumer's id and queues its callback in one
        step: the next status, carried by the answer to the consumer's `Unload` (on the
        consumer's thread), queues behind it. Held here: the relay, between the consumer's part
        and its own id's notice to itself (an id without a callback: not delivered directly)."""
        seen = {message: threading.Event() for message in ("s0", "s1", "s2")}
        signal = rr.ResourceRegistrar.start(f"signal-{uuid.uuid4().hex[:8]}", network=ways.network)
        try:
            signal.register_server(
                "seen", load=lambda message: seen[message].set(), unload=_no_unload
            )
            ways.provider.register_server(
                "told",
                load=_echo,
                unload=_no_unload,
                on_status=_signalling(ways.provider, signal.name),
            )
            ways.send("r", "warm-up")  # (the provider learns that both are in this process)
            ways.send("r", "relay chosen")  # (this process's statuses go to the relay from now on)
            heard: list[str] = []
            held_id = ways.consumer.call(
                ways.provider.name,
                "told",
                "s",
                on_status=lambda _q, update: heard.append(update.message),
                timeout=20,
            ).id
            ways.relay.call(ways.provider.name, "told", "s", timeout=20)  # (no callback)
            send(ways.provider, held_id, "s0")  # (the consumer's answer was recorded: direct)
            held = Held("s1")
            try:
                with (
                    intercept(ways.relay, "status_notice", before=held),
                    ThreadPoolExecutor(2) as pool,
                ):
                    first = pool.submit(send, ways.provider, held_id, "s1")
                    assert held.reached["s1"].wait(10)  # marked for the consumer's id
                    second = pool.submit(send, ways.provider, held_id, "s2")
                    assert seen["s2"].wait(10)  # sent on, not acknowledged: carried
                    ways.consumer.unload(held_id, timeout=20)
                    held.go["s1"].set()
                    first.result(20)
                    second.result(20)
            finally:
                held.release()
        finally:
            signal.stop()

        assert ["s0", "s1", "s2"] == heard

    def test_statuses_that_overtook_an_answer_are_not_overtaken_by_the_next_one_once_it_lands(
        self, ways: Ways
    ) -> None:
        """Statuses that reached a consumer before the answer to its call (parked) are
        delivered as the answer is recorded; meanwhile the relay does not deliver that id's
        next status directly, ahead of them. Held here: the caller, until the first status is
        parked; then the consumer, as it delivers that one."""
        answered, release = threading.Event(), threading.Event()

        class HeldAfterItsAnswer(CallAttempt):
            def wait(self, timeout: float | None = None) -> bool:
                done = super().wait(timeout)
                answered.set()
                assert release.wait(20)
                return done

        ways.send("r", "warm-up")  # (the provider learns that both are in this process)
        ways.send("r", "relay chosen")  # (this process's statuses go to the relay from now on)
        ways.hold("relay", "s")  # (the relay's id first: the consumer's part is delivered after)
        parked, landing, go, relayed = (threading.Event() for _ in range(4))
        times: collections.Counter[str] = collections.Counter()

        def at_consumer(message: Any) -> None:  # (the consumer's actor thread)
            times[message.message] += 1
            if message.message == "s1" and times["s1"] == 2:  # (delivered as it lands)
                landing.set()
                assert go.wait(20)

        query_id = str(uuid.uuid4())
        heard: list[str] = []
        with (
            intercept(ways.consumer, "status_notice", before=at_consumer),
            intercept(ways.consumer, "status_notice", after=lambda m: parked.set()),
            intercept(
                ways.relay, "status_batch", after=lambda m: m.message == "s2" and relayed.set()
            ),
            ThreadPoolExecutor(3) as pool,
        ):
            with call_futures(ways.consumer, HeldAfterItsAnswer):
                call = pool.submit(
                    ways.consumer.call,
                    ways.provider.name,
                    "leaf",
                    "s",
                    query_id=query_id,
                    on_status=lambda _q, update: heard.append(update.message),
                    timeout=20,
                )
                assert answered.wait(10)
            first = pool.submit(send, ways.provider, query_id, "s1")
            assert parked.wait(10)  # (its answer not recorded yet: parked)
            release.set()
            assert landing.wait(10)
            second = pool.submit(send, ways.provider, query_id, "s2")
            assert relayed.wait(10)
            go.set()
            call.result(20)
            first.result(20)
            second.result(20)

        assert ["s1", "s2"] == heard

    def test_a_status_parked_with_a_due_id_is_not_overtaken_at_the_ids_held_beside_it(
        self, ways: Ways
    ) -> None:
        """One notice names a consumer's ids of a resource; while the answer to one of them is
        due it waits (parked), with the others' status: the next status, sent to the
        consumer itself (the way of the first), waits behind it for those too."""
        answered, release = threading.Event(), threading.Event()

        class HeldAfterItsAnswer(CallAttempt):
            def wait(self, timeout: float | None = None) -> bool:
                done = super().wait(timeout)
                answered.set()
                assert release.wait(20)
                return done

        ways.hold("consumer", "t")  # (the consumer alone holds "t": its statuses go to it)
        ways.send("t", "warm-up")  # (the provider learns the consumer's process)
        parked, batched = threading.Event(), threading.Event()
        with (
            intercept(ways.consumer, "status_notice", after=lambda m: parked.set()),
            intercept(
                ways.consumer, "status_batch", after=lambda m: m.message == "s2" and batched.set()
            ),
            ThreadPoolExecutor(3) as pool,
        ):
            with call_futures(ways.consumer, HeldAfterItsAnswer):
                call = pool.submit(
                    ways.consumer.call, ways.provider.name, "leaf", "t", timeout=20
                )  # (a second id of "t", due)
                assert answered.wait(10)
            first = pool.submit(ways.send, "t", "s1")  # (a notice naming both ids: parked)
            assert parked.wait(10)
            second = pool.submit(ways.send, "t", "s2")  # (a batch to the consumer)
            assert batched.wait(10)
            release.set()
            call.result(20)
            first.result(20)
            second.result(20)

        assert ["warm-up", "s1", "s2"] == ways.heard["consumer"]["t"]

    def test_a_status_left_in_the_mailbox_for_a_due_id_is_not_overtaken_once_its_answer_is_recorded(
        self, ways: Ways
    ) -> None:
        """The relay sends a status for an id whose answer is due to the consumer's mailbox
        (a notice); the consumer records the answer as it takes another message, ahead of that
        notice: the next status, at the relay, waits behind the notice, not delivered
        directly. Held here: the consumer's actor at two pings told to it, the second queued
        ahead of the notice (the answer is recorded as the actor takes it)."""
        pings: list[threading.Event] = [threading.Event(), threading.Event()]
        reached: list[threading.Event] = [threading.Event(), threading.Event()]
        relayed = {message: threading.Event() for message in ("s1", "s2")}

        def at_ping(_message: Any) -> None:  # (the consumer's actor thread)
            turn = sum(event.is_set() for event in reached)
            if turn < len(reached):
                reached[turn].set()
                assert pings[turn].wait(20)

        def at_relay(message: Any) -> None:  # (the consumer's part handled: after)
            if message.message in relayed and ways.consumer.name in dict(message.parts):
                relayed[message.message].set()

        ways.send("r", "warm-up")  # (the provider learns that both are in this process)
        ways.send("r", "relay chosen")  # (this process's statuses go to the relay from now on)
        ways.hold("relay", "s")  # (the relay's id first: the consumer's part is delivered after)
        consumer = DIRECTORY.lookup(ways.consumer.name)
        heard: list[str] = []
        try:
            with (
                intercept(ways.consumer, "ping", before=at_ping),
                intercept(ways.relay, "status_batch", after=at_relay),
                ThreadPoolExecutor(2) as pool,
            ):
                consumer.tell(Ping(FutureReply()))
                assert reached[0].wait(10)  # the consumer's actor held
                query_id = ways.consumer.call(
                    ways.provider.name,
                    "leaf",
                    "s",
                    on_status=lambda _q, update: heard.append(update.message),
                    timeout=20,
                ).id  # (answered; its record waits for the actor: the id is still due)
                consumer.tell(Ping(FutureReply()))  # (ahead of the notice)
                first = pool.submit(send, ways.provider, query_id, "s1")
                assert relayed["s1"].wait(10)  # a notice, the id due: behind the second ping
                pings[0].set()
                assert reached[1].wait(10)  # the answer recorded as the actor took this ping
                second = pool.submit(send, ways.provider, query_id, "s2")
                assert relayed["s2"].wait(10)
                pings[1].set()
                first.result(20)
                second.result(20)
        finally:
            for ping in pings:
                ping.set()

        assert ["s1", "s2"] == heard


class TestTooLarge:
    """A status or a new response its consumer cannot take is a `MessageTooLargeError` for its
    sender.

    A status message over the receiving registrar's `max_message_bytes` used to be dropped
    without a word: `send_status(FATAL, ...)` returned as if every consumer had heard it, and
    the consumer went on using a resource its provider had reported dead (rule 9). Now the
    sender gets the error naming the registrar not reached (`MessageTooLargeError`
    promises this), the provider's log says so, and the FATAL mark stands (rule 1). A new
    response (`update_response`) was only logged: its caller now hears of it too.
    """

    @pytest.mark.across_processes("a message's size counts only where it is pickled")
    def test_a_fatal_whose_message_is_over_the_consumers_limit_fails_its_sender_naming_it(
        self, make_registrar, serve, inbox
    ):
        provider = make_registrar("provider")
        consumer = make_registrar("consumer", max_message_bytes=LIMIT)
        leaf = serve(provider, "leaf")
        heard = inbox()
        dead = consumer.call(provider.name, "leaf", "lidar", on_status=heard, timeout=10)

        with pytest.raises(rr.MessageTooLargeError, match=consumer.name):
            provider.send_status(dead.id, rr.Status.FATAL, "x" * (2 * LIMIT), timeout=10)

        provider.send_status(dead.id, rr.Status.FATAL, "the LiDAR died", timeout=10)
        assert [(dead.id, rr.Status.FATAL, "the LiDAR died")] == [
            (u.query_id, u.status, u.message) for _, u in heard.updates
        ]
        consumer.call(provider.name, "leaf", "lidar", timeout=10)  # marked at the first FATAL:
        assert ["lidar", "lidar"] == leaf.loads  # a new resource for an equal request

    @pytest.mark.across_processes("a message's size counts only where it is pickled")
    def test_a_new_response_over_a_consumers_limit_fails_update_response_naming_it(
        self, make_registrar, serve
    ):
        provider = make_registrar("provider")
        consumer = make_registrar("consumer", max_message_bytes=LIMIT)
        serve(provider, "leaf")
        held = consumer.call(provider.name, "leaf", "lidar", timeout=10)

        with pytest.raises(rr.MessageTooLargeError, match=consumer.name):
            provider.update_response(held.id, "x" * (2 * LIMIT), timeout=10)

        provider.update_response(held.id, "repaired", timeout=10)
        assert ["repaired"] == [q.response for q in consumer.client_queries(timeout=10)]


@pytest.mark.parametrize("coroutine", [False, True], ids=["plain", "coroutine"])
def test_each_callback_s_end_is_published_with_when_it_began_and_let_its_lane_go(
    coroutine: bool,
) -> None:
    """`StatusHandled` (issue 51 finding 6): as a callback returns, with its arrival place,
    the stamp it began at and the one it first waited for a registrar at; the check's
    `status-order` judges an id's callbacks by them. Here the outer callback sends a status
    about its own resource: the inner one runs beside it once it waits (rule 9). A
    coroutine callback's too (on its loop, awaiting the send)."""
    from rr_actors import events  # noqa: PLC0415
    from rr_actors._registrar import start_registrar  # noqa: PLC0415
    from rr_actors_lab.experiments._status_rules import status_order  # noqa: PLC0415

    upstream = events.publisher()
    handled: list[events.StatusHandled] = []
    subscription = upstream.subscribe(
        lambda e: handled.append(e) if isinstance(e, events.StatusHandled) else None
    )
    provider = start_registrar(
        f"provider-{uuid.uuid4().hex[:8]}",
        setup=lambda r: r.register_server("leaf", load=lambda q: q, unload=lambda q, s: None),
        upstream=upstream,
    )
    consumer = start_registrar(f"consumer-{uuid.uuid4().hex[:8]}", upstream=upstream)
    try:

        def reentrant(query: rr.Query, update: rr.StatusUpdate) -> None:
            if update.message == "outer":
                provider.send_status(query.id, rr.Status.OK, "inner", timeout=5)

        async def areentrant(query: rr.Query, update: rr.StatusUpdate) -> None:
            if update.message == "outer":
                await provider.asend_status(query.id, rr.Status.OK, "inner", timeout=5)

        on_status = areentrant if coroutine else reentrant
        query = consumer.call(provider.name, "leaf", "a", on_status=on_status)
        provider.send_status(query.id, rr.Status.WARNING, "outer", timeout=15)
        assert wait_for(lambda: len(handled) == 2)
    finally:
        consumer.stop()
        provider.stop()
        subscription.close()

    outer, inner = sorted(handled, key=lambda e: e.arrived)
    assert [rr.Status.WARNING, rr.Status.OK] == [outer.status, inner.status]
    assert {consumer.name} == {e.registrar for e in handled}
    assert {query.id} == {e.query_id for e in handled}
    assert outer.began < outer.opened < inner.began < inner.hlc < outer.hlc
    assert 0 == inner.opened
    assert [] == status_order([(1, outer), (2, inner)])


@pytest.mark.xfail(
    strict=True,
    reason="a simulation artefact, not rule 9 broken (issue 68 item 8, traced): the simulated "
    "link's `close` fails its waiters on the closing thread, here m1's watch in pid 1, so "
    "db's resends ran as pid 1 (its clients local: in-process tells, no wire, no stamp), "
    "and db's answer, which did wait for them, is stamped below their StatusHandled. "
    "Fixed on branch `relayfind` (the failure crosses the wire back to the sender's "
    "process), not landed: it moves the kept seed simprogram 67, which no seed reaches yet",
)
def test_a_relay_killed_before_a_batch_arrives_answers_no_send_before_its_callbacks() -> None:
    # Rule 9: a `send_status` is answered once the callbacks it reached returned. simrelay
    # seed 5 (deterministic): db's status 96b50f37 goes as one batch to m1, the relay of
    # the run process (its first consumer there); m1's registrar crashes (a thread
    # manager's kill) before it takes the batch; db sends each part again, to m1 (gone),
    # client-0 and client-1, whose callbacks run (a probe saw each begin and return).
    # db's StatusAnswered lists both clients' ids as reached, and its hlc is below their
    # StatusHandled's. Seeds 10, 13 and 17 of 1-20 show it too (one to three ids each).
    pytest.importorskip("greenlet")  # (the simulation extra)
    from pathlib import Path  # noqa: PLC0415

    from rr_actors_lab.experiments import load_plan, simulate  # noqa: PLC0415

    plan = Path(__file__).parent / "plans" / "simrelay.toml"  # (not shipped: this finding)
    run = simulate.run_seed(load_plan(plan), 5)

    assert ("held", ()) == (run.verdict, run.findings)
