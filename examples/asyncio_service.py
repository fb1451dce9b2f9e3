"""A Starlette service that loads, shares and unloads cameras through registrars.

The cameras are served by a manager process under a supervisor; the web process has a
consumer registrar of its own and awaits it from its event loop (no thread per request):

    POST   /cameras            {"camera": "front"}  ->  {"id": ..., "response": ...}
    GET    /cameras/{id}/events                     ->  the camera's statuses (SSE)
    DELETE /cameras/{id}                            ->  its consumer id released
    GET    /streams                                 ->  {"open": event streams open}

Equal requests share one camera (one `load`), each request gets its own id; the last
`DELETE` unloads it. The camera's `load` and `unload` are coroutine functions, run on
the manager's event loop; while a camera is open, a task of its own sends a status per
frame, which the service streams to the client as server-sent events; a stream's watch
is closed when its client leaves.

Run it as a program and it serves on a free port, then plays a client against itself
with httpx over a real socket and prints what it saw. Serve it for real with
`uvicorn asyncio_service:app` (from `examples/`). It needs Starlette, sse-starlette,
uvicorn and httpx, the `service` extra: `pip install -e ".[service]"`.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import socket
import sys
from collections.abc import AsyncIterator
from typing import Any

import httpx
import uvicorn
from sse_starlette.sse import EventSourceResponse
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

import rr_actors as rr

FRAME_EVERY = 0.05
"""Seconds between two frames of an open camera (each one a status)."""


def cameras_setup(registrar: rr.ResourceRegistrar) -> None:
    """The manager's servers (run in its process): a camera, opened by a coroutine."""
    frames: dict[str, asyncio.Task[None]] = {}

    async def send_frames(camera: str) -> None:  # on the manager's event loop
        for frame in itertools.count(1):
            await asyncio.sleep(FRAME_EVERY)
            held = await registrar.aserver_queries("camera")
            ids = [q.id for q in held if q.request == {"camera": camera}]
            if ids:  # a status reaches every consumer of the camera (rule 9)
                await registrar.asend_status(ids[0], rr.Status.UPDATE, f"frame {frame}")

    async def open_camera(request: dict[str, str]) -> dict[str, str]:
        await asyncio.sleep(0.01)  # (a driver that takes a while: no thread waits)
        camera = request["camera"]
        frames[camera] = asyncio.get_running_loop().create_task(send_frames(camera))
        return {"camera": camera, "stream": f"rtsp://robot/{camera}"}

    async def close_camera(request: dict[str, str], _response: Any) -> None:
        frames.pop(request["camera"]).cancel()

    registrar.register_server("camera", load=open_camera, unload=close_camera)


supervisor = rr.Supervisor([rr.ManagerSpec("cameras", setup=cameras_setup, isolation="process")])
web: list[rr.ResourceRegistrar] = []  # the service's consumer registrar, once started
streams: list[rr.StatusWatch] = []  # the watches of its event streams (GET /streams)
ready = asyncio.Event()  # set once it is (on the loop that serves the app)


@contextlib.asynccontextmanager
async def lifespan(_app: Starlette) -> AsyncIterator[None]:
    """Start the tree and the service's registrar with the app; stop them with it."""
    async with supervisor:
        web.append(await supervisor.aregistrar("web"))
        ready.set()
        yield


async def open_camera(request: Request) -> Response:
    body = await request.json()
    query = await web[0].acall("cameras", "camera", {"camera": body["camera"]})
    return JSONResponse({"id": query.id, "response": query.response})


async def close_camera(request: Request) -> Response:
    try:
        await web[0].aunload(request.path_params["query_id"])
    except rr.UnknownQueryError:
        return JSONResponse({"error": "unknown id"}, status_code=404)
    return Response(status_code=204)


async def camera_events(request: Request) -> Response:
    async def events() -> AsyncIterator[dict[str, str]]:
        # `async with` closes the watch when the stream ends, also when the client
        # leaves (the stream's task is cancelled): a bare `async for` would leave it
        # open, the query's status callback, queueing frames for nobody.
        async with web[0].watch(request.path_params["query_id"]) as updates:
            streams.append(updates)
            async for update in updates:
                yield {"event": update.status.name, "data": update.message}

    return EventSourceResponse(events())


async def open_streams(_request: Request) -> Response:
    streams[:] = [watch for watch in streams if not watch.closed]
    return JSONResponse({"open": len(streams)})


app = Starlette(
    routes=[
        Route("/cameras", open_camera, methods=["POST"]),
        Route("/cameras/{query_id}", close_camera, methods=["DELETE"]),
        Route("/cameras/{query_id}/events", camera_events),
        Route("/streams", open_streams),
    ],
    lifespan=lifespan,
)


async def play_client(base: str) -> None:
    """What a client does: open the front camera twice, hear two frames, close both."""
    async with httpx.AsyncClient(base_url=base, timeout=10.0) as client:
        first = (await client.post("/cameras", json={"camera": "front"})).json()
        second = (await client.post("/cameras", json={"camera": "front"})).json()
        differ = first["id"] != second["id"]
        print(f"opened {first['response']['stream']} twice: ids differ: {differ}")
        heard = []
        async with client.stream("GET", f"/cameras/{first['id']}/events") as events:
            async for line in events.aiter_lines():
                if line.startswith("data: "):
                    heard.append(line.removeprefix("data: "))
                if len(heard) == 2:
                    break
        print(f"heard {len(heard)} frames: {all(h.startswith('frame ') for h in heard)}")
        print(f"event streams open once the client left: {await streams_left(client)}")
        for opened in (first, second):
            status = (await client.delete(f"/cameras/{opened['id']}")).status_code
            print(f"closed {opened['id'][:8]}: {status}")
        missing = await client.delete(f"/cameras/{first['id']}")
        print(f"closing it again: {missing.status_code}")


async def streams_left(client: httpx.AsyncClient) -> int:
    """The event streams the service holds open once it heard the client leave (a
    moment after the connection closed; asked every 50 ms, for at most 5 s)."""
    for _ in range(100):
        left = (await client.get("/streams")).json()["open"]
        if left == 0:
            break
        await asyncio.sleep(0.05)
    return int(left)


async def main() -> int:
    """Serve on a free port of this host, play the client against it, stop."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    serving = asyncio.ensure_future(server.serve(sockets=[listener]))
    started = asyncio.ensure_future(ready.wait())
    await asyncio.wait((started, serving), return_when=asyncio.FIRST_COMPLETED)
    if not started.done():  # the server ended before it served (its error was logged)
        return 1
    try:
        await play_client(f"http://127.0.0.1:{port}")
    finally:
        server.should_exit = True
        await serving
    print("service stopped: the tree and its registrars with it")
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
