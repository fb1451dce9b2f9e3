"""The W3C trace context a call carries (`rr_actors._core.traces`)."""

from __future__ import annotations

import contextvars
import subprocess
import sys

import pytest
from opentelemetry import trace
from opentelemetry.sdk.trace import TracerProvider

from rr_actors._core import traces


def test_without_a_span_current_a_call_carries_nothing() -> None:
    assert traces.begin() is None
    assert "" == traces.current()


def test_under_a_span_a_call_names_a_fresh_client_span_in_the_callers_trace() -> None:
    tracer = TracerProvider().get_tracer("test")
    with tracer.start_as_current_span("step") as step:
        first, second = traces.begin(), traces.begin()
    caller = step.get_span_context()
    assert first is not None
    assert second is not None
    for traceparent, caller_span in (first, second):
        parsed = traces.parse(traceparent)
        assert parsed is not None
        trace_id, client, flags = parsed
        assert (caller.trace_id, int(caller.trace_flags)) == (trace_id, flags)
        assert f"{caller.span_id:016x}" == caller_span
        assert client not in (0, caller.span_id)
    assert first[0] != second[0]  # (a span id per call)


def test_the_server_span_is_derived_from_the_client_span_and_current_in_the_load() -> None:
    traceparent = f"00-{'ab' * 16}-{'0123456789abcdef'}-01"
    token = traces.attach(traceparent)
    try:
        current = trace.get_current_span().get_span_context()
    finally:
        traces.detach(token)
    assert (int("ab" * 16, 16), traces.server_span(0x0123456789ABCDEF)) == (
        current.trace_id,
        current.span_id,
    )
    assert traces.server_span(traces.server_span(7)) == 7
    assert trace.get_current_span().get_span_context().is_valid is False  # (detached)


def test_a_caller_span_adopted_in_another_context_is_current_there_only() -> None:
    traceparent = f"00-{'cd' * 16}-{'1' * 16}-01"
    scope = contextvars.copy_context()
    scope.run(traces.adopt, traceparent)
    assert traceparent == scope.run(traces.current)
    assert "" == traces.current()


@pytest.mark.parametrize(
    "bad",
    ["", "00-xyz", f"01-{'a' * 32}-{'b' * 16}-01", f"00-{'0' * 32}-{'b' * 16}-01",
     f"00-{'a' * 32}-{'0' * 16}-01", f"00-{'g' * 32}-{'b' * 16}-01"],
)  # fmt: skip
def test_a_bad_traceparent_is_none_and_continues_nothing(bad: str) -> None:
    assert traces.parse(bad) is None
    assert traces.context_of(bad) is None
    assert traces.attach(bad) is None


def test_an_untraced_program_does_not_import_opentelemetry() -> None:
    script = (
        "import sys\n"
        "import rr_actors as rr\n"
        "erm = rr.ResourceRegistrar.start('erm')\n"
        "erm.register_server('cam', load=lambda r: r, unload=lambda q, r: None)\n"
        "erm.unload(erm.call('erm', 'cam', 1, timeout=10).id)\n"
        "erm.stop()\n"
        "print(sorted(m for m in sys.modules if m.startswith('opentelemetry')))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=False
    )
    assert 0 == done.returncode, done.stderr[-2000:]
    assert "[]" == done.stdout.strip()  # (its import costs milliseconds; no span can be current)


def test_a_call_under_a_calls_server_span_is_a_fresh_client_span_in_its_trace() -> None:
    carried = "00-" + "ab" * 16 + "-" + "0123456789abcdef" + "-01"

    traceparent, caller_span = traces.under(carried) or ("", "")

    trace_id, client, flags = traces.parse(traceparent) or (0, 0, 0)
    assert (int("ab" * 16, 16), 1) == (trace_id, flags)
    assert client not in (0, int("0123456789abcdef", 16))
    assert traces.server_span(int("0123456789abcdef", 16)) == traces.span_id(caller_span)
    assert traces.under("") is None
    assert traces.under("00-bad") is None
