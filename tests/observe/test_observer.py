"""The `Observer` handle (`rr_actors.observe._observer`): a context manager that needs the extra,
and `Supervisor.observe(sock=...)`: the page served on a listening socket made by the caller.

(`rr-actors demo --hosts 2 --observe` binds one in the machine's network namespace and
hands it to the station's process, in a namespace of its own: tests/mission.)

- a listening socket on loopback: the page answers there, the `url` names its address,
  and the observer closes it when it closes;
- a socket that does not listen, or one on an address that is not a loopback one
  without `allow_remote`: a `ConfigError` that says which, and the socket is closed.
"""

from __future__ import annotations

import socket
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.observe import Observer
from tests.support.observed_tree import figure_27
from tests.support.observing import (
    base,
    get_json,
)


@pytest.fixture
def tree(supervisors: Any, process_helpers: Any) -> rr.Supervisor:
    return figure_27(supervisors, isolation="thread").start()


def test_the_page_is_served_on_the_socket_given_and_closed_with_the_observer(
    tree: rr.Supervisor,
) -> None:
    listening = socket.create_server(("127.0.0.1", 0))
    port = listening.getsockname()[1]

    observer = tree.observe(sock=listening, port=1)  # (port and host are not used)

    assert f"http://127.0.0.1:{port}/" == base(observer.url)
    assert (observer.host, observer.port) == ("127.0.0.1", port)
    assert "live" == get_json(observer.url, "/api/state")["hello"]["mode"]
    observer.close()
    assert -1 == listening.fileno()  # closed
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", port), timeout=5).close()


def test_a_socket_that_does_not_listen_is_a_config_error(tree: rr.Supervisor) -> None:
    bound = socket.socket()
    bound.bind(("127.0.0.1", 0))

    with pytest.raises(rr.ConfigError, match=r"sock must be a listening TCP socket"):
        tree.observe(sock=bound)

    assert -1 == bound.fileno()


def test_a_socket_on_another_address_than_loopback_needs_allow_remote(
    tree: rr.Supervisor,
) -> None:
    listening = socket.create_server(("0.0.0.0", 0))  # noqa: S104 - the case under test

    with pytest.raises(rr.ConfigError, match=r"sock listens on '0\.0\.0\.0', not a loopback"):
        tree.observe(sock=listening)

    assert -1 == listening.fileno()


def test_the_observer_needs_the_observe_extra_to_serve(
    tree: rr.Supervisor, monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys  # noqa: PLC0415

    import rr_actors.observe  # noqa: PLC0415

    monkeypatch.setitem(sys.modules, "rr_actors.observe._server", None)  # as if not installed
    monkeypatch.delattr(rr_actors.observe, "_server", raising=False)

    with pytest.raises(rr.MissingExtraError, match=r"needs an extra: pip install .*\[observe\]"):
        tree.observe()


def test_observer_is_a_context_manager(tree: rr.Supervisor) -> None:
    with tree.observe() as observer:
        assert isinstance(observer, Observer)
        assert "live" == get_json(observer.url, "/api/state")["hello"]["mode"]

    assert observer.closed
