"""Which of two servers of one name is kept after a heal (rule 22): the system's policy.

Each process decides alone from the same `Claimant`s, so all use one deterministic policy:
docs/explanation/failure-semantics.md ("Which one a heal keeps").
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterable
from typing import Protocol, TypeVar, runtime_checkable

from rr_actors._core.hlc import seconds
from rr_actors._core.throttle import LogThrottle
from rr_actors.errors import ConfigError

logger = logging.getLogger("rr_actors")

RESOLVE_STRATEGIES = ("first_served", "majority")  # or a function of two `Claimant`s


@dataclasses.dataclass(frozen=True)
class Claimant:
    """One of two servers of one name after a healed cut (rule 22), as `resolve=` gets it.

    Attributes:
        name: the registrar's name.
        process: its process as the carrier names it (a Zenoh id, a simulated pid).
        stamp: when it began to serve (hybrid logical clock); the lower served first.
        served_since: `stamp` as wall-clock seconds since the epoch (`time.time()`).
        side: members its process heard when it began to serve, its own included (`0`:
            unknown).
        members: members the system had then, as its process counted them (`0`: unknown).
    """

    name: str
    process: str
    stamp: int
    served_since: float
    side: int = 0
    members: int = 0

    @property
    def majority(self) -> bool:
        """Whether it began to serve on a side that held more than half the members."""
        return self.members > 0 and 2 * self.side > self.members


Resolve = str | Callable[[Claimant, Claimant], Claimant]
"""`resolve=`: `"first_served"`, `"majority"`, or `fn(first, second) -> the one kept`."""


@runtime_checkable
class Sided(Protocol):
    """A server of a name as rule 22 orders it; `rank`: the lower served first."""

    @property
    def stamp(self) -> int: ...
    @property
    def who(self) -> str: ...
    @property
    def rank(self) -> tuple[int, int]: ...
    @property
    def side(self) -> int: ...
    @property
    def members(self) -> int: ...


S = TypeVar("S", bound=Sided)


def check_resolve(value: object) -> Resolve:
    """`value` if it is a strategy `resolve=` takes, else `ConfigError`."""
    if isinstance(value, str) and value in RESOLVE_STRATEGIES:
        return value
    if callable(value) and not isinstance(value, str | type):
        return value  # (its signature is not checked: a wrong answer falls back)
    raise ConfigError(
        f"resolve must be 'first_served', 'majority' or a function (first, second) -> the "
        f"one kept, not {value!r}"
    )


class Resolution:
    """A system's rule 22 policy (`resolve` as `ZenohNetwork`'s); `ConfigError` if bad."""

    def __init__(self, resolve: object = "first_served") -> None:
        self.resolve = check_resolve(resolve)
        self._warn = LogThrottle(logger)

    def __repr__(self) -> str:
        return f"Resolution({self.resolve!r})"

    def kept(self, name: str, servers: Iterable[S]) -> S | None:
        """Which of `servers` of `name` is kept: folded in first-served order."""
        ordered = sorted(servers, key=lambda server: server.rank)
        if not ordered:
            return None
        winner = ordered[0]
        for other in ordered[1:]:
            winner = self.keep(name, winner, other)
        return winner

    def keep(self, name: str, first: S, second: S) -> S:
        """Which of `first` and `second` (first served first: the lower `rank`) is kept."""
        if self.resolve == "first_served":
            return first
        one, two = claimant(name, first), claimant(name, second)
        if self.resolve == "majority":
            if one.majority != two.majority:
                return first if one.majority else second
            return second if one.majority else first  # (both: the later; neither: the first)
        return second if self._ask(one, two) is two else first

    def _ask(self, one: Claimant, two: Claimant) -> Claimant:
        """The user's function's answer, or `one` with a WARNING if it failed."""
        resolve = self.resolve
        assert callable(resolve)
        try:
            answer = resolve(one, two)
        except Exception as exc:  # noqa: BLE001 - user code must not break rule 22
            self._warn.warning(
                "resolve=%r raised %s: %s for registrar %s; the one served first is kept",
                resolve,
                type(exc).__name__,
                exc,
                one.name,
            )
            return one
        if answer is two or (answer is not one and answer == two):
            return two
        if answer is not one and answer != one:
            self._warn.warning(
                "resolve=%r answered %r for registrar %s, which is neither claimant; the "
                "one served first is kept",
                resolve,
                answer,
                one.name,
            )
        return one


def claimant(name: str, server: Sided) -> Claimant:
    return Claimant(
        name=name,
        process=server.who,
        stamp=server.stamp,
        served_since=seconds(server.stamp),
        side=server.side,
        members=server.members,
    )


FIRST_SERVED = Resolution()
