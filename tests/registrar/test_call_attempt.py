"""One call attempt's state machine, driven without threads (`CallAttempt`).

Each row is one order in which the parties of a call act: its caller (`sent`, and
`withdraw` when its time runs out), the thread that brings the answer (`answer` for a
plain call, an error or a provider's death as `fail`), and its registrar's actor (`take`
and `settle` for a durable call's answer, `fail` when it stops). Each step names the
state the transition must return (what that party acts on), and the row ends with what
the caller gets. The threads themselves race in `test_registrar_races.py` and
`test_registrar_timeouts.py`; here every interleaving is written out.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pykka
import pytest

import rr_actors as rr
from rr_actors._registrar.calls import AttemptState, CallAttempt

SENT = AttemptState.SENT
RECORDING = AttemptState.RECORDING
ANSWERED = AttemptState.ANSWERED
FAILED = AttemptState.FAILED
WITHDRAWN = AttemptState.WITHDRAWN

LOAD_ERROR = rr.ResourceLoadError(
    (rr.ErrorFrame("prov", "leaf", "ValueError", "bad request", traceback=""),)
)
PROVIDER_DIED = rr.RegistrarUnavailableError("registrar 'prov' died")
STOPPED = rr.RegistrarStoppedError("registrar 'cons' stopped during the call")
NOT_WRITTEN = rr.CatalogWriteError("state/cons.db", "disk full")

STEPS: dict[str, Callable[[CallAttempt], AttemptState]] = {
    "sent": CallAttempt.sent,  # the caller: its Load leaves
    "answer": lambda a: a.answer("loaded"),  # the answering thread (a plain call)
    "take": CallAttempt.take,  # the actor, a durable call's answer: commit it
    "committed": lambda a: a.settle("loaded"),  # the actor: the record is on disk
    "not kept": lambda a: a.settle(error=NOT_WRITTEN),  # the actor: the write failed
    "load error": lambda a: a.fail(LOAD_ERROR),  # the answering thread: load raised
    "provider died": lambda a: a.fail(PROVIDER_DIED),  # the answering thread
    "stop": lambda a: a.fail(STOPPED),  # the actor stops: it fails durable calls in flight
    "timeout": CallAttempt.withdraw,  # the caller's time runs out (or it is interrupted)
}

TIMED_OUT = "timed out"  # the caller withdrew: CallTimeoutError, the id given back
WAITS = "waits"  # the caller waits on (for the commit)

ROWS: list[tuple[str, list[tuple[str, AttemptState]], Any]] = [
    # -- a plain call: the answering thread hands the answer to the caller, who records it
    ("plain: answered", [("sent", SENT), ("answer", ANSWERED)], "loaded"),
    ("plain: load error", [("sent", SENT), ("load error", FAILED)], LOAD_ERROR),
    ("plain: provider died", [("sent", SENT), ("provider died", FAILED)], PROVIDER_DIED),
    ("plain: timeout", [("sent", SENT), ("timeout", WITHDRAWN)], TIMED_OUT),
    (
        "plain: timeout, then the answer (dropped: the caller gave the id back)",
        [("sent", SENT), ("timeout", WITHDRAWN), ("answer", WITHDRAWN)],
        TIMED_OUT,
    ),
    (
        "plain: the answer, then the timeout (the answer won: the caller reads it)",
        [("sent", SENT), ("answer", ANSWERED), ("timeout", ANSWERED)],
        "loaded",
    ),
    (
        "plain: timeout, then the provider died (not a failure: withdrawn)",
        [("sent", SENT), ("timeout", WITHDRAWN), ("provider died", WITHDRAWN)],
        TIMED_OUT,
    ),
    (
        "plain: an error, then the timeout (a failed call is not withdrawn)",
        [("sent", SENT), ("load error", FAILED), ("timeout", FAILED)],
        LOAD_ERROR,
    ),
    (
        "plain: interrupted before its Load left",
        [("timeout", WITHDRAWN), ("sent", WITHDRAWN)],
        TIMED_OUT,
    ),
    # -- a durable call: the actor takes the answer, commits it, then settles the attempt
    (
        "durable: answered",
        [("sent", SENT), ("take", RECORDING), ("committed", ANSWERED)],
        "loaded",
    ),
    (
        "durable: the answer cannot be written",
        [("sent", SENT), ("take", RECORDING), ("not kept", FAILED)],
        NOT_WRITTEN,
    ),
    ("durable: load error", [("sent", SENT), ("load error", FAILED)], LOAD_ERROR),
    ("durable: provider died", [("sent", SENT), ("provider died", FAILED)], PROVIDER_DIED),
    ("durable: timeout", [("sent", SENT), ("timeout", WITHDRAWN)], TIMED_OUT),
    (
        "durable: timeout, then the answer (not kept: the actor drops it)",
        [("sent", SENT), ("timeout", WITHDRAWN), ("take", WITHDRAWN)],
        TIMED_OUT,
    ),
    (
        "durable: the timeout while it is committed (the caller waits for the commit)",
        [("sent", SENT), ("take", RECORDING), ("timeout", RECORDING)],
        WAITS,
    ),
    (
        "durable: the timeout while it is committed, then the commit",
        [("sent", SENT), ("take", RECORDING), ("timeout", RECORDING), ("committed", ANSWERED)],
        "loaded",
    ),
    (
        "durable: the registrar stops and dies while it commits (its holder settles it)",
        [("sent", SENT), ("take", RECORDING), ("stop", RECORDING), ("not kept", FAILED)],
        NOT_WRITTEN,
    ),
    (
        "durable: the registrar stops before the Load left (nothing is sent)",
        [("stop", FAILED), ("sent", FAILED)],
        STOPPED,
    ),
    (
        "durable: the registrar stops after the Load left, then the answer (dropped)",
        [("sent", SENT), ("stop", FAILED), ("take", FAILED), ("timeout", FAILED)],
        STOPPED,
    ),
    (
        "durable: timeout, then the registrar stops (withdrawn stays withdrawn)",
        [("sent", SENT), ("timeout", WITHDRAWN), ("stop", WITHDRAWN), ("take", WITHDRAWN)],
        TIMED_OUT,
    ),
    (
        "durable: answered, then a late failure changes nothing",
        [("sent", SENT), ("take", RECORDING), ("committed", ANSWERED), ("stop", ANSWERED)],
        "loaded",
    ),
]


def _outcome(attempt: CallAttempt) -> Any:
    """What the caller gets, as `Calls.call` reads it once it stops waiting."""
    if attempt.state is WITHDRAWN:
        return TIMED_OUT
    if not attempt.wait(0):
        return WAITS
    try:
        return attempt.get(timeout=0)
    except rr.RrError as exc:
        return exc


@pytest.mark.parametrize(("steps", "expected"), [row[1:] for row in ROWS], ids=[r[0] for r in ROWS])
def test_each_party_acts_on_the_state_its_transition_returns(
    steps: list[tuple[str, AttemptState]], expected: Any
) -> None:
    attempt = CallAttempt()
    assert AttemptState.SENDING is attempt.state

    returned = [(step, STEPS[step](attempt)) for step, _ in steps]

    assert steps == returned
    assert expected == _outcome(attempt)


def test_an_attempt_nobody_settled_keeps_its_caller_waiting() -> None:
    attempt = CallAttempt()
    attempt.sent()

    assert not attempt.wait(0)
    with pytest.raises(pykka.Timeout):
        attempt.get(timeout=0)


@pytest.mark.parametrize(
    "settled_by",
    [["answer"], ["load error"], ["take", "committed"], ["take", "not kept"], ["timeout"]],
)
def test_an_attempt_is_settled_once_whatever_comes_after(settled_by: list[str]) -> None:
    attempt = CallAttempt()
    attempt.sent()
    for step in settled_by:
        STEPS[step](attempt)
    settled = attempt.state

    for step in ["answer", "take", "committed", "not kept", "load error", "stop", "timeout"]:
        assert settled is STEPS[step](attempt)
    assert settled is attempt.state
