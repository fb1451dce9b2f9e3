"""A supervisor's errors say what to do: start it first; the closest child name."""

from __future__ import annotations

from collections.abc import Callable

import pytest

import rr_actors as rr
from tests.support.supervising import echo_setup


def thread(name: str) -> rr.ManagerSpec:
    return rr.ManagerSpec(name, echo_setup)


def test_registrar_before_start_says_to_start_the_supervisor(
    supervisors: Callable[..., rr.Supervisor],
) -> None:
    sup = supervisors([thread("erm")], name="tree")

    with pytest.raises(rr.ConfigError) as info:
        sup.registrar("app")

    assert (
        "supervisor 'tree' is not running yet: start it first (`with sup:` or "
        "`sup.start()`), then call `registrar()`"
    ) == str(info.value)


def test_registrar_after_stop_says_it_was_stopped(
    supervisors: Callable[..., rr.Supervisor],
) -> None:
    sup = supervisors([thread("erm")], name="tree")
    with sup:
        pass

    with pytest.raises(rr.ConfigError, match=r"^supervisor 'tree' was stopped: call `registrar"):
        sup.registrar("app")


def test_child_before_start_says_it_is_not_started_and_its_snapshot_is_stopped(
    supervisors: Callable[..., rr.Supervisor],
) -> None:
    sup = supervisors([thread("erm")])

    with pytest.raises(rr.ConfigError, match="is not started"):
        sup.child("erm")
    info = sup.snapshot("erm")

    assert ("stopped", None) == (info.state, info.pid)


def test_a_misspelled_child_name_suggests_the_closest_one(
    supervisors: Callable[..., rr.Supervisor],
) -> None:
    sup = supervisors([thread("erm"), thread("cm")], name="tree")

    with pytest.raises(rr.UnknownServerError) as info:
        sup.child("emr")

    assert (
        "supervisor 'tree' has no child named 'emr'; did you mean 'erm'? (known: 'cm', 'erm')"
    ) == str(info.value)


def test_run_in_and_wait_restarted_suggest_the_closest_name_too(
    supervisors: Callable[..., rr.Supervisor],
) -> None:
    sup = supervisors([thread("erm"), thread("cm")], name="tree").start()

    with pytest.raises(rr.UnknownServerError, match=r"did you mean 'erm'\?"):
        sup.run_in("emr", lambda registrar: None)
    with pytest.raises(rr.UnknownServerError, match=r"did you mean 'erm'\?"):
        sup.wait_restarted("emr", timeout=1.0)
