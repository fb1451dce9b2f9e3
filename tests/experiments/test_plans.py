"""The shipped plans (`rr_actors_lab.experiments.plans`): every shipped plan (and those of
examples/experiments/) runs (shortened: one repeat, a shorter duration) and shows what its docs
page says it shows.

The full runs (`--repeat 3`, under a minute each) made the figures of docs/explanation/experiments/.
"""

from __future__ import annotations

import csv
import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rr_actors_lab.experiments import Results, RunResult, load_plan, plans, run

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "experiments"

SHIPPED = {
    "strategies",
    "crashloop",
    "hang",
    "resource",
    "first",
    "killheavy",
    "leases",
    "nobackup",
    "simchain",
    "simretry",
    "simheal",
    "simcancel",
    "simdoubt",
    "simhosts",
    "simshare",
    "simnostate",
    "simrest",
    "simprogram",
    "simslow",
    "simways",
    "simshed",
    "simkept",
    "simkeptdep",
    "simpatient",
    "simoverload",
    "simfair",
    "simcommit",
    "simanswer",
    "simbackup",
    "simstop",
    "simgone",
    "simtimeout",
    "simlisten",
    "simwithdraw",
    "simlong",
    "bigtree",
    "simescalate",
}
"""Every plan shipped in the package; the tutorial's `first` runs in the docs test."""


def shortened(name: str, duration: float) -> Results:
    path = EXAMPLES / "workload.toml" if name == "workload" else plans.find(name)
    return run(load_plan(path), repeat=1, duration=duration)


def by_value(results: Results) -> dict[object, RunResult]:
    return {value: runs[0] for value, runs in results.by_value()}


def test_this_test_knows_every_shipped_plan() -> None:
    assert SHIPPED == set(plans.shipped())
    assert {"workload"} == {p.stem for p in EXAMPLES.glob("*.toml")}


def restarted_for_first_kill(result: RunResult) -> set[str]:
    """Managers the tree took down for the run's first kill and that served again, from the
    down intervals the run recorded: each that went down from the kill on, before the
    killed one served again (a strategy takes its managers down before it starts any) and
    before the next kill. Not "restarted before the next kill": a loaded machine's restarts
    outlast the 0.93 s gap, and the next kill, due at 2.08 s, lands in a 2 s run whose end
    is seen late (the injector fires until it is stopped)."""
    kills = [f for f in result.faults if f.injected_s is not None]
    first = kills[0]
    assert first.injected_s is not None
    assert first.target is not None
    start, back = next(i for i in result.down[first.target] if i[0] >= first.injected_s)
    ends = [float("inf") if back is None else back, *(f.injected_s or 0.0 for f in kills[1:2])]
    return {
        name
        for name, intervals in result.down.items()
        for a, b in intervals
        if start <= a < min(ends) and b is not None
    }


def test_strategies_restart_one_all_or_the_rest_after_a_kill() -> None:
    runs = by_value(shortened("strategies", 2.0))

    for strategy, result in runs.items():
        first = next(f for f in result.faults if f.injected_s is not None)
        restarted = restarted_for_first_kill(result)
        order = ["erm", "cm", "rm"]
        expected = {
            "one_for_one": {first.target},
            "one_for_all": set(order),
            "rest_for_one": set(order[order.index(str(first.target)) :]),
        }[str(strategy)]
        assert expected == restarted, (strategy, first, result.down)
        assert 0 == result.leaked_processes


def tripped(result: RunResult) -> bool:
    """Whether the pool's intensity was exceeded: 3 kills of its worker within its 2 s
    period (its `max_restarts` is 2). A kill is skipped while the worker is down, so how
    many land depends on how fast it restarts, which a loaded machine slows."""
    kills = sorted(
        f.injected_s for f in result.faults if f.injected_s is not None and not f.skipped
    )
    # (2.5 s, not 2: the period counts restarts, which follow their kills by how long each
    # exit took to be seen and handled)
    return any(last - first <= 2.5 for first, last in zip(kills, kills[2:], strict=False))


