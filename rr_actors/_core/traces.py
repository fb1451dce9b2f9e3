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

A traceparent (`"00-" 32 hex "-" 16 hex "-" 2 hex`, 55 characters) is a plain `str`:
it pickles as one, a JSON line holds it, and an untraced call carries `""`. The spans
themselves are made later, from the events, by `rr_actors.otel`: the ids are drawn here
so that both sides, in whichever process their spans are made, name the same spans.

Without the `otel` extra, before the application imported OpenTelemetry (this module does
not import it: no span can be current until then), or with no span current in the caller
(an empty context), `begin` returns `None` after a look-up or two and nothing is carried.
"""

from __future__ import annotations

import hashlib
import sys
from typing import Any

from rr_actors._core import runtime

# OpenTelemetry's API, once bound (`_bind`). Not imported with this module: importing it
# costs milliseconds (its context finds its runtime through entry points), and until the
# application imported it no span can be current. A call looks it up in `sys.modules`.
_context: Any = None
_trace: Any = None


def _bind(*, load: bool = False) -> bool:
    """Bind OpenTelemetry's API if the application imported it (or, with `load`, import
    it now); whether it is bound. `False`: the otel extra is missing, or not imported."""
    global _context, _trace
    if _context is not None:
        return True
    if load:
        try:
            import opentelemetry.context  # noqa: PLC0415
            import opentelemetry.trace  # noqa: F401, PLC0415
        except ImportError:  # the otel extra is missing: nothing is carried
            return False
    context = sys.modules.get("opentelemetry.context")
    trace = sys.modules.get("opentelemetry.trace")
    if context is None or trace is None:
        return False
    _trace, _context = trace, context  # (`_context` last: it says both are bound)
    return True


__all__ = [
    "adopt",
    "attach",
    "begin",
    "caller_parent",
    "context_of",
    "current",
    "derived",
    "detach",
    "own_trace",
    "parse",
    "server_span",
    "span_id",
    "status_callback",
    "under",
]

_SERVER = 0x7272_5F61_6374_6F72  # (b"rr_actor"): a SERVER span's id is its CLIENT's xor this
_MASK = (1 << 64) - 1


def _new_span() -> str:
    """A fresh span id, 16 hex digits from `runtime.getrandbits` (a simulation's seeded
    generator): neither 0 (invalid) nor one whose SERVER span's id would be 0."""
    while True:
        span = runtime.getrandbits(64)
        if span not in (0, _SERVER):
            return f"{span:016x}"


# The caller's span last seen, and what a traceparent under it is made of: its
# `"00-<trace id>-"`, its `"-<flags>"` and its own id (`""`s: not a valid span). A caller
# makes many calls under one span: each pays one identity check, not the formatting.
# (Swapped whole: a tuple, so a thread reads one span's parts, never a mix.)
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

    Read in the caller's thread or task (contextvars: an `acall` keeps its caller's
    context across `await`). `traceparent` names the call's CLIENT span (a fresh id)
    under the caller's trace id and sampled flag; `caller_span` is the id (16 hex) of the
    caller's current span, the CLIENT span's parent. `None` without the extra or without
    a valid span current.
    """
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
    """The W3C traceparent of the span current here (a thread's or task's), `""` if none:
    what a handle on a registrar of another process carries there (`adopt`)."""
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
    """Make the span `traceparent` names current here (a non-recording one: a caller's
    span in another process), for the rest of this context; nothing for a bad one."""
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
    """The trace context of a call made by the provider of the call that carried
    `traceparent` (a registrar's own: an unload's dependency releases), as `begin`'s:
    a fresh CLIENT span under that call's SERVER span; `None` for `""` or a bad one."""
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
    """The OpenTelemetry context whose current span is the SERVER span of the call that
    carried `traceparent` (a non-recording span: the real one is made from the events),
    or `None` (nothing carried, or no extra). Spans made under it are its children."""
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
    """The (trace id, span id) of the span of a status callback's run: a trace of its own,
    derived from what its `StatusHandled` names, so that the subscriber that makes the
    span from that event gives it the ids the callback's calls named as their parent."""
    parts = ("status callback", status_id, registrar, query_id)
    return derived(*parts, bits=128), derived(*parts)


def own_trace(callback: tuple[str, str, str] | None = None) -> object | None:
    """Run what follows as a trace of its own: make current here, in a context of its
    own, the span of the status callback `callback` names (`(status_id, registrar,
    query_id)`: `status_callback`'s ids, sampled), or no span at all (`None`); what was
    current (a span a `load` left, the context a coroutine callback was bound in) is
    not its parent. Its token for `detach`; `None` where OpenTelemetry is not imported."""
    if _context is None and not _bind():
        return None
    span = _trace.INVALID_SPAN
    if callback is not None:
        ids = status_callback(*callback)
        made = _trace.SpanContext(*ids, is_remote=False, trace_flags=_trace.TraceFlags(1))
        span = _trace.NonRecordingSpan(made)
    token: object = _context.attach(_trace.set_span_in_context(span, _context.Context()))
    return token
