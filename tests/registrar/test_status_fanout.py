"""A status to many consumer registrars of several processes, in one pass per process
(rule 9; issue 34 item 2).

The provider serves in this process; each of three manager processes runs eight consumer
registrars that hold two ids each of one resource, their callbacks recording what they
hear there. The manager's own registrar serves `probe`, through which the test reads
what was recorded in its process and releases a hung callback.
"""

from __future__ import annotations

import collections
import contextlib
import threading
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import STEPS, RemoteRegistrar, intercept
from tests.conftest import placement_network
from tests.support.waiting import wait_for

pytestmark = pytest.mark.usefixtures("by_value")

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

    def send(self, message: str, *, timeout: float = 20.0) -> None:
        self.provider.send_status(self.query_id, rr.Status.UPDATE, message, timeout=timeout)

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


@pytest.fixture(params=["process", "zenoh"])
def fanout(request: pytest.FixtureRequest) -> Iterator[Callable[..., Fanout]]:
    made: list[Fanout] = []

    def make(**kwargs: Any) -> Fanout:
        made.append(Fanout(request.param))
        return made[-1].start(**kwargs)

    yield make
    for each in made:
        each.close()


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


def test_each_consumer_id_of_every_process_hears_each_status_once_and_in_order(
    fanout: Callable[..., Fanout],
) -> None:
    tree = fanout()
    tree.send("warm-up")  # (the provider learns which process each registrar is in)
    burst = [f"s{n}" for n in range(8)]
    for message in burst:  # sent back to back: each still on its way as the next leaves
        with contextlib.suppress(rr.CallTimeoutError):
            tree.send(message, timeout=0.01)
    tree.send("last")

    expected = ["warm-up", *burst, "last"]
    heard = wait_heard(tree, lambda h: all(len(s) >= 10 for p in h for s in p.values()))

    assert [REGISTRARS * IDS] * PROCESSES == [len(process) for process in heard]
    assert [[expected] * REGISTRARS * IDS] * PROCESSES == [
        list(process.values()) for process in heard
    ]


def test_a_status_reaches_the_consumer_registrars_of_a_process_as_one_message(
    fanout: Callable[..., Fanout],
) -> None:
    tree = fanout(count=True)
    tree.send("warm-up")  # (one message to each registrar: their answers say where they are)
    before = [tree.ask(host, "steps") for host in tree.hosts]

    tree.send("one")
    tree.send("two")

    after = [tree.ask(host, "steps") for host in tree.hosts]
    handled = [
        {step: counts.get(step, 0) - was.get(step, 0) for step in ("status_batch", "status_notice")}
        for was, counts in zip(before, after, strict=True)
    ]
    assert [{"status_batch": 2, "status_notice": 0}] * PROCESSES == handled
    assert [[["warm-up", "one", "two"]] * REGISTRARS * IDS] * PROCESSES == [
        list(process.values()) for process in tree.heard()
    ]


def test_a_hung_or_raising_callback_keeps_no_other_consumer_of_its_process_from_hearing(
    fanout: Callable[..., Fanout],
) -> None:
    tree = fanout(hang=True)  # (in each process: registrar 0's callbacks hang, 1's raise)

    with pytest.raises(rr.CallTimeoutError):  # (the hung callbacks are not done)
        tree.send("first", timeout=1.0)
    heard = wait_heard(tree, lambda h: all(len(p) == REGISTRARS * IDS for p in h))

    assert [[["first"]] * REGISTRARS * IDS] * PROCESSES == [list(p.values()) for p in heard]
    tree.send("second")  # (a hung callback holds its own id's next one back a moment only)
    assert [[["first", "second"]] * REGISTRARS * IDS] * PROCESSES == [
        list(p.values()) for p in tree.heard()
    ]
    for host in tree.hosts:
        tree.ask(host, "release")
    tree.send("third")  # (every callback returns now: delivered everywhere)
    assert [[["first", "second", "third"]] * REGISTRARS * IDS] * PROCESSES == [
        list(p.values()) for p in tree.heard()
    ]


def test_a_relay_that_fails_after_delivering_runs_no_callback_twice(
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