def test_the_crash_loop_escalates_and_only_a_tolerant_top_survives_it() -> None:
    runs = by_value(shortened("crashloop", 3.0))

    for result in runs.values():  # the pool gives up only when kills came fast enough
        assert tripped(result) or "pool" not in {sup for sup, _ in result.give_ups}
    # (whether they did depends on restart speed, which load slows: a loaded machine may
    # see no escalation at all; the top that tolerates none gives up with its pool)
    pool_gave_up = "pool" in {sup for sup, _ in runs[0].give_ups}
    assert runs[0].gave_up == pool_gave_up
    assert not runs[5].gave_up
    # The tolerant top keeps serving: it fails no more calls than the top that gave up (a
    # call may still time out on a loaded machine while its worker is being restarted).
    assert runs[5].calls_ok > 0
    assert runs[5].calls_failed <= runs[0].calls_failed


def test_the_kill_heavy_plan_breaks_no_rule_and_leaves_nothing() -> None:
    (result,) = shortened("killheavy", 3.0).runs

    assert result.restarts >= 3  # (a kill every 0.15-0.4 s, of edge, api or db)
    assert [] == list(result.findings)
    # (a consumer killed after a release failed, its provider being down, reconciles
    # with every registrar when it is restored: the provider releases the id)
    assert 0 == result.catalog_entries_left, result.findings
    assert 0 == result.leaked_processes


@pytest.mark.timeout(600)  # (its 200 managers start one by one, each with its backup)
def test_the_big_tree_plan_runs_200_managers_through_kills_and_failed_loads_and_holds() -> None:
    plan = load_plan(plans.find("bigtree"))
    isolations = [m.isolation for m in plan.tree.managers()]

    (result,) = run(plan, repeat=1).runs

    assert (200, 10) == (len(isolations), isolations.count("process"))
    assert ("held", []) == (result.verdict, list(result.findings))
    kinds = {f.kind for f in result.faults if f.injected_s is not None}
    assert {"kill_manager", "load_error"} == kinds
    assert result.restarts >= 1  # (a kill every 0.3-0.6 s of a thread or process manager)
    assert result.calls_ok > 0
    assert 0 == result.leaked_processes


def test_the_heartbeat_finds_a_hang_and_without_it_the_hang_lasts() -> None:
    runs = by_value(shortened("hang", 2.0))

    off, fast = runs[False], runs[0.1]
    assert 0 == off.restarts
    # without a heartbeat the planner is down from its hang until its SIGCONT 1.2 s later, or
    # until the run's end if that comes first (a hang injected late on a loaded machine)
    hang = next(f for f in off.faults if f.injected_s is not None)
    assert hang.injected_s is not None
    lasts = min(1.2, off.duration_s - hang.injected_s)
    assert off.unavailable_s["planner"] >= lasts - 0.01, (hang, off.down["planner"])
    assert 1 == fast.restarts
    (hang,) = fast.faults
    assert hang.recovery_s is not None  # the heartbeat's restart served again (how soon is
    # a figure of docs/explanation/experiments/hang.md, measured on a quiet machine, not a
    # test's bound)


def test_a_killed_resource_process_is_heard_and_loaded_again() -> None:
    results = shortened("resource", 2.5)

    killed = [f for _, f in results.faults() if f.injected_s is not None]
    assert killed
    assert all("a process of erm" in f.detail for f in killed)
    assert any(f.recovery_s is not None for f in killed)
    assert [0, 0] == [r.leaked_processes for r in results.runs]


def test_the_workload_plan_calls_through_its_factory_in_lidars_py() -> None:
    # workload.toml names `factory = "lidars:lidar"`: examples/experiments/lidars.py
    (result,) = shortened("workload", 2.0).runs

    assert result.calls_ok > 0
    assert {"cm"} == {c.manager for c in result.calls}
    (kill,) = result.faults
    assert kill.recovery_s is not None


def test_the_leases_plan_compares_three_leases_under_a_cut_and_a_freeze() -> None:
    """(Its runs need root and take minutes: tests/experiments/test_hosts.py
    runs a small plan of the same shape for real.)"""
    plan = load_plan(plans.find("leases"))
    assert [0.5, 1.0, 2.0] == [value for value, _ in plan.variants]
    assert [0.5, 1.0, 2.0] == [p.hosts.lease for _, p in plan.variants if p.hosts is not None]
    assert ["cut", "freeze"] == [fault.kind for fault in plan.faults]


