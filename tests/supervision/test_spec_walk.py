"""The one walk over a spec tree (`config.walk`) and what is read through it."""

from __future__ import annotations

import rr_actors as rr
from rr_actors.config import managers, tree_names, walk


def noop(_: rr.ResourceRegistrar) -> None:
    """A setup that registers nothing."""


def nested() -> rr.SupervisorSpec:
    """root: a, inner (b, deep (c)), d."""
    deep = rr.SupervisorSpec("deep", (rr.ManagerSpec("c", noop, isolation="process"),))
    inner = rr.SupervisorSpec("inner", (rr.ManagerSpec("b", noop), deep))
    return rr.SupervisorSpec("root", (rr.ManagerSpec("a", noop), inner, rr.ManagerSpec("d", noop)))


def test_walk_yields_every_child_depth_first_with_the_supervisors_above_it() -> None:
    walked = [(child.name, [s.name for s in path]) for child, path in walk(nested())]

    assert [
        ("a", ["root"]),
        ("inner", ["root"]),
        ("b", ["root", "inner"]),
        ("deep", ["root", "inner"]),
        ("c", ["root", "inner", "deep"]),
        ("d", ["root"]),
    ] == walked


def test_names_managers_and_processes_are_read_through_the_walk() -> None:
    spec = nested()

    assert ["a", "inner", "b", "deep", "c", "d"] == tree_names(spec)
    assert ["a", "b", "c", "d"] == [m.name for m in managers(spec)]
    threads_only = rr.SupervisorSpec("t", (rr.ManagerSpec("a", noop),))
    assert (True, False) == (spec.has_processes(), threads_only.has_processes())
