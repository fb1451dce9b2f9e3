"""A durable consumer's manager process SIGKILLed while a call is on its way, then restarted.

Real manager processes under a supervisor (`state_dir`: `save_on_modify`), a real SIGKILL.
Code run in the consumer's process (`Supervisor.run_in`) holds its actor at one point of
the interleaving (the actor being slow there, as under load); the kill comes from the
test once shared events say the interleaving was reached.
"""

from __future__ import annotations

import os
import signal
import sys
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._manager import start_forkserver
from rr_actors.testing import SharedObjects

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")


@pytest.fixture(scope="module", autouse=True)
def by_value() -> Iterator[None]:
    start_forkserver()
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield
    cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


def _provider_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=lambda r: f"loaded {r}", unload=lambda _q, _r: None)


def _pair(
    supervisors: Callable[..., rr.Supervisor], tmp_path: Path
) -> tuple[rr.Supervisor, str, str]:
    uid = uuid.uuid4().hex[:8]
    p, c = f"p-{uid}", f"c-{uid}"
    sup = supervisors(
        [
            rr.ManagerSpec(p, _provider_setup, isolation="process"),
            rr.ManagerSpec(c, None, isolation="process", heartbeat=None),
        ],
        state_dir=tmp_path / "state",
    ).start()
    return sup, p, c


def _both_ends(sup: rr.Supervisor, p: str, c: str) -> tuple[list[str], list[str]]:
    held_at_provider = sup.run_in(p, lambda r: [q.id for q in r.server_queries("leaf")])
    held_by_consumer = sup.run_in(c, lambda r: [q.id for q in r.client_queries()])
    return held_at_provider, held_by_consumer


def test_a_durable_call_leaves_only_after_its_pending_record_is_committed(
    supervisors: Callable[..., rr.Supervisor], tmp_path: Path, process_helpers: SharedObjects
) -> None:
    # If the Load left before the pending record was committed, a dedup hit could be
    # answered (so the provider's release of an undelivered answer never fires) while the
    # record is not on disk yet; killed then, the restarted consumer would know nothing of
    # an id the provider holds for good (a restart is expected: no death watch).
    sup, p, c = _pair(supervisors, tmp_path)
    qid = str(uuid.uuid4())
    pending_reached = process_helpers.event()

    def arm(registrar: rr.ResourceRegistrar) -> None:
        import threading  # noqa: PLC0415 - runs in the consumer's process

        import rr_actors._registrar as m  # noqa: PLC0415

        original_pending = m.RegistrarActor._handlers[m._Pending]

        def busy_pending(actor: Any, message: Any) -> None:
            if message.record.query.id == qid:
                pending_reached.set()
                threading.Event().wait()  # busy until the process dies
            original_pending(actor, message)

        m.RegistrarActor._handlers[m._Pending] = busy_pending
        threading.Thread(
            target=lambda: registrar.call(p, "leaf", "x", query_id=qid, timeout=60), daemon=True
        ).start()

    sup.run_in(c, arm)
    assert pending_reached.wait(10)
    assert qid not in sup.run_in(p, lambda r: [q.id for q in r.server_queries("leaf")])
    os.kill(sup.child(c).pid or 0, signal.SIGKILL)
    sup.wait_restarted(c, timeout=15.0)

    held_at_provider, held_by_consumer = _both_ends(sup, p, c)
    assert held_at_provider == held_by_consumer
