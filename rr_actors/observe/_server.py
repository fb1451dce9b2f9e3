"""The observer's web server: a Starlette app on uvicorn, in a thread of its own.

```
 browser ── GET /                 ── index.html, /static/app.js, app.css, vendor/cytoscape.min.js
         ── GET /api/state        ── every section and the recent events, as one JSON document
         ── GET /api/stream       ── server-sent events: "hello", then "section" and "events"
         ── POST /api/faults/KIND ── teaching mode only: JSON in, JSON out, with the token
 uvicorn thread (asyncio loop) ◄── Hub listeners (call_soon_threadsafe) ◄── source threads
```

Everything the browser sends is JSON or a URL; nothing from it is ever unpickled. Every
request must name this server in its `Host` header (a page of another site that
resolves its own name to 127.0.0.1, DNS rebinding, gets 400); the fault endpoints also
need the token of the observer's URL (`#token=...`, sent back in the `X-RR-Token`
header) and a JSON content type, which a page of another origin cannot send without
a CORS preflight this server never answers.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import secrets
import socket
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable, MutableMapping
from importlib import resources
from typing import Any

import anyio.to_thread
import uvicorn
from sse_starlette import EventSourceResponse, ServerSentEvent
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from rr_actors.observe._faults import FaultRefused, Faults
from rr_actors.observe._hub import Hub

__all__ = ["COALESCE", "Server", "build_app"]

COALESCE = 0.01
"""Seconds a page's stream waits after a change, so that changes close together go as one."""

EVENTS_EVERY = 0.1
"""Seconds between two batches of events to a page (a change of a section goes at once)."""

PING = 10.0
"""Seconds between keep-alive comments on an idle stream."""

MAX_BODY = 4096
"""Bytes a fault request's body may have."""

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


class _Guard:
    """ASGI middleware: check the `Host` header, add the security headers."""

    def __init__(self, app: ASGIApp, hosts: set[str] | None) -> None:
        self.app = app
        self.hosts = hosts

    async def __call__(self, scope: Scope, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if self.hosts is not None:
            host = dict(scope["headers"]).get(b"host", b"").decode("latin-1").lower()
            if host not in self.hosts:
                response = Response("unknown Host header", status_code=400)
                await response(scope, receive, send)
                return

        async def secured(message: MutableMapping[str, Any]) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                headers.extend((k.lower().encode(), v.encode()) for k, v in _HEADERS.items())
                message["headers"] = headers
            await send(message)

        await self.app(scope, receive, secured)


def _static(name: str) -> str:
    return resources.files("rr_actors.observe").joinpath("static", name).read_text("utf-8")


def build_app(
    hub: Hub,
    *,
    hello: dict[str, Any],
    faults: Faults | None,
    token: str,
    hosts: set[str] | None,
) -> ASGIApp:
    """The observer's ASGI app.

    Args:
        hub: what the page shows.
        hello: the first message of every stream (mode, title, whether faults are on).
        faults: the teaching mode's faults (`None`: off; the endpoints answer 403).
        token: what a fault request's `X-RR-Token` header must be.
        hosts: the accepted `Host` headers (`None`: any).
    """
    index = _static("index.html")
    static = StaticFiles(directory=str(resources.files("rr_actors.observe").joinpath("static")))

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
        return EventSourceResponse(_stream(hub, hello, request), ping=PING, send_timeout=10.0)

    async def fault(request: Request) -> Response:  # noqa: PLR0911 - one answer per check
        if faults is None:
            return _refuse(
                "teaching mode is off: the observer was opened without allow_faults", 403
            )
        given = request.headers.get("x-rr-token", "")
        if not secrets.compare_digest(given.encode(), token.encode()):
            return _refuse("wrong or missing token: open the URL the observer printed", 403)
        if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
            return _refuse("a fault request is JSON (Content-Type: application/json)", 415)
        body = await request.body()
        if len(body) > MAX_BODY:
            return _refuse("request too large", 413)
        try:
            data = json.loads(body)
        except ValueError:
            return _refuse("the body is not JSON", 400)
        if not isinstance(data, dict):
            return _refuse("the body must be a JSON object", 400)
        kind = request.path_params["kind"]
        try:
            message = await anyio.to_thread.run_sync(_inject, faults, kind, data)
        except FaultRefused as exc:
            return _refuse(str(exc), exc.status)
        hub.add_event({"type": "ObserverFault", "kind": kind, "text": message, "at": time.time()})
        return JSONResponse({"ok": True, "message": message})

    app = Starlette(
        routes=[
            Route("/", page),
            Route("/api/state", full_state),
            Route("/api/stream", stream),
            Route("/api/faults/{kind}", fault, methods=["POST"]),
            Mount("/static", app=static, name="static"),
        ]
    )
    return _Guard(app, hosts)


def _refuse(message: str, status: int) -> Response:
    return JSONResponse({"ok": False, "message": message}, status_code=status)


def _inject(faults: Faults, kind: str, data: dict[str, Any]) -> str:
    """Run one fault request (on a worker thread: a FATAL waits for its delivery)."""
    if kind in ("kill", "hang", "resume"):
        child, pid = data.get("child"), data.get("pid")
        if not isinstance(child, str) or isinstance(pid, bool) or not isinstance(pid, int):
            raise FaultRefused('expected {"child": NAME, "pid": PID}', 400)
        action: Callable[[str, int], str] = getattr(faults, kind)
        return action(child, pid)
    if kind == "fatal":
        registrar, resource_id = data.get("registrar"), data.get("resource_id")
        if not isinstance(registrar, str) or not isinstance(resource_id, str):
            raise FaultRefused('expected {"registrar": NAME, "resource_id": ID}', 400)
        return faults.fatal(registrar, resource_id)
    raise FaultRefused(f"no fault {kind!r} (kill, hang, resume, fatal)", 404)


async def _stream(hub: Hub, hello: dict[str, Any], request: Request) -> AsyncIterator[Any]:
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
    counted = hub.stream()
    counted.__enter__()
    seen: dict[str, int] = {}
    last_seq = 0
    events_at = 0.0  # when the last batch of events went (loop time)
    later: asyncio.TimerHandle | None = None
    try:
        yield ServerSentEvent(json.dumps({**hello, "instance": hub.instance}), event="hello")
        while not hub.closed:
            flagged[0] = False
            due = loop.time() - events_at >= EVENTS_EVERY
            changes = hub.changes(seen, last_seq, with_events=due)
            for key, _, value in changes.sections:
                yield ServerSentEvent(json.dumps({"key": key, "value": value}), event="section")
            if changes.events or changes.missed:
                events_at = loop.time()
                last_seq = changes.events[-1]["seq"] if changes.events else hub.last_seq
                data = {"events": changes.events, "missed": changes.missed}
                yield ServerSentEvent(json.dumps(data), event="events")
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
        counted.__exit__(None, None, None)


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
            http="h11",
            ws="none",
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
