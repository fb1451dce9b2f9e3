"""User code that raises anything, or never returns, costs that call or that resource, never
the registrar (issue 16, bug 3): requests' `__eq__`, `__hash__` and pickling, callbacks."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import pending_work


class ExitsWhenCompared:
    """A request whose `==` raises `SystemExit` (unhashable: compared with every one)."""

    def __eq__(self, other: object) -> bool:
        raise SystemExit("compared")

    __hash__ = None  # type: ignore[assignment]


class ExitsWhenHashed:
    def __eq__(self, other: object) -> bool:
        return isinstance(other, ExitsWhenHashed)

    def __hash__(self) -> int:
        raise SystemExit("hashed")


class ExitsWhenPickled:
    def __reduce__(self) -> Any:
        raise SystemExit("pickled")


class HangsWhenCompared:
    """A request whose `==` blocks until `gate` is set (at the test's teardown)."""

    def __init__(self, gate: Any) -> None:
        self.gate = gate

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, HangsWhenCompared):
            return NotImplemented
        self.gate.wait(20)
        return False

    __hash__ = None  # type: ignore[assignment]


def serving(registrar: Any) -> Any:
    """`registrar`, with a server "ok" that `still_serve` calls."""
    registrar.register_server("ok", load=lambda r: ("ok", r), unload=lambda r, s: None)
    return registrar


def still_serve(*registrars: Any) -> list[Any]:
    """Each registrar (made with `serving`) loads a request on its own server "ok"."""
    return [r.call(r.name, "ok", "fresh", timeout=5).response for r in registrars]


# -- what raises a BaseException ------------------------------------------------------------


def test_a_request_whose_equality_raises_system_exit_fails_that_call_at_once_and_nothing_else(
    make_registrar, serve
):
    provider, consumer, bystander = (
        serving(make_registrar("provider")),
        serving(make_registrar("consumer")),
        serving(make_registrar("bystander")),
    )
    leaf = serve(provider, "leaf")
    held = consumer.call(provider.name, "leaf", ExitsWhenCompared(), timeout=5)  # (alone)

    with pytest.raises(rr.ConfigError, match="SystemExit"):
        consumer.call(provider.name, "leaf", ExitsWhenCompared(), timeout=5)

    assert [("ok", "fresh")] * 3 == still_serve(provider, consumer, bystander)
    assert [held.id] == [q.id for q in provider.server_queries("leaf")]
    assert 1 == len(leaf.loads)


def test_a_request_whose_hash_raises_system_exit_fails_that_call_and_nothing_else(
    make_registrar, serve
):
    provider, consumer = serving(make_registrar("provider")), serving(make_registrar("consumer"))
    leaf = serve(provider, "leaf")

    with pytest.raises(rr.ConfigError, match="SystemExit"):
        consumer.call(provider.name, "leaf", ExitsWhenHashed(), timeout=5)

    assert [("ok", "fresh")] * 2 == still_serve(provider, consumer)
    assert [] == leaf.loads


@pytest.mark.thread_only("the transport pickles the request on the caller's thread first")
def test_a_request_whose_pickling_raises_system_exit_at_a_durable_provider_fails_that_call(
    make_registrar, serve, tmp_path: Path
):
    provider = serving(
        make_registrar("provider", backup_path=tmp_path / "p.db", save_on_modify=True)
    )
    consumer = serving(make_registrar("consumer"))
    leaf = serve(provider, "leaf")

    with pytest.raises(rr.ConfigError, match="pickled"):
        consumer.call(provider.name, "leaf", ExitsWhenPickled(), timeout=5)

    assert [("ok", "fresh")] * 2 == still_serve(provider, consumer)
    assert [] == leaf.loads


def test_callbacks_that_raise_system_exit_fail_their_call_or_are_logged_and_nothing_else(
    make_registrar,
):
    provider, consumer = serving(make_registrar("provider")), serving(make_registrar("consumer"))

    def exits(*_: Any) -> None:
        raise SystemExit("callback")

    provider.register_server("load", load=exits, unload=lambda r, s: None)
    provider.register_server("rest", load=lambda r: r, unload=exits, on_status=exits)
    with pytest.raises(rr.ResourceLoadError, match="SystemExit"):
        consumer.call(provider.name, "load", "x", timeout=5)
    query = consumer.call(provider.name, "rest", "x", on_status=exits, timeout=5)

    provider.send_status(query.id, rr.Status.WARNING, "hot", timeout=5)
    consumer.unload(query.id, timeout=5)

    assert [] == provider.server_queries("rest")
    assert [("ok", "fresh")] * 2 == still_serve(provider, consumer)


# -- what never returns ---------------------------------------------------------------------


def test_a_request_whose_equality_hangs_fails_that_call_after_compare_timeout_and_others_go_on(
    make_registrar, serve, gates
):
    provider = make_registrar("provider", compare_timeout=0.5)
    consumer = make_registrar("consumer")
    gate = gates()
    serve(provider, "leaf")
    serve(provider, "other")
    held = consumer.call(provider.name, "leaf", HangsWhenCompared(gate), timeout=5)

    with ThreadPoolExecutor(1) as pool:
        hung = pool.submit(
            consumer.call, provider.name, "leaf", HangsWhenCompared(gate), timeout=10
        )
        # while that comparison hangs, the registrar serves its other servers
        other = consumer.call(provider.name, "other", "x", timeout=5)
        with pytest.raises(rr.CallTimeoutError, match="compare_timeout"):
            hung.result(timeout=10)

    assert {"resource": "x"} == other.response
    assert [held.id] == [q.id for q in provider.server_queries("leaf")]
    assert {"resource": "y"} == consumer.call(provider.name, "leaf", "y", timeout=5).response


