"""Where the page's sections come from (`rr_actors_lab.observe._sources`): the observer's trust
boundary at a directory of backups (issue 21, bugs 1 and 5): looking at a backup runs nothing
from it, and a crafted file fails fast; a live tree's status sent, named once; a live
registrar's catalog read in its own process, which a hostile `__repr__` does not stop (bug 6)."""

from __future__ import annotations

import io
import os
import pickle
import sqlite3
import sys
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
import rr_actors_lab.observe as _lab_observe
from rr_actors import events
from rr_actors._catalog.texts import NOT_SHOWN_OLD
from rr_actors._store import SqliteStore, read_backup, schema
from rr_actors._store.schema import dumps
from rr_actors.config import SupervisorSpec
from rr_actors_lab.__main__ import main
from rr_actors_lab.observe._hub import Hub
from rr_actors_lab.observe._sources import LiveSource, TreeAccess, event_dict, read_catalogs
from tests.support.durable_pair import new_store
from tests.support.hostile import CreatesAFile, ExitsWhenShown, HangsWhenShown


def run(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    code = main(list(argv), out)
    return code, out.getvalue()


def stored_backup(path: Path) -> None:
    """A backup as a registrar writes it: one resource with its display texts."""
    store, catalog = new_store(path)
    resource = catalog.begin_load("r0", "lidar", {"name": "lidar2"})
    resource.request_text = "{'name': 'lidar2'}"
    catalog.finish_load("r0", "ok").response_text = "'ok'"
    catalog.add_consumer("r0", "q0", "action")
    store.write(catalog.drain_changes())
    store.close(erase=False)


def plant(path: Path, marker: Path) -> None:
    """Replace the stored request with a pickle that creates `marker` when unpickled."""
    db = sqlite3.connect(path)
    db.execute(
        "UPDATE resources SET request = ?", (pickle.dumps(CreatesAFile(str(marker)), protocol=5),)
    )
    db.commit()
    db.close()


# -- bug 1: looking at a backup runs no code from it -------------------------------------------


@pytest.fixture
def foreign_state(tmp_path: Path) -> tuple[Path, Path]:
    """A state directory whose backup another user (uid 65534) owns, holding a planted pickle."""
    if os.geteuid() != 0:
        pytest.skip("giving a file to another uid needs root (chown)")
    state = tmp_path / "state"
    state.mkdir()
    marker = tmp_path / "ran-code-from-the-backup"
    stored_backup(state / "cm.db")
    plant(state / "cm.db", marker)
    for file in state.iterdir():
        os.chown(file, 65534, 65534)
    return state, marker


def test_graph_of_another_users_backup_shows_its_texts_and_unpickles_nothing(
    foreign_state: tuple[Path, Path],
) -> None:
    state, marker = foreign_state

    code, text = run("graph", "--state", str(state))

    assert (0, False) == (code, marker.exists())
    assert "lidar2" in text


def test_observe_of_another_users_backup_shows_its_texts_and_unpickles_nothing(
    foreign_state: tuple[Path, Path],
) -> None:
    state, marker = foreign_state

    catalogs = read_catalogs(sorted(state.glob("*.db")))

    resource = catalogs["cm"]["resources"][0]
    assert ("{'name': 'lidar2'}", "'ok'") == (resource["request"], resource["response"])
    assert not marker.exists()


def test_inspect_and_restore_refuse_another_users_backup(
    foreign_state: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    state, marker = foreign_state

    with pytest.raises(rr.ConfigError, match="belongs to uid 65534"):
        read_backup(state / "cm.db")
    with pytest.raises(rr.ConfigError, match="belongs to uid 65534"):
        rr.ResourceRegistrar.start(rr.RegistrarConfig("cm", backup_path=str(state / "cm.db")))
    code, _ = run("inspect", str(state / "cm.db"))

    assert (1, False) == (code, marker.exists())
    assert "belongs to uid 65534" in capsys.readouterr().err


def write_v3_backup(path: Path) -> None:
    """A backup as rr_actors wrote it with schema version 3 (no display texts)."""
    db = sqlite3.connect(path, isolation_level=None)
    db.execute(f"PRAGMA application_id = {schema.APPLICATION_ID}")
    for step in schema.MIGRATIONS[:3]:
        step(db)
    db.execute("UPDATE rr_actors_schema SET version = 3")
    db.execute(
        "INSERT INTO resources (seq, id, server, state, digest, request, response) "
        "VALUES (1, 'r0', 'lidar', 1, NULL, ?, ?)",
        (dumps({"name": "lidar1"}), dumps("ok")),
    )
    db.execute("INSERT INTO consumers VALUES (1, 2, 'q0', 'action')")
    db.close()


def test_an_older_backup_reads_not_shown_and_still_restores(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    write_v3_backup(state / "cm.db")

    catalogs = read_catalogs([state / "cm.db"])
    code, text = run("graph", "--state", str(state))
    store = SqliteStore.open(state / "cm.db")
    try:
        restored = store.load()
    finally:
        store.close(erase=False)

    resource = catalogs["cm"]["resources"][0]
    assert (NOT_SHOWN_OLD, NOT_SHOWN_OLD) == (resource["request"], resource["response"])
    assert 0 == code
    assert "not shown" in text
    assert restored is not None
    assert {"name": "lidar1"} == restored[0][0].request


# -- bug 5: a crafted backup fails fast -------------------------------------------------------


ENDLESS = (
    "WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM n) "
    "SELECT i AS seq, 'r' || i AS id, 'lidar' AS server, 1 AS state, NULL AS digest, "
    "randomblob(100000) AS request, NULL AS response, NULL AS request_text, "
    "NULL AS response_text, NULL AS label FROM n"
)


def resources_a_view(path: Path) -> None:
    """`resources` a view over an endless query; its indexes' names kept on another table."""
    db = sqlite3.connect(path)
    db.execute("DROP TABLE resources")
    db.execute(f"CREATE VIEW resources AS {ENDLESS}")
    db.execute("CREATE TABLE decoy (seq INTEGER, server TEXT, digest INTEGER, id TEXT)")
    db.execute("CREATE UNIQUE INDEX resources_by_id ON decoy (id)")
    db.execute("CREATE INDEX resources_by_request ON decoy (server, digest)")
    db.execute("CREATE INDEX resources_unsettled ON decoy (seq)")
    db.commit()
    db.close()


def a_trigger_besides(path: Path) -> None:
    db = sqlite3.connect(path)
    db.execute(
        "CREATE TRIGGER grow AFTER INSERT ON consumers BEGIN "
        "INSERT INTO consumers SELECT resource, seq + 1, query_id, origin_rr "
        "FROM consumers; END"
    )
    db.commit()
    db.close()


def a_table_of_another_shape(path: Path) -> None:
    db = sqlite3.connect(path)
    db.execute("ALTER TABLE clients ADD COLUMN extra BLOB DEFAULT (randomblob(10))")
    db.commit()
    db.close()


@pytest.mark.timeout(30)
@pytest.mark.parametrize(
    ("craft", "why"),
    [
        (resources_a_view, "'resources' is a view, not a table"),
        (a_trigger_besides, "an unknown trigger 'grow'"),
        (a_table_of_another_shape, "the table 'clients' is not as rr_actors creates it"),
    ],
    ids=["view", "trigger", "other-table"],
)
def test_a_crafted_schema_is_catalog_corrupt_naming_the_file_before_any_read(
    tmp_path: Path, craft: Callable[[Path], None], why: str
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    path = state / "cm.db"
    stored_backup(path)
    craft(path)

    code, _ = run("graph", "--state", str(state))
    with pytest.raises(rr.CatalogCorruptError, match=why) as caught:
        read_catalogs([path])
    with pytest.raises(rr.CatalogCorruptError, match=why):
        SqliteStore.open(path)

    assert 1 == code
    assert str(path) == caught.value.path
    assert os.path.getsize(path) < 100_000  # (nothing was written to it)


# -- a live tree: how a status sent is named ----------------------------------------------


def test_a_status_sent_is_named_once_from_what_the_observer_saw_before_it() -> None:
    # What its pages draw whenever they open: the catalog last read may lag the send
    # (here: none was read); the provider's ConsumerAdded and ResourceLoaded do not.
    hub = Hub(convert=event_dict)
    access = TreeAccess(
        spec=SupervisorSpec("root", []),
        changes=Any,  # (no thread is started: only the event handler runs)
        restart_due={},
        running=lambda: True,
        registrars=list,
    )
    source = LiveSource(Any, access, hub)
    source._on_event(events.ResourceLoaded("erm", "camera", "r1", "q1", 0.01, None, "'cam'"))
    for query in ("q1", "q2"):
        source._on_event(events.ConsumerAdded("erm", "r1", query, "cm"))
    source._on_event(events.ConsumerReleased("erm", "r1", "q2", "cm", "unload"))
    for query in ("q1", "q2", "q3"):
        source._on_event(events.StatusSent("erm", query, rr.Status.FATAL, "unplugged"))

    sent = [e for e in hub.changes({}, 0).events if e["type"] == "StatusSent"]
    assert ["erm/camera 'cam'", "erm (query q2)", "erm (query q3)"] == [e["resource"] for e in sent]


# -- a live registrar's catalog read for the observer (`catalog_of`) ---------------------------
# -- bug 6: a hostile __repr__ stops nothing -----------------------------------------------------


def hostile_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=lambda r: "ok", unload=lambda r, s: None)


@pytest.mark.timeout(60)
def test_a_hanging_or_exiting_repr_shows_failed_and_the_graph_keeps_updating_without_new_threads(
    supervisors: Any,
) -> None:
    gate = threading.Event()
    sup = supervisors(
        [
            rr.ManagerSpec(
                "erm",
                setup=hostile_setup,
                config=rr.RegistrarConfig("erm", compare_timeout=0.5),
            )
        ]
    ).start()
    observer = _lab_observe.observe(sup)
    try:
        app = sup.registrar(rr.RegistrarConfig("action", compare_timeout=0.5))
        app.call("erm", "leaf", HangsWhenShown(gate), timeout=5)
        app.call("erm", "leaf", ExitsWhenShown(), timeout=5)
        before = threading.active_count()
        drawn = [_lab_observe.graph(sup)]
        deadline = time.monotonic() + 10
        while "repr failed: TimeoutError" not in drawn[-1] and time.monotonic() < deadline:
            drawn.append(_lab_observe.graph(sup))  # (the text is made once compare_timeout is over)
        drawn += [_lab_observe.graph(sup) for _ in range(10)]
        app.call("erm", "leaf", "after", timeout=5)
        last = _lab_observe.graph(sup)
        after = threading.active_count()
    finally:
        gate.set()
        observer.close()

    assert "repr failed: TimeoutError" in drawn[-1]
    assert "repr failed: SystemExit" in last
    assert "after" in last  # the graph still follows the catalog
    assert after <= before + 3  # (a worker or two may start; not one hung thread per look: 12+)


class HangsForGood:
    """A request whose `repr` never returns (in a manager process: no gate reaches it)."""

    def __eq__(self, other: object) -> bool:
        return isinstance(other, HangsForGood)

    def __hash__(self) -> int:
        return 3

    def __repr__(self) -> str:
        threading.Event().wait(60)
        return "HangsForGood()"


def hung_in_repr(sup: rr.Supervisor, name: str) -> int:
    """Threads of manager `name`'s process that are in `HangsForGood.__repr__` now.

    (Not its count of threads: a connection's writer thread starts when an answer first
    has to wait for the socket, and `run_in`'s thread may still be ending after it
    answered; a loaded machine showed one more, with no hung thread more.)
    """

    def count(_registrar: Any) -> int:
        hung = 0
        for frame in sys._current_frames().values():
            stack = traceback.walk_stack(frame)
            hung += any(f.f_code.co_qualname == "HangsForGood.__repr__" for f, _ in stack)
        return hung

    return int(sup.run_in(name, count, timeout=5))


@pytest.mark.timeout(60)
def test_a_hanging_repr_in_a_process_manager_costs_one_thread_once_not_one_per_refresh(
    supervisors: Any, process_helpers: Any
) -> None:
    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # (for the manager process)
    sup = supervisors(
        [
            rr.ManagerSpec(
                "erm",
                setup=hostile_setup,
                isolation="process",
                config=rr.RegistrarConfig("erm", compare_timeout=0.5),
            )
        ]
    ).start()
    app = sup.registrar(rr.RegistrarConfig("action", compare_timeout=0.5))
    app.call("erm", "leaf", HangsForGood(), timeout=30)  # (a bound that holds under load)
    drawn = [_lab_observe.graph(sup)]
    deadline = time.monotonic() + 10
    while "repr failed: TimeoutError" not in drawn[-1] and time.monotonic() < deadline:
        drawn.append(_lab_observe.graph(sup))

    hung = hung_in_repr(sup, "erm")
    drawn += [_lab_observe.graph(sup) for _ in range(20)]  # each reads erm's catalog in its process
    hung_after = hung_in_repr(sup, "erm")

    assert "repr failed: TimeoutError" in drawn[-1]
    assert (1, 1) == (hung, hung_after)  # one thread hangs, once: not one more per refresh


def test_only_a_life_s_start_or_end_a_give_up_or_a_gap_refreshes_every_catalog() -> None:
    """An event names the registrars whose catalog it changed, or none: a share refusal or a
    status's answer refreshed every manager's catalog (a flood of them, every interval);
    only a restore, a registrar's stop, a supervisor's give-up and events dropped may have
    changed any (a share's admission, `ShareAdmitted`, none: its load's events do)."""
    from rr_actors_lab.observe._sources import _touched  # noqa: PLC0415
    from tests.events.test_events import EXAMPLES  # noqa: PLC0415 - one example a kind

    every = sorted(type(event).__name__ for event in EXAMPLES if _touched(event) is None)

    assert ["CatalogRestored", "EventsDropped", "RegistrarStopped", "SupervisorGaveUp"] == every
