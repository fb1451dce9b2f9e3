"""What a consumer does with a call's answer, decided without threads (`flight.decide`).

Each row is one situation an answer can meet at its consumer's actor: a plain answer
(`ClientLoaded`: its caller has it) or a durable one (`DurableLoaded`: the actor answers
the caller after the commit), withdrawn or not (a durable attempt the actor could not
take), a top-level call or a dependency, the registrar stopping or not, the resource the
dependency belongs to gone or not. The row names the action. What each action does to
the catalog and the provider is tested through real registrars in
`test_registrar_races.py`, `test_registrar_timeouts.py` and `test_durable_consumer_kill.py`.
"""

from __future__ import annotations

import itertools

import pytest

from rr_actors._registrar.consumer import Action, InFlight, decide

KEEP = Action.KEEP
COMMIT = Action.COMMIT
LEAVE = Action.LEAVE
GIVE_BACK = Action.GIVE_BACK
REFUSE = Action.REFUSE
FORGET = Action.FORGET
RELEASE_LATE = Action.RELEASE_LATE

# (durable, withdrawn, dependency, stopping, owner_gone) -> action
ROWS: list[tuple[str, tuple[bool, bool, bool, bool, bool], Action]] = [
    # -- a plain answer: its caller has it; the actor records it, or gives the id back
    ("plain, top level", (False, False, False, False, False), KEEP),
    ("plain, top level, stopping", (False, False, False, True, False), FORGET),
    ("plain dependency", (False, False, True, False, False), KEEP),
    ("plain dependency, stopping (its owner releases it)", (False, False, True, True, False), KEEP),
    ("plain dependency, its owner gone", (False, False, True, False, True), RELEASE_LATE),
    ("plain dependency, its owner gone, stopping", (False, False, True, True, True), RELEASE_LATE),
    # -- a durable answer the actor took: commit it, then answer the caller
    ("durable, top level", (True, False, False, False, False), COMMIT),
    ("durable, top level, stopping", (True, False, False, True, False), REFUSE),
    ("durable dependency", (True, False, True, False, False), COMMIT),
    ("durable dependency, stopping", (True, False, True, True, False), COMMIT),
    ("durable dependency, its owner gone", (True, False, True, False, True), RELEASE_LATE),
    (
        "durable dependency, its owner gone, stopping",
        (True, False, True, True, True),
        RELEASE_LATE,
    ),
    # -- a durable answer its caller withdrew (or a stop failed): not kept
    ("durable withdrawn, top level", (True, True, False, False, False), LEAVE),
    ("durable withdrawn, top level, stopping", (True, True, False, True, False), GIVE_BACK),
    ("durable withdrawn dependency", (True, True, True, False, False), LEAVE),
    ("durable withdrawn dependency, stopping", (True, True, True, True, False), GIVE_BACK),
    ("durable withdrawn dependency, its owner gone", (True, True, True, False, True), LEAVE),
    (
        "durable withdrawn dependency, its owner gone, stopping",
        (True, True, True, True, True),
        GIVE_BACK,
    ),
]


def _possible() -> set[tuple[bool, bool, bool, bool, bool]]:
    """Every situation an answer can meet: a plain answer is never withdrawn; only a
    dependency has an owner that can be gone."""
    return {
        (durable, withdrawn, dependency, stopping, owner_gone)
        for durable, withdrawn, dependency, stopping, owner_gone in itertools.product(
            (False, True), repeat=5
        )
        if (durable or not withdrawn) and (dependency or not owner_gone)
    }


@pytest.mark.parametrize(
    ("situation", "action"), [(s, a) for _, s, a in ROWS], ids=[r[0] for r in ROWS]
)
def test_each_situation_of_an_answer_names_its_action(
    situation: tuple[bool, bool, bool, bool, bool], action: Action
) -> None:
    durable, withdrawn, dependency, stopping, owner_gone = situation

    assert action == decide(
        durable=durable,
        withdrawn=withdrawn,
        dependency=dependency,
        stopping=stopping,
        owner_gone=owner_gone,
    )


def test_the_table_has_every_possible_situation_once() -> None:
    situations = [situation for _, situation, _ in ROWS]

    assert len(situations) == len(set(situations))
    assert _possible() == set(situations)


def test_every_action_is_named_by_a_row() -> None:
    assert set(Action) == {action for _, _, action in ROWS}


def test_an_in_flight_record_is_idle_only_when_nothing_is_left_of_it() -> None:
    flight = InFlight()
    assert flight.idle()

    flight.unsettled_at = "prov"
    assert not flight.idle()
    flight.unsettled_at = None
    flight.parked.append(object())  # type: ignore[arg-type]  # (any notice)
    assert not flight.idle()
    flight.parked.clear()
    assert flight.idle()
