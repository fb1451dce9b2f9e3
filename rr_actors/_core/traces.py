"""The W3C trace context a call carries: read from its caller's OpenTelemetry context.

```
 caller (call/acall/unload, its thread or task)      provider (any process, any host)
 ─────────────────────────────────────────────       ─────────────────────────────────
 current span: trace T, span P, flags F
 begin() ──► ("00-T-C-F", "P")   C: the CLIENT span's id, drawn here
   Load/Release/Unload .trace = "00-T-C-F" ─────────► its events' `trace`; the SERVER
   its end event: trace "00-T-C-F", caller_span "P"     span's id is server_span(C)
                                                      a load runs under
                                                      context_of("00-T-C-F"): span S
```

A traceparent (55 characters) is a plain `str`, `""` for an untraced call. `rr_actors_lab.otel`
makes the spans later, from the events; the ids are drawn here so both sides name the same
spans. OpenTelemetry is not imported here: until the application imported it no span can
be current, and `begin` returns `None` after a look-up or two.
"""

from __future__ import annotations

import hashlib
import sys
from typing import Any

from rr_actors._core import runtime

API = "opentelemetry.context"
"""The module of OpenTelemetry's API whose import makes a span possible: until it is in
`sys.modules`, `begin` returns `None` (a caller may skip it)."""

# OpenTelemetry's API, once bound (`_bind`): looked up in `sys.modules`, not imported.
_context: Any = None
_trace: Any = None


def _bind(*, load: bool = False) -> bool:
    """Bind OpenTelemetry's API if imported (with `load`, import it now); whether it is bound."""
    global _context, _trace
    if _context is not None:
        return True
    if load:
        try:
            import opentelemetry.context  # noqa: PLC0415
            import opentelemetry.trace  # noqa: F401, PLC0415
        except ImportError:  # the otel extra is missing: nothing is carried
            return False
    context = sys.modules.get(API)
    trace = sys.modules.get("opentelemetry.trace")
    if context is None or trace is None:
        return False
    _trace, _context = trace, context  # (`_context` last: it says both are bound)
    return True


_SERVER = 0x7272_5F61_6374_6F72  # (b"rr_actor"): a SERVER span's id is its CLIENT's xor this
_MASK = (1 << 64) - 1


def _new_span() -> str:
    """A fresh span id (16 hex): neither 0 nor one whose SERVER span's is 0."""
    while True:
        span = runtime.getrandbits(64)
        if span not in (0, _SERVER):
            return f"{span:016x}"


# The caller's span last seen and its traceparent's parts, swapped whole (one check a call).
_last: tuple[object, str, str, str] = (None, "", "", "")


def _parts(span: Any) -> tuple[object, str, str, str]:
    global _last
    caller = span.get_span_context()
    if caller.is_valid:
        prefix, suffix = f"00-{caller.trace_id:032x}-", f"-{caller.trace_flags:02x}"
        _last = (span, prefix, suffix, f"{caller.span_id:016x}")
    else:
        _last = (span, "", "", "")
    return _last


def begin() -> tuple[str, str] | None:
    """The trace context of a call made now: `(traceparent, caller_span)` or `None`.
    `traceparent` names the call's CLIENT span (a fresh id) under the caller's trace and flags;
    `caller_span`: the caller's current span's id (16 hex). `None`: no extra or valid span."""
    if _context is None and not _bind():
        return None
    current = _context.get_current()
    if not current:  # (an empty context: nothing traced here)
        return None
    span = _trace.get_current_span(current)
    parts = _last
    if parts[0] is not span:
        parts = _parts(span)
    _, prefix, suffix, caller_span = parts
    if not prefix:
        return None
    return f"{prefix}{_new_span()}{suffix}", caller_span


def current() -> str:
    """The traceparent of the span current here, `""` if none (what a handle carries to `adopt`)."""
    if _context is None and not _bind():
        return ""
    current = _context.get_current()
    if not current:
        return ""
    span = _trace.get_current_span(current).get_span_context()
    if not span.is_valid:
        return ""
    return f"00-{span.trace_id:032x}-{span.span_id:016x}-{span.trace_flags:02x}"


