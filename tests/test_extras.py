"""The extras of `pyproject.toml`, tried without them as a new user would (issue 44, item 1).

Each command and API that needs an extra runs in a virtual environment that has rr_actors
and its two dependencies only (`tests/support/bare_venv.py`, made once per session), from
the checkout as after the README's `pip install -e ...`. Without its extra, each says so in
one line that names the extra and the command that installs it, exits with 2 and leaves
nothing behind; no traceback. What runs without its extra (the demo without `demo`, a
manager process without `title`) runs, and says what it left out.
"""

from __future__ import annotations

import subprocess
import textwrap
from pathlib import Path

import pytest

from rr_actors._extras import DISTRIBUTION
from tests.support.bare_venv import ROOT, make_bare_venv


@pytest.fixture(scope="session")
def bare(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The `python` of a virtual environment without any extra."""
    return make_bare_venv(tmp_path_factory.mktemp("bare") / "venv")


def run(python: Path, argv: list[str], *, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    """`python argv...` from `cwd` (the checkout, as a new user runs `rr-actors` there)."""
    return subprocess.run(
        [str(python), *argv], cwd=cwd, capture_output=True, text=True, timeout=120, check=False
    )


def command(extra: str) -> str:
    """The command that installs `extra` from the working directory, the checkout."""
    return f'pip install -e ".[{extra}]"'


def make_backup(python: Path, state: Path) -> None:
    """A catalog backup in `state` (`rr-actors observe --state` wants one)."""
    source = (
        "import sys, rr_actors as rr\n"
        "r = rr.ResourceRegistrar.start(rr.RegistrarConfig(name='erm', backup_path=sys.argv[1]))\n"
        "r.stop()\n"
    )
    result = run(python, ["-c", source, str(state / "erm.db")])
    assert 0 == result.returncode, result.stderr


CLI_CASES = [  # (the extra, the command, the line's subject: the command or what needs it)
    ("zenoh", ["demo", "--hosts", "2", "--out", "{out}"], "demo: --hosts 2"),
    ("zenoh", ["certs", "init", "{out}", "--system", "lab"], "certs"),
    (
        "zenoh",
        ["events", "--network", "tcp/127.0.0.1:7447", "--system", "lab"],
        "events: --network",
    ),
    (
        "zenoh",
        ["observe", "--system", "lab", "--connect", "tcp/127.0.0.1:7447"],
        "observe: --system",
    ),
    ("observe", ["observe", "--state", "{state}"], "observe"),
    ("observe", ["demo", "--fast", "--observe", "--out", "{out}"], "demo: --observe"),
    ("experiments", ["experiment", "--list"], "experiment"),
    ("experiments", ["experiment", "first", "--out", "{out}"], "experiment"),
    ("experiments", ["check", "{state}"], "check"),
]


@pytest.mark.parametrize(
    ("extra", "argv", "what"), CLI_CASES, ids=[" ".join(c[1][:2]) for c in CLI_CASES]
)
def test_a_command_without_its_extra_says_which_and_how_to_install_it_in_one_line(
    bare: Path, tmp_path: Path, extra: str, argv: list[str], what: str
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    make_backup(bare, state)
    out = tmp_path / "out"
    filled = [a.format(out=out, state=state) for a in argv]

    result = run(bare, ["-m", "rr_actors_lab", *filled])

    [line] = result.stderr.splitlines()
    wheel = line.replace(command(extra), f'pip install "{DISTRIBUTION}[{extra}]"')
    assert (2, "") == (result.returncode, result.stdout)
    assert f"rr-actors {what} needs an extra: {command(extra)}" == line
    assert [] == [text for text in (line, wheel) if len(text) > 80]  # 80 columns, as a wheel too
    assert not out.exists()


API_CASES = [
    ("zenoh", "import rr_actors as rr\nrr.ZenohNetwork", "rr.ZenohNetwork"),
    ("zenoh", "import rr_actors as rr\nrr.ZenohTLS", "rr.ZenohTLS"),
    (
        "observe",
        "import rr_actors as rr\nfrom rr_actors_lab.observe import observe\n"
        "with rr.Supervisor([]) as sup:\n    observe(sup)",
        "the observer",
    ),
    ("experiments", "import rr_actors_lab.experiments", "rr_actors_lab.experiments"),
    ("simulation", "import rr_actors.simulation", "rr_actors.simulation"),
]


@pytest.mark.parametrize(("extra", "source", "what"), API_CASES, ids=[c[2] for c in API_CASES])
def test_an_api_without_its_extra_raises_missing_extra_error_naming_it(
    bare: Path, extra: str, source: str, what: str
) -> None:
    caught = (
        "import rr_actors as rr\n"
        "try:\n" + textwrap.indent(source, "    ") + "\n"
        "except rr.MissingExtraError as exc:\n"
        "    assert isinstance(exc, ImportError) and isinstance(exc, rr.ConfigError)\n"
        "    print(exc.extra)\n"
        "    print(exc)\n"
    )

    result = run(bare, ["-c", caught])

    assert (0, "") == (result.returncode, result.stderr)
    assert [extra, f"{what} needs an extra: {command(extra)}"] == (result.stdout.splitlines())


def test_the_demo_without_its_extra_runs_and_says_what_installs_the_plot(
    bare: Path, tmp_path: Path
) -> None:
    out = tmp_path / "demo"

    result = run(bare, ["-m", "rr_actors_lab", "demo", "--fast", "--out", str(out)])

    assert (0, "") == (result.returncode, result.stderr)
    assert f"plot:   not drawn: mission.png needs an extra: {command('demo')}" in (
        result.stdout.splitlines()
    )
    assert (out / "report.json").exists()
    assert not (out / "mission.png").exists()


def test_a_manager_process_without_the_title_extra_runs_named_and_says_nothing(
    bare: Path,
) -> None:
    """Nothing needs `title`: without setproctitle the kernel's name of the process is
    still the manager's (`ps -o comm`); only the command line stays Python's."""
    source = textwrap.dedent(
        """
        import rr_actors as rr

        def setup(erm):
            erm.register_server("camera", load=lambda r: r, unload=lambda r, s: None)

        with rr.Supervisor([rr.ManagerSpec("erm", setup, isolation="process")]) as sup:
            with open(f"/proc/{sup.child('erm').pid}/comm") as comm:
                print(comm.read().strip())
        """
    )

    result = run(bare, ["-c", source])

    assert (0, "erm\n", "") == (result.returncode, result.stdout, result.stderr)


def test_every_extra_a_user_installs_is_in_pyproject_and_said_what_it_brings() -> None:
    import tomllib  # noqa: PLC0415

    from rr_actors._extras import EXTRAS  # noqa: PLC0415

    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]

    assert set(EXTRAS) <= set(declared)
    assert {"demo", "experiments", "observe", "teach", "title", "zenoh"} == set(EXTRAS)


def test_the_teach_extra_holds_what_the_replay_page_and_the_progress_bar_need() -> None:
    """Issue 70 item 6: `pip install ".[teach]"` left `rr-actors teach replay` asking for
    the `observe` extra."""
    import tomllib  # noqa: PLC0415

    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"
    ]

    assert set(declared["observe"]) <= set(declared["teach"])
    assert {"greenlet>=3.0", "msgspec>=0.18", "rich>=13"} <= set(declared["teach"])


def _closure(requirements: list[str]) -> set[str]:
    """The distributions `requirements` install, with theirs (normalized names)."""
    import importlib.metadata  # noqa: PLC0415
    import re  # noqa: PLC0415

    def name(requirement: str) -> str:
        return re.split(r"[\s;<>=!~\[(]", requirement, maxsplit=1)[0].lower().replace("_", "-")

    seen: set[str] = set()
    todo = [name(r) for r in requirements if "extra ==" not in r]
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        seen.add(current)
        try:
            nested = importlib.metadata.requires(current) or []
        except importlib.metadata.PackageNotFoundError:
            continue
        todo.extend(name(r) for r in nested if "extra ==" not in r)
    return seen


def test_the_dev_extra_holds_every_import_of_the_tests_and_no_benchmark_peer() -> None:
    """`pip install -e ".[dev]"` is what the tests and linters need, no more (issue 44)."""
    import ast  # noqa: PLC0415
    import importlib.metadata  # noqa: PLC0415
    import sys  # noqa: PLC0415
    import tomllib  # noqa: PLC0415

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    dev = _closure(project["optional-dependencies"]["dev"] + project["dependencies"])
    modules = {
        (node.module if isinstance(node, ast.ImportFrom) else alias.name).split(".")[0]
        for path in (ROOT / "tests").rglob("*.py")
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Import | ast.ImportFrom) and not getattr(node, "level", 0)
        for alias in node.names
        if not isinstance(node, ast.ImportFrom) or node.module
    }
    third_party = (
        modules
        - set(sys.stdlib_module_names)
        - {"rr_actors", "rr_actors_lab", "tests", "__future__"}
    )
    owners = importlib.metadata.packages_distributions()
    missing = {
        module: owners.get(module)
        for module in third_party
        if not any(d.lower().replace("_", "-") in dev for d in owners.get(module, [module]))
    }

    assert {} == missing
    assert "xoscar" not in dev
    assert "opentelemetry-exporter-otlp-proto-common" not in dev
    assert [
        "xoscar>=0.12",  # bench_xoscar.py's peer
        "opentelemetry-exporter-otlp-proto-common>=1.20",  # bench_otel_cross.py's OTLP encoder
    ] == project["optional-dependencies"]["bench"]