def test_an_unload_that_never_returns_drops_its_resource_after_unload_timeout_and_tells_the_caller(
    make_registrar, gates, shared
):
    provider = make_registrar("provider", unload_timeout=0.5)
    consumer = make_registrar("consumer")
    gate, loads = gates(), shared.list()

    def load(request: Any) -> Any:
        loads.append(request)
        return len(loads)

    provider.register_server("leaf", load=load, unload=lambda r, s: gate.wait(20))
    query = consumer.call(provider.name, "leaf", "camera", timeout=5)

    with pytest.raises(rr.CallTimeoutError, match="unload callback"):
        consumer.unload(query.id, timeout=10)

    assert [] == provider.server_queries("leaf")
    assert [] == consumer.client_queries()
    # the equal request loads afresh (it would wait for the hung unload for good)
    assert 2 == consumer.call(provider.name, "leaf", "camera", timeout=5).response
    assert ["camera", "camera"] == loads


@pytest.mark.thread_only("counts the worker threads of this process")
def test_a_comparison_that_hangs_does_not_keep_its_worker_counted(make_registrar, serve, gates):
    provider = make_registrar("provider", compare_timeout=0.2, max_workers=1)
    gate = gates()
    serve(provider, "leaf")
    provider.call(provider.name, "leaf", HangsWhenCompared(gate), timeout=5)

    with pytest.raises(rr.CallTimeoutError):
        provider.call(provider.name, "leaf", HangsWhenCompared(gate), timeout=5)

    # its one worker hangs, abandoned: the next callback gets a thread of its own
    assert {"resource": "y"} == provider.call(provider.name, "leaf", "y", timeout=5).response
    hung = [t for t in threading.enumerate() if t.name.startswith(f"rr-{provider.name}-worker")]
    assert len(hung) >= 2


# -- worker threads -------------------------------------------------------------------------


def test_loads_beyond_max_workers_wait_in_line_for_a_free_worker(
    make_registrar, gates, shared, eventually
):
    provider = make_registrar("provider", max_workers=2)
    gate, started = gates(), shared.list()

    def load(request: Any) -> Any:
        started.append(request)
        assert gate.wait(20)
        return request

    provider.register_server("leaf", load=load, unload=lambda r, s: None)
    with ThreadPoolExecutor(3) as pool:
        calls = [pool.submit(provider.call, provider.name, "leaf", n, timeout=20) for n in "abc"]
        assert eventually(lambda: pending_work(provider).queued_callbacks == 1)
        # two workers, both held: the third load waits its turn (a worker that took its
        # load may not have reached `started.append` yet when the third one is queued)
        assert eventually(lambda: 2 == len(started))
        assert 1 == pending_work(provider).queued_callbacks

        gate.set()

        assert ["a", "b", "c"] == [call.result(timeout=10).response for call in calls]
    assert ["a", "b", "c"] == sorted(started)


@pytest.mark.thread_only("makes thread starts fail in this process")
def test_a_load_that_gets_no_worker_thread_fails_alone_and_the_registrar_serves_on(
    make_registrar, serve, monkeypatch: pytest.MonkeyPatch
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")
    start = threading.Thread.start

    def refused(thread: threading.Thread) -> None:
        if thread.name.startswith(f"rr-{provider.name}-worker"):
            raise RuntimeError("can't start new thread")
        start(thread)

    monkeypatch.setattr(threading.Thread, "start", refused)  # say, RLIMIT_NPROC reached
    with pytest.raises(rr.ResourceLoadError, match="no worker thread"):
        consumer.call(provider.name, "leaf", "x", timeout=5)
    monkeypatch.undo()

    assert [] == provider.server_queries("leaf")
    assert {"resource": "x"} == consumer.call(provider.name, "leaf", "x", timeout=5).response
    assert ["x"] == leaf.loads


# -- values that cross between processes ----------------------------------------------------


class ExitsWhenUnpickled:
    def __reduce__(self) -> Any:
        return (_exit, ("unpickled",))


def _exit(why: str) -> Any:
    raise SystemExit(why)


@pytest.mark.parametrize("kind", [ExitsWhenPickled, ExitsWhenUnpickled], ids=lambda k: k.__name__)
def test_a_response_that_raises_system_exit_as_it_crosses_fails_that_call_alone(
    make_registrar, registrar_placement, kind
):
    provider, consumer = serving(make_registrar("provider")), serving(make_registrar("consumer"))
    provider.register_server("odd", load=lambda _r: kind(), unload=lambda r, s: None)

    if registrar_placement == "thread":  # nothing crosses: nothing is pickled
        assert isinstance(consumer.call(provider.name, "odd", "x", timeout=5).response, kind)
    else:
        with pytest.raises(rr.RrError):
            consumer.call(provider.name, "odd", "x", timeout=5)

    assert [("ok", "fresh")] * 2 == still_serve(provider, consumer)


@pytest.mark.parametrize(
    "value", [ExitsWhenPickled(), ExitsWhenUnpickled()], ids=lambda v: type(v).__name__
)
def test_a_request_that_raises_system_exit_as_it_crosses_fails_that_call_alone(
    make_registrar, serve, registrar_placement, value
):
    provider, consumer = serving(make_registrar("provider")), serving(make_registrar("consumer"))
    leaf = serve(provider, "leaf")

    if registrar_placement == "thread":
        consumer.call(provider.name, "leaf", value, timeout=5)
    else:
        with pytest.raises(rr.RrError):
            consumer.call(provider.name, "leaf", value, timeout=5)

    assert [("ok", "fresh")] * 2 == still_serve(provider, consumer)
    assert len(leaf.loads) == (registrar_placement == "thread")
