"""Reconciling after a supervised provider's SIGKILL, with work in flight (issue 29).

- A retry made after the provider's restart, whose `Load` leaves after the consumer's
  `Reconcile` and is answered before that reconcile's answer is handled, keeps its id:
  the provider's "unknown" was about its catalog before the retry reached it (rules 15,
  19, 20). Found by a random model test and in kill-heavy experiment runs: the retry
  returned, then its id was reported `FATAL` and forgotten.
- An `unload` its provider died during (it ran the unload callback, or never got to it)
  fails with `RegistrarUnavailableError`, and the reconcile after the restart releases
  the id there: the unload callback runs once in all, and nobody hears `FATAL` for an id
  its consumer gave up. Found 30 times in 30 under load.

Real manager processes, real SIGKILLs; the consumer is the application's registrar in
the supervisor's process, held at its steps (`rr_actors.testing.intercept`).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import SharedObjects, intercept
from tests.support.supervising import sigkill

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]


class Heard:
    """What the consumer registrar handles, seen on its actor thread as it happens.

    `notices`: the status notices it handles (a `FATAL` for a lost id is one, handled
    while the `Reconcile`'s answer is); `reconciled`: set once it handled the answer to
    a `Reconcile` (a tuple of the ids the provider does not know).
    """

    def __init__(self) -> None:
        self.notices: list[tuple[tuple[str, ...], rr.Status]] = []
        self.reconciled = threading.Event()

    def notice(self, message: Any) -> None:
        self.notices.append((tuple(message.query_ids), message.status))

    def answer(self, message: Any) -> None:
        if message.error is None and isinstance(message.value, tuple):
            self.reconciled.set()


def blocking_provider(
    entered: Any, release: Any, unloads: Any
) -> Callable[[rr.ResourceRegistrar], None]:
    """Server "leaf": loading "fresh" blocks until `release` is set (`entered` says it
    started); each unload is recorded in `unloads`."""

    def setup(registrar: rr.ResourceRegistrar) -> None:
        def load(request: Any) -> Any:
            if request == "fresh" and not release.is_set():
                entered.set()
                release.wait(60)  # (killed meanwhile)
            return {"for": request}

        registrar.register_server(
            "leaf", load=load, unload=lambda request, _r: unloads.append(request)
        )

    return setup


def test_a_retry_answered_after_the_reconcile_left_keeps_its_id(
    tmp_path: Path, process_helpers: SharedObjects
) -> None:
    entered, release, unloads = (
        process_helpers.event(),
        process_helpers.event(),
        process_helpers.list(),
    )
    name = f"provider-{uuid.uuid4().hex[:8]}"
    spec = rr.ManagerSpec(name, blocking_provider(entered, release, unloads), isolation="process")
    statuses: list[rr.StatusUpdate] = []

    def note(_query: rr.Query, update: rr.StatusUpdate) -> None:
        statuses.append(update)

    with rr.Supervisor([spec], state_dir=tmp_path, max_restarts=5, period=10.0) as sup:
        app = sup.registrar(f"app-{uuid.uuid4().hex[:8]}")
        app.call(name, "leaf", "held", timeout=10)  # its restart asks the app to reconcile
        qid = str(uuid.uuid4())
        failed: list[BaseException] = []

        def first_attempt() -> None:
            try:
                app.call(name, "leaf", "fresh", query_id=qid, on_status=note, timeout=30)
            except rr.RrError as exc:
                failed.append(exc)

        caller = threading.Thread(target=first_attempt)
        caller.start()
        assert entered.wait(10)  # its Load reached the provider; its load never finishes
        restarted, listed, returned = threading.Event(), threading.Event(), threading.Event()
        asks: list[Any] = []

        def wait_served(message: Any) -> None:  # (its first ask may come before it serves)
            asks.append(message)
            if len(asks) == 1:
                assert restarted.wait(30)

        def hold(_message: Any) -> None:  # the Reconcile left: hold until the retry returned
            if len(asks) == 1 and not listed.is_set():
                listed.set()
                assert returned.wait(30)

        heard = Heard()
        with (
            intercept(app, "reconcile_ask", before=wait_served, after=hold),
            intercept(app, "answer", after=heard.answer),
            intercept(app, "status_notice", before=heard.notice),
        ):
            sigkill(sup, name)
            caller.join(10)
            assert [rr.RegistrarUnavailableError] == [type(e) for e in failed]
            release.set()  # the restarted provider loads "fresh" at once
            sup.wait_restarted(name, timeout=30)
            restarted.set()
            assert listed.wait(30)  # the app's Reconcile left, listing qid (a failed call)
            try:
                retried = app.call(name, "leaf", "fresh", query_id=qid, on_status=note, timeout=10)
            finally:
                returned.set()
            assert heard.reconciled.wait(10)  # its answer (qid unknown) was handled

        assert asks[0].holds_yours  # (it reconciled: it holds ids there)
        assert qid == retried.id
        assert [] == heard.notices  # no FATAL for qid
        assert qid in [query.id for query in app.client_queries()]
        assert [qid] == [query.id for query in app.fetch_queries(name, "leaf") if query.id == qid]
        app.unload(qid, timeout=10)
        assert ["fresh"] == [request for request in unloads if request == "fresh"]  # once
        assert [] == statuses


def dying_provider(
    unloads: Any, armed: Any, *, ran: bool
) -> Callable[[rr.ResourceRegistrar], None]:
    """Server "leaf" whose unloads are recorded in `unloads`. While `armed` is set, the
    next `Unload` kills the provider's process (and disarms it): after the unload
    callback ran (`ran`), or before the registrar handles the `Unload` at all."""

    def setup(registrar: rr.ResourceRegistrar) -> None:
        def die() -> None:
            armed.clear()
            os.kill(os.getpid(), signal.SIGKILL)

        def unload(request: Any, _response: Any) -> None:
            unloads.append(request)  # (written by the helper process before the kill)
            if ran and armed.is_set():
                die()

        def before_unload(_message: Any) -> None:
            if not ran and armed.is_set():
                die()

        registrar.register_server("leaf", load=lambda r: {"for": r}, unload=unload)
        intercept(registrar, "unload", before=before_unload)

    return setup


@pytest.mark.parametrize("ran", [True, False], ids=["after-its-unload-ran", "before-it-ran"])
def test_an_unload_its_provider_died_during_is_released_by_the_reconcile_not_reported_fatal(
    ran: bool,
    tmp_path: Path,
    process_helpers: SharedObjects,
    eventually: Callable[..., bool],
) -> None:
    unloads, armed = process_helpers.list(), process_helpers.event()
    name = f"provider-{uuid.uuid4().hex[:8]}"
    spec = rr.ManagerSpec(name, dying_provider(unloads, armed, ran=ran), isolation="process")
    statuses: list[rr.StatusUpdate] = []

    def note(_query: rr.Query, update: rr.StatusUpdate) -> None:
        statuses.append(update)

    with rr.Supervisor([spec], state_dir=tmp_path, max_restarts=5, period=10.0) as sup:
        app = sup.registrar(f"app-{uuid.uuid4().hex[:8]}")
        query = app.call(name, "leaf", "doomed", on_status=note, timeout=10)
        heard = Heard()
        with (
            intercept(app, "answer", after=heard.answer),
            intercept(app, "status_notice", before=heard.notice),
        ):
            armed.set()
            with pytest.raises(rr.RegistrarUnavailableError) as raised:
                app.unload(query.id, timeout=10)
            sup.wait_restarted(name, timeout=20)
            assert heard.reconciled.wait(20)  # the app reconciled with the restarted one

        assert [] == heard.notices  # no FATAL for an id its consumer released
        assert eventually(lambda: len(unloads) >= 1, timeout=10)
        assert [] == sup.run_in(name, lambda r: [q.id for q in r.server_queries("leaf")])
        assert ["doomed"] == list(unloads)  # its unload ran once in all
        assert [] == statuses
        # The caller was told, and its registrar gave the id up.
        assert "released" in str(raised.value)
        assert query.id not in [q.id for q in app.client_queries()]
        with pytest.raises(rr.UnknownQueryError):
            app.unload(query.id, timeout=10)
