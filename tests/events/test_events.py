"""rr_actors.events: every event kind constructs, pickles, goes through JSON and back, reads.

Publishing these events through a registrar or a supervisor is tested with those; the bus
that carries them is tested in `test_bus.py`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import pickle
import threading
import time
import typing
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors.events import kinds
from rr_actors.events.lines import to_line, to_lines

WAIT = 5.0

QID = "5e6f7a8b-0000-4000-8000-000000000001"
RID = "1a2b3c4d-0000-4000-8000-000000000002"

EXAMPLES: list[events.Event] = [
    events.ChildStarted("root", "erm", 4242),
    events.ChildExited("root", "erm", 4242, "killed by SIGKILL"),
    events.ChildRestarted("root", "erm", 4243, 0.0231),
    events.SupervisorGaveUp("root", "erm crashed 4 times within 5 s", 3, 5.0),
    events.ManagerOverloaded("root", "erm", 4242, 1.25, 0.75, 1.1, 0.9, 312),
    events.ResourceLoaded("erm", "start_process", RID, QID, 0.0123, 77, "camera 0"),
    events.LoadFailed("erm", "start_process", RID, QID, "SensorError", "no camera"),
    events.ResourceUnloaded("erm", "start_process", RID),
    events.ConsumerAdded("erm", RID, QID, "cm"),
    events.ConsumerReleased("erm", RID, QID, "cm", "death watch"),
    events.CallAnswered("cm", QID, "erm", "start_process", RID, retry=True),
    events.CallFailed(
        "cm", QID, "erm", "start_process", "RegistrarUnavailableError", "it died", True
    ),
    events.CallWithdrawn("cm", QID, "erm", "start_process", "timeout"),
    events.QueriesFetched("cm", "erm", "start_process", (QID,), 7354725256007057408),
    events.ServerQueriesListed("erm", "start_process", (QID,), 7354725256007057408),
    events.QueryForgotten("cm", QID, "erm", "provider lost"),
    events.StatusSent("erm", QID, rr.Status.FATAL, "process died"),
    events.StatusDelivered("cm", QID, rr.Status.FATAL, 2, 0.0012),
    events.StatusHandled("cm", QID, rr.Status.FATAL, "s1", 3, 7354725256007057408),
    events.StatusAnswered("erm", QID, "s1", (QID,), ()),
    events.InDoubt("erm", QID, "start_process", "unload"),
    events.CatalogRestored(
        "erm", ((RID, "start_process", "loaded"),), ((QID, RID, "cm"),), (), (1, 1, 0)
    ),
    events.RegistrarStopped("cm", (), (), ((QID, "erm", "start_process", ""),), (0, 0, 1)),
    events.UnloadCutShort("erm", "start_process", RID),
    events.ServerOverloaded("erm", "start_process", 1000, 1000, 17),
    events.ShareRefused("erm", "start_process", "api", 6, 5, 5, 2, 1, 10, 0.5, (1,), (0.25,)),
    events.ShareAdmitted("erm", "start_process", "api", 5, 1, 2, 2, 5, 0.25, (0,), (0.5,)),
    events.EventsDropped(17),
    events.EventsUnpublished((4, 5), pid=42),
]

KINDS = typing.get_args(events.Event)


def kind(event: events.Event) -> str:
    return type(event).__name__


def line(event: events.Event) -> dict[str, Any]:
    """`event` written as one JSON line and parsed again (as `events.jsonl` readers do)."""
    text = json.dumps(events.to_dict(event))
    assert "\n" not in text
    parsed: dict[str, Any] = json.loads(text)
    return parsed


def test_the_examples_cover_every_event_kind() -> None:
    assert sorted(k.__name__ for k in KINDS) == sorted(kind(e) for e in EXAMPLES)
    assert sorted(events.__all__) == sorted(
        [*(k.__name__ for k in KINDS), "Event", "describe", "from_dict", "order", "to_dict"]
    )


@pytest.mark.parametrize("event", EXAMPLES, ids=kind)
def test_every_event_kind_pickles(event: events.Event) -> None:
    assert event == pickle.loads(pickle.dumps(event))


@pytest.mark.parametrize("event", EXAMPLES, ids=kind)
def test_every_event_kind_round_trips_through_a_json_line(event: events.Event) -> None:
    assert event == events.from_dict(line(event))


@pytest.mark.parametrize("event", EXAMPLES, ids=kind)
def test_every_event_kind_is_frozen(event: events.Event) -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        event.at = 0.0  # type: ignore[misc]


@pytest.mark.parametrize("event", EXAMPLES, ids=kind)
def test_every_event_kind_has_its_own_fields_first_then_keyword_only_at_and_pid(
    event: events.Event,
) -> None:
    names = [f.name for f in dataclasses.fields(event)]
    keyword_only = [f.name for f in dataclasses.fields(event) if f.kw_only]
    if kind(event).startswith("Child") or kind(event) == "ManagerOverloaded":
        # a child's pid is one of its own fields (a manager's, the supervisor's event)
        assert ["at", "host", "hlc"] == keyword_only
        assert "pid" == names[2]
    else:
        assert ["at", "pid", "seq", "host", "hlc"] == keyword_only
    assert keyword_only == names[-len(keyword_only) :]


@pytest.mark.parametrize("event", EXAMPLES, ids=kind)
def test_every_event_kind_is_slotted_without_a_dict_per_event(event: events.Event) -> None:
    assert not hasattr(event, "__dict__")


def test_a_kind_that_declares_a_stamp_it_inherits_is_refused() -> None:
    with pytest.raises(TypeError, match=r"Clash: \['seq'\] are stamps it inherits"):

        @kinds._kind
        class Clash(kinds._Numbered):
            seq: int


def test_a_stamp_without_a_place_in_the_line_is_refused() -> None:
    with pytest.raises(TypeError, match=r"Stray: \['when'\] are not stamps"):

        @kinds._stamps
        class Stray(kinds._Stamped):
            when: float = dataclasses.field(default_factory=time.time)


@pytest.mark.parametrize("event", EXAMPLES, ids=kind)
def test_every_event_kind_describes_itself_in_one_line(event: events.Event) -> None:
    text = events.describe(event)
    assert text
    assert "\n" not in text


def test_an_event_is_stamped_with_the_wall_clock_and_this_process() -> None:
    before = time.time()
    event = events.InDoubt("erm", QID)
    after = time.time()
    assert before <= event.at <= after
    assert os.getpid() == event.pid


def test_at_and_pid_can_be_given_by_keyword_only() -> None:
    event = events.ResourceUnloaded("erm", "s", RID, at=12.5, pid=7)
    assert (12.5, 7) == (event.at, event.pid)
    with pytest.raises(TypeError):
        events.ResourceUnloaded("erm", "s", RID, 12.5)  # type: ignore[call-arg]


def test_a_child_event_carries_the_childs_pid_in_its_own_fields() -> None:
    event = events.ChildRestarted("root", "erm", 4243, 0.02)
    assert 4243 == event.pid
    with pytest.raises(TypeError):
        events.ChildStarted("root", "erm")  # type: ignore[call-arg]


def test_an_event_made_in_a_forked_child_has_the_childs_pid() -> None:
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child process
        os.write(write, str(events.InDoubt("erm", QID).pid).encode())
        os._exit(0)
    os.close(write)
    with os.fdopen(read) as reader:
        reported = int(reader.read())
    os.waitpid(pid, 0)
    assert pid == reported
    assert os.getpid() == events.InDoubt("erm", QID).pid


def test_to_dict_names_the_type_and_writes_the_status_by_name() -> None:
    event = events.StatusSent(
        "erm", QID, rr.Status.WARNING, "hot", at=1.5, pid=9, host="robot", hlc=7 << 12
    )
    expected = {
        "type": "StatusSent",
        "registrar": "erm",
        "query_id": QID,
        "status": "WARNING",
        "message": "hot",
        "status_id": "",
        "patience": None,
        "at": 1.5,
        "pid": 9,
        "seq": 0,
        "host": "robot",
        "hlc": 7 << 12,
        "schema": events.lines.SCHEMA,
    }
    assert expected == events.to_dict(event)


@pytest.mark.parametrize("event", EXAMPLES, ids=kind)
def test_to_line_is_the_json_of_to_dict_byte_for_byte(event: events.Event) -> None:
    extra = {"run": 3, "seed": 12}
    odd = dataclasses.replace(event, host='h\u00e9\n"', at=float("nan"))  # (escapes, NaN)
    for each in (event, odd):
        assert json.dumps(events.to_dict(each)) == to_line(each)
        assert json.dumps({**events.to_dict(each), **extra}) == to_line(each, extra)


def test_to_line_refuses_what_json_refuses_as_to_dict_does() -> None:
    event = events.LoadFailed("erm", "cam", RID, QID, "E", object())  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="not JSON serializable"):
        json.dumps(events.to_dict(event))
    with pytest.raises(TypeError, match="not JSON serializable"):
        to_line(event)


def _odd(event: events.Event) -> events.Event:
    """`event` with values whose text is escaped or unusual: a newline, `%`, NaN."""
    return dataclasses.replace(event, host='h\u00e9\n%s"', at=float("nan"), pid=-1)


@pytest.mark.parametrize("extra", [None, {}, {"run": 3, "seed": 12}, {"pid": "%d", "x": [1, 2]}])
def test_to_lines_writes_each_event_as_json_dumps_of_to_dict_does(
    extra: dict[str, Any] | None,
) -> None:
    seen = [*EXAMPLES, *map(_odd, EXAMPLES), *EXAMPLES]
    expected = "".join(f"{json.dumps({**events.to_dict(e), **(extra or {})})}\n" for e in seen)
    assert expected == to_lines(seen, extra)
    assert "" == to_lines([], extra)


def test_to_lines_refuses_what_json_refuses_as_to_line_does() -> None:
    event = events.LoadFailed("erm", "cam", RID, QID, "E", object())  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="Object of type object is not JSON serializable"):
        to_lines([EXAMPLES[0], event])


def test_from_dict_reads_a_schema_1_line_without_the_fields_added_since() -> None:
    data = line(events.ConsumerReleased("erm", RID, QID, "cm", "reconcile", at=2.0, pid=9))
    del data["reason"], data["seq"]
    del data["host"], data["hlc"]
    data["schema"] = 1
    old = events.ConsumerReleased(
        "erm", RID, QID, "cm", at=2.0, pid=9, host="", hlc=2_000_000 << 12
    )
    assert old == events.from_dict(data)  # (no host known; the stamp of its wall time)
    del data["pid"]  # at and pid were always there
    with pytest.raises(rr.ConfigError, match="pid"):
        events.from_dict(data)


def test_from_dict_answers_a_mistyped_event_type_with_the_closest_one() -> None:
    data = {**line(events.ConsumerReleased("erm", RID, QID, "cm", at=2.0, pid=9))}
    data["type"] = "ConsumerRelease"

    with pytest.raises(rr.ConfigError) as caught:
        events.from_dict(data)

    assert "unknown event type 'ConsumerRelease'; did you mean 'ConsumerReleased'?" == str(
        caught.value
    )


def test_from_dict_reads_a_schema_4_query_forgotten_without_its_release_stamps() -> None:
    data = line(events.QueryForgotten("cm", QID, "erm", "unload", 5, 3, at=2.0, pid=9))
    del data["unload_sent"], data["reconciled"]
    data["schema"] = 4

    read = events.from_dict(data)

    assert isinstance(read, events.QueryForgotten)
    assert (0, 0) == (read.unload_sent, read.reconciled)  # (not known)


def test_from_dict_reads_a_schema_5_child_exited_without_its_strategy() -> None:
    exited = events.ChildExited(
        "pool", "worker", 9, "killed", "permanent", False, False, 2, 2.0, "one_for_all",
        ("worker", "cache"), at=2.0,
    )  # fmt: skip
    assert ["worker", "cache"] == line(exited)["children"]  # (a list in JSON)
    assert exited == events.from_dict(line(exited))
    data = line(exited)
    del data["strategy"], data["children"]
    data["schema"] = 5

    read = events.from_dict(data)

    assert isinstance(read, events.ChildExited)
    assert ("", ()) == (read.strategy, read.children)  # (not known: not judged)


def test_from_dict_reads_a_schema_6_call_without_its_start_and_trace_context() -> None:
    traceparent = f"00-{'a' * 32}-{'b' * 16}-01"
    answered = events.CallAnswered(
        "app", QID, "erm", "cam", started=1.5, trace=traceparent, caller_span="c" * 16, at=2.0
    )
    assert answered == events.from_dict(line(answered))
    data = line(answered)
    del data["started"], data["trace"], data["caller_span"]
    data["schema"] = 6

    read = events.from_dict(data)

    assert isinstance(read, events.CallAnswered)
    assert (0.0, "", "") == (read.started, read.trace, read.caller_span)  # (not known)
    data["schema"] = events.lines.SCHEMA
    with pytest.raises(rr.ConfigError, match="started"):  # (a line of this schema has them)
        events.from_dict(data)


def test_from_dict_reads_a_schema_7_resource_loaded_without_its_trace() -> None:
    traceparent = f"00-{'a' * 32}-{'b' * 16}-01"
    loaded = events.ResourceLoaded("erm", "cam", "r1", QID, 0.5, trace=traceparent, at=2.0)
    assert loaded == events.from_dict(line(loaded))
    data = line(loaded)
    del data["trace"]
    data["schema"] = 7

    assert dataclasses.replace(loaded, trace="") == events.from_dict(data)
    data["schema"] = events.lines.SCHEMA
    with pytest.raises(rr.ConfigError, match="trace"):  # (a line of this schema has it)
        events.from_dict(data)


def test_from_dict_reads_a_schema_8_share_refused_without_those_waiting() -> None:
    refused = events.ShareRefused("erm", "cam", "api", 5, 3, 2, 2, 1, 8, 0.5, (1,), (0.25,))
    assert refused == events.from_dict(line(refused))
    data = line(refused)
    for name in ("since", "waiting", "firsts"):
        del data[name]
    data["schema"] = 8

    expected = dataclasses.replace(refused, since=0.0, waiting=(), firsts=())
    assert expected == events.from_dict(data)
    data["schema"] = events.lines.SCHEMA
    with pytest.raises(rr.ConfigError, match="since"):  # (a line of this schema has them)
        events.from_dict(data)


def test_from_dict_accepts_an_int_for_a_float() -> None:
    data = line(events.ChildRestarted("root", "erm", 1, 0.5, at=10.0))
    data["restart_s"] = 2
    data["at"] = 11
    event = events.from_dict(data)
    assert isinstance(event, events.ChildRestarted)
    assert (2.0, 11.0) == (event.restart_s, event.at)
    assert isinstance(event.restart_s, float)


_DROP = object()
"""Marks a key `_with` removes."""


def _with(**changes: Any) -> dict[str, Any]:
    data = line(events.StatusDelivered("cm", QID, rr.Status.OK, 1, 0.001))
    for key, value in changes.items():
        if value is _DROP:
            del data[key]
        else:
            data[key] = value
    return data


@pytest.mark.parametrize(
    ("data", "named"),
    [
        ([1, 2], "list"),
        (_with(schema=10), "schema 10"),
        (_with(schema=_DROP), "schema None"),
        (_with(type="Exploded"), "'Exploded'"),
        (_with(type=_DROP), "None"),
        (_with(colour="red"), "colour"),
        (_with(hop=_DROP, at=_DROP), "['hop', 'at']"),
        (_with(hop="two"), "StatusDelivered.hop"),
        (_with(hop=True), "StatusDelivered.hop"),
        (_with(latency_s="fast"), "StatusDelivered.latency_s"),
        (_with(status="BROKEN"), "StatusDelivered.status"),
        (_with(status=3), "StatusDelivered.status"),
        (_with(registrar=None), "StatusDelivered.registrar"),
        (_with(hlc=-1), "StatusDelivered.hlc"),
        (_with(hlc=2**64), "StatusDelivered.hlc"),
        (_with(host=_DROP), "['host']"),
    ],
    ids=[
        "not-a-dict",
        "other-schema",
        "no-schema",
        "unknown-type",
        "no-type",
        "unknown-field",
        "missing-fields",
        "str-for-int",
        "bool-for-int",
        "str-for-float",
        "unknown-status",
        "int-for-status",
        "none-for-str",
        "negative-stamp",
        "stamp-over-64-bits",
        "schema-3-without-host",
    ],
)
def test_from_dict_names_what_is_wrong(data: Any, named: str) -> None:
    with pytest.raises(rr.ConfigError) as caught:
        events.from_dict(data)
    assert named in str(caught.value)


@pytest.mark.parametrize(
    ("event", "expected"),
    [
        (events.ChildStarted("root", "erm", 4242), "erm started (pid 4242)"),
        (
            events.ChildExited("root", "erm", 4242, "killed by SIGKILL"),
            "erm exited: killed by SIGKILL (pid 4242)",
        ),
        (
            events.ChildRestarted("root", "erm", 4242, 0.0231),
            "erm restarted after 23.1 ms (pid 4242)",
        ),
        (events.ChildRestarted("root", "erm", 4242, 2.5), "erm restarted after 2.50 s (pid 4242)"),
        (
            events.SupervisorGaveUp("root", "erm crashed", 3, 5.0),
            "supervisor root gave up (more than 3 restarts within 5 s): erm crashed",
        ),
        (
            events.ManagerOverloaded("root", "erm", 4242, 1.25, 0.75, 1.1, 0.9, 312),
            "erm is overloaded, not hung: it answered its heartbeat after 1.25 s (bound 750.0 "
            "ms), 1.10 s of it excused (its registrar busy for 900.0 ms, 312 messages queued) "
            "(pid 4242)",
        ),
        (
            events.ResourceLoaded("erm", "start_process", RID, QID, 0.0123, 77, "camera 0"),
            "erm/start_process loaded 1a2b3c4d in 12.3 ms (query 5e6f7a8b)",
        ),
        (
            events.LoadFailed("erm", "cam", RID, QID, "SensorError", "no\ncamera"),
            "erm/cam failed to load 1a2b3c4d (query 5e6f7a8b): SensorError: no\\ncamera",
        ),
        (events.ResourceUnloaded("erm", "cam", RID), "erm/cam unloaded 1a2b3c4d"),
        (
            events.ServerOverloaded("erm", "cam", 4, 4, 17),
            "erm/cam is overloaded: 4 loads queued or running (max_pending=4), 17 calls refused",
        ),
        (
            events.UnloadCutShort("erm", "cam", RID),
            "erm/cam: the unload of 1a2b3c4d was cut short by a stop (in doubt at the next start)",
        ),
        (events.ConsumerAdded("erm", RID, QID, "cm"), "erm: cm consumes 1a2b3c4d (query 5e6f7a8b)"),
        (
            events.ConsumerReleased("erm", RID, QID, "cm", "death watch"),
            "erm: cm released 1a2b3c4d (query 5e6f7a8b, death watch)",
        ),
        (
            events.StatusSent("erm", QID, rr.Status.FATAL, "process died"),
            "erm sent FATAL for query 5e6f7a8b: process died",
        ),
        (
            events.StatusDelivered("cm", QID, rr.Status.FATAL, 2, 0.0012),
            "cm received FATAL for query 5e6f7a8b (hop 2, 1.2 ms after it was sent)",
        ),
        (
            events.StatusHandled("cm", QID, rr.Status.FATAL, "s1", 3, 7354725256007057408),
            "cm: the callback of FATAL for query 5e6f7a8b returned",
        ),
        (events.EventsDropped(17), "17 events dropped (a subscriber or forwarder fell behind)"),
        (
            events.EventsUnpublished((4, 5), pid=42),
            "2 numbers of process 42 never used: it was killed before it published those "
            "events (none lost)",
        ),
    ],
    ids=lambda value: kind(value) if not isinstance(value, str) else "",
)
def test_describe_reads_as_one_line_of_a_timeline(event: events.Event, expected: str) -> None:
    assert expected == events.describe(event)


def test_describe_shortens_a_long_message() -> None:
    text = events.describe(events.StatusSent("erm", QID, rr.Status.OK, "x" * 1000))
    assert text.endswith("x...")
    assert len(text) < 300


def test_the_events_publisher_logs_describe_lines_and_reports_gaps_as_events_dropped(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="rr_actors.test_events")
    publisher = events.publisher(logging.getLogger("rr_actors.test_events"))
    gate, entered = threading.Event(), threading.Event()
    got: list[events.Event] = []

    def slow(event: events.Event) -> None:
        got.append(event)
        if not entered.is_set():
            entered.set()
            assert gate.wait(WAIT)

    try:
        with publisher.subscribe(slow, maxsize=1) as subscription:
            publisher.publish(events.InDoubt("erm", "q0"))
            assert entered.wait(WAIT)
            for i in range(1, 4):
                publisher.publish(events.InDoubt("erm", f"q{i}"))
            gate.set()
            assert subscription.wait_delivered(timeout=WAIT)
    finally:
        gate.set()
    assert ["q0", "q1"] == [e.query_id for e in got if isinstance(e, events.InDoubt)]
    assert isinstance(got[-1], events.EventsDropped)
    assert 2 == got[-1].count
    infos = [r for r in caplog.records if r.name == "rr_actors.test_events"]
    assert [events.describe(events.InDoubt("erm", f"q{i}")) for i in range(4)] == [
        r.getMessage() for r in infos
    ]


def test_subscription_is_public_as_rr_subscription() -> None:
    publisher = events.publisher()
    with publisher.subscribe(lambda _: None) as subscription:
        assert isinstance(subscription, rr.Subscription)


def test_the_events_module_is_reachable_as_rr_events() -> None:
    assert events is rr.events
