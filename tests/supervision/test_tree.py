"""What a whole supervision tree shares (`rr_actors._supervision.tree`): the network its
managers are served on, and finding a child anywhere in it."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import RemoteRegistrar, SharedObjects, System
from tests.support.names import named
from tests.support.supervising import echo_setup, kill_and_wait_restarted, process
from tests.support.waiting import wait_for


def thread(name: str, setup: Any = echo_setup) -> rr.ManagerSpec:
    return rr.ManagerSpec(name, setup, isolation="thread")


STOP_ROUNDS = 30
"""Registrars stopped in a row by the next test (the race it guards took one in ~30)."""


class Heard:
    """A status callback that records `(query id, status)` in a shared list."""

    def __init__(self, records: Any) -> None:
        self.records = records

    def __call__(self, query: rr.Query, update: rr.StatusUpdate) -> None:
        self.records.append((query.id, update.status))


class TestNetwork:
    """The process layer over any carrier: `Supervisor(network=)`, `ResourceRegistrar.start(
    network=)`, `RemoteRegistrar.start` with a `Transport` (issue 22, "The seam").

    Each with the AF_UNIX carrier (a `System` the test makes and closes); the Zenoh carrier
    plugs into the same keywords.
    """

    pytestmark = pytest.mark.usefixtures("by_value")  # (tests/conftest.py)

    @pytest.fixture
    def network(self) -> Iterator[System]:
        made = System.create()
        yield made
        made.close()

    @pytest.fixture
    def outsider(self, network: System) -> Iterator[Callable[[], RemoteRegistrar]]:
        """A registrar in a manager process of `network` that no supervisor started."""
        made: list[RemoteRegistrar] = []

        def make() -> RemoteRegistrar:
            registrar = RemoteRegistrar.start(named("outsider"), network)
            made.append(registrar)
            return registrar

        yield make
        for registrar in reversed(made):
            registrar.stop()

    def test_a_supervisor_serves_its_managers_and_registrars_on_the_network_it_is_given(
        self,
        network: System,
        outsider: Callable[[], RemoteRegistrar],
        supervisors: Callable[..., rr.Supervisor],
    ) -> None:
        in_process, in_thread = named("proc"), named("thr")
        sup = supervisors([process(in_process), thread(in_thread)], network=network)
        with sup:
            app = sup.registrar(named("app"))
            app.register_server("echo", load=lambda r: r, unload=lambda _r, _s: None)
            other = outsider()

            assert network is sup.system
            for target in (in_process, in_thread, app.name):
                query = other.call(target, "echo", f"to {target}", timeout=10)
                assert f"to {target}" == query.response
                other.unload(query.id, timeout=10)
        assert not network.closed  # the supervisor leaves a network it was given open
        after = rr.ResourceRegistrar.start(named("after"), setup=echo_setup, network=network)
        try:
            assert "still" == other.call(after.name, "echo", "still", timeout=10).response
        finally:
            after.stop()

    def test_a_supervisor_with_thread_managers_only_serves_them_on_its_network(
        self,
        network: System,
        outsider: Callable[[], RemoteRegistrar],
        supervisors: Callable[..., rr.Supervisor],
    ) -> None:
        name = named("thr")
        with supervisors([thread(name)], network=network):
            assert "hello" == outsider().call(name, "echo", "hello", timeout=10).response

    def test_a_supervisor_given_something_else_as_its_network_raises_config_error(self) -> None:
        with pytest.raises(rr.ConfigError, match="network"):
            rr.Supervisor([thread(named("thr"))], network="tcp/10.0.0.1:7447")  # type: ignore[arg-type]

    def test_a_supervisor_given_a_closed_network_does_not_start(
        self,
        supervisors: Callable[..., rr.Supervisor],
    ) -> None:
        closed = System.create()
        closed.close()
        sup = supervisors([process(named("proc"))], network=closed)

        with pytest.raises(rr.ConfigError, match="network was closed"):
            sup.start()

    def test_a_registrar_started_with_a_network_is_reached_from_another_process_until_it_stops(
        self, network: System, outsider: Callable[[], RemoteRegistrar]
    ) -> None:
        registrar = rr.ResourceRegistrar.start(named("erm"), setup=echo_setup, network=network)
        other = outsider()
        try:
            query = other.call(registrar.name, "echo", "camera", timeout=10)
            assert "camera" == query.response
            other.unload(query.id, timeout=10)
        finally:
            registrar.stop()

        with pytest.raises(rr.RegistrarStoppedError):
            other.call(registrar.name, "echo", "camera", timeout=10)

    @pytest.mark.timeout(300)
    def test_a_call_right_after_stop_raises_registrar_stopped_error_every_time(
        self, network: System, outsider: Callable[[], RemoteRegistrar]
    ) -> None:
        # The caller's connection is made by its first call and ended by the stop; that end
        # raced with the connection's writer thread (tests/transport/unix/test_link.py's
        # TestWriterClose): the connection stayed open, and the next call's load was read
        # and never answered.
        other = outsider()
        outcomes = []
        for _ in range(STOP_ROUNDS):
            registrar = rr.ResourceRegistrar.start(named("erm"), setup=echo_setup, network=network)
            try:
                other.unload(
                    other.call(registrar.name, "echo", "camera", timeout=10).id, timeout=10
                )
            finally:
                registrar.stop()
            try:
                other.call(registrar.name, "echo", "camera", timeout=5)
                outcomes.append("answered")
            except rr.RrError as exc:
                outcomes.append(type(exc).__name__)

        assert ["RegistrarStoppedError"] * STOP_ROUNDS == outcomes

    def test_a_registrar_whose_name_another_process_serves_is_refused_and_leaves_nothing(
        self, network: System, started: list[rr.ResourceRegistrar]
    ) -> None:
        name = named("erm")
        remote = RemoteRegistrar.start(name, network, setup=echo_setup)
        try:
            with pytest.raises(rr.DuplicateNameError):
                rr.ResourceRegistrar.start(name, setup=echo_setup, network=network)
            caller = rr.ResourceRegistrar.start(named("caller"))
            started.append(caller)

            assert "x" == caller.call(name, "echo", "x", timeout=10).response  # the remote one
        finally:
            remote.stop()

    def test_a_registrar_given_something_else_as_its_network_raises_config_error_and_starts_nothing(
        self,
        started: list[rr.ResourceRegistrar],
    ) -> None:
        name = named("erm")
        with pytest.raises(rr.ConfigError, match="network"):
            rr.ResourceRegistrar.start(name, network=object())  # type: ignore[arg-type]
        registrar = rr.ResourceRegistrar.start(name)  # the name is free
        started.append(registrar)

    def test_a_consumer_outside_the_tree_hears_fatal_for_ids_a_restart_without_backup_lost(
        self,
        network: System,
        outsider: Callable[[], RemoteRegistrar],
        supervisors: Callable[..., rr.Supervisor],
        process_helpers: SharedObjects,
    ) -> None:
        name = named("proc")
        heard = process_helpers.list()
        sup = supervisors([process(name)], network=network)  # no state_dir: no backup
        with sup:
            other = outsider()
            query = other.call(name, "echo", "camera", on_status=Heard(heard), timeout=10)

            kill_and_wait_restarted(sup, name)
            assert wait_for(lambda: len(heard) > 0, 10)

            assert [(query.id, rr.Status.FATAL)] == list(heard)
            assert [] == other.client_queries()


class TestHints:
    """A supervisor's errors say what to do: start it first; the closest child name."""

    def test_registrar_before_start_says_to_start_the_supervisor(
        self,
        supervisors: Callable[..., rr.Supervisor],
    ) -> None:
        sup = supervisors([thread("erm")], name="tree")

        with pytest.raises(rr.ConfigError) as info:
            sup.registrar("app")

        assert (
            "supervisor 'tree' is not running yet: start it first (`with sup:` or "
            "`sup.start()`), then call `registrar()`"
        ) == str(info.value)

    def test_registrar_after_stop_says_it_was_stopped(
        self,
        supervisors: Callable[..., rr.Supervisor],
    ) -> None:
        sup = supervisors([thread("erm")], name="tree")
        with sup:
            pass

        with pytest.raises(
            rr.ConfigError, match=r"^supervisor 'tree' was stopped: call `registrar"
        ):
            sup.registrar("app")

    def test_child_before_start_says_it_is_not_started_and_its_snapshot_is_stopped(
        self,
        supervisors: Callable[..., rr.Supervisor],
    ) -> None:
        sup = supervisors([thread("erm")])

        with pytest.raises(rr.ConfigError, match="is not started"):
            sup.child("erm")
        info = sup.snapshot("erm")

        assert ("stopped", None) == (info.state, info.pid)

    def test_a_misspelled_child_name_suggests_the_closest_one(
        self,
        supervisors: Callable[..., rr.Supervisor],
    ) -> None:
        sup = supervisors([thread("erm"), thread("cm")], name="tree")

        with pytest.raises(rr.UnknownServerError) as info:
            sup.child("emr")

        assert (
            "supervisor 'tree' has no child named 'emr'; did you mean 'erm'? (known: 'cm', 'erm')"
        ) == str(info.value)

    def test_run_in_and_wait_restarted_suggest_the_closest_name_too(
        self,
        supervisors: Callable[..., rr.Supervisor],
    ) -> None:
        sup = supervisors([thread("erm"), thread("cm")], name="tree").start()

        with pytest.raises(rr.UnknownServerError, match=r"did you mean 'erm'\?"):
            sup.run_in("emr", lambda registrar: None)
        with pytest.raises(rr.UnknownServerError, match=r"did you mean 'erm'\?"):
            sup.wait_restarted("emr", timeout=1.0)
