"""`rr-actors inspect PATH`: a catalog backup as a tree or as JSON, also of a live file."""

from __future__ import annotations

import io
import json
import sqlite3
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.__main__ import main
from rr_actors._catalog import Catalog
from rr_actors._store import codec, schema
from rr_actors._store.schema import SCHEMA_VERSION
from rr_actors._store.sqlite import SqliteStore


def run(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    code = main(list(argv), out)
    return code, out.getvalue()


@pytest.fixture
def live(tmp_path: Path) -> Iterator[tuple[rr.ResourceRegistrar, Path, dict[str, Any]]]:
    """A running provider with a backup: a leaf loaded twice and a nested resource."""
    path = tmp_path / "p.db"
    name = f"P-{uuid.uuid4().hex[:8]}"
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=name, backup_path=path, save_on_modify=True)
    )
    try:
        provider.register_server("leaf", load=lambda r: {"pid": 42}, unload=lambda r, s: None)
        provider.register_server(
            "nested",
            load=lambda r: provider.call(name, "leaf", {"sub": r}).response,
            unload=lambda r, s: None,
        )
        ids = {
            "first": provider.call(name, "leaf", {"cam": 1}).id,
            "second": provider.call(name, "leaf", {"cam": 1}).id,
            "nested": provider.call(name, "nested", "x").id,
        }
        yield provider, path, ids
    finally:
        provider.stop()


def test_inspect_prints_servers_resources_consumer_ids_and_dependencies_as_a_tree(
    live: tuple[rr.ResourceRegistrar, Path, dict[str, Any]],
) -> None:
    _, path, ids = live

    code, out = run("inspect", str(path))

    lines = out.splitlines()
    leaf = next(i for i, line in enumerate(lines) if "{'cam': 1} = {'pid': 42}" in line)
    nested = next(i for i, line in enumerate(lines) if "'x' = {'pid': 42}" in line)
    assert (0, True, True, True, True) == (
        code,
        "server leaf" in out and "server nested" in out,
        ids["first"] in lines[leaf + 1] and ids["second"] in lines[leaf + 2],
        ids["nested"] in lines[nested + 1],
        "dependency" in lines[nested + 2] and "/leaf {'sub': 'x'}" in lines[nested + 2],
    )


def test_inspect_json_gives_the_same_catalog_as_data(
    live: tuple[rr.ResourceRegistrar, Path, dict[str, Any]],
) -> None:
    _, path, ids = live

    code, out = run("inspect", str(path), "--json")

    data = json.loads(out)
    [leaf, sub] = data["servers"]["leaf"]
    [nested] = data["servers"]["nested"]
    assert (0, SCHEMA_VERSION, [ids["first"], ids["second"]], ["{'sub': 'x'}"], False) == (
        code,
        data["schema_version"],
        [c["query_id"] for c in leaf["consumers"]],
        [d["request"] for d in nested["dependencies"]],
        sub["in_doubt"],
    )


def test_inspect_works_on_the_file_of_a_running_registrar_without_disturbing_it(
    live: tuple[rr.ResourceRegistrar, Path, dict[str, Any]],
) -> None:
    provider, path, _ = live
    run("inspect", str(path))

    later = provider.call(provider.name, "leaf", {"cam": 2})

    assert later.id in run("inspect", str(path))[1]


def test_inspect_marks_in_doubt_resources(tmp_path: Path) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    catalog.begin_load("r-loading", "start_process", {"cmd": "sleep"})
    store.write(catalog.drain_changes())
    store.close(erase=False)

    code, out = run("inspect", str(tmp_path / "p.db"))

    [line] = [line for line in out.splitlines() if "r-loading" in line]
    assert (0, True, True) == (code, "[IN DOUBT: loading]" in line, "1 in doubt" in out)


def test_inspect_marks_a_resource_its_provider_reported_fatal(tmp_path: Path) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    for rid in ("r-dead", "r-new"):
        catalog.begin_load(rid, "leaf", "lidar")
        catalog.finish_load(rid, {"pid": rid})
        catalog.add_consumer(rid, "q" + rid, "C")
        if rid == "r-dead":
            catalog.mark_failed(rid)
    store.write(catalog.drain_changes())
    store.close(erase=False)

    code, out = run("inspect", str(tmp_path / "p.db"))
    data = json.loads(run("inspect", str(tmp_path / "p.db"), "--json")[1])

    marked = [line for line in out.splitlines() if "[FATAL" in line]
    assert (0, 1, True) == (code, len(marked), "r-dead" in marked[0])
    assert [("r-dead", True), ("r-new", False)] == [
        (r["id"], r["failed"]) for r in data["servers"]["leaf"]
    ]


