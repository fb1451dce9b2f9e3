"""The `rr-actors` command line (`rr_actors_lab._cli`): the command itself and the subcommands
it implements (`inspect`, `events`, `check`'s files); those another package implements
(`demo`, `experiment`, `observe`, `graph`, `certs`) are tested with that package."""

from __future__ import annotations

import importlib.metadata
import io
import json
import re
import sqlite3
import subprocess
import sys
import sysconfig
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors
import rr_actors as rr
from rr_actors import events
from rr_actors._catalog import request_digest
from rr_actors._core import hlc
from rr_actors._store import files, schema
from rr_actors._store.restore import read_backup
from rr_actors._store.schema import SCHEMA_VERSION
from rr_actors.events import lines
from rr_actors_lab.__main__ import main
from tests.support.durable_pair import new_store
from tests.support.hosts import free_port
from tests.support.persisting import write_unloading
from tests.support.python import python
from tests.support.terminal import drawn, on_a_terminal

PACKAGE = Path(rr_actors.__file__).resolve().parent


def rr_actors_command(*argv: str) -> subprocess.CompletedProcess[str]:
    """The installed `rr-actors` console script, next to this interpreter."""
    script = Path(sysconfig.get_path("scripts")) / "rr-actors"
    return subprocess.run(
        [str(script), *argv], capture_output=True, text=True, timeout=30, check=False
    )


def test_version_prints_the_installed_version() -> None:
    result = rr_actors_command("--version")

    assert (0, "") == (result.returncode, result.stderr)
    assert f"rr-actors {importlib.metadata.version('rr-actors')}\n" == result.stdout


def test_the_package_version_is_the_distribution_version() -> None:
    assert importlib.metadata.version("rr-actors") == rr_actors.__version__


def test_help_lists_every_subcommand_and_the_version_option() -> None:
    result = python("-m", "rr_actors_lab", "--help", timeout=30)

    assert 0 == result.returncode
    for word in ("demo", "inspect", "--version"):
        assert word in result.stdout


def test_without_a_command_it_prints_the_help_and_exits_2() -> None:
    result = rr_actors_command()

    assert (2, "") == (result.returncode, result.stderr)
    assert result.stdout.startswith("usage: rr-actors [-h] [--version] COMMAND ...\n")
    listed = {line.split()[0] for line in result.stdout.splitlines() if line.startswith("    ")}
    assert {"demo", "inspect", "observe", "graph", "experiment"} <= listed


@pytest.mark.parametrize(
    ("argv", "meant"),
    [(["experimnt"], "'experiment'"), (["graph", "--state", ".", "--format", "dt"], "'dot'")],
)
def test_a_misspelt_choice_exits_2_saying_which_was_meant(argv: list[str], meant: str) -> None:
    result = rr_actors_command(*argv)

    assert 2 == result.returncode
    assert f"invalid choice: {argv[-1]!r}; did you mean {meant}? (known: " in result.stderr


OPTION_TYPOS = [  # (the command line, the subcommand, what was meant): every subcommand
    (["--verison"], "", "--version"),
    (["demo", "--fats"], "demo", "--fast"),
    (["inspect", "x.db", "--jsno"], "inspect", "--json"),
    (["observe", "--state", "s", "--prot", "3"], "observe", "--port"),
    (["graph", "--state", "s", "--fromat", "dot"], "graph", "--format"),
    (["events", "--merge", "a.jsonl", "--cuont", "3"], "events", "--count"),
    (["experiment", "first", "--repaet", "1"], "experiment", "--repeat"),
    (["check", "run", "--quite"], "check", "--quiet"),
    (["replay", "run", "--stroy"], "replay", "--story"),
    (["shrink", "run", "--seed", "1", "--tires", "3"], "shrink", "--tries"),
    (["certs", "init", "ca", "--system", "lab", "--froce"], "certs init", "--force"),
    (["certs", "issue", "ca", "robot", "--dyas", "3"], "certs issue", "--days"),
    (["teach", "check", ".", "--sede", "1"], "teach check", "--seed"),
    (["teach", "hint", ".", "--hepl"], "teach hint", "--help"),
]


