"""The observer's commands (`rr_actors_lab.observe._commands`): `rr-actors observe --state DIR` and
`rr-actors graph --state DIR`."""

from __future__ import annotations

import hashlib
import io
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors_lab.__main__ import main
from rr_actors_lab.observe import observe_backups
from tests.support.observed_tree import REQUEST, figure_27
from tests.support.observing import get_json, request, wait_state
from tests.support.python import python


@pytest.fixture
def state(supervisors: Any, process_helpers: Any, tmp_path: Path) -> Iterator[Path]:
    """A state directory whose backups hold figure 2.7 loaded (its tree still runs)."""
    directory = tmp_path / "state"
    sup = figure_27(supervisors, isolation="thread", state_dir=directory).start()
    app = sup.registrar(rr.RegistrarConfig("action", backup_path=str(directory / "action.db")))
    query = app.call("cm", "filtered_camera", REQUEST)
    yield directory
    app.unload(query.id)


def digests(directory: Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(directory.iterdir())
        if p.suffix == ".db"
    }


def run(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    code = main(list(argv), out)
    return code, out.getvalue()


# -- graph ----------------------------------------------------------------------------------------


def test_graph_prints_the_dependency_graph_of_the_backups_as_mermaid(state: Path) -> None:
    code, text = run("graph", "--state", str(state))

    assert 0 == code
    assert text.startswith("flowchart TB\n")
    assert 'subgraph r2["cm"]' in text
    assert 'subgraph r3["erm"]' in text
    assert 3 == text.count(" -.")  # action -> cm -> erm (camera, filter)


def test_graph_prints_dot(state: Path) -> None:
    code, text = run("graph", "--state", str(state), "--format", "dot")

    assert 0 == code
    assert text.startswith("digraph rr_actors {")
    assert "subgraph cluster_r3 {" in text
    assert 3 == text.count("style=dashed")


@pytest.mark.parametrize(
    ("command", "where", "error"),
    [
        (["graph"], "nope", "does not exist"),
        (["graph"], "", "holds no catalog backup"),
        (["observe", "--for", "0.1"], "nope", "does not exist"),
    ],
    ids=[
        "graph_of_a_missing_directory",
        "graph_of_a_directory_without_backups",
        "observe_of_a_missing_directory",
    ],
)
def test_a_state_directory_missing_or_without_backups_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str], where: str, error: str
) -> None:
    code, _ = run(*command, "--state", str(tmp_path / where))

    assert 1 == code
    assert error in capsys.readouterr().err


def test_a_corrupt_backup_is_named_and_left_as_it_was(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "erm.db"
    bad.write_bytes(b"this is not a catalog" * 50)
    before = bad.read_bytes()

    code, _ = run("graph", "--state", str(tmp_path))

    assert 1 == code
    assert str(bad) in capsys.readouterr().err
    assert before == bad.read_bytes()
    assert ["erm.db"] == sorted(p.name for p in tmp_path.iterdir())


# -- observe --------------------------------------------------------------------------------------


def test_the_offline_page_shows_every_backup_and_the_graph(state: Path) -> None:
    with observe_backups(state) as observer:
        sections = get_json(observer.url, "/api/state")["sections"]

    assert ["action", "cm", "erm"] == [f["registrar"] for f in sections["files"]["files"]]
    assert 1 == len(sections["catalog/cm"]["catalog"]["resources"])
    assert 3 == len(sections["graph"]["edges"])


def test_the_offline_page_writes_nothing_to_the_backups(state: Path) -> None:
    before = digests(state)

    with observe_backups(state) as observer:
        get_json(observer.url, "/api/state")

    assert before == digests(state)


def test_the_offline_page_follows_the_backups_as_they_change(
    supervisors: Any, process_helpers: Any, tmp_path: Path
) -> None:
    directory = tmp_path / "state"
    sup = figure_27(supervisors, isolation="thread", state_dir=directory).start()
    app = sup.registrar("action")
    with observe_backups(directory) as observer:
        query = app.call("cm", "filtered_camera", REQUEST)

        state = wait_state(  # (erm's backup and cm's are written apart: wait for both)
            observer.url,
            lambda s: (
                len(s["sections"]["catalog/erm"]["catalog"]["resources"]) == 2
                and len(s["sections"]["graph"]["edges"]) >= 3
            ),
        )

    assert 3 == len(state["sections"]["graph"]["edges"])  # action (no backup: from cm) -> cm -> erm
    app.unload(query.id)


def test_the_offline_page_has_no_fault_buttons(state: Path) -> None:
    with observe_backups(state) as observer:
        status, _, _ = request(
            observer.url,
            "/api/faults/kill",
            method="POST",
            body=b"{}",
            headers={"Content-Type": "application/json"},
        )

    assert 403 == status


def test_observe_serves_until_its_time_is_up(state: Path) -> None:
    code, text = run("observe", "--state", str(state), "--for", "0.2")

    assert 0 == code
    assert text.startswith("observer: http://127.0.0.1:")


@pytest.mark.parametrize("seconds", ["-1", "nan", "inf", "1e400"])
def test_observe_for_what_is_not_a_positive_number_of_seconds_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], seconds: str
) -> None:
    """`--for -1` (or `nan`) used to serve nothing and exit 0 as if it had served; `inf`
    ended in an OverflowError's traceback. Each is an error that names `--for`."""
    try:
        code, _ = run("observe", "--state", str(tmp_path), "--for", seconds)
    except SystemExit as exc:  # (argparse's refusal)
        code = exc.code  # type: ignore[assignment]

    assert (True, True) == (code not in (0, None), "--for" in capsys.readouterr().err)


def test_observe_on_a_non_loopback_host_needs_allow_remote(
    state: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _ = run("observe", "--state", str(state), "--host", "0.0.0.0", "--for", "0.1")  # noqa: S104

    assert 1 == code
    assert "--allow-remote" in capsys.readouterr().err


def test_the_command_runs_as_a_console_script(state: Path) -> None:
    done = python(
        "-m", "rr_actors_lab", "graph", "--state", str(state), "--format", "dot", timeout=60
    )

    assert (0, "") == (done.returncode, done.stderr)
    assert "digraph" in done.stdout


def test_help_lists_observe_and_graph() -> None:
    done = python("-m", "rr_actors_lab", "--help", timeout=30)

    assert 0 == done.returncode
    assert "observe" in done.stdout
    assert "graph" in done.stdout
