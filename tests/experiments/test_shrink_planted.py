"""Each shipped planted bug's shrunk run tells its story in at most `STORY` events and
still shows its finding (issue 68 item 9).

`benchmarks/planted_bugs.py --shrink --keep` finds each plant's seed, shrinks it
(`rr_actors_lab.experiments.shrink`) and keeps the shrunk plan, its seed in it, in
`benchmarks/shrunk/PLANT.toml`. Here each kept plan runs at its seed on a scratch copy
of the package with the plant applied (a child process, as the script runs it): the
plant's rule is violated, in at most `STORY` events.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

pytest.importorskip("greenlet")  # (the simulation extra)

ROOT = Path(__file__).resolve().parent.parent.parent

STORY = 30
"""The most events a shrunk story may have: what a reader follows line by line."""

OVER = {"intensity-stale-exit": 65, "status-seen-server": 37, "unload-held": 175}
"""The plants whose kept shrunk run is still longer: its events (issue 68 item 9, open).

Two floors keep them there: the run's stop (each resource a client still holds is
released and unloaded, every registrar stops: 5 events a resource, 2 a manager), and
the scheduler's one seeded stream of choices, which any cut of a call or a manager
redraws, so the race the violation needs is lost with it."""


def _planted() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "planted_bugs", ROOT / "benchmarks" / "planted_bugs.py"
    )
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["planted_bugs"] = module  # (its dataclass looks it up)
    spec.loader.exec_module(module)
    return module


PLANTED = _planted()
KEPT = sorted(path.stem for path in PLANTED.KEPT.glob("*.toml"))


def test_every_kept_shrunk_plan_names_a_planted_bug() -> None:
    assert set(KEPT) <= {plant.name for plant in PLANTED.PLANTS}


@pytest.mark.timeout(120)  # (a scratch copy and one small run in a child; slower loaded)
@pytest.mark.parametrize(
    "name",
    [
        pytest.param(name, marks=pytest.mark.xfail(reason=f"{OVER[name]} events"))
        if name in OVER
        else name
        for name in KEPT
    ],
)
def test_a_planted_bugs_shrunk_run_shows_its_finding_in_at_most_30_events(name: str) -> None:
    plant = next(p for p in PLANTED.PLANTS if p.name == name)

    answer = PLANTED.run_kept(plant, PLANTED.KEPT / f"{name}.toml")

    assert "violated" == answer["verdict"]
    assert answer["violations"], f"no [{plant.rule}] violation"
    assert answer["events"] <= STORY
