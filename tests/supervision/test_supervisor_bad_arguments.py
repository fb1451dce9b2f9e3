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
from tests.supervision.conftest import CallWithRetry
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
    sup: rr.Supervisor, call_with_retry: CallWithRetry, arguments: dict[str, Any], named: str
) -> None:
    app = sup.registrar(f"app-{uuid.uuid4().hex[:8]}")
    call: dict[str, Any] = {"consumer": app, "target_rr": _erm(sup), "server": "echo"}
    call.update(arguments)

    with pytest.raises(rr.ConfigError, match=named):
        call_with_retry(
            sup, call.pop("consumer"), call.pop("target_rr"), call.pop("server"), "x", **call
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


# -- the traps a new user fell into (issue 44, item 5) ---------------------------------------


def test_child_before_the_start_says_the_supervisor_is_not_started() -> None:
    sup = rr.Supervisor([rr.ManagerSpec("erm", echo_setup)])

    with pytest.raises(rr.ConfigError, match="is not started: its child 'erm' is not running"):
        sup.child("erm")
    assert "stopped" == sup.snapshot("erm").state  # (what the observer shows before it)


def test_one_spec_alone_is_a_tree_of_that_one_child() -> None:
    name = f"erm-{uuid.uuid4().hex[:8]}"

    with rr.Supervisor(rr.ManagerSpec(name, echo_setup)) as sup:
        assert [name] == [c.name for c in sup.which_children()]
        assert "running" == sup.child(name).state


@pytest.mark.parametrize("children", ["erm", 5, None])
def test_children_that_are_not_specs_are_a_config_error_saying_a_list(children: Any) -> None:
    with pytest.raises(rr.ConfigError, match="children must be a list of ManagerSpec"):
        rr.Supervisor(children)


def test_call_with_retry_with_a_name_first_says_the_consumer_comes_first(
    sup: rr.Supervisor,
    call_with_retry: CallWithRetry,
) -> None:
    with pytest.raises(
        rr.ConfigError,
        match=r"call_with_retry\(consumer, target_rr, server, request\): the consumer comes "
        "first",
    ):
        call_with_retry(sup, _erm(sup), "echo", 0)  # type: ignore[arg-type]


def test_call_with_retry_without_a_request_says_it_is_missing(
    sup: rr.Supervisor, call_with_retry: CallWithRetry
) -> None:
    app = sup.registrar(f"app-{uuid.uuid4().hex[:8]}")

    with pytest.raises(rr.ConfigError, match="request is missing"):
        call_with_retry(sup, app, _erm(sup), "echo")


def test_a_second_with_on_a_stopped_supervisor_says_make_a_new_one() -> None:
    sup = rr.Supervisor([rr.ManagerSpec(f"erm-{uuid.uuid4().hex[:8]}", echo_setup)])
    with sup:
        pass

    with pytest.raises(rr.ConfigError, match="cannot be restarted: make a new one"), sup:
        pass


def test_starting_a_running_supervisor_says_it_is_running(sup: rr.Supervisor) -> None:
    with pytest.raises(rr.ConfigError, match="is already started \\(it is running\\)"):
        sup.start()