@pytest.mark.parametrize(
    ("argv", "command", "meant"), OPTION_TYPOS, ids=[" ".join(c[0]) for c in OPTION_TYPOS]
)
def test_a_misspelt_option_exits_2_with_its_commands_usage_saying_which_was_meant(
    argv: list[str], command: str, meant: str, tmp_path: Path
) -> None:
    """Issue 70, item 9: argparse told a subcommand's unknown option with the top-level
    usage and no hint (`rr-actors demo --fats`: `usage: rr-actors [-h] ...`)."""
    result = subprocess.run(
        [str(Path(sysconfig.get_path("scripts")) / "rr-actors"), *argv],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=tmp_path,  # (nothing is read or written: the option is refused first)
    )

    prog = f"rr-actors {command}".strip()
    (wrong,) = [a for a in argv if a.startswith("--") and sorted(a) == sorted(meant)]
    lines = result.stderr.splitlines()
    assert (2, "") == (result.returncode, result.stdout)
    assert lines[0].startswith(f"usage: {prog} "), result.stderr
    assert f"{prog}: error: unknown option {wrong}; did you mean {meant}?" == lines[-1]
    assert [] == list(tmp_path.iterdir())


def test_an_unknown_option_without_a_close_one_is_named_alone_and_a_stray_argument_too() -> None:
    unknown = rr_actors_command("inspect", "x.db", "--zzzzzz")
    stray = rr_actors_command("inspect", "x.db", "y.db")

    said = [result.stderr.splitlines()[-1] for result in (unknown, stray)]
    assert (2, 2) == (unknown.returncode, stray.returncode)
    assert [
        "rr-actors inspect: error: unknown option --zzzzzz",
        "rr-actors inspect: error: unrecognized arguments: y.db",
    ] == said


HEAVY = (
    "rr_actors_lab.observe",  # the observer (and its web server's starlette, uvicorn)
    "rr_actors_lab.mission",
    "rr_actors_lab.experiments",
    "rr_actors_lab.otel",
    "starlette",
    "sse_starlette",
    "uvicorn",
    "matplotlib",
    "rich",
    "opentelemetry",
    "zenoh",
    "cryptography",
)
"""What a command that does not use them must not import (issue 70, item 9: `rr-actors
--version` took about 1 s, importing the observer to build the parser)."""


def imported(argv: list[str], *, cwd: Path) -> list[str]:
    """The modules `python -X importtime argv...` imported, in order (its stderr's table)."""
    result = python("-X", "importtime", *argv, timeout=60, cwd=cwd)
    assert 0 == result.returncode, result.stderr
    rows = [line.split("|")[-1] for line in result.stderr.splitlines()]
    return [row.strip() for row in rows if row.startswith(" ")]


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["teach", "hint"]], ids=" ".join)
def test_a_command_imports_no_tool_it_does_not_run(argv: list[str], tmp_path: Path) -> None:
    started = python(
        "-m", "rr_actors_lab", "teach", "start", "camera", str(tmp_path / "ex"), timeout=60
    )
    assert 0 == started.returncode, started.stderr

    modules = imported(["-m", "rr_actors_lab", *argv], cwd=tmp_path / "ex")

    assert "rr_actors_lab._cli" in modules  # (the table was read)
    assert [] == [m for m in modules if any(m == h or m.startswith(f"{h}.") for h in HEAVY)]


@pytest.mark.parametrize("argv", [["--version"], ["--help"]], ids=" ".join)
def test_the_console_script_prints_its_version_and_help_without_the_runtime(
    argv: list[str], tmp_path: Path
) -> None:
    """`rr-actors --version` and `--help` need no module of rr_actors: Python's start."""
    script = Path(sysconfig.get_path("scripts")) / "rr-actors"

    modules = imported([str(script), *argv], cwd=tmp_path)

    assert "rr_actors_lab._cli" in modules
    assert [] == [m for m in modules if m == "rr_actors" or m.startswith("rr_actors.")]


# -- 80 columns (issue 44, item 2) ----------------------------------------------------------

TERMINAL_COMMANDS = {
    "help": ["--help"],
    "experiment --help": ["experiment", "--help"],
    "experiment --list": ["experiment", "--list"],
    "demo": ["demo", "--fast", "--out", "{out}"],
    "demo --observe": ["demo", "--fast", "--observe", "--linger", "0.1", "--out", "{out}"],
    "experiment": ["experiment", "first", "--repeat", "1", "--out", "{out}"],
}
CUT = re.compile(r"\w~(\s|$)|…")
"""What a name cut short looks like: `one_for~`, `manag…`."""