def test_inspect_shows_a_value_it_cannot_unpickle_instead_of_failing(tmp_path: Path) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", "placeholder")
    store.write(catalog.drain_changes())
    store.close(erase=False)
    db = sqlite3.connect(tmp_path / "p.db")
    db.execute("UPDATE resources SET request = ?", (b"cno_such_module_here\nThing\n.",))
    db.commit()
    db.close()

    code, out = run("inspect", str(tmp_path / "p.db"))

    assert (0, True) == (code, "<unreadable" in out and "no_such_module_here" in out)


def test_inspect_of_a_corrupt_file_exits_1_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "p.db").write_bytes(b"not a database at all" * 100)

    code, _ = run("inspect", str(tmp_path / "p.db"))

    assert (1, True) == (code, str(tmp_path / "p.db") in capsys.readouterr().err)


def test_inspect_of_a_missing_file_exits_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _ = run("inspect", str(tmp_path / "nothing.db"))

    assert (1, True) == (code, "no catalog backup" in capsys.readouterr().err)


def test_the_command_line_runs_as_a_program(
    live: tuple[rr.ResourceRegistrar, Path, dict[str, Any]],
) -> None:
    _, path, ids = live

    done = subprocess.run(
        [sys.executable, "-m", "rr_actors", "inspect", str(path), "--json"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )

    assert (0, ids["first"]) == (
        done.returncode,
        json.loads(done.stdout)["servers"]["leaf"][0]["consumers"][0]["query_id"],
    )


def write_v1_backup(path: Path) -> None:
    """A backup as rr_actors wrote it with schema version 1 (text states, no digests)."""
    db = sqlite3.connect(path, isolation_level=None)
    db.execute(f"PRAGMA application_id = {schema.APPLICATION_ID}")
    schema.MIGRATIONS[0](db)
    db.execute("UPDATE rr_actors_schema SET version = 1")
    db.execute("PRAGMA journal_mode = WAL")
    db.execute(
        "INSERT INTO resources VALUES (1, 'r1', 'leaf', 'loaded', ?, ?)",
        (codec.dumps({"cam": 1}), codec.dumps({"pid": 42})),
    )
    db.execute("INSERT INTO consumers VALUES (2, 'q1', 'r1', 'C')")
    db.close()


def test_inspect_reads_a_schema_1_backup_without_changing_it(tmp_path: Path) -> None:
    path = tmp_path / "v1.db"
    write_v1_backup(path)
    before = path.read_bytes()

    code, out = run("inspect", str(path), "--json")

    resource = json.loads(out)["servers"]["leaf"][0]
    assert (0, "q1", [], before) == (
        code,
        resource["consumers"][0]["query_id"],
        sorted({p.name for p in tmp_path.iterdir()} - {"v1.db"}),
        path.read_bytes(),
    )


def _backup(path: Path, name: str) -> None:
    """A backup at `path` of a registrar `name` (started and stopped)."""
    rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, backup_path=path)).stop()


def test_inspect_of_a_state_dir_prints_every_backup_in_it_and_its_subfolders(
    tmp_path: Path,
) -> None:
    """`rr-actors inspect DIR` on a supervisor's state_dir, as a user tries it (issue 44)."""
    names = [f"erm-{uuid.uuid4().hex[:8]}", f"cm-{uuid.uuid4().hex[:8]}"]
    (tmp_path / "robot").mkdir()
    _backup(tmp_path / "robot" / "erm.db", names[0])
    _backup(tmp_path / "cm.db", names[1])

    code, out = run("inspect", str(tmp_path))
    _, as_json = run("inspect", str(tmp_path), "--json")

    assert 0 == code
    headers = [line.split(" (schema")[0] for line in out.splitlines() if "(schema" in line]
    assert [str(tmp_path / "cm.db"), str(tmp_path / "robot" / "erm.db")] == headers
    assert [str(tmp_path / "cm.db"), str(tmp_path / "robot" / "erm.db")] == [
        b["path"] for b in json.loads(as_json)
    ]


def test_inspect_of_a_folder_without_a_backup_says_what_to_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _ = run("inspect", str(tmp_path))

    assert 1 == code
    assert "is a folder that holds no catalog backup (*.db): name a registrar's backup" in (
        capsys.readouterr().err
    )