def adopt(traceparent: str) -> None:
    """Make the remote span `traceparent` names current in this context (bad: nothing)."""
    parsed = parse(traceparent)
    if parsed is None or not _bind(load=True):
        return
    trace_id, span, flags = parsed
    remote = _trace.SpanContext(
        trace_id, span, is_remote=True, trace_flags=_trace.TraceFlags(flags)
    )
    _context.attach(_trace.set_span_in_context(_trace.NonRecordingSpan(remote)))


def parse(traceparent: str) -> tuple[int, int, int] | None:
    """`(trace_id, span_id, flags)` of a traceparent, or `None` for `""` or a bad one."""
    if len(traceparent) != 55 or traceparent[:3] != "00-":
        return None
    try:
        trace_id = int(traceparent[3:35], 16)
        span = int(traceparent[36:52], 16)
        flags = int(traceparent[53:55], 16)
    except ValueError:
        return None
    if not (trace_id and span):
        return None
    return trace_id, span, flags


def span_id(hexadecimal: str) -> int:
    """A span id of 16 hex digits (`caller_span`), 0 for `""` or a bad one."""
    try:
        return int(hexadecimal, 16) if len(hexadecimal) == 16 else 0
    except ValueError:
        return 0


def server_span(client_span: int) -> int:
    """The id of the SERVER span of the call whose CLIENT span is `client_span`."""
    return (client_span ^ _SERVER) & _MASK


def under(traceparent: str) -> tuple[str, str] | None:
    """The trace context of a call the provider of `traceparent`'s call makes (an unload's
    dependency releases): a fresh CLIENT span under that call's SERVER span; `None` if bad."""
    parsed = parse(traceparent)
    if parsed is None:
        return None
    trace_id, client, flags = parsed
    return f"00-{trace_id:032x}-{_new_span()}-{flags:02x}", f"{server_span(client):016x}"


def caller_parent(traceparent: str, caller_span: str) -> Any:
    """The span context of a call's caller (its CLIENT span's parent), or `None`."""
    parsed = parse(traceparent)
    parent = span_id(caller_span)
    if parsed is None or not parent or not _bind(load=True):
        return None
    trace_id, _client, flags = parsed
    return _trace.SpanContext(
        trace_id, parent, is_remote=True, trace_flags=_trace.TraceFlags(flags)
    )


def context_of(traceparent: str) -> Any:
    """The context whose current span is the SERVER span of `traceparent`'s call, or `None`."""
    parsed = parse(traceparent)
    if parsed is None or not _bind(load=True):
        return None
    trace_id, client, flags = parsed
    server = _trace.SpanContext(
        trace_id, server_span(client), is_remote=False, trace_flags=_trace.TraceFlags(flags)
    )
    return _trace.set_span_in_context(_trace.NonRecordingSpan(server))


def attach(traceparent: str) -> object | None:
    """Make `context_of(traceparent)` current in this thread or task: its token, or `None`."""
    context = context_of(traceparent) if traceparent else None
    return _context.attach(context) if context is not None else None


def detach(token: object | None) -> None:
    """Undo `attach` (with its token; `None`: nothing was attached)."""
    if token is not None:
        _context.detach(token)


def derived(*parts: str, bits: int = 64) -> int:
    """An id of `bits` bits made from `parts` alone (the same in every process), not 0."""
    digest = hashlib.blake2b("\0".join(parts).encode(), digest_size=bits // 8).digest()
    return int.from_bytes(digest, "big") or 1


def status_callback(status_id: str, registrar: str, query_id: str) -> tuple[int, int]:
    """The (trace id, span id) of a status callback's run, from what its `StatusHandled` names."""
    parts = ("status callback", status_id, registrar, query_id)
    return derived(*parts, bits=128), derived(*parts)


def own_trace(callback: tuple[str, str, str] | None = None) -> object | None:
    """Make current, in a context of its own, the span of the status callback `callback` names
    (or no span): what was current is not its parent. Its token for `detach`, or `None`."""
    if _context is None and not _bind():
        return None
    span = _trace.INVALID_SPAN
    if callback is not None:
        ids = status_callback(*callback)
        made = _trace.SpanContext(*ids, is_remote=False, trace_flags=_trace.TraceFlags(1))
        span = _trace.NonRecordingSpan(made)
    token: object = _context.attach(_trace.set_span_in_context(span, _context.Context()))
    return token