@pytest.mark.timeout(150)
@pytest.mark.parametrize("name", list(TERMINAL_COMMANDS))
def test_on_an_80_column_terminal_every_line_fits_and_no_name_is_cut(
    name: str, tmp_path: Path
) -> None:
    argv = [a.format(out=tmp_path / "out") for a in TERMINAL_COMMANDS[name]]

    code, text = on_a_terminal(
        [sys.executable, "-m", "rr_actors_lab", *argv], columns=80, timeout=120, cwd=tmp_path
    )

    pieces = drawn(text)
    assert 0 == code, text
    assert [] == [p for p in pieces if len(p) > 80], text
    assert [] == [p for p in pieces if CUT.search(p)], text
    assert str(tmp_path) not in text  # (paths as typed: relative to the working directory)
    assert str(PACKAGE) not in text  # (nor where rr_actors is installed)
    if name == "experiment":
        runs = [m[1] for p in pieces if (m := re.match(r"run \d+/\d+ (\S+) seed \d+: ", p))]
        assert {"one_for_one", "rest_for_one"} == set(runs), text
    if name == "demo --observe":
        urls = re.findall(r"http://127\.0\.0\.1:\d+/\S*", text)
        assert 2 <= len(urls), text
        assert {urls[0]} == set(urls), text  # whole at the start and at the end


@pytest.mark.timeout(150)
def test_on_an_80_column_terminal_the_certs_lines_fit_and_the_next_command_is_whole(
    tmp_path: Path,
) -> None:
    """`certs init` then `certs issue`, as the securing how-to runs them: each says what
    to do next within 80 columns (their lines were 107 and 186 columns)."""
    said = []
    for argv in (
        ["certs", "init", "certs", "--system", "lab"],
        ["certs", "issue", "certs", "robot", "--address", "10.0.0.2", "--address", "robot.local"],
    ):
        code, text = on_a_terminal(
            [sys.executable, "-m", "rr_actors_lab", *argv], columns=80, timeout=120, cwd=tmp_path
        )
        assert 0 == code, text
        said.append(text)

    pieces = drawn("".join(said))
    assert [] == [p for p in pieces if len(p) > 80], said
    assert "    rr-actors certs issue certs NAME --address ADDR" in pieces, said
    assert any(p.endswith("rr.ZenohTLS(members=[...])") for p in pieces), said  # (whole)


def run(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    code = main(list(argv), out)
    return code, out.getvalue()


def write_v1_backup(path: Path) -> None:
    """A backup as rr_actors wrote it with schema version 1 (text states, no digests)."""
    db = sqlite3.connect(path, isolation_level=None)
    db.execute(f"PRAGMA application_id = {schema.APPLICATION_ID}")
    schema.MIGRATIONS[0](db)
    db.execute("UPDATE rr_actors_schema SET version = 1")
    db.execute("PRAGMA journal_mode = WAL")
    db.execute(
        "INSERT INTO resources VALUES (1, 'r1', 'leaf', 'loaded', ?, ?)",
        (schema.dumps({"cam": 1}), schema.dumps({"pid": 42})),
    )
    db.execute("INSERT INTO consumers VALUES (2, 'q1', 'r1', 'C')")
    db.close()


def _backup(path: Path, name: str) -> None:
    """A backup at `path` of a registrar `name` (started and stopped)."""
    rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, backup_path=path)).stop()


# -- inspect reads one consistent snapshot of a live file ---------------------------------------


class WriterBetweenReads:
    """A read connection; right after the resources were read, another connection commits a
    resource with a consumer (what a live registrar may do while `inspect` reads)."""

    def __init__(self, db: sqlite3.Connection, path: Path) -> None:
        self._db = db
        self._path = path
        self.wrote = False

    def execute(self, sql: str, *args: Any) -> Any:
        cursor = self._db.execute(sql, *args)
        if not sql.startswith("SELECT seq, id, server, state") or self.wrote:
            return cursor
        rows = cursor.fetchall()
        self.wrote = True
        writer = sqlite3.connect(self._path, isolation_level=None)
        try:
            writer.execute("BEGIN IMMEDIATE")
            writer.execute(
                "INSERT INTO resources (seq, id, server, state, digest, request, response) "
                "VALUES (50, 'r-new', 'leaf', 1, ?, ?, NULL)",
                (request_digest(2), schema.dumps(2)),
            )
            writer.execute("INSERT INTO consumers VALUES (50, 51, 'q-new', 'C')")
            writer.execute("COMMIT")
        finally:
            writer.close()
        return _Rows(rows)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._db, name)


