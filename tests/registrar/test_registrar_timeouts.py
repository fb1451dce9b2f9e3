"""Timeouts on blocking calls, and calls to registrars that die (DESIGN rule 17)."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import pytest

import rr_actors as rr
from rr_actors.testing import CallAttempt, call_futures, catalog_snapshot, crash

pytestmark = pytest.mark.both_apis  # the rules, against the async API too (conftest)


def test_a_call_whose_load_hangs_raises_call_timeout_error(make_registrar, serve, gated_load):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf", gated_load(wait=20))

    with pytest.raises(rr.CallTimeoutError) as info:
        consumer.call(provider.name, "leaf", "x", timeout=0.3)

    assert isinstance(info.value, TimeoutError)


def test_the_default_timeout_comes_from_the_registrar_config(make_registrar, serve, gated_load):
    provider, consumer = make_registrar("provider"), make_registrar("consumer", call_timeout=0.3)
    serve(provider, "leaf", gated_load(wait=20))
    began = time.monotonic()

    with pytest.raises(rr.CallTimeoutError):
        consumer.call(provider.name, "leaf", "x")

    assert time.monotonic() - began < 5.0


def test_a_load_that_completes_after_its_caller_timed_out_is_released(
    make_registrar, serve, gated_load, eventually
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    stuck = gated_load(wait=20)
    leaf = serve(provider, "leaf", stuck)
    with pytest.raises(rr.CallTimeoutError):
        consumer.call(provider.name, "leaf", "x", timeout=0.3)

    stuck.gate.set()

    assert leaf.unloaded.wait(5)
    assert [("x", "x")] == leaf.unloads
    # the unload callback has run; the registrar drops the row when it hears so
    assert eventually(lambda: () == catalog_snapshot(provider).resources)
    assert () == catalog_snapshot(consumer).clients


def test_a_timed_out_waiter_does_not_take_the_resource_from_a_patient_caller(
    make_registrar, serve, gated_load, arrived
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    stuck = gated_load(wait=20)
    leaf = serve(provider, "leaf", stuck)
    with ThreadPoolExecutor(1) as pool:
        patient = pool.submit(consumer.call, provider.name, "leaf", "x", timeout=20)
        assert stuck.started.wait(5)
        with pytest.raises(rr.CallTimeoutError):
            consumer.call(provider.name, "leaf", "x", timeout=0.3)
        stuck.gate.set()
        query = patient.result(timeout=20)

    assert [query.id] == [q.id for q in provider.server_queries("leaf")]
    assert [query] == consumer.client_queries()
    assert [] == leaf.unloads


def test_a_timed_out_call_inside_a_load_leaves_no_dependency_behind(
    make_registrar, serve, gated_load, eventually
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    stuck = gated_load(wait=20)
    slow = serve(provider, "slow", stuck)

    def impatient(request):
        return provider.call(provider.name, "slow", request, timeout=0.3)

    serve(provider, "composite", impatient)
    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(provider.name, "composite", "x", timeout=10)
    stuck.gate.set()

    assert "CallTimeoutError" == info.value.stack[0].exc_type
    assert slow.unloaded.wait(5)

    def empty() -> bool:
        snapshot = catalog_snapshot(provider)
        return ((), ()) == (snapshot.resources, snapshot.clients)

    assert eventually(empty)  # the registrar drops the rows once it hears of the unload


def test_an_unload_whose_callback_hangs_raises_call_timeout_error(make_registrar, gates):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    gate = gates()
    provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: gate.wait(20))
    query = consumer.call(provider.name, "leaf", "x")

    with pytest.raises(rr.CallTimeoutError):
        consumer.unload(query.id, timeout=0.3)


def test_unregister_server_with_a_hanging_unload_raises_call_timeout_error(make_registrar, gates):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    gate = gates()
    provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: gate.wait(20))
    consumer.call(provider.name, "leaf", "x")

    with pytest.raises(rr.CallTimeoutError):
        provider.unregister_server("leaf", timeout=0.3)


def test_a_call_in_flight_to_a_registrar_that_dies_fails_at_once(make_registrar, serve, gated_load):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    stuck = gated_load(wait=20)
    serve(provider, "leaf", stuck)
    with ThreadPoolExecutor(1) as pool:
        call = pool.submit(consumer.call, provider.name, "leaf", "x", timeout=30)
        assert stuck.started.wait(5)
        began = time.monotonic()

        crash(provider)

        assert isinstance(call.exception(timeout=10), rr.RegistrarUnavailableError)
        assert time.monotonic() - began < 10.0


@pytest.mark.parametrize("timeout", [0, -1.0, True, "1"])
def test_an_invalid_timeout_is_a_config_error(make_registrar, serve, timeout):
    provider = make_registrar("provider")
    serve(provider, "leaf")

    with pytest.raises(rr.ConfigError):
        provider.call(provider.name, "leaf", "x", timeout=timeout)


def test_retrying_a_timed_out_call_with_its_query_id_gets_the_resource(
    make_registrar, serve, gated_load, arrived
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    stuck = gated_load(wait=20)
    leaf = serve(provider, "leaf", stuck)
    with pytest.raises(rr.CallTimeoutError):
        consumer.call(provider.name, "leaf", "x", timeout=0.3, query_id=QUERY_ID)
    with ThreadPoolExecutor(1) as pool:
        retry = pool.submit(
            consumer.call, provider.name, "leaf", "x", timeout=10, query_id=QUERY_ID
        )
        assert arrived(provider, [QUERY_ID, QUERY_ID])  # the retry joined the running load
        stuck.gate.set()
        query = retry.result(timeout=20)

    assert (QUERY_ID, "x") == (query.id, query.response)
    assert [QUERY_ID] == [q.id for q in provider.server_queries("leaf")]
    assert 1 == len(leaf.loads)


QUERY_ID = "0b4f8b8e-9a1e-4c55-8f43-2a7f3b1d6e10"


def test_a_huge_finite_timeout_waits_and_a_non_finite_one_is_refused(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    query = consumer.call(provider.name, "leaf", "x", timeout=1e300)  # beyond a lock's wait
    consumer.unload(query.id, timeout=1e300)
    for timeout in (float("inf"), float("nan")):
        with pytest.raises(rr.ConfigError, match="timeout"):
            consumer.call(provider.name, "leaf", "x", timeout=timeout)
    assert [] == consumer.client_queries()


class _AnswerThenTimeout(CallAttempt):
    """A caller's future whose bounded wait runs out just after its answer arrived."""

    def wait(self, timeout=None):
        if timeout is None:
            return super().wait()
        assert super().wait(10)  # the answer lands...
        return False  # ...as the caller's wait runs out


@pytest.mark.thread_only("replaces the caller's future class in this process")
def test_an_answer_that_lands_as_the_wait_times_out_is_taken_not_lost(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    with call_futures(consumer, _AnswerThenTimeout):
        query = consumer.call(provider.name, "leaf", "x", timeout=1.0)

    assert [query.id] == [q.id for q in consumer.client_queries()]
    assert [query.id] == [q.id for q in provider.server_queries("leaf")]
    consumer.unload(query.id)
    assert [] == provider.server_queries("leaf")
