"""The kit's own rules: what an exercise asks of a student's code that the checker's rules
(`rr_actors.experiments.check.RULES`) do not judge, over the same numbered events.

Each rule takes a run's events (`(line, event)`, the lines of its history) and the
names of the plan's managers, and gives findings (`check.Finding`: rule, `"violation"`,
message, the lines that show it), in the order of their lines.

- `dependency` (rule 7): a call a manager makes is made while it loads a resource, and
  so is a dependency of that resource (`CallAnswered.parent` set): released with the
  resource, never left held by a manager for nothing.
- `survives`: no supervisor gives up (`SupervisorGaveUp`): the tree's restart intensity
  holds out under the exercise's faults.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence

from rr_actors import events
from rr_actors.experiments.check import Finding, Line

__all__ = ["RULES"]


def dependency(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`dependency`: every call a manager made was a dependency of one of its resources."""
    return [
        Finding(
            "dependency",
            "violation",
            f"{e.registrar} holds {e.serving_rr}/{e.server} query {e.query_id[:8]} as a call of "
            "its own, not as a dependency of a resource it loads (no parent): nothing "
            "releases it with a resource",
            (line,),
            (e.registrar,),
        )
        for line, e in history
        if isinstance(e, events.CallAnswered) and e.registrar in managers and e.parent is None
    ]


def survives(history: Sequence[Line], managers: Collection[str]) -> list[Finding]:
    """`survives`: no supervisor gave up."""
    return [
        Finding(
            "survives",
            "violation",
            f"supervisor {e.supervisor} gave up: {e.reason}",
            (line,),
            (e.supervisor, *managers),  # (its children's exits: the story before it)
        )
        for line, e in history
        if isinstance(e, events.SupervisorGaveUp)
    ]


RULES: dict[str, Callable[[Sequence[Line], Collection[str]], list[Finding]]] = {
    "dependency": dependency,
    "survives": survives,
}
"""The kit's rules by name (what an exercise's `rules` lists)."""