ROOT = Path(__file__).resolve().parents[2]
NEEDED = ("pykka", "cloudpickle", "msgspec")  # the core's and the plan reader's


def sh(*argv: str | Path, cwd: Path, env: dict[str, str]) -> str:
    done = subprocess.run(
        [str(a) for a in argv],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert 0 == done.returncode, f"{argv}:\n{done.stdout}\n{done.stderr}"
    return done.stdout


class TestFromAWheel:
    """A wheel of rr_actors runs its shipped plans by name from anywhere (issue 24, item 10).

    The wheel is built from a copy of the sources, installed with `--no-deps` into a fresh
    virtual environment that sees only the core's and the plan reader's dependencies (pykka,
    cloudpickle, msgspec, taken from this interpreter), and run from a directory that is not
    the repository, with no `PYTHONPATH`: what a user who ran `pip install rr-actors` has.
    """

    @pytest.mark.timeout(240)
    def test_the_wheel_lists_and_runs_a_shipped_plan_from_anywhere(self, tmp_path: Path) -> None:
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
        source = tmp_path / "source"
        for package in ("rr_actors", "rr_actors_lab"):  # the runtime and the lab beside it
            shutil.copytree(ROOT / package, source / package, symlinks=False)
        for name in ("pyproject.toml", "README.md", "LICENSE"):
            shutil.copy(ROOT / name, source / name)
        sh(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
           "-w", tmp_path / "dist", source, cwd=tmp_path, env=env)  # fmt: skip
        (wheel,) = (tmp_path / "dist").glob("rr_actors-*.whl")

        venv = tmp_path / "venv"
        sh(sys.executable, "-m", "venv", "--without-pip", venv, cwd=tmp_path, env=env)
        python = venv / "bin" / "python"
        sh(sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", wheel,
           cwd=tmp_path, env=env)  # fmt: skip
        deps = tmp_path / "deps"
        deps.mkdir()
        for name in NEEDED:
            spec = importlib.util.find_spec(name)
            assert spec is not None
            assert spec.submodule_search_locations
            (deps / name).symlink_to(next(iter(spec.submodule_search_locations)))
        site = sh(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])",
                  cwd=tmp_path, env=env).strip()  # fmt: skip
        (Path(site) / "needed-deps.pth").write_text(f"{deps}\n")
        elsewhere = tmp_path / "elsewhere"
        elsewhere.mkdir()

        where = sh(
            python,
            "-c",
            "import rr_actors_lab; print(rr_actors_lab.__file__)",
            cwd=elsewhere,
            env=env,
        )
        listed = sh(venv / "bin" / "rr-actors", "experiment", "--list", cwd=elsewhere, env=env)
        help_text = sh(venv / "bin" / "rr-actors", "experiment", "--help", cwd=elsewhere, env=env)
        license_text = sh(
            python, "-c", "from importlib.metadata import distribution as d; "
            "print(d('rr-actors').read_text('LICENSE'))", cwd=elsewhere, env=env,
        )  # fmt: skip
        sh(venv / "bin" / "rr-actors", "experiment", "first", "--out", "out", "--repeat", "1",
           "--duration", "1", cwd=elsewhere, env=env)  # fmt: skip

        assert where.startswith(str(venv))
        assert {"crashloop", "first", "hang", "resource", "strategies"} <= {
            line.split()[0] for line in listed.splitlines() if line.strip()
        }
        assert "the format: " in " ".join(help_text.split())  # the shipped reference, named
        # The footer names the shipped folder relative to the package (80 columns, no absolute
        # path, issue 44): the reference is there, in the installed wheel.
        assert "rr_actors_lab/experiments/plans/" in listed
        assert "plan-reference.md" in listed
        reference = Path(where.strip()).parent / "experiments" / "plans" / "plan-reference.md"
        assert reference.is_file()
        assert "# Experiment plans" in reference.read_text()
        assert "MIT License" in license_text
        assert "the rr_actors developers" in license_text
        with (elsewhere / "out" / "runs.csv").open(newline="") as rows:
            assert ["one_for_one", "rest_for_one"] == [row["value"] for row in csv.DictReader(rows)]
