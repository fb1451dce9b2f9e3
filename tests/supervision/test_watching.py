"""What a supervisor shows of its tree (`rr_actors._supervision.watching`): the observer is
the lab's, found through `Observing`, a protocol of the supervisor's own; the runtime never
imports it (issue 54; the import contract "The runtime never imports the lab")."""

from __future__ import annotations

import socket
import subprocess
import sys
import textwrap
import uuid
from collections.abc import Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._supervision import watching
from rr_actors._supervision.watching import TreeAccess, attach_observer
from tests.support.supervising import echo_setup


class FakePage:
    """A page as the supervisor keeps it (`Page`), counting what it was told."""

    def __init__(self, keep_serving: bool) -> None:
        self.url = "http://127.0.0.1:1/"
        self.keep_serving = keep_serving
        self.told: list[str] = []

    @property
    def closed(self) -> bool:
        return "source_ended" in self.told

    def set_clock(self, origin: float, label: str = "") -> None:
        self.told.append("set_clock")

    def refresh(self) -> None:
        self.told.append("refresh")

    def source_ended(self) -> None:
        self.told.append("source_ended")

    def close(self, *, timeout: float = 5.0) -> None:
        self.told.append("close")

    def __enter__(self) -> FakePage:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


class FakeObserver:
    """An observer that records what supervisors ask of it (`Observing`)."""

    def __init__(self) -> None:
        self.asked: list[tuple[str, Any, TreeAccess, dict[str, Any]]] = []
        self.pages: list[FakePage] = []

    def observe(
        self,
        sup: Any,
        access: TreeAccess,
        *,
        host: str,
        port: int,
        allow_faults: bool,
        allow_remote: bool,
        keep_serving: bool,
        across_hosts: bool | None,
        sock: socket.socket | None,
    ) -> FakePage:
        self.asked.append(("observe", sup, access, {"host": host, "port": port}))
        self.pages.append(FakePage(keep_serving))
        return self.pages[-1]

    def graph(self, sup: Any, access: TreeAccess, format: str) -> str:
        self.asked.append(("graph", sup, access, {"format": format}))
        return "drawn\n"


@pytest.fixture
def observer() -> Iterator[FakeObserver]:
    """A fake observer attached to this process's supervisors, the real one put back after."""
    assert rr.Supervisor  # (its first use attaches the lab's: this one comes after)
    before = list(watching._FOUND)
    fake = FakeObserver()
    attach_observer(lambda: fake)
    try:
        yield fake
    finally:
        watching._FOUND[:] = before


def test_a_supervisor_asks_the_observer_it_finds_and_tells_its_pages_that_it_stopped(
    observer: FakeObserver,
) -> None:
    name = f"erm-{uuid.uuid4().hex[:8]}"
    sup = rr.Supervisor([rr.ManagerSpec(name, echo_setup)])
    kept, closed = sup.observe(port=8, keep_serving=True), sup.observe()
    sup.start()
    try:
        assert "drawn\n" == sup.graph("dot")
    finally:
        sup.stop()

    (_, asked_sup, access, where), _, (_, _, _, drawn) = observer.asked
    assert (sup, {"host": "127.0.0.1", "port": 8}) == (asked_sup, where)
    assert ([name], False) == ([child.name for child in access.spec.children], access.running())
    assert {"format": "dot"} == drawn
    assert ["refresh", "source_ended"] == kept.told  # (its last look, before the stop)
    assert ["source_ended"] == closed.told


def _run(code: str) -> list[str]:
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return done.stdout.splitlines()


LAB = 'sorted(m for m in sys.modules if m.startswith("rr_actors.observe"))'


def test_a_supervisor_of_a_process_that_attached_no_observer_says_how_to_attach_one() -> None:
    """Made from its module, in a process where nothing imported the observer: `graph`
    names the import that attaches it, and works once it is imported."""
    refused, imported, drawn = _run(
        f"""
        import sys
        from rr_actors._supervision import Supervisor
        from rr_actors.config import SupervisorSpec
        from rr_actors.errors import ConfigError

        sup = Supervisor(SupervisorSpec("root", ()))
        try:
            sup.graph()
        except ConfigError as exc:
            print("refused:", exc)
        print({LAB})
        import rr_actors.observe
        print(sup.graph().splitlines()[0])
        """
    )

    assert "refused: no observer is attached in this process: import rr_actors.observe" in refused
    assert ("[]", "flowchart TB") == (imported, drawn)


def test_rr_supervisor_finds_the_observer_itself_importing_it_at_the_first_graph() -> None:
    before, drawn, after = _run(
        f"""
        import sys
        import rr_actors as rr

        sup = rr.Supervisor(rr.SupervisorSpec("root", ()))
        print({LAB})
        print(sup.graph().splitlines()[0])
        print("rr_actors.observe._observer" in {LAB})
        """
    )

    assert ("[]", "flowchart TB", "True") == (before, drawn, after)
