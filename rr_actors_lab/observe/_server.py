"""The observer's web server: a Starlette app on uvicorn, in a thread of its own.

```
 browser ── GET /?token=T         ── index.html (sets the cookie), /static/app.js, app.css, ...
         ── GET /api/state        ── every section and the recent events, as one JSON document
         ── GET /api/stream       ── server-sent events: "hello", then "section", "patch",
                                     "events" (encoded once in the hub, shared by every page)
         ── POST /api/faults/KIND ── teaching mode only: JSON in, JSON out; across
                                     hosts, {"host": MEMBER, ...} goes to that host
                                     as a command (`_system.SystemView.fault`)
         ── POST /api/control     ── a replay's page only (`rr_actors_lab.teach.replay`):
                                     {"step": N} in, the step shown out
 uvicorn thread (asyncio loop) ◄── Hub listeners (call_soon_threadsafe) ◄── source threads
```

Who gets in (docs/explanation/failure-semantics.md, docs/reference/observer.md): every
route needs the token (`?token=`, an `X-RR-Token` header, or the page's `HttpOnly`,
`SameSite=Strict` cookie; none: 401, a wrong one: 403) and an allowed `Host` header (DNS
rebinding: 400); the fault endpoints want the header and a JSON content type (no CORS
preflight is ever answered). Streams, silent clients and idle connections are bounded;
nothing the browser sends is unpickled.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import html
import json
import secrets
import socket
import threading
import time
import weakref
from collections.abc import AsyncIterator, Awaitable, Callable, MutableMapping
from http.cookies import SimpleCookie
from importlib import resources
from typing import Any
from urllib.parse import parse_qs

import anyio.to_thread
import uvicorn
from sse_starlette import EventSourceResponse
from sse_starlette.sse import SendTimeoutError
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from uvicorn.protocols.http.h11_impl import H11Protocol

from rr_actors._platform import PLATFORM
from rr_actors.errors import ConfigError
from rr_actors_lab.observe._faults import FaultRefused, Faults, inject
from rr_actors_lab.observe._hub import MAX_STREAMS, Hub, sse

__all__ = ["ABORT_AFTER", "COALESCE", "SEND_TIMEOUT", "Server", "build_app", "host_name"]

COALESCE = 0.01
"""Seconds a page's stream waits after a change, so that changes close together go as one."""

EVENTS_EVERY = 0.1
"""Seconds between two batches of events to a page (a change of a section goes at once)."""

PING = 10.0
"""Seconds between keep-alive comments on an idle stream."""

MAX_BODY = 4096
"""Bytes a fault request's body may have."""

SEND_TIMEOUT = 5.0
"""Seconds a page's stream may wait for its client to take one message; then it ends."""

ABORT_AFTER = 5.0
"""Seconds a closed connection may keep unsent bytes for a peer that does not read."""

SEND_BUFFER = 256 * 1024
"""Bytes of a connection's kernel send buffer (fixed: not grown for a peer that never reads)."""

RELEASE_AFTER = 2.0
"""Seconds without a connection closing after which the memory the closed ones held is
handed back to the system (`_release_memory_soon`); at most `RELEASE_AFTER * 5` seconds
after the first of a burst, however long it goes on."""

_RELEASES: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, tuple[float, asyncio.TimerHandle]]
_RELEASES = weakref.WeakKeyDictionary()
"""Each server loop's due release of free memory: when the burst began, and its timer."""

_CONNECTIONS: dict[tuple[int, str, int], asyncio.Transport] = {}
"""(local port, peer host, peer port) -> the transport: what a stream aborts when it times out."""

Scope = MutableMapping[str, Any]
ASGIApp = Callable[[Scope, Any, Any], Awaitable[None]]

