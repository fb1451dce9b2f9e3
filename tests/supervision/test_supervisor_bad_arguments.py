"""`Supervisor.call_with_retry`, `subscribe`, `observe`, `run_in`, `child` and
`wait_restarted` given what they cannot use.

Each is a `ConfigError` naming the argument, raised before anything is sent: no id is
abandoned at the provider for a call never made, no subscription logs a `TypeError` per
event for ever, no `AttributeError` from the observer's error path.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
from tests.support.supervising import echo_setup


@pytest.fixture
def sup() -> Iterator[rr.Supervisor]:
    """A started tree of one manager in a thread, `erm-<hex>`, serving `echo`."""
    with rr.Supervisor([rr.ManagerSpec(f"erm-{uuid.uuid4().hex[:8]}", echo_setup)]) as started:
        yield started  # (`with` started it)


def _erm(sup: rr.Supervisor) -> str:
    return sup.which_children()[0].name


@pytest.mark.parametrize(
    ("arguments", "named"),
    [
        ({"consumer": "app"}, "consumer"),
        ({"consumer": None}, "consumer"),
        ({"target_rr": 5}, "target_rr"),
        ({"server": None}, "server"),
        ({"timeout": -1}, "timeout"),
        ({"timeout": float("nan")}, "timeout"),
        ({"query_id": ""}, "query_id"),
    ],
    ids=["consumer-str", "consumer-None", "target-int", "server-None", "timeout-neg", "nan", "qid"],
)
def test_call_with_retry_with_an_argument_it_cannot_use_is_a_config_error_naming_it(
    sup: rr.Supervisor, arguments: dict[str, Any], named: str
) -> None:
    app = sup.registrar(f"app-{uuid.uuid4().hex[:8]}")
    call: dict[str, Any] = {"consumer": app, "target_rr": _erm(sup), "server": "echo"}
    call.update(arguments)

    with pytest.raises(rr.ConfigError, match=named):
        sup.call_with_retry(
            call.pop("consumer"), call.pop("target_rr"), call.pop("server"), "x", **call
        )

    assert [] == sup.run_in(_erm(sup), lambda erm: erm.server_queries("echo"), timeout=10)


def test_subscribe_with_a_callback_that_is_not_callable_is_a_config_error(
    sup: rr.Supervisor,
) -> None:
    with pytest.raises(rr.ConfigError, match="callback"):
        sup.subscribe(42)  # type: ignore[arg-type]


def test_observe_with_a_sock_that_is_not_a_socket_is_a_config_error_naming_it(
    sup: rr.Supervisor,
) -> None:
    pytest.importorskip("uvicorn")
    with pytest.raises(rr.ConfigError, match="sock"):
        sup.observe(sock="127.0.0.1:8080")  # type: ignore[arg-type]


def test_subscribe_after_stop_is_a_config_error_not_a_subscription_that_never_hears() -> None:
    sup = rr.Supervisor([rr.ManagerSpec(f"erm-{uuid.uuid4().hex[:8]}", echo_setup)])
    sup.start()
    sup.stop()

    with pytest.raises(rr.ConfigError, match="was stopped"):
        sup.subscribe(print)


@pytest.mark.parametrize(
    ("method", "named"),
    [
        (lambda sup, erm: sup.run_in(erm, lambda r: r.name, timeout=-1), "timeout"),
        (lambda sup, erm: sup.run_in(erm, "not callable"), "fn"),
        (lambda sup, erm: sup.run_in([erm], lambda r: r.name), "name"),
        (lambda sup, erm: sup.child([erm]), "name"),
        (lambda sup, erm: sup.wait_restarted([erm], timeout=1), "name"),
        (lambda sup, erm: sup.wait_restarted(erm, timeout=-1), "timeout"),
    ],
    ids=["run_in-timeout", "run_in-fn", "run_in-name", "child", "wait_restarted", "wait-timeout"],
)
def test_run_in_child_and_wait_restarted_refuse_what_they_cannot_use_naming_it(
    sup: rr.Supervisor, method: Callable[[rr.Supervisor, str], object], named: str
) -> None:
    with pytest.raises(rr.ConfigError, match=named):
        method(sup, _erm(sup))

    assert "running" == sup.child(_erm(sup)).state
