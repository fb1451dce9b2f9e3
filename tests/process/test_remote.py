"""A handle on a registrar in a manager process (`rr_actors._process.remote`): its owner,
which started the process, and plain handles, which reach the registrar over the carrier.

The rules run through `RemoteRegistrar` in every registrar test of the process and zenoh
placements (`make_registrar`); here is what only this handle has.
"""

from __future__ import annotations

import pickle
import uuid
from collections.abc import Iterator
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors.testing import RemoteRegistrar, System
from tests.support.waiting import wait_for

pytestmark = pytest.mark.usefixtures("by_value", "process_helpers")


def _same(request: Any) -> Any:
    return request


def _drop(_request: Any, _response: Any) -> None:
    return None


def _span(_request: Any) -> str:
    """The W3C traceparent of the OpenTelemetry span current in the load ("" if none)."""
    from opentelemetry import trace  # noqa: PLC0415 - the otel extra, only where used

    span = trace.get_current_span().get_span_context()
    return f"00-{span.trace_id:032x}-{span.span_id:016x}-01" if span.is_valid else ""


def _serve_leaf(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=_same, unload=_drop)
    registrar.register_server("span", load=_span, unload=_drop)


@pytest.fixture
def owner() -> Iterator[RemoteRegistrar]:
    """A registrar in a manager process of a fresh system, serving `leaf`; its owner."""
    system = System.create()
    registrar = RemoteRegistrar.start(f"remote-{uuid.uuid4().hex[:8]}", system, setup=_serve_leaf)
    yield registrar
    registrar.stop()
    system.close()


def test_a_pickled_handle_reaches_the_registrar_but_does_not_own_its_process(
    owner: RemoteRegistrar,
) -> None:
    plain: RemoteRegistrar = pickle.loads(cloudpickle.dumps(owner))

    query = plain.call(owner.name, "leaf", "r")

    assert [query.id] == [q.id for q in owner.server_queries("leaf")]
    assert (None, True) == (plain.pid, isinstance(owner.pid, int))
    assert f"<RemoteRegistrar {owner.name!r}>" == repr(plain)
    assert f"<RemoteRegistrar {owner.name!r} pid {owner.pid}>" == repr(owner)
    plain.unload(query.id)
    assert [] == owner.server_queries("leaf")


def test_a_call_through_the_handle_continues_the_trace_of_the_span_current_here(
    owner: RemoteRegistrar,
) -> None:
    from opentelemetry.sdk.trace import TracerProvider  # noqa: PLC0415 - the otel extra

    untraced = owner.call(owner.name, "span", 1).response  # (made there: no span current)
    with TracerProvider().get_tracer("test").start_as_current_span("step") as step:
        traced = owner.call(owner.name, "span", 2).response

    assert "" == untraced
    here = step.get_span_context()
    # made in the registrar's process, under this span: its load ran in this trace
    assert traced.startswith(f"00-{here.trace_id:032x}-")
    assert f"{here.span_id:016x}" not in traced  # (under its call's SERVER span)


def test_a_plain_handles_kill_makes_the_process_kill_itself_and_its_owner_sees_it_dead(
    owner: RemoteRegistrar,
) -> None:
    plain: RemoteRegistrar = pickle.loads(cloudpickle.dumps(owner))
    assert plain.is_alive()

    plain.kill(timeout=5.0)

    assert wait_for(lambda: not owner.is_alive(), 10.0)
    assert not plain.is_alive()
    with pytest.raises(rr.RegistrarUnavailableError):
        plain.call(owner.name, "leaf", "r", timeout=5.0)


def _no_camera(_registrar: rr.ResourceRegistrar) -> None:
    raise RuntimeError("no camera on this bench")  # the line a failed start must show


def test_a_setup_that_raises_is_reported_with_its_own_file_and_line() -> None:
    system = System.create()
    try:
        with pytest.raises(rr.RegistrarUnavailableError) as info:
            RemoteRegistrar.start(f"remote-{uuid.uuid4().hex[:8]}", system, setup=_no_camera)
    finally:
        system.close()

    assert f'File "{__file__}", line ' in str(info.value)
    assert "the line a failed start must show" in str(info.value)