_HEADERS = {
    "Content-Security-Policy": (
        # cytoscape.js sets styles of its own elements: 'unsafe-inline' for styles only
        "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
        "img-src 'self' data:; connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; "
        "form-action 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


def host_name(header: str) -> str:
    """The name in a `Host` header, without its port (`[::1]:80` -> `::1`), lowercased."""
    header = header.strip().lower()
    if header.startswith("["):
        return header[1:].partition("]")[0]
    return header.rpartition(":")[0] if header.count(":") == 1 else header


class _Guard:
    """ASGI middleware: check the `Host` header and the token, add the security headers."""

    def __init__(self, app: ASGIApp, hosts: frozenset[str], token: str, cookie: str) -> None:
        self.app = app
        self.hosts = hosts
        self.token = token.encode()
        self.cookie = cookie

    def _given(self, scope: Scope) -> tuple[str | None, bool]:
        """The token a request carries, and whether it came in the URL's query."""
        headers = dict(scope["headers"])
        if b"x-rr-token" in headers:
            return headers[b"x-rr-token"].decode("latin-1"), False
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        if "token" in query:
            return query["token"][0], True
        cookies = SimpleCookie()
        try:
            cookies.load(headers.get(b"cookie", b"").decode("latin-1"))
        except Exception:  # noqa: BLE001 - a malformed cookie header is no token
            return None, False
        morsel = cookies.get(self.cookie)
        return (morsel.value if morsel is not None else None), False

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        host = dict(scope["headers"]).get(b"host", b"").decode("latin-1")
        if host_name(host) not in self.hosts:
            await _refuse("unknown Host header: open the URL the observer printed", 400)(
                scope, receive, send
            )
            return
        given, in_query = self._given(scope)
        if given is None:
            message = "this page needs its token: open the URL the observer printed (?token=...)"
            await _refuse(message, 401)(scope, receive, send)
            return
        if not secrets.compare_digest(given.encode("utf-8", "replace"), self.token):
            await _refuse("wrong token: open the URL the observer printed", 403)(
                scope, receive, send
            )
            return
        cookie = (
            f"{self.cookie}={given}; Path=/; HttpOnly; SameSite=Strict".encode()
            if in_query
            else None
        )

        async def secured(message: MutableMapping[str, Any]) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                headers.extend((k.lower().encode(), v.encode()) for k, v in _HEADERS.items())
                if cookie is not None:  # the page's own requests carry it from now on
                    headers.append((b"set-cookie", cookie))
                message["headers"] = headers
            await send(message)

        await self.app(scope, receive, secured)


def _static(name: str) -> str:
    return resources.files("rr_actors_lab.observe").joinpath("static", name).read_text("utf-8")


def _index(hello: dict[str, Any]) -> str:
    """index.html as its first paint should look for this observer (before any data)."""
    offline = hello.get("mode") == "backups"
    fields = {
        "mode": str(hello.get("mode", "live")),
        "title": str(hello.get("title", "")),
        "badge": "offline" if offline else "connecting",
        "badge_class": "still" if offline else "down",
        "tree_heading": "Backups (read-only)" if offline else "Supervision tree",
        "waiting": "Reading the backups…" if offline else "Waiting for the tree…",
    }
    page = _static("index.html")
    for name, value in fields.items():
        page = page.replace("{{" + name + "}}", html.escape(value))
    return page


def build_app(
    hub: Hub,
    *,
    hello: dict[str, Any],
    faults: Faults | None,
    token: str,
    hosts: frozenset[str],
    cookie: str = "rr-observer",
    remote: Callable[[str, str, dict[str, Any]], str] | None = None,
    member: str | None = None,
    fault_events: Hub | None = None,
    control: Callable[[dict[str, Any]], dict[str, Any]] | None = None,
) -> ASGIApp:
    """The observer's ASGI app.

    Args:
        hub: what the page shows.
        hello: the first message of every stream (mode, title, whether faults are on).
        faults: the teaching mode's faults (`None`: off; the endpoints answer 403).
        token: what every request must carry (query, header or cookie).
        hosts: the accepted names in the `Host` header (without a port).
        cookie: the name of the cookie that keeps the token for the page's requests.
        remote: across hosts, sends a fault to another host: `remote(member, kind, data)`.
        member: this host's member name across hosts (a request naming it, or none, is ours).
        fault_events: the hub recording this host's own faults (default `hub`).
        control: a replay's step control, JSON object in and out (a `ConfigError` is a 400);
            `None`: the endpoint answers 404.
    """
    index = _index(hello)
    static = StaticFiles(directory=str(resources.files("rr_actors_lab.observe").joinpath("static")))

    def state() -> dict[str, Any]:
        changes = hub.changes({}, 0)
        return {
            "hello": {**hello, "instance": hub.instance},
            "sections": {key: value for key, _, value in changes.sections},
            "events": changes.events,
        }

    async def page(_: Request) -> Response:
        return HTMLResponse(index)

    async def full_state(_: Request) -> Response:
        return JSONResponse(state())

    async def stream(request: Request) -> Response:
        if not hub.open_stream():
            return _refuse(f"too many pages open (at most {MAX_STREAMS}): close one", 503)
        return _CountedStream(
            hub, _stream(hub, hello, request), ping=PING, send_timeout=SEND_TIMEOUT
        )

    async def body_of(request: Request) -> dict[str, Any] | Response:
        """The JSON object a button sent, or the refusal (the token in the header: a
        cookie is not enough; a JSON content type; at most `MAX_BODY` bytes)."""
        given = request.headers.get("x-rr-token", "")
        if not secrets.compare_digest(given.encode("utf-8", "replace"), token.encode()):
            return _refuse("wrong or missing token: open the URL the observer printed", 403)
        if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
            return _refuse("a request is JSON (Content-Type: application/json)", 415)
        body = await request.body()
        if len(body) > MAX_BODY:
            return _refuse("request too large", 413)
        try:
            data = json.loads(body)
        except (ValueError, RecursionError):  # (nested past the parser: not a request)
            return _refuse("the body is not JSON", 400)
        if not isinstance(data, dict):
            return _refuse("the body must be a JSON object", 400)
        return data

    async def fault(request: Request) -> Response:  # noqa: PLR0911 - one answer per check
        if faults is None and remote is None:
            return _refuse(
                "teaching mode is off: the observer was opened without allow_faults", 403
            )
        data = await body_of(request)
        if isinstance(data, Response):
            return data
        kind = request.path_params["kind"]
        target = data.get("host", member)
        if target is not None and target != member:
            if remote is None or not isinstance(target, str):
                return _refuse(f"this page shows no host {target!r}", 404)
            try:
                message = await anyio.to_thread.run_sync(remote, target, kind, data)
            except FaultRefused as exc:
                return _refuse(str(exc), exc.status)
            return JSONResponse({"ok": True, "message": message})
        if faults is None:
            return _refuse(
                "teaching mode is off: the observer was opened without allow_faults", 403
            )
        try:
            message = await anyio.to_thread.run_sync(inject, faults, kind, data)
        except FaultRefused as exc:
            return _refuse(str(exc), exc.status)
        event = {"type": "ObserverFault", "kind": kind, "text": message, "at": time.time()}
        (fault_events or hub).add_event(event)
        return JSONResponse({"ok": True, "message": message})

    async def step(request: Request) -> Response:
        if control is None:
            return _refuse("this page replays nothing", 404)
        data = await body_of(request)
        if isinstance(data, Response):
            return data
        try:
            answer = await anyio.to_thread.run_sync(control, data)
        except ConfigError as exc:
            return _refuse(str(exc), 400)
        return JSONResponse(answer)

    app = Starlette(
        routes=[
            Route("/", page),
            Route("/api/state", full_state),
            Route("/api/stream", stream),
            Route("/api/faults/{kind}", fault, methods=["POST"]),
            Route("/api/control", step, methods=["POST"]),
            Mount("/static", app=static, name="static"),
        ]
    )
    return _Guard(app, hosts, token, cookie)


def _refuse(message: str, status: int) -> Response:
    return JSONResponse({"ok": False, "message": message}, status_code=status)


class _CountedStream(EventSourceResponse):
    """A page's stream that gives its place back (`Hub.close_stream`) however it ends."""

    def __init__(self, hub: Hub, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._hub = hub

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        try:
            await super().__call__(scope, receive, send)
        except SendTimeoutError:  # its client takes nothing: its connection goes, unsent bytes too
            server, client = scope.get("server"), scope.get("client")
            if server and client:
                transport = _CONNECTIONS.get((server[1], client[0], client[1]))
                if transport is not None:
                    transport.abort()
                    for _ in range(3):  # (its connection_lost runs: uvicorn sees a disconnect)
                        await asyncio.sleep(0)
        finally:
            self._hub.close_stream()


async def _stream(hub: Hub, hello: dict[str, Any], request: Request) -> AsyncIterator[bytes]:
    """One page's stream: the hello, then what changed since it last looked, until closed."""
    loop = asyncio.get_running_loop()
    wake = asyncio.Event()
    flagged = [False]

    def listener() -> None:  # any thread; at most one wake-up per look
        if not flagged[0]:
            flagged[0] = True
            with contextlib.suppress(RuntimeError):  # its loop closed: the stream is over
                loop.call_soon_threadsafe(wake.set)

    unlisten = hub.listen(listener)
    seen: dict[str, int] = {}
    last_seq = 0
    events_at = 0.0  # when the last batch of events went (loop time)
    later: asyncio.TimerHandle | None = None
    try:
        yield sse("hello", json.dumps({**hello, "instance": hub.instance}))
        while not hub.closed:
            flagged[0] = False
            due = loop.time() - events_at >= EVENTS_EVERY
            before = last_seq
            messages, last_seq = hub.messages(seen, last_seq, with_events=due)
            for message in messages:
                yield message
            if last_seq != before:
                events_at = loop.time()
            elif not due and hub.last_seq > last_seq and later is None:
                wait = EVENTS_EVERY - (loop.time() - events_at)
                later = loop.call_later(wait, wake.set)  # the events that wait go then
            await wake.wait()
            wake.clear()
            later = None if later is None or later.when() <= loop.time() else later
            await asyncio.sleep(COALESCE)
            if await request.is_disconnected():
                return
    finally:
        if later is not None:
            later.cancel()
        unlisten()


class _Transport:
    """An asyncio transport that aborts a closed connection whose peer has not read for
    `ABORT_AFTER` s."""

    def __init__(self, transport: asyncio.Transport, loop: asyncio.AbstractEventLoop) -> None:
        self._transport = transport
        self._loop = loop

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)

    def close(self) -> None:
        self._transport.close()
        if self._transport.get_write_buffer_size():
            self._loop.call_later(ABORT_AFTER, self._abort_if_stuck)

    def _abort_if_stuck(self) -> None:
        if self._transport.get_write_buffer_size():
            self._transport.abort()


class _Protocol(H11Protocol):
    """uvicorn's HTTP/1.1 protocol (a private extension point, used only here) with two bounds: an
    idle connection closes after the keep-alive timeout, a closed one is aborted
    (`_Transport`); its send buffer is `SEND_BUFFER` bytes, so a silent peer times out soon."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        sock = transport.get_extra_info("socket")
        with contextlib.suppress(OSError, AttributeError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        self._key: tuple[int, str, int] | None = None
        with contextlib.suppress(TypeError, IndexError):
            local, peer = transport.get_extra_info("sockname"), transport.get_extra_info("peername")
            self._key = (local[1], str(peer[0]), peer[1])
            _CONNECTIONS[self._key] = transport
        super().connection_made(_Transport(transport, self.loop))  # type: ignore[arg-type]
        self.timeout_keep_alive_task = self.loop.call_later(
            self.timeout_keep_alive, self.timeout_keep_alive_handler
        )

    def connection_lost(self, exc: Exception | None) -> None:
        if self._key is not None:
            _CONNECTIONS.pop(self._key, None)
        super().connection_lost(exc)
        _release_memory_soon(self.loop)


def _release_memory_soon(loop: asyncio.AbstractEventLoop) -> None:
    """A full collection, then `PLATFORM.release_free_memory` (glibc's `malloc_trim`), on the
    server's thread `RELEASE_AFTER` s from now: closed streams' buffers are held by cycles and
    then by the C heap."""
    now = loop.time()
    began, due = _RELEASES.pop(loop, (now, None))
    if due is not None:
        due.cancel()

    def release() -> None:
        _RELEASES.pop(loop, None)
        gc.collect()
        PLATFORM.release_free_memory()

    at = min(now, began + RELEASE_AFTER * 4) + RELEASE_AFTER  # (a burst that goes on)
    _RELEASES[loop] = (began, loop.call_at(at, release))


class _Uvicorn(uvicorn.Server):
    """uvicorn's server that says when it serves (`ready`), for a bounded wait."""

    def __init__(self, config: uvicorn.Config) -> None:
        super().__init__(config)
        self.ready = threading.Event()

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        await super().startup(sockets)
        self.ready.set()


class Server:
    """uvicorn serving `app` on an already bound socket, on a thread of its own.

    Args:
        app: the ASGI app.
        sock: a bound TCP socket (the observer bound it, so a port in use failed there).
        name: for the thread's name.
    """

    def __init__(self, app: ASGIApp, sock: socket.socket, name: str) -> None:
        config = uvicorn.Config(
            app,
            log_level="warning",
            access_log=False,
            lifespan="off",
            loop="asyncio",
            http=_Protocol,
            ws="none",
            timeout_keep_alive=5,
            timeout_graceful_shutdown=2,
        )
        self._server = _Uvicorn(config)
        self._sock = sock
        self._thread = threading.Thread(
            target=self._server.run, kwargs={"sockets": [sock]}, name=name, daemon=True
        )

    def start(self, timeout: float) -> bool:
        """Start serving; whether it serves within `timeout` seconds."""
        self._thread.start()
        return self._server.ready.wait(timeout)

    def close(self, timeout: float) -> None:
        """Stop serving (open streams end) and wait for the thread at most `timeout` s."""
        self._server.should_exit = True
        self._thread.join(timeout)
        if self._thread.is_alive():
            self._server.force_exit = True
            self._thread.join(timeout)
        with contextlib.suppress(OSError):
            self._sock.close()