class _Rows:
    def __init__(self, rows: list[Any]) -> None:
        self._rows = rows

    def fetchall(self) -> list[Any]:
        return self._rows


class TestInspect:
    """`rr-actors inspect PATH`: a catalog backup as a tree or as JSON, also of a live file."""

    @pytest.fixture
    def live(self, tmp_path: Path) -> Iterator[tuple[rr.ResourceRegistrar, Path, dict[str, Any]]]:
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
        self,
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
        self,
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
        self,
        live: tuple[rr.ResourceRegistrar, Path, dict[str, Any]],
    ) -> None:
        provider, path, _ = live
        run("inspect", str(path))

        later = provider.call(provider.name, "leaf", {"cam": 2})

        assert later.id in run("inspect", str(path))[1]

    def test_inspect_marks_in_doubt_resources(self, tmp_path: Path) -> None:
        store, catalog = new_store(tmp_path / "p.db")
        catalog.begin_load("r-loading", "start_process", {"cmd": "sleep"})
        store.write(catalog.drain_changes())
        store.close(erase=False)

        code, out = run("inspect", str(tmp_path / "p.db"))

        [line] = [line for line in out.splitlines() if "r-loading" in line]
        assert (0, True, True) == (code, "[IN DOUBT: loading]" in line, "1 in doubt" in out)

    def test_inspect_marks_a_resource_its_provider_reported_fatal(self, tmp_path: Path) -> None:
        store, catalog = new_store(tmp_path / "p.db")
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

    def test_inspect_shows_a_value_it_cannot_unpickle_instead_of_failing(
        self, tmp_path: Path
    ) -> None:
        store, catalog = new_store(tmp_path / "p.db")
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
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str]
    ) -> None:
        (tmp_path / "p.db").write_bytes(b"not a database at all" * 100)

        code, _ = run("inspect", str(tmp_path / "p.db"))

        assert (1, True) == (code, str(tmp_path / "p.db") in capsys.readouterr().err)

    def test_inspect_of_a_missing_file_exits_1(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str]
    ) -> None:
        code, _ = run("inspect", str(tmp_path / "nothing.db"))

        assert (1, True) == (code, "no catalog backup" in capsys.readouterr().err)

    def test_the_command_line_runs_as_a_program(
        self,
        live: tuple[rr.ResourceRegistrar, Path, dict[str, Any]],
    ) -> None:
        _, path, ids = live

        done = python("-m", "rr_actors_lab", "inspect", str(path), "--json", timeout=30)

        assert (0, ids["first"]) == (
            done.returncode,
            json.loads(done.stdout)["servers"]["leaf"][0]["consumers"][0]["query_id"],
        )

    def test_inspect_reads_a_schema_1_backup_without_changing_it(self, tmp_path: Path) -> None:
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

    def test_inspect_of_a_state_dir_prints_every_backup_in_it_and_its_subfolders(
        self,
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
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str]
    ) -> None:
        code, _ = run("inspect", str(tmp_path))

        assert 1 == code
        assert "is a folder that holds no catalog backup (*.db): name a registrar's backup" in (
            capsys.readouterr().err
        )

    def test_inspect_marks_a_half_unloaded_resource_in_doubt_in_the_tree_and_the_json(
        self,
        tmp_path: Path,
    ) -> None:
        path = tmp_path / "p.db"
        write_unloading(path)

        code, tree = run("inspect", str(path))
        json_code, data = run("inspect", str(path), "--json")

        [line] = [line for line in tree.splitlines() if "r-stop" in line]
        [resource] = json.loads(data)["servers"]["start_process"]
        assert (0, 0, True, True, True) == (
            code,
            json_code,
            "[IN DOUBT: unloading]" in line,
            "1 in doubt" in tree,
            resource["in_doubt"],
        )

    def test_inspect_json_marks_a_half_loaded_resource_in_doubt(self, tmp_path: Path) -> None:
        path = tmp_path / "p.db"
        store, catalog = new_store(path)
        catalog.begin_load("r-loading", "start_process", {"cmd": "sleep"})
        catalog.begin_load("r-fine", "start_process", {"cmd": "true"})
        catalog.finish_load("r-fine", {"pid": 1})
        store.write(catalog.drain_changes())
        store.close(erase=False)

        code, out = run("inspect", str(path), "--json")

        flags = {r["id"]: r["in_doubt"] for r in json.loads(out)["servers"]["start_process"]}
        assert (0, {"r-loading": True, "r-fine": False}) == (code, flags)

    def test_inspect_reads_one_snapshot_while_a_registrar_commits(
        self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        path = tmp_path / "p.db"
        store, catalog = new_store(path)
        catalog.begin_load("r1", "leaf", 1)
        catalog.finish_load("r1", 1)
        catalog.add_consumer("r1", "q1", "C")
        store.write(catalog.drain_changes())  # the live registrar keeps its store open
        real_connect = files.connect
        wrappers: list[WriterBetweenReads] = []

        def connect(where: Path, *, read_only: bool) -> Any:
            db = real_connect(where, read_only=read_only)
            if not read_only:
                return db
            wrapper = WriterBetweenReads(db, path)
            wrappers.append(wrapper)
            return wrapper

        monkeypatch.setattr(files, "connect", connect)
        try:
            backup = read_backup(path)
        finally:
            monkeypatch.undo()
            store.close(erase=False)

        assert any(w.wrote for w in wrappers)
        assert [("r1", ["q1"])] == [(r.id, list(r.consumers)) for r in backup.resources]
        assert {"r1", "r-new"} == {r.id for r in read_backup(path).resources}


BOUND = 30.0


# -- an experiment's events.jsonl, and what --merge refuses (issue 44) ------------------------

PLAN = """\
name = "merged"
duration = 1.0
repeat = 2
seed = 7

[tree]
strategy = "one_for_one"

[[tree.children]]
name = "db"
setup = "rr_actors_lab.experiments.services:service"

[workload]
clients = 1
rate = 10.0
hold = 0.2

[[workload.calls]]
manager = "db"
server = "resource"

[[faults]]
kind = "kill_manager"
target = "db"
at = [0.5]
"""


def _rr_actors(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(  # noqa: PLW1510 - the exit code is what is checked
        [sys.executable, "-m", "rr_actors_lab", *argv],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


REFUSED = {
    # name: (the line, what the refusal says)
    "a field of neither": (
        json.dumps(
            {**events.to_dict(events.ResourceLoaded("erm", "cam", "r1", "q1", 0.1)), "x": 1}
        ),
        "out/events.jsonl line 1: ResourceLoaded: unknown fields ['x']",
    ),
    "an event without some of its fields": (
        json.dumps(
            {
                "type": "ResourceLoaded",
                "query_id": "q1",
                "load_s": 0.1,
                "schema": events.lines.SCHEMA,
            }
        ),
        "out/events.jsonl line 1: ResourceLoaded: missing fields ['registrar', 'server', "
        "'resource_id', 'digest', 'label', 'trace', 'at', 'pid', 'seq', 'host', 'hlc']",
    ),
    "not JSON": (
        '{"type": ResourceLoaded}',
        "out/events.jsonl line 1: not JSON (column 10: Expecting value)",
    ),
    "a run that is no number": (
        json.dumps({**events.to_dict(events.ChildStarted("root", "db", 4)), "run": "one"}),
        "out/events.jsonl line 1: run must be an int >= 0, got 'one'",
    ),
}


class TestEvents:
    """`rr-actors events`: every host's events as JSON lines (`--network`), or files merged
    (`--merge`).

    The live stream runs in a child process (`python -m rr_actors_lab events ...`) against a
    `ZenohNetwork` of this process on loopback (plain TCP, `--plain`): it prints what this
    process's registrar does, one `events.to_dict` line per event, and ends after `--count`.
    """

    def test_merge_prints_the_files_events_ordered_by_hlc(self, tmp_path: Path) -> None:
        robot = [
            events.ConsumerAdded("erm", "r1", "q1", "app", at=105.0, pid=2, host="robot", hlc=10),
            events.ResourceLoaded(
                "erm", "cam", "r1", "q1", 0.1, at=104.0, pid=2, host="robot", hlc=9
            ),
        ]
        operator = [
            events.CallAnswered("app", "q1", "erm", "cam", at=100.0, pid=1, host="operator", hlc=11)
        ]
        (tmp_path / "robot.jsonl").write_text(
            "".join(json.dumps(events.to_dict(e)) + "\n" for e in robot)
        )
        (tmp_path / "operator.jsonl").write_text(
            "".join(json.dumps(events.to_dict(e)) + "\n" for e in operator)
        )
        out = io.StringIO()

        code = main(
            ["events", "--merge", str(tmp_path / "operator.jsonl"), str(tmp_path / "robot.jsonl")],
            out,
        )

        assert 0 == code
        printed = [events.from_dict(json.loads(line)) for line in out.getvalue().splitlines()]
        assert [robot[1], robot[0], operator[0]] == printed  # by hlc, not by file nor by `at`

    def test_merge_names_the_file_and_line_of_what_is_not_an_event(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str]
    ) -> None:
        bad = tmp_path / "bad.jsonl"
        bad.write_text('{"type": "Exploded", "schema": 3}\n')
        assert 1 == main(["events", "--merge", str(bad)], io.StringIO())
        assert f"{bad} line 1" in capsys.readouterr().err

    @pytest.mark.parametrize(
        ("argv", "named"),
        [
            ([], "--network"),
            (["--network", "tls/10.0.0.1:7447"], "--system"),
            (["--network", "tls/10.0.0.1:7447", "--system", "lab"], "--certs"),
            (
                ["--network", "tcp/10.0.0.1:7447", "--system", "lab", "--plain", "--member", "x"],
                "--plain",
            ),
        ],
    )
    def test_without_what_joins_the_system_it_says_what_is_missing(
        self, argv: list[str], named: str, capsys: pytest.CaptureFixture[str]
    ) -> None:
        assert 1 == main(["events", *argv], io.StringIO())
        assert named in capsys.readouterr().err

    def test_the_live_stream_prints_what_a_registrar_of_the_system_does(self) -> None:
        port = free_port()
        system = f"cli-{uuid.uuid4().hex[:8]}"
        net = rr.ZenohNetwork(system=system, listen=[f"tcp/127.0.0.1:{port}"], tls=None)
        erm = rr.ResourceRegistrar.start(rr.RegistrarConfig(name="erm"), network=net)
        erm.register_server("camera", load=lambda request: request, unload=lambda *_: None)
        command = [sys.executable, "-m", "rr_actors_lab", "events", "--network"]
        command += [f"tcp/127.0.0.1:{port}", "--system", system, "--plain", "--count", "3"]
        child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            probe = 0
            while True:  # (its subscription reaches this process a little after it starts)
                probe += 1
                erm.unload(erm.call("erm", "camera", {"probe": probe}).id)
                try:
                    out, err = child.communicate(timeout=0.2)
                    break
                except subprocess.TimeoutExpired:
                    assert probe < BOUND / 0.2, "rr-actors events printed nothing"
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
            erm.stop()
            net.close()
        assert 0 == child.returncode, err
        printed = [json.loads(line) for line in out.splitlines()]
        assert 3 == len(printed)
        assert {"erm"} == {line["registrar"] for line in printed}
        assert [line["hlc"] for line in printed] == sorted(line["hlc"] for line in printed)
        assert all(line["schema"] == events.lines.SCHEMA for line in printed)

    @pytest.mark.timeout(180)
    def test_merge_reads_an_experiments_events_file_with_its_runs_and_faults(
        self, tmp_path: Path
    ) -> None:
        """An experiment adds `run` and `seed` to each event and writes a line per fault: the
        file merges as it is (it was refused: `unknown fields ['run', 'seed']`, exit 1;
        issue 44). Every line comes out once, unchanged, the events in `hlc` order and each
        fault at its `at`, among the events of its run."""
        (tmp_path / "plan.toml").write_text(PLAN)
        ran = _rr_actors("experiment", "plan.toml", "--out", "out", cwd=tmp_path)
        assert 0 == ran.returncode, ran.stderr
        written = (tmp_path / "out" / "events.jsonl").read_text().splitlines()
        station = events.ConsumerAdded("erm", "r1", "q1", "app", at=1.0, pid=9, host="station")
        (tmp_path / "station.jsonl").write_text(json.dumps(events.to_dict(station)) + "\n")

        merged = _rr_actors("events", "--merge", "out/events.jsonl", "station.jsonl", cwd=tmp_path)

        assert (0, "") == (merged.returncode, merged.stderr)
        lines = merged.stdout.splitlines()
        assert sorted([*written, json.dumps(events.to_dict(station))]) == sorted(lines)
        printed = [json.loads(line) for line in lines]
        faults = [line for line in printed if line["type"] == "FaultInjected"]
        assert [(1, 7), (2, 8)] == [(fault["run"], fault["seed"]) for fault in faults]
        stamps = [hlc.from_seconds(p["at"]) if "hlc" not in p else p["hlc"] for p in printed]
        assert stamps == sorted(stamps)
        assert {(1, 7), (2, 8)} == {(p["run"], p["seed"]) for p in printed if "run" in p}
        assert 1 == sum("run" not in p for p in printed)  # the station's event

    @pytest.mark.parametrize("refused", sorted(REFUSED))
    def test_what_merge_refuses_is_one_line_in_a_pipe_and_fits_80_columns_on_a_terminal(
        self, tmp_path: Path, refused: str
    ) -> None:
        """One line naming the file, the line and the problem (exit 1); on an 80-column
        terminal that line wraps at words (`out/events.jsonl line 1: ...` and the problem
        take more than 80 columns with the prefix `rr-actors events: `)."""
        line, says = REFUSED[refused]
        (tmp_path / "out").mkdir()
        (tmp_path / "out" / "events.jsonl").write_text(line + "\n")
        argv = ["events", "--merge", "out/events.jsonl"]

        piped = _rr_actors(*argv, cwd=tmp_path)
        code, shown = on_a_terminal(
            [sys.executable, "-m", "rr_actors_lab", *argv], columns=80, timeout=60, cwd=tmp_path
        )

        assert (1, 1) == (piped.returncode, code)
        assert [f"rr-actors events: {says}"] == piped.stderr.splitlines()
        wide = [f"[{len(row)}] {row}" for row in shown.splitlines() if len(row) > 80]
        assert [] == wide, "lines over 80 columns:\n" + "\n".join(wide)
        assert " ".join(f"rr-actors events: {says}".split()) == " ".join(shown.split())


EVENT = events.to_dict(events.ResourceLoaded("erm", "cam", "r1", "q1", 0.1, at=1.0, pid=2))


def _event_line(**changes: object) -> bytes:
    return (json.dumps({**EVENT, **changes}) + "\n").encode()


FILES: dict[str, tuple[Callable[[Path], None], str, str]] = {
    # name: (how the file is made at the path, what check's error says, what events' says)
    "binary": (
        lambda p: p.write_bytes(_event_line() + b"\xff\xfe\x00\x01\n"),
        "line 2: not UTF-8",
        "line 2: not UTF-8",
    ),
    "nested": (
        lambda p: p.write_bytes(b"[" * 100_000 + b"\n"),
        "line 1: not JSON",
        "line 1: not JSON",
    ),
    "long integer": (  # (Python converts at most 4300 digits: CVE-2020-10735)
        lambda p: p.write_bytes(
            _event_line() + _event_line().replace(b'"pid": 2', b'"pid": 1' + b"0" * 5000)
        ),
        "line 2: not JSON that can be read (a number of more than 4300 digits)",
        "line 2: not JSON that can be read (a number of more than 4300 digits)",
    ),
    **{
        f"{name} at": (
            lambda p, text=text: p.write_bytes(
                _event_line() + _event_line().replace(b'"at": 1.0', b'"at": ' + text)
            ),
            "line 2: ResourceLoaded.at must be a finite number",
            "line 2: ResourceLoaded.at must be a finite number",
        )
        for name, text in (
            ("NaN", b"NaN"),
            ("infinite", b"Infinity"),
            ("minus infinite", b"-Infinity"),
            ("overflowing", b"1e999"),
            ("whole overflowing", b"1" + b"0" * 400),
        )
    },
    "missing": (lambda p: None, "no events.jsonl at", "cannot be read"),
    "directory": (lambda p: p.mkdir(), "no events.jsonl at", "cannot be read"),
}


class TestHostileFiles:
    """`rr-actors check` and `rr-actors events --merge` on files that are not events files.

    Whatever the file holds (binary, JSON nested past the parser's stack, an integer of 5,000
    digits, a time that is `NaN` or infinite, a `run` that is not a number, a line of 64 MiB,
    nothing), or if it is missing or a directory, the command
    prints one line naming the file (and the line) and exits with its error code: 2 for
    `check`, 1 for `events`. No traceback.
    """

    @pytest.mark.parametrize("kind", sorted(FILES))
    @pytest.mark.parametrize(("command", "code"), [("check", 2), ("events", 1)])
    def test_a_file_that_cannot_be_read_is_one_line_naming_it(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str, command: str, code: int
    ) -> None:
        make, check_says, events_says = FILES[kind]
        says = check_says if command == "check" else events_says
        path = tmp_path / "events.jsonl"
        make(path)
        argv = ["check", str(path)] if command == "check" else ["events", "--merge", str(path)]

        assert code == main(argv, io.StringIO())

        err = capsys.readouterr().err
        assert (1, True, True) == (len(err.splitlines()), f"{path}" in err, says in err), err

    @pytest.mark.parametrize("run", ["one", [1], -1, True])
    def test_check_of_a_line_whose_run_is_not_a_run_number_names_the_line(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str], run: object
    ) -> None:
        path = tmp_path / "events.jsonl"
        path.write_bytes(_event_line(run=0) + _event_line(run=run))

        assert 2 == main(["check", str(path)], io.StringIO())

        assert f"{path} line 2: run must be an int" in capsys.readouterr().err

    def test_a_line_over_the_bound_is_refused_naming_it_without_reading_it_whole(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
    ) -> None:
        monkeypatch.setattr(lines, "MAX_LINE_BYTES", 1000)
        path = tmp_path / "events.jsonl"
        path.write_bytes(_event_line() + b'{"x": "' + b"x" * 5000 + b'"}\n')

        assert 1 == main(["events", "--merge", str(path)], io.StringIO())

        assert f"{path} line 2: longer than 1000 bytes" in capsys.readouterr().err

    @pytest.mark.parametrize("text", ["", "\n\n", '{"not": "an event"}\n[1, 2]\n'])
    def test_check_of_a_file_without_events_says_so_instead_of_printing_nothing(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str
    ) -> None:
        path = tmp_path / "events.jsonl"
        path.write_text(text)
        out = io.StringIO()

        assert 2 == main(["check", str(path)], out)

        assert ("", True) == (out.getvalue(), f"{path}: no events" in capsys.readouterr().err)

    @pytest.mark.parametrize("option", [["--count", "0"], ["--count", "-1"], ["--seconds", "-5"]])
    def test_events_with_a_count_or_seconds_that_is_not_positive_is_a_usage_error(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str], option: list[str]
    ) -> None:
        path = tmp_path / "events.jsonl"
        path.write_bytes(_event_line() + _event_line(hlc=EVENT["hlc"] + 1))

        with pytest.raises(SystemExit) as exited:
            main(["events", "--merge", str(path), *option], io.StringIO())

        assert (2, True) == (exited.value.code, option[0] in capsys.readouterr().err)

    @pytest.mark.parametrize(
        ("rows", "says"),
        [
            ({"consumers": [["q1"]]}, "CatalogRestored.consumers: a row of fewer than 3 fields"),
            ({"clients": [["q1", "erm"]]}, "CatalogRestored.clients: a row of fewer than 4 fields"),
            (
                {"resources": [["r1", "cam", "loaded", "x" * 5000]]},
                "CatalogRestored.resources: a digest that is not a whole number",
            ),
        ],
    )
    def test_check_of_a_catalog_row_it_cannot_read_names_the_line(
        self, tmp_path: Path, capsys: pytest.CaptureFixture[str], rows: dict[str, object], says: str
    ) -> None:
        restored = events.to_dict(events.CatalogRestored("erm", (), (), (), at=1.0, pid=2))
        path = tmp_path / "events.jsonl"
        path.write_bytes(_event_line() + (json.dumps({**restored, **rows}) + "\n").encode())

        assert 2 == main(["check", str(path)], io.StringIO())

        err = capsys.readouterr().err
        assert (1, True) == (len(err.splitlines()), f"{path} line 2: {says}" in err), err
