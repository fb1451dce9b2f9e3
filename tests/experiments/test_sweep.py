"""`rr-actors experiment PLAN --simulate --seeds A-B` and `rr-actors replay RUN --seed S`
(`rr_actors_lab.experiments.sweep`): a verdict and a hash per seed, the violating seeds named
and their histories kept, a replay that gives the same hash (exit 1 if not)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import psutil
import pytest

from rr_actors.errors import ConfigError
from rr_actors_lab.__main__ import main
from rr_actors_lab.experiments import simulate, sweep
from rr_actors_lab.experiments.cli import Display
from rr_actors_lab.experiments.plan import Plan
from tests.experiments.test_simulate import BASE, PLAN, plant_second_load, simkill
from tests.support import selecting

pytest.importorskip("greenlet")  # (the simulation extra)

SWEEP = pytest.mark.timeout(300)
"""Each command may run again in a child process (`PYTHONHASHSEED=0`): a few seconds,
several times that under load."""

BUGGY = '''\
"""A setup that plants a bug in every provider of its process: a second load of an
equal request instead of a dedup hit (undone by the test's monkeypatch)."""

from rr_actors._catalog.records import ResourceState
from rr_actors._registrar.provider import Provider
from rr_actors_lab.experiments.services import service

_matched = Provider.matched


def _buggy(self, message, key, resource):
    if resource is not None and resource.state is ResourceState.LOADED:
        resource = None
    _matched(self, message, key, resource)


def setup(registrar, **options):
    Provider.matched = _buggy
    service(registrar, **options)
'''


def command(*argv: str) -> tuple[int, str]:
    stream = io.StringIO()
    code = main(list(argv), stream)
    return code, stream.getvalue()


def recorded(out: Path) -> dict[int, dict[str, object]]:
    lines = (out / sweep.SEEDS_FILE).read_text().splitlines()
    return {line["seed"]: line for line in map(json.loads, lines)}


@SWEEP
def test_a_sweep_writes_the_simulated_systems_error_lines_by_seed_to_its_log_not_stderr(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """A second server yields at each heal with an ERROR (rule 22, as on Zenoh): the
    simulated system's line, kept as a real run keeps its processes' (`stderr.txt`)."""
    plan, out = tmp_path / "plan.toml", tmp_path / "out"
    plan.write_text(BASE + '[[faults]]\nkind = "split_brain"\ntarget = "db"\nat = 0.5\nfor = 0.6\n')

    code, printed = command(
        "experiment", str(plan), "--simulate", "--seeds", "1-2", "--out", str(out)
    )

    assert 0 == code, printed
    assert "one name is one registrar" not in capfd.readouterr().err
    said = " ".join(printed.split())  # (the display wraps its lines)
    assert "log.txt (the simulated system's 2 log lines of ERROR, by seed)" in said
    logged = (out / sweep.LOG_FILE).read_text().splitlines()
    assert ["seed 1: ERROR rr_actors", "seed 2: ERROR rr_actors"] == [
        line.split(": registrar")[0] for line in logged
    ]
    assert all("one name is one registrar (rule 22)" in line for line in logged)


@SWEEP
def test_a_sweep_gives_each_seed_a_verdict_and_a_hash_and_a_replay_the_same_hash(
    tmp_path: Path,
) -> None:
    plan, out = tmp_path / "plan.toml", tmp_path / "out"
    plan.write_text(PLAN)

    code, printed = command(
        "experiment", str(plan), "--simulate", "--seeds", "1-3", "--out", str(out)
    )

    assert 0 == code, printed
    assert "violated: none" in printed
    assert "seeds/CPU-min" in printed
    seeds = recorded(out)
    assert [1, 2, 3] == sorted(seeds)
    assert all(
        line["verdict"] == "held" and len(str(line["hash"])) == 64 for line in seeds.values()
    )
    assert (out / "plan.toml").read_text() == PLAN

    code, printed = command("replay", str(out), "--seed", "2", "--events", str(tmp_path / "e"))
    assert 0 == code, printed
    assert f"hash {seeds[2]['hash']}" in printed
    assert "the same history" in printed
    assert (tmp_path / "e").read_text().count('"seed": 2') > 10


@SWEEP
def test_a_replay_whose_hash_differs_from_the_recorded_one_exits_1(tmp_path: Path) -> None:
    plan, out = tmp_path / "plan.toml", tmp_path / "out"
    plan.write_text(PLAN)
    assert 0 == command("experiment", str(plan), "--simulate", "--out", str(out))[0]
    line = recorded(out)[1]
    (out / sweep.SEEDS_FILE).write_text(json.dumps({**line, "hash": "0" * 64}) + "\n")

    code, printed = command("replay", str(out), "--seed", "1")

    assert 1 == code
    assert "a different history" in printed


@SWEEP
def test_a_planted_bug_names_the_violating_seeds_keeps_their_histories_and_replays_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from rr_actors._registrar.provider import Provider  # noqa: PLC0415

    monkeypatch.setattr(Provider, "matched", Provider.matched)  # (put back at the end)
    (tmp_path / "buggy.py").write_text(BUGGY)
    plan, out = tmp_path / "plan.toml", tmp_path / "out"
    plan.write_text(PLAN.replace("rr_actors_lab.experiments.services:service", "buggy:setup"))
    monkeypatch.syspath_prepend(str(tmp_path))

    code, printed = command(
        "experiment", str(plan), "--simulate", "--seeds", "1-2", "--out", str(out)
    )

    assert 0 == code, printed
    violated = [seed for seed, line in recorded(out).items() if line["verdict"] == "violated"]
    assert violated
    assert f"violated: seeds {', '.join(map(str, violated))}" in printed
    assert f"rr-actors replay {out} --seed {violated[0]}" in " ".join(printed.split())
    history = out / f"events-seed-{violated[0]}.jsonl"
    assert 1 == main(["check", str(history), "--quiet"], io.StringIO())

    code, printed = command("replay", str(out), "--seed", str(violated[0]))
    assert 0 == code, printed
    assert f"seed {violated[0]}: violated" in printed
    assert "the same history" in printed
    assert "[dedup]" in printed


@SWEEP
def test_a_sweep_keeps_the_history_of_each_seed_that_did_not_hold_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run_seed = simulate.run_seed

    def buggy_if_odd(plan: Plan, seed: int) -> simulate.SimulatedRun:
        with monkeypatch.context() as patched:
            if seed % 2:
                plant_second_load(patched)
            return run_seed(plan, seed)

    monkeypatch.setattr(simulate, "run_seed", buggy_if_odd)
    with Display(io.StringIO(), quiet=True) as display:  # (a history is megabytes: 10,000
        runs = sweep.run_seeds(simkill(), range(1, 3), tmp_path, display)  # would not fit)

    assert {"held", "violated"} <= {run.verdict for run in runs}
    for run, line in zip(runs, recorded(tmp_path).values(), strict=True):
        written = tmp_path / f"events-seed-{run.seed}.jsonl"
        if run.verdict == "held":
            assert ("", False) == (run.history, written.exists())
        else:
            assert run.history == written.read_text(encoding="utf-8")
            assert line["hash"] == simulate.history_hash(run.history)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seeds", "1-3"], "--seeds needs --simulate"),
        (["--simulate", "--seeds", "5-2"], "the last seed is below the first"),
        (["--simulate", "--seeds", "x"], "--seeds must be A-B or S"),
        (["--simulate", "--repeat", "2"], "not --repeat, --seed, --observe or --trace"),
        (["--seed-timeout", "5"], "--seed-timeout needs --simulate"),
    ],
    ids=["without --simulate", "backwards", "not numbers", "with --repeat", "a seed timeout"],
)
def test_bad_seeds_exit_2_before_anything_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)

    code = main(["experiment", str(plan), "--out", str(tmp_path / "out"), *argv])

    assert 2 == code
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out" / sweep.SEEDS_FILE).exists()


def test_a_fault_kind_not_simulated_exits_2_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = tmp_path / "plan.toml"
    plan.write_text(f'{PLAN}\n[[faults]]\nkind = "kill_resource"\ntarget = "db"\nat = 1.0\n')

    code = main(["experiment", str(plan), "--simulate", "--out", str(tmp_path / "out")])

    assert 2 == code
    assert "faults[1].kind: 'kill_resource' is not simulated" in capsys.readouterr().err


@SWEEP
def test_a_sweep_through_a_pipe_says_how_far_it_is_while_it_runs(tmp_path: Path) -> None:
    """`experiment PLAN --simulate --seeds 1-500 | cat`: the first seed's line comes
    through the pipe while the others still run, not with the summary at the end."""
    plan = tmp_path / "plan.toml"
    plan.write_text(PLAN)
    argv = ["experiment", str(plan), "--simulate", "--seeds", "1-12", "--jobs", "1"]
    with subprocess.Popen(
        [sys.executable, "-m", "rr_actors_lab", *argv, "--out", str(tmp_path / "out")],
        stdout=subprocess.PIPE,
        text=True,
    ) as sweep_run:
        assert sweep_run.stdout is not None
        first = sweep_run.stdout.readline()
        running = sweep_run.poll() is None  # (11 seeds to go: a few seconds)
        rest = sweep_run.stdout.read()
        sweep_run.wait(timeout=240)

    assert "seeds: 1/12 run, 0 did not hold (" in first
    assert running, "the first line came with the end"
    assert (0, True) == (sweep_run.returncode, "violated: none" in rest)


@SWEEP
def test_a_sweep_without_a_bar_says_a_progress_line_every_progress_seconds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PYTHONHASHSEED", sweep.HASH_SEED)  # (here: the constant is patched)
    monkeypatch.setattr(sweep, "PROGRESS_SECONDS", 0.0)
    plan, out = tmp_path / "plan.toml", tmp_path / "out"
    plan.write_text(PLAN)

    code, printed = command(
        "experiment", str(plan), "--simulate", "--seeds", "1-3", "--jobs", "1", "--out", str(out)
    )

    assert 0 == code, printed
    said = [line.split(" did not")[0] for line in printed.splitlines() if "seeds: " in line]
    assert ["seeds: 1/3 run, 0", "seeds: 2/3 run, 0", "seeds: 3/3 run, 0"] == said


def test_a_replay_of_a_seed_not_run_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "plan.toml").write_text(PLAN)
    lines = "".join(json.dumps({"seed": s, "hash": "0" * 64}) + "\n" for s in (1, 2, 3, 7))
    (tmp_path / sweep.SEEDS_FILE).write_text(lines)

    assert 2 == main(["replay", str(tmp_path), "--seed", "9"], io.StringIO())
    err = capsys.readouterr().err
    assert (1, True) == (len(err.splitlines()), "seed 9 was not run (seeds run: 1-3,7)" in err)


def test_a_replay_of_a_missing_folder_exits_2_saying_the_folder_is_missing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert 2 == main(["replay", str(tmp_path / "nowhere"), "--seed", "1"], io.StringIO())
    err = capsys.readouterr().err
    assert (1, True) == (len(err.splitlines()), f"{tmp_path / 'nowhere'}: no such folder" in err)


def test_a_check_of_a_simulations_folder_exits_2_pointing_to_seeds_and_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / sweep.SEEDS_FILE).write_text(json.dumps({"seed": 1, "hash": "0" * 64}) + "\n")

    assert 2 == main(["check", str(tmp_path)], io.StringIO())
    err = capsys.readouterr().err
    assert 1 == len(err.splitlines()), err
    assert "seeds.jsonl" in err
    assert f"rr-actors replay {tmp_path} --seed S" in err


MARKER = """\
\"\"\"db's setup, which tells the test through a FIFO that a seed's run began (its
folder exists), then serves as usual.\"\"\"

import contextlib
import os

from rr_actors_lab.experiments.services import service


def setup(registrar, *, fifo):
    with contextlib.suppress(OSError):  # (the pipe full, or the test gone: serve anyway)
        fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        try:
            os.write(fd, b"running\\n")
        finally:
            os.close(fd)
    service(registrar)
"""


def marked_plan(folder: Path, fifo: Path) -> Path:
    """`PLAN` whose db's setup writes a line into `fifo` at each of its starts."""
    (folder / "sweep_marker.py").write_text(MARKER)
    plan = folder / "plan.toml"
    plan.write_text(
        PLAN.replace(
            'name = "db"\nsetup = "rr_actors_lab.experiments.services:service"',
            f'name = "db"\nsetup = "sweep_marker:setup"\noptions = {{ fifo = "{fifo}" }}',
        )
    )
    return plan


@pytest.mark.timeout(240)
@pytest.mark.parametrize(
    ("signum", "hash_seed", "jobs"),
    [
        (signal.SIGTERM, "0", "1"),
        (signal.SIGTERM, None, "1"),
        (signal.SIGINT, "0", "1"),
        (signal.SIGTERM, "0", "2"),
        (signal.SIGTERM, None, "2"),
        (signal.SIGINT, None, "2"),
    ],
    ids=[
        "SIGTERM",
        "SIGTERM to the parent of PYTHONHASHSEED's child",
        "SIGINT",
        "SIGTERM, two workers",
        "SIGTERM to the parent of PYTHONHASHSEED's child, two workers",
        "a Ctrl-C to the whole group, two workers",
    ],
)
def test_a_sweep_stopped_by_a_signal_removes_its_run_folder_and_exits_128_plus_it(
    tmp_path: Path, signum: int, hash_seed: str | None, jobs: str, eventually: Callable[..., bool]
) -> None:
    # With workers (`--jobs 2`) every worker's seed is cancelled and its folder removed,
    # no worker is left, and the seeds that ran are summed up. A Ctrl-C at a terminal
    # reaches the whole process group (each worker, and the parent of a hash's child).
    scratch, fifo = tmp_path / "tmp", tmp_path / "started"
    scratch.mkdir()
    os.mkfifo(fifo)
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # (before the setup's open)
    plan = marked_plan(tmp_path, fifo)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONHASHSEED"}
    env |= {"TMPDIR": str(scratch)} | ({"PYTHONHASHSEED": hash_seed} if hash_seed else {})
    command = ["experiment", str(plan), "--simulate", "--seeds", "1-100000", "--jobs", jobs]
    sweep_process = subprocess.Popen(
        [sys.executable, "-m", "rr_actors_lab", *command, "--out", str(tmp_path / "out")],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # (its group: killed whole if the test fails)
    )
    try:
        ready, _, _ = selecting.select([reader], [], [], 120)  # (a seed's run began)
        assert ready, "no seed began within 120 s"
        assert list(scratch.rglob("rr-sim-run-*"))  # (a worker's: in its pool's folder)

        if "group" in os.environ.get("PYTEST_CURRENT_TEST", ""):
            os.killpg(sweep_process.pid, signum)  # (as a terminal's Ctrl-C)
        else:
            sweep_process.send_signal(signum)
        _, err = sweep_process.communicate(timeout=120)
        # (the pool's resource tracker ends once it reads the end of its pipe)
        eventually(lambda: not _group(sweep_process.pid), timeout=30)
        left = [_cmdline(pid) for pid in _group(sweep_process.pid)]
    finally:
        os.close(reader)
        with contextlib.suppress(ProcessLookupError):  # (a child left: the test failed)
            os.killpg(sweep_process.pid, signal.SIGKILL)
        sweep_process.wait()

    assert 128 + signum == sweep_process.returncode, err
    assert [] == [p.name for p in scratch.rglob("rr-sim-*")]
    assert f"stopped by {signal.Signals(signum).name}" in err
    assert "Traceback" not in err
    assert [] == left, "a process of the sweep was left"


def _group(group: int) -> list[int]:
    """The processes of process group `group`."""
    pids = [int(name) for name in os.listdir("/proc") if name.isdigit()]
    return [pid for pid in pids if _in_group(pid, group)]


def _in_group(pid: int, group: int) -> bool:
    with contextlib.suppress(OSError):
        return os.getpgid(pid) == group
    return False


def _cmdline(pid: int) -> str:
    with contextlib.suppress(OSError):
        return Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ")
    return str(pid)


@pytest.mark.timeout(120)
def test_a_ctrl_c_while_a_worker_still_starts_is_ignored_by_it_not_a_traceback(
    capfd: pytest.CaptureFixture[str],
) -> None:
    # CI: a Ctrl-C to the whole group reached a worker still in `spawn_main` (importing,
    # before the pool's initializer ran), which died with a traceback. Forced here: the
    # SIGINT is sent as soon as the worker exists, long before its interpreter is up;
    # the same worker then runs a task (not one the pool started in its place).
    pool = sweep._Pool(1)
    try:
        future = pool.submit(os.getpid)  # (the worker starts here)
        (started,) = pool.processes
        os.kill(started, signal.SIGINT)
        assert started == future.result(timeout=60)
    finally:
        pool.end()
    assert "Traceback" not in capfd.readouterr().err


@SWEEP
def test_seeds_run_in_two_workers_give_what_one_process_gives_in_seed_order(
    tmp_path: Path,
) -> None:
    # `--jobs 2`: each seed runs alone in a worker process; its hash, verdict, counts
    # and error lines are what the serial sweep gives, written in seed order.
    plan = tmp_path / "plan.toml"
    plan.write_text(BASE + '[[faults]]\nkind = "split_brain"\ntarget = "db"\nat = 0.5\nfor = 0.6\n')
    outs = {jobs: tmp_path / f"out-{jobs}" for jobs in ("1", "2")}
    for jobs, out in outs.items():
        code, printed = command(
            "experiment", str(plan), "--simulate", "--seeds", "1-4", "--out", str(out),
            "--jobs", jobs,
        )  # fmt: skip
        assert 0 == code, printed

    def lines(out: Path) -> list[dict[str, object]]:
        seeds = (out / sweep.SEEDS_FILE).read_text().splitlines()
        return [{k: v for k, v in json.loads(line).items() if k != "cpu_s"} for line in seeds]

    assert [1, 2, 3, 4] == [line["seed"] for line in lines(outs["2"])]
    assert lines(outs["1"]) == lines(outs["2"])
    log = (outs["2"] / sweep.LOG_FILE).read_text()
    assert (outs["1"] / sweep.LOG_FILE).read_text() == log
    assert [f"seed {s}" for s in (1, 2, 3, 4)] == [line.split(":")[0] for line in log.splitlines()]


def test_jobs_without_simulate_exit_2(tmp_path: Path) -> None:
    code, _ = command("experiment", "simchain", "--out", str(tmp_path), "--jobs", "2")
    assert 2 == code


def test_a_seed_timeout_not_a_positive_number_of_seconds_exits_2_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["experiment", "simchain", "--simulate", "--out", str(tmp_path / "out")]
    with pytest.raises(SystemExit) as exited:
        main([*argv, "--seed-timeout", "0"], io.StringIO())

    assert 2 == exited.value.code
    assert "--seed-timeout: must be a positive number of seconds, got 0" in capsys.readouterr().err


STOPPER = """\
\"\"\"db's setup that stops its own process (a SIGTERM: a worker takes it as a stop, not as
its seed's death): in a worker, the pool breaks with no seed lost, each time.\"\"\"

import os
import signal


def setup(registrar, **_options):
    os.kill(os.getpid(), signal.SIGTERM)
"""


@SWEEP
def test_a_sweep_whose_workers_die_before_any_seed_finishes_gives_up_after_three_pools(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "sweep_stopper.py").write_text(STOPPER)
    plan = tmp_path / "plan.toml"
    plan.write_text(
        PLAN.replace(
            'name = "db"\nsetup = "rr_actors_lab.experiments.services:service"',
            'name = "db"\nsetup = "sweep_stopper:setup"',
        )
    )

    code, printed = command(
        "experiment", str(plan), "--simulate", "--seeds", "1-2", "--jobs", "2",
        "--out", str(tmp_path / "out"),
    )  # fmt: skip

    assert 1 == code, printed
    err = capfd.readouterr().err
    assert "the pool of worker processes broke 3 times in a row with no seed finished" in err
    assert "Traceback" not in err


def test_the_default_jobs_are_the_cores_available_at_most_one_per_seed() -> None:
    cores = len(os.sched_getaffinity(0))
    assert (1, min(cores, 3)) == (sweep.default_jobs(range(1, 2)), sweep.default_jobs(range(3)))


def plant_a_crash(monkeypatch: pytest.MonkeyPatch) -> None:
    """An exception inside every seed's run, once its workload ended: where the runner
    counts what the catalogs still hold (the system's code, in the run)."""

    def crashing(*_args: object) -> None:
        raise AssertionError("catalog: a consumer id held twice")

    monkeypatch.setattr(simulate, "count_entries", crashing)
    monkeypatch.setenv("PYTHONHASHSEED", sweep.HASH_SEED)  # (no child: the plant is here)


@SWEEP
def test_a_seed_whose_system_raises_is_crashed_the_sweep_goes_on_and_replay_and_shrink_take_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    plant_a_crash(monkeypatch)
    plan, out = tmp_path / "plan.toml", tmp_path / "out"
    plan.write_text(PLAN)

    code, printed = command(  # (one process: the plant is in this one)
        "experiment", str(plan), "--simulate", "--seeds", "1-2", "--out", str(out), "--jobs", "1"
    )

    assert 0 == code, printed  # (a result, not a failure of the tool)
    seeds = recorded(out)
    assert ["crashed", "crashed"] == [seeds[s]["verdict"] for s in (1, 2)]
    [finding] = seeds[2]["findings"]
    assert re.fullmatch(
        r"  crashed: AssertionError: catalog: a consumer id held twice "
        r"\(at [0-9.]+ virtual s, step [0-9]+\)",
        str(finding),
    )
    assert "crashed: seeds 1, 2" in printed
    crash = json.loads((out / "events-seed-2.jsonl").read_text().splitlines()[-1])
    assert ("Crashed", "AssertionError", 2) == (crash["type"], crash["error_type"], crash["seed"])
    assert crash["virtual_s"] > 3.0  # (after the run's 3 s: the count comes at the end)

    code, printed = command("replay", str(out), "--seed", "2", "--story")
    assert 0 == code, printed
    assert f"seed 2: crashed, hash {seeds[2]['hash']}" in printed
    assert re.search(r"crashed +AssertionError: catalog: a consumer id held twice \(step ", printed)
    assert "the same history" in printed

    shrunk = tmp_path / "shrunk"
    code, printed = command(
        "shrink", str(out), "--seed", "2", "--out", str(shrunk), "--budget", "20"
    )
    assert 0 == code, printed
    assert "[crashed] AssertionError: catalog: a consumer id held twice" in printed
    code, printed = command("replay", str(shrunk))
    assert 0 == code, printed
    assert ": crashed, hash" in printed


LINE = {"seed": 1, "hash": "0" * 64, "duration": 3.0, "plan": None}
"""A seed's line of `seeds.jsonl`, as far as a replay reads it."""

HOSTILE_SEEDS = {
    "cut short": (b'{"seed": 1, "hash": "ab', ":1: not a JSON line (Unterminated string"),
    "not UTF-8": (b"\xff\xfe\n", ":1: not UTF-8 text (invalid start byte)"),
    "nested too deeply": (
        b"[" * 100_000 + b"]" * 100_000 + b"\n",
        ":1: not a seed's line: nested too deeply to read",
    ),
    "a huge integer": (
        b'{"seed": ' + b"9" * 5000 + b"}\n",
        ":1: not a seed's line: a number of over 4300 digits",
    ),
    "not an object": (b"\n[1]\n", ":2: not a seed's line: a JSON array"),
    "no hash": (b'{"seed": 1}\n', ":1: not a seed's line: no hash"),
    "a seed not a number": (
        json.dumps({**LINE, "seed": "1"}).encode(),
        ":1: seed must be a whole number, got '1'",
    ),
    "a duration not a number": (
        json.dumps({**LINE, "duration": [3]}).encode(),
        ":1: duration must be a number of seconds, got a JSON array",
    ),
}
TOO_LONG = b" " * 200 + b"\n"
"""A line longer than the test's `LINE_LIMIT` of 100 bytes."""
HOSTILE_SEEDS["a line too long"] = (TOO_LONG, ":1: longer than 100 bytes")


@pytest.mark.timeout(60)  # (before: each a traceback; the too long line was read whole)
@pytest.mark.parametrize(("data", "message"), HOSTILE_SEEDS.values(), ids=HOSTILE_SEEDS.keys())
def test_a_hostile_seeds_file_is_one_error_line_naming_it_and_its_line_and_exit_2(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    data: bytes,
    message: str,
) -> None:
    if data == TOO_LONG:
        monkeypatch.setattr(sweep, "LINE_LIMIT", 100)
    (tmp_path / "plan.toml").write_text(PLAN)
    (tmp_path / sweep.SEEDS_FILE).write_bytes(data)

    for argv in (["--seed", "1"], []):  # (a given seed, and the only one)
        assert 2 == main(["replay", str(tmp_path), *argv], io.StringIO())

        err = capsys.readouterr().err
        assert err.startswith(f"rr-actors replay: {tmp_path / sweep.SEEDS_FILE}{message}"), err
        assert 1 == err.count("\n")  # (one line: no traceback)


def fifo(path: Path) -> None:
    os.mkfifo(path)  # (opening it for reading would wait for a writer)


def dev_zero(path: Path) -> None:
    path.symlink_to("/dev/zero")  # (endless: read whole, gigabytes)


NOT_REGULAR = {
    "a link to /dev/zero": (dev_zero, "a character device"),
    "a pipe": (fifo, "a pipe"),
    "a directory": (Path.mkdir, "a directory"),
}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("name", ["plan.toml", sweep.SEEDS_FILE])
@pytest.mark.parametrize(("make", "kind"), NOT_REGULAR.values(), ids=NOT_REGULAR.keys())
def test_a_run_file_that_is_not_a_regular_file_is_refused_unread_naming_it(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    name: str,
    make: Callable[[Path], None],
    kind: str,
) -> None:
    (tmp_path / "plan.toml").write_text(PLAN)
    (tmp_path / sweep.SEEDS_FILE).write_text(json.dumps(LINE) + "\n")
    (tmp_path / name).unlink()
    make(tmp_path / name)

    for command in ("replay", "shrink"):
        assert 2 == main([command, str(tmp_path), "--seed", "1"], io.StringIO())

        err = capsys.readouterr().err
        assert (
            f"rr-actors {command}: {tmp_path / name}: not a regular file ({kind}): refused\n" == err
        )


@pytest.mark.timeout(60)
def test_a_plan_file_bigger_than_its_limit_is_refused_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "plan.toml").write_text("#" * sweep.PLAN_LIMIT + "\n" + PLAN)
    (tmp_path / sweep.SEEDS_FILE).write_text(json.dumps(LINE) + "\n")

    assert 2 == main(["replay", str(tmp_path), "--seed", "1"], io.StringIO())

    plan = tmp_path / "plan.toml"
    assert f"rr-actors replay: {plan}: bigger than {sweep.PLAN_LIMIT} bytes: not a plan\n" == (
        capsys.readouterr().err
    )


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("duration = [[[\n", "is not valid TOML"),
        ("\xff", "is not UTF-8 text"),
        ("duration = " + "9" * 5000 + "\n", "is not a plan: a number of over 4300 digits"),
    ],
    ids=["not TOML", "not UTF-8", "a huge integer"],
)
def test_a_bad_plan_copy_is_reported_under_its_own_path_not_the_original_plans(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, problem: str
) -> None:
    original = "/somewhere/else/simkill.toml"
    plan = tmp_path / "plan.toml"
    plan.write_bytes(text.encode("utf-8", "surrogateescape") if text != "\xff" else b"\xff")
    (tmp_path / sweep.SEEDS_FILE).write_text(json.dumps({**LINE, "plan": original}) + "\n")

    assert 2 == main(["replay", str(tmp_path), "--seed", "1"], io.StringIO())

    err = capsys.readouterr().err
    assert err.startswith(f"rr-actors replay: {plan}: {problem}"), err
    assert original not in err
    assert 1 == err.count("\n")


@pytest.mark.parametrize(
    ("text", "seeds"), [("1-3", range(1, 4)), ("7", range(7, 8)), (" 0 - 0 ", range(1))]
)
def test_seeds_are_a_range_or_one(text: str, seeds: range) -> None:
    assert seeds == sweep.parse_seeds(text)


def test_too_many_seeds_are_refused() -> None:
    with pytest.raises(ConfigError, match="more than"):
        sweep.parse_seeds(f"1-{sweep.MAX_SEEDS + 1}")


HOLDER = """\
\"\"\"db's setup: the first start after the test armed it (`armed` exists) claims the hold,
says its process's pid through the FIFO and waits there for good (a seed that never ends,
in a worker the test then kills or stops); every other start serves as usual.\"\"\"

import contextlib
import os

from rr_actors_lab.experiments.services import service


def setup(registrar, *, armed, claim, fifo, gate):
    if os.path.exists(armed):
        with contextlib.suppress(FileExistsError):
            os.close(os.open(claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            fd = os.open(fifo, os.O_WRONLY)
            os.write(fd, f"{os.getpid()}\\n".encode())
            os.close(fd)
            os.open(gate, os.O_RDONLY)  # (a FIFO no one writes: blocks until killed)
    service(registrar)
"""


def held_plan(folder: Path) -> Path:
    """`PLAN` whose db's setup holds one seed for good once `folder/armed` exists."""
    (folder / "sweep_holder.py").write_text(HOLDER)
    for fifo in ("said", "gate"):
        os.mkfifo(folder / fifo)
    files = ", ".join(
        f'{name} = "{folder / path}"'
        for name, path in (
            ("armed", "armed"),
            ("claim", "claim"),
            ("fifo", "said"),
            ("gate", "gate"),
        )
    )
    plan = folder / "plan.toml"
    plan.write_text(
        PLAN.replace(
            'name = "db"\nsetup = "rr_actors_lab.experiments.services:service"',
            f'name = "db"\nsetup = "sweep_holder:setup"\noptions = {{ {files} }}',
        )
    )
    return plan


def hashes(out: Path) -> dict[int, object]:
    return {seed: line["hash"] for seed, line in recorded(out).items()}


@pytest.mark.timeout(400)
@pytest.mark.parametrize(
    ("signum", "timeout", "how"),
    [
        (signal.SIGKILL, [], "killed by SIGKILL"),
        (signal.SIGSTOP, ["--seed-timeout", "45"], "hung: no answer in 45 s, killed"),
    ],
    ids=["SIGKILL", "SIGSTOP"],
)
def test_a_sweep_whose_worker_is_killed_or_stopped_in_a_seed_ends_naming_that_seed_and_how(
    tmp_path: Path, signum: int, timeout: list[str], how: str
) -> None:
    # Issue 68: a `--jobs 2` sweep with a worker SIGKILLed ran on for good, printing
    # nothing. Now it ends (exit 1: a run failed), the seed that worker ran is named lost
    # (its line in seeds.jsonl says how), and every other seed has a control sweep's hash.
    # A worker stopped (SIGSTOP) is killed once its seed ran past --seed-timeout.
    plan = held_plan(tmp_path)
    argv = ["experiment", str(plan), "--simulate", "--seeds", "1-6", "--jobs", "2"]
    code, printed = command(*argv, "--out", str(tmp_path / "control"))  # (nothing armed)
    assert 0 == code, printed
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    env = {**os.environ, "PYTHONHASHSEED": sweep.HASH_SEED, "TMPDIR": str(scratch)}
    said = os.open(tmp_path / "said", os.O_RDONLY | os.O_NONBLOCK)  # (before the setup's open)
    out = tmp_path / "out"
    with subprocess.Popen(
        [sys.executable, "-m", "rr_actors_lab", *argv, *timeout, "--out", str(out)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # (its group: killed whole if the test fails)
    ) as sweep_run:
        try:
            assert sweep_run.stdout is not None
            assert "seeds: 1/6 run" in sweep_run.stdout.readline()  # (mid-sweep from here)
            (tmp_path / "armed").touch()  # (the next db start in a worker holds its seed)
            ready, _, _ = selecting.select([said], [], [], 120)
            assert ready, "no seed was held within 120 s"
            held = int(os.read(said, 64))
            workers = psutil.Process(sweep_run.pid).children(recursive=True)
            assert held in [w.pid for w in workers if "spawn_main" in " ".join(w.cmdline())]
            psutil.Process(held).send_signal(signum)
            rest, err = sweep_run.communicate(timeout=240)
        finally:
            os.close(said)
            with contextlib.suppress(ProcessLookupError):  # (a process left: the test failed)
                os.killpg(sweep_run.pid, signal.SIGKILL)

    assert 1 == sweep_run.returncode, err
    losses = [line for line in recorded(out).values() if line["verdict"] == "lost"]
    assert 1 == len(losses), (losses, rest, err)  # (the lines say how each was lost)
    [lost] = losses
    seed = lost["seed"]
    assert (None, how) == (lost["hash"], lost["worker"])
    assert f"seed {seed}: lost, worker {how}" in rest
    assert f"lost: seed {seed}, worker {how}" in rest
    assert [1, 2, 3, 4, 5, 6] == list(recorded(out))  # (in seed order)
    control = hashes(tmp_path / "control")
    del control[seed]
    assert control == {s: h for s, h in hashes(out).items() if s != seed}
    assert [] == [p.name for p in scratch.rglob("rr-sim-*")]
    assert "Traceback" not in err


def test_a_replay_of_a_lost_seed_exits_2_saying_how_its_worker_ended(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "plan.toml").write_text(PLAN)
    lost = sweep.lost_line(sweep.LostSeed(3, "killed by SIGKILL"), simkill())
    (tmp_path / sweep.SEEDS_FILE).write_text(
        json.dumps({**LINE, "seed": 2}) + "\n" + json.dumps(lost) + "\n"
    )

    assert 2 == main(["replay", str(tmp_path), "--seed", "3"], io.StringIO())

    err = capsys.readouterr().err
    assert 1 == len(err.splitlines()), err
    assert f"{tmp_path / sweep.SEEDS_FILE}:2: seed 3 was lost (its worker killed by SIGKILL)" in err


@pytest.mark.parametrize(
    ("exits", "killed", "died"),
    [
        ({11: -9, 12: 143}, {}, {11: "killed by SIGKILL"}),
        ({11: -15, 12: 143, 13: 3}, {}, {13: "exited with code 3"}),
        (
            {11: -9, 12: -9},
            {11: "hung: no answer in 5 s, killed", 12: ""},
            {11: "hung: no answer in 5 s, killed"},
        ),
        ({11: -11, 12: None}, {}, {11: "killed by SIGSEGV"}),
    ],
    ids=[
        "one killed, one the pool stopped",
        "SIGTERM is the pool's",
        "one hung, one left",
        "not reaped",
    ],
)
def test_a_broken_pools_dead_workers_are_those_it_did_not_end_itself(
    exits: dict[int, int | None], killed: dict[int, str], died: dict[int, str]
) -> None:
    assert died == sweep._died(exits, killed)


@pytest.mark.parametrize(
    ("running", "failed", "lost"),
    [
        ({11: 3, 12: 4}, [3, 4], [sweep.LostSeed(3, "killed by SIGKILL")]),
        ({12: 4}, [3, 4], []),
        ({11: 1, 12: 4}, [3, 4], []),
    ],
    ids=[
        "the seed it said it runs",
        "killed before it said its seed: that seed runs again",
        "killed after its seed's result came: nothing lost",
    ],
)
def test_a_seed_is_lost_only_if_the_worker_that_died_said_it_runs_it_and_it_did_not_finish(
    running: dict[int, int], failed: list[int], lost: list[sweep.LostSeed]
) -> None:
    assert lost == sweep._lost(running, {11: "killed by SIGKILL"}, failed)


def test_the_seed_bound_is_the_timeout_given_or_the_default_or_ten_times_the_slowest_seed() -> None:
    assert 7.5 == sweep.seed_bound(7.5, 100.0)
    assert sweep.SEED_TIMEOUT == sweep.seed_bound(None, 1.0)
    assert 10 * 100.0 == sweep.seed_bound(None, 100.0)


@pytest.mark.timeout(120)
def test_a_silent_pool_with_seeds_in_flight_and_none_running_is_killed_whole() -> None:
    # A worker stopped while idle holds the executor's queue: no seed runs, none is
    # said, nothing comes. Its workers are killed and lose no seed (the seeds run again).
    pool = sweep._Pool(1)
    try:
        (started,) = [pool.submit(os.getpid).result(timeout=60)]
        pool.kill_hung({5}, 10.0, pool.heard + 10.5)  # (a pool's start may take longer)
        assert {} == pool.killed
        pool.kill_hung({5}, 10.0, pool.heard + sweep.SEED_TIMEOUT + 0.5)
        assert {started: ""} == pool.killed
    finally:
        died = pool.end()
    assert {} == died
    assert -signal.SIGKILL == pool.processes[started].exitcode
